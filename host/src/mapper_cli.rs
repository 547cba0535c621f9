//! `himap map` and `himap demo`: replay a posed sequence through the core's [`Mapper`] on the
//! multi-threaded CPU backend, evaluate after every mapping update, and write the outputs:
//! `metrics.csv`, `summary.json`, `mesh.ply`, `renders/`, `map.safetensors`.
//!
//! Evaluation after an update renders the update's newest frame at `eval.scale` of the input
//! resolution (bin-centre samples, no jitter) and compares it with the input image resized the
//! same way (PSNR, SSIM) and, when the dataset has depth, with the ground-truth depth (Depth L1
//! in cm over the pixels with valid depth).
//!
//! `map.safetensors` holds `params.<group>`, `adam_m.<group>`, `adam_v.<group>` (f32) and the
//! metadata `himap_config` (the run's TOML), `himap_aabb` (JSON `[[min], [max]]`) and
//! `adam_t`; [`load_map`] rebuilds the field from it alone.

use std::collections::HashMap;
use std::io::{IsTerminal, Write};
use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{bail, Context};
use himap_core::camera::{Intrinsics, Pose};
use himap_core::mapper::{view_rays, IterInfo, Mapper, MapperError, UpdateKind, UpdateReport};
use himap_core::mapping::{pack_rgba8, PixelResult, PixelSample};
use himap_core::model::{Group, ModelLayout, Ray, RayResult};
use himap_core::step::{Backend, ImageStore};
use himap_core::Aabb;
use serde::{Deserialize, Serialize};

use crate::backend::{ModelData, ParallelCpuBackend};
use crate::checkpoint::{self, DatasetId, RunState};
use crate::config::Config;
use crate::dataset::{self, LoadOptions, RgbImage};
use crate::select::{decide, BackendChoice, MapBackend};

/// Options of [`run_map`].
#[derive(Clone, Debug)]
pub struct MapOptions {
    pub dataset: PathBuf,
    pub out: PathBuf,
    pub config: Config,
    /// Source frame range and stride.
    pub start: usize,
    pub end: Option<usize>,
    pub stride: usize,
    pub resize: Option<(u32, u32)>,
    /// Worker threads (0 = all cores).
    pub threads: usize,
    /// `cpu`, `vulkan` or `auto` (see [`crate::select`]).
    pub backend: String,
    /// Show a progress bar.
    pub progress: bool,
    /// Check every frame's files and image headers before the first iteration.
    pub preflight: bool,
    /// Stop mapping once this many frames are pushed, without the final flush (the map as it
    /// stood then is evaluated and saved). `None` maps the whole selection.
    pub stop_after: Option<usize>,
    /// Write `checkpoint.safetensors` into `out` after every this many pushed frames (0 =
    /// never; see [`crate::checkpoint`]).
    pub checkpoint_every: usize,
    /// Continue from this checkpoint (a file, or the folder holding it).
    pub resume: Option<PathBuf>,
}

impl MapOptions {
    /// Every frame of `dataset` at its size on `threads` CPU threads with `config`: no
    /// progress output, preflight on, the whole selection mapped.
    pub fn new(dataset: PathBuf, out: PathBuf, config: Config, threads: usize) -> Self {
        Self {
            dataset,
            out,
            config,
            start: 0,
            end: None,
            stride: 1,
            resize: None,
            threads,
            backend: "cpu".into(),
            progress: false,
            preflight: true,
            stop_after: None,
            checkpoint_every: 0,
            resume: None,
        }
    }
}

/// One row of `metrics.csv`.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct UpdateMetrics {
    /// Index of the update's newest frame in the source sequence.
    pub frame: usize,
    pub kind: String,
    pub psnr: f64,
    pub ssim: f64,
    pub depth_l1_cm: Option<f64>,
    /// Loss of the update's first and last iteration.
    pub loss_first: f32,
    pub loss: f32,
    pub color_loss: f32,
    pub warp_loss: f32,
    /// Fraction of the last iteration's pixels with a valid warp term.
    pub warp_valid: f32,
    /// Share of the last iteration's sampled rays that left the scene box unabsorbed.
    pub open_rays: f32,
    pub window_keyframes: u32,
    pub iters: u32,
    /// Optimisation time of the update (s), excluding evaluation.
    pub seconds: f64,
}

/// `summary.json`.
#[derive(Clone, Debug, Serialize)]
pub struct MapSummary {
    pub dataset: PathBuf,
    pub frames: usize,
    pub width: u32,
    pub height: u32,
    pub backend: String,
    pub threads: usize,
    pub scene_box: [[f32; 3]; 2],
    pub scene_box_source: String,
    pub updates: usize,
    pub iterations: u32,
    /// Mapping steps rejected as not finite (skipped, parameters kept), and the times the
    /// learning rates were lowered after `mapper.rejected_lr_after` of them in a row.
    pub rejected_steps: u32,
    pub lr_reductions: u32,
    pub mean_psnr: Option<f64>,
    pub mean_ssim: Option<f64>,
    pub mean_depth_l1_cm: Option<f64>,
    /// Frames whose camera centre lay outside the scene box (warned at the first).
    pub frames_outside_box: usize,
    /// The final map re-rendered at every `eval.final_every`-th frame of the whole sequence:
    /// how many frames, and their average PSNR, SSIM, Depth L1 (cm).
    pub final_frames: usize,
    pub final_psnr: Option<f64>,
    pub final_ssim: Option<f64>,
    pub final_depth_l1_cm: Option<f64>,
    pub final_per_frame: Vec<FinalFrame>,
    /// Accuracy, Completion (cm), Completion ratio (%) when a ground truth exists.
    pub mesh: Option<crate::eval::MeshMetrics>,
    pub mesh_ground_truth: Option<String>,
    pub mesh_error: Option<String>,
    pub mesh_faces: usize,
    /// Faces of `mesh_full.ply` (the extraction region before the visibility culling).
    pub mesh_full_faces: usize,
    /// SDF level of `mesh.ply` (m) and the trained beta it was derived from.
    pub mesh_level: f32,
    pub beta: f32,
    pub seconds_total: f64,
    pub seconds_mapping: f64,
    pub seconds_per_iteration: f64,
    pub seconds_per_frame: f64,
    pub parameters: usize,
    pub config: Config,
}

/// Builds the parallel backend for a configuration over `aabb` with image slots for `k`.
pub fn build_backend(
    config: &Config,
    aabb: Aabb,
    k: &Intrinsics,
    threads: usize,
) -> anyhow::Result<ParallelCpuBackend> {
    build_backend_at(config, aabb, k, threads, None)
}

/// [`build_backend`] whose geometric initialisation (`model.geo_init`) centres its sphere on
/// `center` (default: the box centre).
pub fn build_backend_at(
    config: &Config,
    aabb: Aabb,
    k: &Intrinsics,
    threads: usize,
    center: Option<[f32; 3]>,
) -> anyhow::Result<ParallelCpuBackend> {
    let data = initial_data(config, aabb, center)?;
    let mapper = config.mapper_config()?;
    Ok(
        ParallelCpuBackend::new(data, config.adam_config(), threads)?.with_images(ImageStore {
            width: k.width,
            height: k.height,
            slots: mapper.slots_needed(),
        }),
    )
}

/// The model a run starts from: seeded initialisation, then the geometric initialisation of
/// `model.geo_init` (its sphere centred on `center`, default the box centre).
pub fn initial_data(
    config: &Config,
    aabb: Aabb,
    center: Option<[f32; 3]>,
) -> anyhow::Result<ModelData> {
    let mc = config.model_config(aabb)?;
    let layout = ModelLayout::new(&mc).map_err(|e| anyhow::anyhow!("model: {e}"))?;
    let mut data = ModelData::new(layout, config.seed as u32)
        .map_err(|e| anyhow::anyhow!("model init: {e}"))?;
    if config.model.geo_init == "sphere" {
        let c = center.unwrap_or_else(|| [0, 1, 2].map(|a| 0.5 * (aabb.min[a] + aabb.max[a])));
        crate::geo_init::fit_sphere(
            &mut data,
            &crate::geo_init::SphereInit {
                center: c,
                radius: config.model.geo_init_radius,
                solid: config.model.geo_init_solid,
                iters: config.model.geo_init_iters,
                points: 4096,
                lr: 0.01,
                seed: config.seed,
            },
        );
    }
    Ok(data)
}

/// Renders a view (colour, depth, opacity per pixel, row-major).
pub fn render_view<B: Backend>(
    backend: &mut B,
    k: &Intrinsics,
    pose: &Pose,
) -> anyhow::Result<Vec<RayResult>>
where
    B::Error: std::error::Error + Send + Sync + 'static,
{
    let n = k.width as usize * k.height as usize;
    let mut rays = vec![
        Ray {
            origin: [0.0; 3],
            dir: [0.0; 3],
            target: [0.0; 3],
            target_depth: 0.0,
        };
        n
    ];
    view_rays(k, pose, &mut rays).map_err(|e| anyhow::anyhow!("{e}"))?;
    let mut out = vec![RayResult::default(); n];
    backend.render(&rays, &mut out)?;
    Ok(out)
}

/// Packs an RGB image into RGBA8 words.
pub fn pack_image(img: &RgbImage) -> Vec<u32> {
    img.data
        .as_chunks::<3>()
        .0
        .iter()
        .map(|c| pack_rgba8(*c))
        .collect()
}

/// Writes the map: parameters, Adam moments, configuration and box.
pub fn save_map(path: &Path, config: &Config, data: &ModelData) -> anyhow::Result<()> {
    save_map_with(path, config, data, &[])
}

/// [`save_map`] with more metadata entries (a checkpoint's run state).
pub fn save_map_with(
    path: &Path,
    config: &Config,
    data: &ModelData,
    extra: &[(&str, String)],
) -> anyhow::Result<()> {
    use safetensors::tensor::{Dtype, TensorView};
    let mut bufs: Vec<(String, Vec<u8>, usize)> = Vec::new();
    for g in Group::ALL {
        let i = g as usize;
        for (prefix, v) in [
            ("params", &data.params[i]),
            ("adam_m", &data.m[i]),
            ("adam_v", &data.v[i]),
        ] {
            let bytes: Vec<u8> = v.iter().flat_map(|x| x.to_le_bytes()).collect();
            bufs.push((format!("{prefix}.{}", g.name()), bytes, v.len()));
        }
    }
    let views = bufs
        .iter()
        .map(|(n, b, len)| Ok((n.clone(), TensorView::new(Dtype::F32, vec![*len], b)?)))
        .collect::<Result<Vec<_>, safetensors::SafeTensorError>>()?;
    let aabb = data.layout.config.aabb;
    let mut meta = HashMap::new();
    meta.insert("himap_config".to_string(), config.to_toml());
    meta.insert(
        "himap_aabb".to_string(),
        serde_json::to_string(&[aabb.min, aabb.max])?,
    );
    meta.insert("adam_t".to_string(), data.t.to_string());
    for (k, v) in extra {
        meta.insert(k.to_string(), v.clone());
    }
    let bytes = safetensors::serialize(views, Some(meta))
        .with_context(|| format!("serialising {}", path.display()))?;
    crate::atomic::write_bytes_atomic(path, &bytes)
}

/// Reads a map written by [`save_map`]: its configuration and model data.
pub fn load_map(path: &Path) -> anyhow::Result<(Config, ModelData)> {
    let (config, data, _) = load_map_with_meta(path)?;
    Ok((config, data))
}

/// [`load_map`] and every metadata entry of the file.
pub fn load_map_with_meta(
    path: &Path,
) -> anyhow::Result<(Config, ModelData, HashMap<String, String>)> {
    let bytes = std::fs::read(path).with_context(|| format!("reading {}", path.display()))?;
    load_map_bytes(&bytes).with_context(|| format!("loading map {}", path.display()))
}

/// [`load_map_with_meta`] of a file already read. The configuration in the file sizes the
/// map; it is checked against the file's length before the map is allocated.
pub fn load_map_bytes(
    bytes: &[u8],
) -> anyhow::Result<(Config, ModelData, HashMap<String, String>)> {
    let (_, header) =
        safetensors::SafeTensors::read_metadata(bytes).context("not a safetensors file")?;
    let meta = header.metadata().clone().context("no himap metadata")?;
    let get = |k: &str| {
        meta.get(k)
            .with_context(|| format!("metadata '{k}' missing"))
    };
    let config = Config::from_toml(get("himap_config")?)?;
    let [min, max]: [[f32; 3]; 2] = serde_json::from_str(get("himap_aabb")?)?;
    let t: u32 = get("adam_t")?.parse().context("adam_t")?;
    let layout = ModelLayout::new(&config.model_config(Aabb::new(min, max))?)
        .map_err(|e| anyhow::anyhow!("model: {e}"))?;
    // Parameters and both Adam moments, 4 bytes each, must all be in the file.
    let need = (layout.param_count() as u64).saturating_mul(12);
    if need > bytes.len() as u64 {
        bail!(
            "its configuration needs {need} bytes of parameters and Adam moments, the file \
             holds {}",
            bytes.len()
        );
    }
    let st = safetensors::SafeTensors::deserialize(bytes)?;
    let mut data = ModelData::new(layout, 0).map_err(|e| anyhow::anyhow!("{e}"))?;
    for g in Group::ALL {
        let i = g as usize;
        for (prefix, dst) in [
            ("params", &mut data.params[i]),
            ("adam_m", &mut data.m[i]),
            ("adam_v", &mut data.v[i]),
        ] {
            let name = format!("{prefix}.{}", g.name());
            let t = st.tensor(&name).with_context(|| format!("tensor {name}"))?;
            if t.dtype() != safetensors::Dtype::F32 || t.data().len() != 4 * dst.len() {
                bail!("tensor {name} has the wrong type or length for the configuration");
            }
            for (d, c) in dst.iter_mut().zip(t.data().as_chunks::<4>().0) {
                *d = f32::from_le_bytes(*c);
            }
        }
    }
    data.t = t;
    Ok((config, data, meta))
}

/// A blue-to-red colour map of depth in [lo, hi] (black where there is none).
fn depth_color(d: f32, lo: f32, hi: f32) -> [u8; 3] {
    if d <= 0.0 || !d.is_finite() {
        return [0, 0, 0];
    }
    let x = ((d - lo) / (hi - lo).max(1e-6)).clamp(0.0, 1.0);
    let r = (1.5 - (4.0 * x - 3.0).abs()).clamp(0.0, 1.0);
    let g = (1.5 - (4.0 * x - 2.0).abs()).clamp(0.0, 1.0);
    let b = (1.5 - (4.0 * x - 1.0).abs()).clamp(0.0, 1.0);
    [(r * 255.0) as u8, (g * 255.0) as u8, (b * 255.0) as u8]
}

/// Writes `input | rendered | rendered depth | gt depth` side by side.
fn write_render(
    path: &Path,
    input: &RgbImage,
    out: &[RayResult],
    gt_depth: Option<&[f32]>,
) -> anyhow::Result<()> {
    let (w, h) = (input.width as usize, input.height as usize);
    let panels = if gt_depth.is_some() { 4 } else { 3 };
    let mut img = vec![0u8; w * panels * h * 3];
    let (mut lo, mut hi) = (f32::INFINITY, 0.0f32);
    for d in gt_depth
        .unwrap_or(&[])
        .iter()
        .copied()
        .chain(out.iter().map(|r| r.depth))
    {
        if d > 0.0 && d.is_finite() {
            lo = lo.min(d);
            hi = hi.max(d);
        }
    }
    for y in 0..h {
        for x in 0..w {
            let i = y * w + x;
            let mut put = |panel: usize, c: [u8; 3]| {
                let o = 3 * (y * w * panels + panel * w + x);
                img[o..o + 3].copy_from_slice(&c);
            };
            let q = |v: f32| (v.clamp(0.0, 1.0) * 255.0 + 0.5) as u8;
            put(0, [0, 1, 2].map(|c| q(input.data[3 * i + c])));
            put(1, out[i].color.map(q));
            put(2, depth_color(out[i].depth, lo, hi));
            if let Some(g) = gt_depth {
                put(3, depth_color(g[i], lo, hi));
            }
        }
    }
    let mut png = Vec::new();
    use image::ImageEncoder;
    image::codecs::png::PngEncoder::new(&mut png)
        .write_image(
            &img,
            (w * panels) as u32,
            h as u32,
            image::ExtendedColorType::Rgb8,
        )
        .with_context(|| format!("encoding {}", path.display()))?;
    crate::atomic::write_bytes_atomic(path, &png)
}

fn mean(v: impl Iterator<Item = f64>) -> Option<f64> {
    let (mut s, mut n) = (0.0, 0usize);
    for x in v {
        if x.is_finite() {
            s += x;
            n += 1;
        }
    }
    (n > 0).then(|| s / n as f64)
}

/// The columns of `metrics.csv`, one row per mapping update.
const CSV_HEADER: &str = "frame,kind,psnr,ssim,depth_l1_cm,loss_first,loss,color_loss,warp_loss,\
warp_valid,window_keyframes,iters,seconds,open_rays";

/// Writes `metrics.csv`: the header and every row so far, atomically ([`crate::atomic`]).
fn write_metrics(path: &Path, rows: &[UpdateMetrics]) -> anyhow::Result<()> {
    crate::atomic::write_atomic(path, |w| {
        writeln!(w, "{CSV_HEADER}")?;
        for r in rows {
            write_csv_row(w, r)?;
        }
        Ok(())
    })
}

/// Appends one update's row to `metrics.csv`.
fn write_csv_row(csv: &mut (impl Write + ?Sized), r: &UpdateMetrics) -> std::io::Result<()> {
    writeln!(
        csv,
        "{},{},{:.4},{:.4},{},{:.6},{:.6},{:.6},{:.6},{:.4},{},{},{:.3},{:.4}",
        r.frame,
        r.kind,
        r.psnr,
        r.ssim,
        r.depth_l1_cm.map(|d| format!("{d:.3}")).unwrap_or_default(),
        r.loss_first,
        r.loss,
        r.color_loss,
        r.warp_loss,
        r.warp_valid,
        r.window_keyframes,
        r.iters,
        r.seconds,
        r.open_rays
    )
}

/// "init" or "map": the kind of an iteration in progress lines.
fn kind_label(kind: UpdateKind) -> &'static str {
    match kind {
        UpdateKind::Init => "init",
        UpdateKind::Online => "map",
    }
}

/// Progress as plain lines on stderr, at most one every [`PlainLog::EVERY`] (plus one per
/// mapping update and one at the end), for runs whose stderr is not a terminal.
struct PlainLog {
    on: bool,
    frames: usize,
    start: Instant,
    last: Option<Instant>,
    updates: usize,
}

impl PlainLog {
    const EVERY: std::time::Duration = std::time::Duration::from_secs(5);

    fn new(on: bool, frames: usize) -> Self {
        Self {
            on,
            frames,
            start: Instant::now(),
            last: None,
            updates: 0,
        }
    }

    fn due(&mut self) -> bool {
        let now = Instant::now();
        let due = self.on && self.last.is_none_or(|t| now - t >= Self::EVERY);
        if due {
            self.last = Some(now);
        }
        due
    }

    fn iteration(&mut self, frame: usize, info: &IterInfo) {
        if self.due() {
            eprintln!(
                "[{:7.1} s] frame {}/{} {} iteration {}/{} loss {:.4}",
                self.start.elapsed().as_secs_f64(),
                frame + 1,
                self.frames,
                kind_label(info.kind),
                info.iter + 1,
                info.iters,
                info.loss
            );
        }
    }

    fn update(&mut self, r: &UpdateMetrics) {
        if self.on {
            self.last = Some(Instant::now());
            self.updates += 1;
            eprintln!(
                "[{:7.1} s] update {} ({}) at frame {}: PSNR {:.2} dB, SSIM {:.3}, Depth L1 {}, \
                 {} iterations in {:.1} s, {:.0} % of rays left the box unabsorbed",
                self.start.elapsed().as_secs_f64(),
                self.updates,
                r.kind,
                r.frame,
                r.psnr,
                r.ssim,
                r.depth_l1_cm
                    .map(|d| format!("{d:.1} cm"))
                    .unwrap_or_else(|| "-".into()),
                r.iters,
                r.seconds,
                100.0 * r.open_rays
            );
        }
    }

    fn done(&mut self, updates: usize, mapping_s: f64) {
        if self.on {
            eprintln!(
                "[{:7.1} s] mapping done: {updates} updates in {mapping_s:.1} s; evaluating and writing outputs",
                self.start.elapsed().as_secs_f64()
            );
        }
    }
}

/// Maps a sequence and writes every output into `opts.out`.
pub fn run_map(opts: &MapOptions) -> anyhow::Result<MapSummary> {
    let t_start = Instant::now();
    let cfg = &opts.config;
    cfg.validate()?;
    let lo = LoadOptions {
        start: opts.start,
        end: opts.end,
        stride: opts.stride.max(1),
        resize: opts.resize,
        crop_edge: 0,
        load_depth: true,
    };
    let ds = dataset::open_with(&opts.dataset, &lo, &opts.config.dataset)
        .with_context(|| format!("opening dataset {}", opts.dataset.display()))?;
    let k = ds.intrinsics();
    let n = ds.len();
    if opts.preflight {
        let t0 = Instant::now();
        for i in 0..n {
            ds.preflight(i).with_context(|| {
                format!("preflight of frame {i} of {n} (--no-preflight skips this check)")
            })?;
        }
        if opts.progress {
            eprintln!(
                "preflight: {n} frames' files and image headers checked in {:.1} s",
                t0.elapsed().as_secs_f64()
            );
        }
    }
    if n == 0 {
        bail!("the dataset selection has no frames");
    }
    // Online: the box and the initialisation know only the first frame's pose, which is the
    // first thing pushed (nothing here reads a later pose).
    let first = ds.pose(0);
    std::fs::create_dir_all(opts.out.join("renders"))
        .with_context(|| format!("creating {}", opts.out.display()))?;

    let choice: BackendChoice = opts.backend.parse()?;
    let decision = decide(choice);
    if opts.progress {
        eprintln!("backend: {}", decision.reason);
    }
    let start = start_map(cfg, &opts.dataset, &first, opts.threads, opts.progress)?;
    let (aabb, box_src, data) = (start.aabb, start.box_src, start.data);
    let store = ImageStore {
        width: k.width,
        height: k.height,
        slots: cfg.mapper_config()?.slots_needed(),
    };
    let mut ctx = RunContext {
        t_start,
        k,
        aabb,
        box_src,
        reason: decision.reason.clone(),
    };
    if decision.vulkan {
        match crate::select::vulkan_backend(&data, cfg.adam_config(), store) {
            Ok(backend) => return map_with(opts, ds.as_ref(), ctx, backend),
            // `auto` keeps going on the CPU when the device cannot take the model.
            Err(e) if choice == BackendChoice::Auto => {
                ctx.reason = format!(
                    "{}; the Vulkan backend failed ({e}), using the CPU",
                    ctx.reason
                );
                if opts.progress {
                    eprintln!("backend: {}", ctx.reason);
                }
            }
            Err(e) => {
                return Err(anyhow::Error::new(e))
                    .context("starting the Vulkan backend (--backend cpu runs without a GPU)")
            }
        }
    }
    let backend =
        ParallelCpuBackend::new(data, cfg.adam_config(), opts.threads)?.with_images(store);
    map_with(opts, ds.as_ref(), ctx, backend)
}

/// The start of an online mapping run: the scene box and where it came from, and the
/// initial model (geometric initialisation around the first camera).
pub struct MapStart {
    pub aabb: Aabb,
    pub box_src: &'static str,
    pub data: ModelData,
}

/// What a mapping run needs before its first frame, from the configuration, the dataset's
/// metadata and the first camera's pose only ([`Config::scene_bounds`], the memory check, the
/// geometric initialisation centred on the first camera). `himap map` and a caller driving
/// [`Mapper::push_frame`] itself start from this and get the same map.
pub fn start_map(
    cfg: &Config,
    dataset_dir: &std::path::Path,
    first: &Pose,
    threads: usize,
    print: bool,
) -> anyhow::Result<MapStart> {
    let (aabb, box_src) = cfg.scene_bounds(dataset_dir, first)?;
    check_map_memory(cfg, aabb, box_src, threads, print)?;
    let data = initial_data(cfg, aabb, Some(first.origin()))?;
    Ok(MapStart {
        aabb,
        box_src,
        data,
    })
}

/// Bytes the map of `aabb` takes on the CPU backend with `threads` workers: parameters and
/// Adam moments (3 x f32), and the gradient buffers (one i64 set per worker and the sum).
pub fn map_bytes(cfg: &Config, aabb: Aabb, threads: usize) -> anyhow::Result<(usize, u64, u64)> {
    let layout =
        ModelLayout::new(&cfg.model_config(aabb)?).map_err(|e| anyhow::anyhow!("model: {e}"))?;
    let workers = if threads == 0 {
        std::thread::available_parallelism().map_or(1, |n| n.get())
    } else {
        threads
    };
    let p = layout.param_count();
    Ok((p, p as u64 * 12, p as u64 * 8 * (workers as u64 + 1)))
}

/// Prints the map's memory for the box before anything is allocated, and refuses a map over
/// `scene.memory_budget_mb` with the settings that change it.
fn check_map_memory(
    cfg: &Config,
    aabb: Aabb,
    box_src: &str,
    threads: usize,
    print: bool,
) -> anyhow::Result<()> {
    let (p, state, grads) = map_bytes(cfg, aabb, threads)?;
    let mb = |b: u64| b as f64 / 1e6;
    let total = mb(state + grads);
    let e = aabb.extent();
    if print {
        eprintln!(
            "map: {p} parameters over the {:.2} x {:.2} x {:.2} m scene box ({box_src}): {:.0} MB \
             (parameters and Adam moments {:.0} MB, gradient buffers {:.0} MB)",
            e[0],
            e[1],
            e[2],
            total,
            mb(state),
            mb(grads)
        );
    }
    if total > cfg.scene.memory_budget_mb {
        bail!(
            "the map of the {:.2} x {:.2} x {:.2} m scene box ({box_src}) needs {total:.0} MB, over \
             scene.memory_budget_mb = {:.0}: give a smaller box (scene.min, scene.max), coarser \
             grids (model.geometry.cell_sizes, model.appearance.cell_sizes) or fewer channels, \
             or raise scene.memory_budget_mb",
            e[0],
            e[1],
            e[2],
            cfg.scene.memory_budget_mb
        );
    }
    Ok(())
}

/// What [`run_map`] computed before choosing the backend.
struct RunContext {
    t_start: Instant,
    k: Intrinsics,
    aabb: Aabb,
    box_src: &'static str,
    reason: String,
}

/// The mapping loop, evaluation and outputs of [`run_map`] on one backend.
fn map_with<B: MapBackend>(
    opts: &MapOptions,
    ds: &dyn crate::dataset::Dataset,
    ctx: RunContext,
    backend: B,
) -> anyhow::Result<MapSummary>
where
    B::Error: std::error::Error + Send + Sync + 'static,
{
    let RunContext {
        t_start,
        k,
        aabb,
        box_src,
        reason,
    } = ctx;
    let cfg = &opts.config;
    let n = ds.len();
    let backend_name = format!("{} ({reason})", backend.name());
    let threads = backend.threads();
    let params = backend.layout().param_count();
    let mcfg = cfg.mapper_config()?;
    let mut px = vec![PixelSample::default(); mcfg.pixels as usize];
    let mut res = vec![PixelResult::default(); mcfg.pixels as usize];
    let resumed = match &opts.resume {
        Some(path) => Some(checkpoint::load(
            path,
            cfg,
            &opts.dataset,
            n,
            (k.width, k.height),
            |m| (0..m).map(|i| Ok(ds.frame(i)?.pose)).collect(),
        )?),
        None => None,
    };
    let mut mapper = match &resumed {
        None => Mapper::new(backend, mcfg, k, &mut px, &mut res)
            .map_err(|e| anyhow::anyhow!("mapper: {e}"))?,
        Some((run, data)) => {
            let mut backend = backend;
            backend.import(data)?;
            for (g, lr) in Group::ALL.into_iter().zip(run.lrs()?) {
                backend.set_adam_lr(g, lr)?;
            }
            let state = run.mapper_state()?;
            let mut m = Mapper::restore(backend, mcfg, k, &mut px, &mut res, &state)
                .map_err(|e| anyhow::anyhow!("mapper: {e}"))?;
            // the images of the frames the mapper holds, back into their slots
            for e in state.held() {
                let frame = ds.frame(e.id as usize)?;
                m.backend_mut()
                    .upload_frame(e.slot, &pack_image(&frame.rgb))?;
            }
            if opts.progress {
                eprintln!(
                    "resuming after frame {} of {n} from {}",
                    run.pushed,
                    checkpoint::path_of(opts.resume.as_deref().unwrap_or(Path::new("."))).display()
                );
            }
            m
        }
    };

    let ek = {
        let w = ((k.width as f32 * cfg.eval.scale).round() as u32).max(1);
        let h = ((k.height as f32 * cfg.eval.scale).round() as u32).max(1);
        k.resized(w, h)
    };
    let expected_updates = if n >= mcfg.init_frames as usize {
        1 + (n - mcfg.init_frames as usize).div_ceil(mcfg.update_every as usize)
    } else {
        1
    };
    let render_every = (expected_updates / cfg.eval.renders.max(1) as usize).max(1);

    // metrics.csv: the header now, then rewritten whole (atomically) after every update, so a
    // run killed halfway keeps what it measured.
    let csv_path = opts.out.join("metrics.csv");
    let (mut rows, mut mapping_s, mut outside_box, start) = match &resumed {
        Some((run, _)) => (
            run.rows.clone(),
            run.mapping_s,
            run.outside_box,
            run.pushed as usize,
        ),
        None => (Vec::new(), 0.0f64, 0usize, 0usize),
    };
    write_metrics(&csv_path, &rows)?;
    // Without a terminal (a log file, a service) the progress bar draws nothing: plain lines
    // every few seconds instead.
    let plain = opts.progress && !std::io::stderr().is_terminal();
    let log = std::cell::RefCell::new(PlainLog::new(plain, n));
    let pb = if opts.progress && !plain {
        let pb = indicatif::ProgressBar::new(n as u64);
        pb.set_style(
            indicatif::ProgressStyle::with_template(
                "{elapsed_precise} [{bar:30}] frame {pos}/{len} {msg}",
            )
            .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar())
            .progress_chars("=> "),
        );
        pb
    } else {
        indicatif::ProgressBar::hidden()
    };
    let mut last_psnr = rows
        .iter()
        .rev()
        .map(|r| r.psnr)
        .find(|p| !p.is_nan())
        .unwrap_or(f64::NAN);
    let mut last_frame: Option<crate::dataset::Frame> = None;

    let handle = |mapper: &mut Mapper<'_, B>,
                  report: UpdateReport,
                  frame: &crate::dataset::Frame,
                  seconds: f64,
                  rows: &mut Vec<UpdateMetrics>,
                  last_psnr: &mut f64|
     -> anyhow::Result<()> {
        let u = rows.len();
        let eval = cfg.eval.every > 0 && u.is_multiple_of(cfg.eval.every as usize);
        let (mut psnr, mut ssim, mut dl1) = (f64::NAN, f64::NAN, None);
        if eval {
            let v = evaluate_view(mapper.backend_mut(), &ek, frame)?;
            (psnr, ssim, dl1) = (v.psnr, v.ssim, v.depth_l1_cm);
            if u.is_multiple_of(render_every) {
                let p = opts
                    .out
                    .join("renders")
                    .join(format!("frame{:06}.png", frame.index));
                write_render(&p, &v.input, &v.out, v.gt_depth.as_deref())?;
            }
            *last_psnr = psnr;
        }
        rows.push(UpdateMetrics {
            frame: frame.index,
            kind: match report.kind {
                UpdateKind::Init => "init".into(),
                UpdateKind::Online => "online".into(),
            },
            psnr,
            ssim,
            depth_l1_cm: dl1,
            loss_first: report.first.loss,
            loss: report.last.loss,
            color_loss: report.last.color_loss,
            warp_loss: report.last.warp_loss,
            warp_valid: report.last.warp_valid,
            open_rays: report.last.open_rays,
            window_keyframes: report.window_keyframes,
            iters: report.iters,
            seconds,
        });
        write_metrics(&csv_path, rows)?;
        if let Some(r) = rows.last() {
            log.borrow_mut().update(r);
        }
        Ok(())
    };

    // Poses of the frames pushed so far (the mesh level is measured over them after mapping).
    let mut poses: Vec<Pose> = Vec::with_capacity(n);
    for i in 0..start {
        poses.push(ds.frame(i)?.pose);
    }
    pb.set_position(start as u64);
    // Frames pushed at the last checkpoint this run wrote (named when the backend fails).
    let mut last_checkpoint: Option<usize> = None;
    let pushed = opts.stop_after.map_or(n, |s| s.min(n));
    for i in start..pushed {
        let frame = ds.frame(i)?;
        poses.push(frame.pose);
        let o = frame.pose.origin();
        if (0..3).any(|a| !(o[a] >= aabb.min[a] && o[a] <= aabb.max[a])) {
            if outside_box == 0 {
                pb.suspend(|| {
                    eprintln!(
                        "warning: frame {}: the camera ({:.2}, {:.2}, {:.2}) is outside the scene \
                         box ({box_src}) [{:.2}, {:.2}, {:.2}]..[{:.2}, {:.2}, {:.2}]; the map cannot \
                         hold what lies beyond the box: give a box that contains the path \
                         (scene.min, scene.max)",
                        frame.index,
                        o[0],
                        o[1],
                        o[2],
                        aabb.min[0],
                        aabb.min[1],
                        aabb.min[2],
                        aabb.max[0],
                        aabb.max[1],
                        aabb.max[2]
                    )
                });
            }
            outside_box += 1;
        }
        let rgba = pack_image(&frame.rgb);
        let t0 = Instant::now();
        let lp = last_psnr;
        let mut observe = |info: &IterInfo| {
            pb.set_message(format!(
                "{} it {}/{} loss {:.4} (c {:.4} w {:.4}) PSNR {:.2}",
                kind_label(info.kind),
                info.iter + 1,
                info.iters,
                info.loss,
                info.color_loss,
                info.warp_loss,
                lp
            ));
            if info.iter.is_multiple_of(10) {
                pb.tick();
            }
            if info.rejected {
                pb.suspend(|| {
                    eprintln!(
                        "warning: frame {}: {} iteration {}/{} was not finite (loss {}); \
                         skipped, parameters kept",
                        frame.index,
                        kind_label(info.kind),
                        info.iter + 1,
                        info.iters,
                        info.loss
                    )
                });
            }
            log.borrow_mut().iteration(i, info);
        };
        let rep = mapper
            .push_frame_observed(&rgba, frame.pose, &mut observe)
            .map_err(|e| {
                let at = format!("frame {}", frame.index);
                mid_run_error(e, &at, &backend_name, last_checkpoint, opts)
            })?;
        let dt = t0.elapsed().as_secs_f64();
        if let Some(r) = rep {
            mapping_s += dt;
            handle(&mut mapper, r, &frame, dt, &mut rows, &mut last_psnr)?;
        }
        pb.inc(1);
        last_frame = Some(frame);
        if opts.checkpoint_every > 0 && (i + 1).is_multiple_of(opts.checkpoint_every) {
            let id = DatasetId::new(&opts.dataset, n, k.width, k.height, &poses);
            let lrs = Group::ALL.map(|g| mapper.backend().adam_lr(g));
            let run = RunState::new(cfg, id, &mapper.state(), lrs, &rows, outside_box, mapping_s);
            let data = mapper.backend_mut().export()?;
            checkpoint::save(&opts.out, cfg, &data, &run)?;
            last_checkpoint = Some(i + 1);
        }
    }
    if let Some(frame) = last_frame.filter(|_| pushed == n) {
        let t0 = Instant::now();
        if let Some(r) = mapper.flush(&mut |_: &IterInfo| {}).map_err(|e| {
            mid_run_error(e, "the final update", &backend_name, last_checkpoint, opts)
        })? {
            let dt = t0.elapsed().as_secs_f64();
            mapping_s += dt;
            handle(&mut mapper, r, &frame, dt, &mut rows, &mut last_psnr)?;
        }
    }
    pb.finish_and_clear();
    let iterations = mapper.iterations();
    let (rejected_steps, lr_reductions) = (mapper.rejected_steps(), mapper.lr_reductions());
    if lr_reductions > 0 {
        eprintln!(
            "warning: {rejected_steps} mapping steps were not finite; the learning rates were \
             lowered {lr_reductions} times (mapper.rejected_lr_after / rejected_lr_factor)"
        );
    }

    log.borrow_mut().done(rows.len(), mapping_s);

    let mut backend = mapper.into_backend();
    let fin = final_map_eval(&mut backend, ds, &ek, cfg.eval.final_every as usize)?;
    if opts.progress {
        eprintln!(
            "final map over {} frames of the sequence: PSNR {} dB, SSIM {}, Depth L1 {} cm",
            fin.frames,
            fmt_opt(fin.psnr, 2),
            fmt_opt(fin.ssim, 3),
            fmt_opt(fin.depth_l1_cm, 2)
        );
    }
    // mesh
    let beta = {
        let mut b = [0.0f32; 1];
        backend.read_params(Group::Beta, &mut b)?;
        b[0]
    };
    let mesh_level = match cfg.eval.mesh_level {
        Some(l) => l,
        None => {
            let lk = ek.resized((ek.width / 2).max(1), (ek.height / 2).max(1));
            rendered_surface_level(&mut backend, &lk, &poses, 8)?
                .unwrap_or_else(|| cfg.surface_level(beta))
        }
    };
    // The observed scene: the mapped views' rendered depth bounds the extraction region
    // (mesh_full.ply) and culls it to what some view saw (mesh.ply).
    let views = observed_views(&mut backend, &k, &poses, OBSERVED_VIEWS)?;
    let region = observed_region(&views, aabb, 2.0 * cfg.eval.mesh_resolution).unwrap_or(aabb);
    let full = map_mesh(&mut backend, region, cfg.eval.mesh_resolution, mesh_level)?;
    full.write_ply(&opts.out.join("mesh_full.ply"))?;
    let mesh = crate::eval::cull_mesh(
        &full,
        views.iter().map(|(k, p, d)| (*k, *p, Some(d.as_slice()))),
        Some(cfg.eval.observed_margin),
    );
    if opts.progress {
        eprintln!(
            "mesh: {} faces over the observed region, {} seen by the mapped views (mesh.ply; \
             mesh_full.ply keeps all)",
            full.faces.len(),
            mesh.faces.len()
        );
    }
    let mesh_path = opts.out.join("mesh.ply");
    mesh.write_ply(&mesh_path)?;
    let has_gt = opts.dataset.join("gt_mesh.ply").is_file() || ds.has_depth();
    let (mesh_metrics, mesh_gt, mesh_err) = if has_gt && !mesh.faces.is_empty() {
        use crate::eval::{Culling, EvalOptions};
        let gt_mesh = opts.dataset.join("gt_mesh.ply").is_file();
        let culling = match cfg.eval.cull.as_str() {
            "none" => Culling::None,
            "frustum" => Culling::Frustum,
            "occlusion" => Culling::FrustumOcclusion,
            _ if gt_mesh => Culling::None,
            _ => Culling::Frustum,
        };
        let eo = EvalOptions {
            n_samples: cfg.eval.mesh_samples,
            culling,
            dataset: cfg.dataset.clone(),
            ..EvalOptions::default()
        };
        match crate::eval::eval_report(&mesh_path, &opts.dataset, &eo) {
            Ok(r) => (Some(r.metrics), Some(r.gt_kind), None),
            Err(e) => (None, None, Some(format!("{e:#}"))),
        }
    } else if has_gt {
        (None, None, Some("empty reconstruction".to_string()))
    } else {
        (None, None, None)
    };

    let data = backend.export()?;
    save_map(&opts.out.join("map.safetensors"), cfg, &data)?;

    let summary = MapSummary {
        dataset: opts.dataset.clone(),
        frames: n,
        width: k.width,
        height: k.height,
        backend: backend_name,
        threads,
        scene_box: [aabb.min, aabb.max],
        scene_box_source: box_src.to_string(),
        updates: rows.len(),
        iterations,
        rejected_steps,
        lr_reductions,
        mean_psnr: mean(rows.iter().map(|r| r.psnr)),
        mean_ssim: mean(rows.iter().map(|r| r.ssim)),
        mean_depth_l1_cm: mean(rows.iter().filter_map(|r| r.depth_l1_cm)),
        frames_outside_box: outside_box,
        final_frames: fin.frames,
        final_psnr: fin.psnr,
        final_ssim: fin.ssim,
        final_depth_l1_cm: fin.depth_l1_cm,
        final_per_frame: fin.per_frame,
        mesh: mesh_metrics,
        mesh_ground_truth: mesh_gt,
        mesh_error: mesh_err,
        mesh_faces: mesh.faces.len(),
        mesh_full_faces: full.faces.len(),
        mesh_level,
        beta,
        seconds_total: t_start.elapsed().as_secs_f64(),
        seconds_mapping: mapping_s,
        seconds_per_iteration: mapping_s / iterations.max(1) as f64,
        seconds_per_frame: mapping_s / n.max(1) as f64,
        parameters: params,
        config: cfg.clone(),
    };
    let sp = opts.out.join("summary.json");
    crate::atomic::write_bytes_atomic(&sp, serde_json::to_string_pretty(&summary)?.as_bytes())?;
    Ok(summary)
}

/// A frame's view rendered from the map at `ek` and compared with the frame.
struct ViewEval {
    out: Vec<RayResult>,
    input: crate::dataset::RgbImage,
    gt_depth: Option<Vec<f32>>,
    psnr: f64,
    ssim: f64,
    depth_l1_cm: Option<f64>,
}

/// Renders `frame`'s view at `ek` and computes PSNR, SSIM and (with a depth) Depth L1.
fn evaluate_view<B: Backend>(
    backend: &mut B,
    ek: &Intrinsics,
    frame: &crate::dataset::Frame,
) -> anyhow::Result<ViewEval>
where
    B::Error: std::error::Error + Send + Sync + 'static,
{
    let out = render_view(backend, ek, &frame.pose)?;
    let input = frame.rgb.resized(ek.width, ek.height);
    let rendered: Vec<f32> = out.iter().flat_map(|r| r.color).collect();
    let psnr = crate::metrics::psnr(&rendered, &input.data);
    let ssim = crate::metrics::ssim(
        &rendered,
        &input.data,
        ek.width as usize,
        ek.height as usize,
    );
    let gt_depth = frame
        .depth
        .as_ref()
        .map(|d| d.resized(ek.width, ek.height).data);
    let depth_l1_cm = gt_depth.as_ref().and_then(|g| {
        let depth: Vec<f32> = out.iter().map(|r| r.depth).collect();
        crate::metrics::depth_l1_cm(&depth, g)
    });
    Ok(ViewEval {
        out,
        input,
        gt_depth,
        psnr,
        ssim,
        depth_l1_cm,
    })
}

/// A mapping failure mid-run (`at`: the frame or the final update): the backend's own error
/// stays in the chain (a GPU failure exits with code 3), with the backend named and the way
/// to go on. The mapper's state inside a failed update is partial, so no checkpoint is
/// written then: the last periodic one (`--checkpoint-every`) is what a run resumes from.
fn mid_run_error<E: std::error::Error + Send + Sync + 'static>(
    e: MapperError<E>,
    at: &str,
    backend: &str,
    last_checkpoint: Option<usize>,
    opts: &MapOptions,
) -> anyhow::Error {
    let hint = match last_checkpoint {
        Some(f) => format!(
            "the last checkpoint (after {f} frames) is {}: continue with `--resume {}` (also \
             on another backend, e.g. `--backend cpu`: the same bits)",
            opts.out.join(checkpoint::FILE).display(),
            opts.out.display()
        ),
        None if opts.checkpoint_every == 0 => {
            "no checkpoint was kept: `--checkpoint-every N` keeps one to resume from".into()
        }
        None => "no checkpoint was written yet".into(),
    };
    match e {
        MapperError::Backend(e) => {
            anyhow::Error::new(e).context(format!("{at}: the {backend} backend failed; {hint}"))
        }
        MapperError::Core(e) => anyhow::anyhow!("{at}: mapper: {e}"),
    }
}

/// Averages of the final map re-rendered over the sequence.
struct FinalEval {
    frames: usize,
    psnr: Option<f64>,
    ssim: Option<f64>,
    depth_l1_cm: Option<f64>,
    per_frame: Vec<FinalFrame>,
}

/// One frame of the final-map evaluation (`summary.json`: `final_per_frame`), so that
/// forgetting shows where along the sequence it happens.
#[derive(Clone, Debug, Serialize)]
pub struct FinalFrame {
    pub frame: usize,
    pub psnr: f64,
    pub ssim: f64,
    pub depth_l1_cm: Option<f64>,
}

/// Renders frames 0, k, 2k, ... of `ds` from the map in `backend` at `ek` (after mapping: the
/// evaluation may read any frame) and averages PSNR, SSIM and Depth L1 over them.
fn final_map_eval<B: Backend>(
    backend: &mut B,
    ds: &dyn crate::dataset::Dataset,
    ek: &Intrinsics,
    every: usize,
) -> anyhow::Result<FinalEval>
where
    B::Error: std::error::Error + Send + Sync + 'static,
{
    let mut per_frame = Vec::new();
    if every > 0 {
        for i in (0..ds.len()).step_by(every) {
            let v = evaluate_view(backend, ek, &ds.frame(i)?)?;
            per_frame.push(FinalFrame {
                frame: i,
                psnr: v.psnr,
                ssim: v.ssim,
                depth_l1_cm: v.depth_l1_cm,
            });
        }
    }
    Ok(FinalEval {
        frames: per_frame.len(),
        psnr: mean(per_frame.iter().map(|f| f.psnr)),
        ssim: mean(per_frame.iter().map(|f| f.ssim)),
        depth_l1_cm: mean(per_frame.iter().filter_map(|f| f.depth_l1_cm)),
        per_frame,
    })
}

fn fmt_opt(x: Option<f64>, digits: usize) -> String {
    x.map(|v| format!("{v:.digits$}"))
        .unwrap_or_else(|| "-".into())
}

/// The SDF level of the surfaces the field renders, estimated without ground truth: `views`
/// poses spread over the sequence are rendered at `k`; every pixel with opacity > 0.9 gives
/// the point at its rendered depth (normalised by the opacity), and the level is the median
/// SDF over these points. `None` when no pixel is opaque. Hi-Map's density proxy has no
/// `delta t`, so where the field draws its surfaces depends on beta and on the sample spacing
/// (not only on the zero crossing); this is the level `mesh.ply` is extracted at by default.
pub fn rendered_surface_level<B: MapBackend>(
    backend: &mut B,
    k: &Intrinsics,
    poses: &[Pose],
    views: usize,
) -> anyhow::Result<Option<f32>>
where
    B::Error: std::error::Error + Send + Sync + 'static,
{
    if poses.is_empty() || views == 0 {
        return Ok(None);
    }
    let mut pts = Vec::new();
    for v in 0..views {
        let pose = &poses[(v * poses.len()) / views];
        let out = render_view(backend, k, pose)?;
        for (i, r) in out.iter().enumerate() {
            if r.opacity > 0.9 && r.depth > 0.0 && r.depth.is_finite() {
                let (u, w) = ((i % k.width as usize) as f32, (i / k.width as usize) as f32);
                let (o, d) = pose.ray(k, u, w);
                let t = r.depth / r.opacity;
                pts.push([o[0] + t * d[0], o[1] + t * d[1], o[2] + t * d[2]]);
            }
        }
    }
    if pts.is_empty() {
        return Ok(None);
    }
    let mut sdf = vec![0.0f32; pts.len()];
    backend.query_sdf(&pts, &mut sdf)?;
    sdf.sort_by(f32::total_cmp);
    Ok(Some(sdf[sdf.len() / 2]))
}

/// Marching cubes on the SDF of `backend` minus `level`, with vertex colours.
pub fn map_mesh<B: MapBackend>(
    backend: &mut B,
    aabb: Aabb,
    resolution: f32,
    level: f32,
) -> anyhow::Result<crate::mesh::Mesh> {
    let backend = std::cell::RefCell::new(backend);
    let query_error = std::cell::RefCell::new(None::<anyhow::Error>);
    let mesh = crate::mesh::extract_mesh(
        aabb,
        resolution,
        |p: &[[f32; 3]]| {
            let mut o = vec![0.0; p.len()];
            if let Err(e) = backend.borrow_mut().query_sdf(p, &mut o) {
                query_error.borrow_mut().get_or_insert(e);
            }
            for x in &mut o {
                *x -= level;
            }
            o
        },
        Some(|p: &[[f32; 3]]| {
            let mut o = vec![[0.0; 3]; p.len()];
            if let Err(e) = backend.borrow_mut().query_color(p, &mut o) {
                query_error.borrow_mut().get_or_insert(e);
            }
            o
        }),
    );
    match query_error.into_inner() {
        Some(e) => Err(e.context("querying the field for the mesh")),
        None => Ok(mesh),
    }
}

/// Views of the pushed frames [`observed_views`] renders for the observed region.
const OBSERVED_VIEWS: usize = 96;

/// Renders the depth of up to `max_views` of `poses` (spread evenly) from the map at a
/// quarter of `k`'s resolution (at least 64 px wide); a pixel with opacity below 0.5 gets depth
/// 0 (nothing seen), others `D / O`.
pub fn observed_views<B: Backend>(
    backend: &mut B,
    k: &Intrinsics,
    poses: &[Pose],
    max_views: usize,
) -> anyhow::Result<Vec<(Intrinsics, Pose, Vec<f32>)>>
where
    B::Error: std::error::Error + Send + Sync + 'static,
{
    let w = (k.width / 4).max(64.min(k.width));
    let h = ((k.height as u64 * w as u64) / k.width.max(1) as u64).max(1) as u32;
    let lk = k.resized(w, h);
    let n = poses.len().min(max_views);
    let mut out = Vec::with_capacity(n);
    for v in 0..n {
        let pose = poses[v * poses.len() / n];
        let r = render_view(backend, &lk, &pose)?;
        let d = r
            .iter()
            .map(|r| {
                if r.opacity >= 0.5 && r.depth.is_finite() {
                    r.depth / r.opacity
                } else {
                    0.0
                }
            })
            .collect();
        out.push((lk, pose, d));
    }
    Ok(out)
}

/// The box around the views' cameras and rendered surface points, grown by `margin` and cut
/// to `aabb`; `None` when it is empty.
pub fn observed_region(
    views: &[(Intrinsics, Pose, Vec<f32>)],
    aabb: Aabb,
    margin: f32,
) -> Option<Aabb> {
    let mut lo = [f32::INFINITY; 3];
    let mut hi = [f32::NEG_INFINITY; 3];
    let mut add = |p: [f32; 3]| {
        for a in 0..3 {
            lo[a] = lo[a].min(p[a]);
            hi[a] = hi[a].max(p[a]);
        }
    };
    for (k, pose, depth) in views {
        add(pose.origin());
        for (i, &d) in depth.iter().enumerate() {
            if d > 0.0 {
                let (u, v) = ((i % k.width as usize) as f32, (i / k.width as usize) as f32);
                add(pose.transform(k.direction(u, v).map(|x| x * d)));
            }
        }
    }
    let b = Aabb::new(
        [0, 1, 2].map(|a| (lo[a] - margin).max(aabb.min[a])),
        [0, 1, 2].map(|a| (hi[a] + margin).min(aabb.max[a])),
    );
    b.is_valid().then_some(b)
}

/// `himap mesh`: extracts the mesh of a saved map at `resolution` (default: its
/// configuration's) and SDF `level` (default: [`Config::surface_level`]) into `out`.
/// Returns the face count and the level used.
pub fn mesh_saved_map(
    map: &Path,
    out: &Path,
    resolution: Option<f32>,
    level: Option<f32>,
    threads: usize,
) -> anyhow::Result<(usize, f32)> {
    let (cfg, data) = load_map(map)?;
    let aabb = data.layout.config.aabb;
    let beta = data.params[Group::Beta as usize][0];
    let level = level.unwrap_or_else(|| cfg.surface_level(beta));
    let mut backend = ParallelCpuBackend::new(data, cfg.adam_config(), threads)?;
    let mesh = map_mesh(
        &mut backend,
        aabb,
        resolution.unwrap_or(cfg.eval.mesh_resolution),
        level,
    )?;
    mesh.write_ply(out)?;
    Ok((mesh.faces.len(), level))
}

/// Prints a short table of a summary.
pub fn summary_table(s: &MapSummary) -> String {
    let f = |x: Option<f64>, p: usize| x.map(|v| format!("{v:.p$}")).unwrap_or("-".into());
    let mut t = String::new();
    t += &format!(
        "{} frames {}x{}, {} updates, {} iterations, backend {}\n",
        s.frames, s.width, s.height, s.updates, s.iterations, s.backend
    );
    t += &format!(
        "PSNR {} dB | SSIM {} | Depth L1 {} cm\n",
        f(s.mean_psnr, 2),
        f(s.mean_ssim, 3),
        f(s.mean_depth_l1_cm, 2)
    );
    if s.final_frames > 0 {
        t += &format!(
            "final map over {} frames of the sequence: PSNR {} dB | SSIM {} | Depth L1 {} cm\n",
            s.final_frames,
            f(s.final_psnr, 2),
            f(s.final_ssim, 3),
            f(s.final_depth_l1_cm, 2)
        );
    }
    match &s.mesh {
        Some(m) => {
            t += &format!(
                "mesh ({} faces, level {:.3} m) vs {}: Accuracy {:.2} cm | Completion {:.2} cm | Completion ratio {:.1} %\n",
                s.mesh_faces,
                s.mesh_level,
                s.mesh_ground_truth.as_deref().unwrap_or("?"),
                m.accuracy_cm,
                m.completion_cm,
                m.completion_ratio_pct
            )
        }
        None => {
            t += &format!(
                "mesh ({} faces): {}\n",
                s.mesh_faces,
                s.mesh_error.as_deref().unwrap_or("no ground truth")
            )
        }
    }
    t += &format!(
        "time {:.1} s total, mapping {:.1} s ({:.1} ms per iteration, {:.2} s per frame)",
        s.seconds_total,
        s.seconds_mapping,
        1e3 * s.seconds_per_iteration,
        s.seconds_per_frame
    );
    t
}

/// `himap demo`: synthesises a small room (into `out`, else a temporary directory), maps it
/// with `config` and returns the summary.
pub fn run_demo(
    out: Option<&Path>,
    config: Config,
    frames: usize,
    size: (u32, u32),
    threads: usize,
    backend: &str,
    progress: bool,
) -> anyhow::Result<(MapSummary, PathBuf)> {
    let root = match out {
        Some(p) => p.to_path_buf(),
        None => std::env::temp_dir().join(format!("himap-demo-{}", std::process::id())),
    };
    let data = root.join("room");
    let synth = crate::synth::SynthOptions {
        frames,
        width: size.0,
        height: size.1,
        seed: config.seed,
    };
    crate::synth::write_synthetic(&data, &synth)
        .with_context(|| format!("writing the synthetic room to {}", data.display()))?;
    let opts = MapOptions {
        backend: backend.to_string(),
        progress,
        ..MapOptions::new(data, root.join("map"), config, threads)
    };
    let s = run_map(&opts)?;
    Ok((s, opts.out))
}
