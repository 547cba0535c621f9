//! `himap map` and `himap demo`: replay a posed sequence through the core's [`Mapper`] on the
//! multi-threaded CPU backend, evaluate after every mapping update, and write the outputs:
//! `metrics.csv`, `summary.json`, `mesh.ply`, `renders/`, `map.safetensors`, `metrics.png`,
//! `report.html`.
//!
//! Evaluation after an update renders the update's newest frame at `eval.scale` of the input
//! resolution (bin-centre samples, no jitter) and compares it with the input image resized the
//! same way (PSNR, SSIM) and, when the dataset has depth, with the ground-truth depth (Depth L1
//! in cm over the pixels with valid depth).
//!
//! Files: [`setup`] (backend, initial map, memory), [`run`] (the mapping loop), [`evaluate`]
//! (per-update and final-map evaluation), [`surface`] (mesh level, observed region, mesh),
//! [`report`] (metrics, log lines, renders, summary), [`plots`] (`metrics.png`,
//! `report.html`), [`persist`] (`map.safetensors`),
//! [`demo`].

use std::collections::HashMap;
use std::io::{IsTerminal, Write};
use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{bail, Context};
use himap_core::camera::{Intrinsics, Pose};
use himap_core::field::model::{Group, ModelLayout, Ray, RayResult};
use himap_core::mapper::{view_rays, IterInfo, Mapper, MapperError, UpdateKind, UpdateReport};
use himap_core::train::backend::{Backend, ImageStore};
use himap_core::train::pixel::{pack_rgba8, PixelResult, PixelSample};
use himap_core::Aabb;
use serde::{Deserialize, Serialize};

use crate::backend::{ModelData, ParallelCpuBackend};
use crate::checkpoint::{self, DatasetId, RunState};
use crate::config::Config;
use crate::dataset::{self, LoadOptions, RgbImage};
use crate::select::{decide, BackendChoice, MapBackend};

mod demo;
mod evaluate;
mod live;
mod persist;
mod plots;
mod report;
mod run;
mod setup;
mod surface;

pub use demo::*;
pub use evaluate::*;
pub use live::*;
pub use persist::*;
pub use plots::*;
pub use report::*;
use run::*;
pub use setup::*;
pub use surface::*;

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
    /// The live view (Rerun viewer or `.rrd` file; cargo feature `rerun`).
    pub live: LiveOptions,
    /// Time the Vulkan backend's passes (timestamp queries) and print the mapping's per-pass
    /// table after the last update (steps are then waited for one by one, not queued).
    pub profile: bool,
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
            live: LiveOptions::default(),
            profile: false,
        }
    }
}

/// Maps a sequence and writes every output into `opts.out`.
pub fn run_map(opts: &MapOptions) -> anyhow::Result<MapSummary> {
    let t_start = Instant::now();
    let cfg = &opts.config;
    cfg.validate()?;
    if opts.live.enabled() && !cfg!(feature = "rerun") {
        // before anything is read or allocated
        LiveView::start(&opts.live)?;
    }
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
    let max_w = opts.config.dataset.max_width;
    if opts.progress && opts.resize.is_none() && max_w > 0 && k.width == max_w {
        println!(
            "frames mapped at {}x{} (at most dataset.max_width = {max_w} wide; --resize WxH or \
             dataset.max_width = 0 for another size)",
            k.width, k.height
        );
    }
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
        let m = &cfg.mapper;
        let window = m.local_frames + m.window_keyframes + m.global_keyframes;
        let started =
            crate::select::vulkan_backend(&data, cfg.adam_config(), store).and_then(|b| {
                // A device that cuts loops (llvmpipe) could not run this window's warping pass
                // exactly: refuse now rather than at the first mapping step.
                let needed = himap_core::gpu_abi::pixel_train_loop_bound(window);
                match b.loop_budget() {
                    Some(budget) if needed > budget => Err(himap_vulkan::VulkanError::LoopBudget {
                        what: format!("the warping pass over the {window}-frame mapping window"),
                        needed,
                        budget,
                    }),
                    _ => Ok(b),
                }
            });
        let started = started.and_then(|mut b| {
            if opts.profile && !b.enable_profiling()? {
                eprintln!("profile: the device has no timestamps; only transfers are timed");
            }
            Ok(b)
        });
        match started {
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
