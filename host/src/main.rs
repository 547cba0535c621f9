//! The `himap` command line.

use std::path::PathBuf;

use anyhow::Context;
use clap::{Args, Parser, Subcommand};
use himap::dump::DumpOptions;

#[derive(Parser)]
#[command(
    name = "himap",
    version,
    about = "Monocular dense mapping with a hierarchical factorized radiance field (Hi-Map)"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Map a posed RGB sequence (Replica or TUM layout) and write metrics.csv, summary.json,
    /// mesh.ply, renders/ and map.safetensors into --out.
    Map(MapArgs),
    /// Synthesise a small room, map it with the demo preset (`small` with 20 online iterations and no early termination), evaluate and print a table.
    Demo(DemoArgs),
    /// List the Vulkan devices with their limits and the features the backend needs.
    Devices(DevicesArgs),
    /// Throughput of each backend present: forward and forward+backward samples/s, ms per
    /// training step at the small and the paper configuration, memory used.
    Bench(BenchArgs),
    /// Extract the mesh of a saved map (map.safetensors of `himap map`).
    Mesh(MeshArgs),
    /// Train a small field on a built-in analytic target and print the loss going down.
    TrainDemo(TrainDemoArgs),
    /// Write a synthetic Replica-layout sequence (colour, exact depth, poses, intrinsics) plus
    /// its ground-truth mesh `gt_mesh.ply`: a procedural room orbited from its middle, or a
    /// house of three rooms with doors walked through from one end to the other (at least
    /// 25 m; no scene box is written, so mapping it uses the default box policy).
    Synth(SynthArgs),
    /// Mesh metrics as the paper reports them: Accuracy and Completion (cm), Completion ratio
    /// (% of ground-truth points within 5 cm), from area-weighted surface samples.
    Eval(EvalArgs),
    /// Diagnostic (reads ground truth): does the warping loss find the true depth? Sweeps the
    /// loss along the ray of sampled pixels with ground-truth depth (0.5x..2x) in windows of
    /// consecutive frames and prints how often its minimum is at the truth; with --map, also
    /// whether the truth scores lower than the map's rendered depth.
    WarpCheck(WarpCheckArgs),
    /// Run one training step of a small model on random rays and write every input, output
    /// and gradient to a safetensors file (see the README for the tensor names and formulas).
    DumpStep(DumpStepArgs),
}

#[derive(Args)]
struct MapArgs {
    /// Dataset folder.
    dataset: PathBuf,
    #[arg(long)]
    out: PathBuf,
    /// Configuration file (TOML; missing fields take the preset's values). May be given
    /// several times: the files are laid over the preset in order, a later file's values win
    /// (e.g. a dataset's scene box and camera, then an experiment's settings).
    #[arg(long)]
    config: Vec<PathBuf>,
    /// Preset: small (2-core CPU), paper, or demo (`himap demo`'s: small with the 20-iteration schedule without early termination and with 4 warping views).
    #[arg(long, default_value = "small")]
    preset: String,
    /// Backend: cpu (multi-threaded), vulkan, or auto (a Vulkan GPU when one is usable,
    /// else the CPU; it says which it chose).
    #[arg(long, default_value = "auto")]
    backend: String,
    /// Frame selection start:end:stride over the source frames (e.g. 0:100:2).
    #[arg(long)]
    frames: Option<String>,
    /// Resize the images to WxH (e.g. 320x240).
    #[arg(long)]
    resize: Option<String>,
    /// Worker threads (0 = all cores).
    #[arg(long, default_value_t = 0)]
    threads: usize,
    /// Skip the preflight (every frame's files and image headers are checked before the
    /// first iteration, so a broken frame fails in the first second, not at its turn).
    #[arg(long)]
    no_preflight: bool,
    /// Write OUT/checkpoint.safetensors (map, Adam state, mapper state, metrics so far)
    /// after every N pushed frames, atomically (0 = never).
    #[arg(long, value_name = "N", default_value_t = 0)]
    checkpoint_every: usize,
    /// Continue an interrupted run from its checkpoint (the file, or the folder holding
    /// checkpoint.safetensors) with the same dataset, frames and configuration; the
    /// result equals the uninterrupted run bit for bit.
    #[arg(long, value_name = "DIR")]
    resume: Option<PathBuf>,
    /// Time the Vulkan backend's passes (timestamp queries) and print the mapping's per-pass
    /// table after the last update; steps then run one at a time instead of queued.
    #[arg(long)]
    profile: bool,
    /// Print the effective configuration (TOML) and exit.
    #[arg(long)]
    print_config: bool,
    /// Live view in the Rerun viewer: spawn one (or use the one already listening), or
    /// connect to URL (rerun+http://HOST:PORT/proxy). Needs `--features rerun`.
    #[arg(long, value_name = "URL", num_args = 0..=1, default_missing_value = "")]
    rerun: Option<String>,
    /// Write the live view's recording to FILE (.rrd; open with `rerun FILE`). Needs
    /// `--features rerun`.
    #[arg(long, value_name = "FILE")]
    rerun_save: Option<PathBuf>,
    /// Log the observed mesh to the live view after every N updates (0 = only the final one).
    #[arg(long, value_name = "N", default_value_t = 10)]
    rerun_mesh_every: usize,
}

#[derive(Args)]
struct DemoArgs {
    /// Keep the room and the outputs here (default: a temporary directory).
    #[arg(long)]
    out: Option<PathBuf>,
    /// Frames of the synthetic sequence.
    #[arg(long, default_value_t = 60)]
    frames: usize,
    /// Image size WxH.
    #[arg(long, default_value = "128x96")]
    size: String,
    /// Configuration file laid over the demo preset (default: the demo preset).
    #[arg(long)]
    config: Option<PathBuf>,
    /// Worker threads (0 = all cores).
    #[arg(long, default_value_t = 0)]
    threads: usize,
    /// Backend: cpu, vulkan or auto.
    #[arg(long, default_value = "auto")]
    backend: String,
}

#[derive(Args)]
struct BenchArgs {
    /// Rays per step.
    #[arg(long, default_value_t = 2048)]
    rays: usize,
    /// Timed steps per measurement (after one warm-up step).
    #[arg(long, default_value_t = 3)]
    steps: usize,
    /// Report the fastest of the timed steps instead of their mean (for side-by-side
    /// comparisons on a machine whose load comes and goes).
    #[arg(long)]
    fastest: bool,
    /// Backends to measure: cpu, vulkan or all.
    #[arg(long, default_value = "all")]
    backend: String,
    /// Configurations: small, paper, step (the paper's model over a 4 m cube, 64 samples
    /// per ray: the step `scripts/bench_step_torch.py` times) or all.
    #[arg(long, default_value = "all")]
    config: String,
    /// CPU worker threads (0 = all cores).
    #[arg(long, default_value_t = 0)]
    threads: usize,
    /// Time each pass of the Vulkan backend's training step (Vulkan timestamp queries;
    /// transfers timed on the host) and print its share of the step.
    #[arg(long)]
    profile: bool,
}

#[derive(Args)]
struct MeshArgs {
    /// The map file.
    #[arg(long)]
    map: PathBuf,
    /// Output PLY.
    #[arg(long)]
    out: PathBuf,
    /// Marching-cubes spacing in metres (default: the map's eval.mesh_resolution; with
    /// --observed, the seen surfaces again on eval.mesh_refine's finer grid, as `himap map`
    /// writes mesh.ply, unless this is given).
    #[arg(long)]
    resolution: Option<f32>,
    /// SDF level of the surface (default: the renderer's surface level for the map's beta).
    #[arg(long, allow_hyphen_values = true)]
    level: Option<f32>,
    /// Worker threads (0 = all cores).
    #[arg(long, default_value_t = 0)]
    threads: usize,
    /// Cut the mesh to what this dataset's frames saw, as `himap map` cuts `mesh.ply` (the
    /// observed region, the rendered depth of up to `eval.observed_views` of its frames; the level from their
    /// renders unless --level is given).
    #[arg(long)]
    observed: Option<PathBuf>,
    /// With --observed: the size the map was made at (WxH), as `himap map --resize`.
    #[arg(long)]
    resize: Option<String>,
}

#[derive(Args)]
struct TrainDemoArgs {
    /// Training steps.
    #[arg(long, default_value_t = 300)]
    steps: usize,
    /// Rays per step.
    #[arg(long, default_value_t = 512)]
    rays: usize,
    /// Worker threads (0 = all cores).
    #[arg(long, default_value_t = 0)]
    threads: usize,
    #[arg(long, default_value_t = 0)]
    seed: u64,
}

#[derive(Args)]
struct SynthArgs {
    #[arg(long)]
    out: PathBuf,
    /// room, house or hall (two 8-9 m halls: views beyond 6 m, a walk that grows the default
    /// box).
    #[arg(long, default_value = "room")]
    scene: String,
    /// Frames (default: 60 for the room, 360 for the house).
    #[arg(long)]
    frames: Option<usize>,
    /// Image width (default: 160 for the room, 320 for the house and the hall, the size
    /// their measurements use).
    #[arg(long)]
    width: Option<u32>,
    /// Image height (default: 120 for the room, 240 for the house and the hall).
    #[arg(long)]
    height: Option<u32>,
    #[arg(long, default_value_t = 0)]
    seed: u64,
}

#[derive(Args)]
struct EvalArgs {
    /// Reconstructed mesh (PLY).
    #[arg(long)]
    mesh: PathBuf,
    /// Ground truth: a mesh PLY, or a dataset directory (its gt_mesh.ply, else its
    /// back-projected ground-truth depth).
    #[arg(long)]
    gt: PathBuf,
    /// Also write the report as JSON.
    #[arg(long)]
    json: Option<PathBuf>,
    /// Surface samples per mesh.
    #[arg(long, default_value_t = 200_000)]
    samples: usize,
    /// Culling of the reconstruction by the dataset's cameras: none, frustum, occlusion.
    #[arg(long, default_value = "none")]
    cull: String,
    /// Culling of the ground-truth mesh by the same cameras (none, frustum, occlusion): the
    /// "observed ground truth", what the sequence's frames see (a dataset with gt_mesh.ply).
    #[arg(long, default_value = "none")]
    gt_cull: String,
    /// A configuration whose [dataset] section says how to read the ground-truth dataset
    /// (its cameras; the one the map was made with).
    #[arg(long)]
    config: Option<PathBuf>,
}

#[derive(Args)]
struct WarpCheckArgs {
    /// Dataset folder (with depth).
    dataset: PathBuf,
    /// Configuration (warp settings); ignored with --map (the map's own is used).
    #[arg(long)]
    config: Option<PathBuf>,
    /// A map.safetensors of `himap map` on this dataset.
    #[arg(long)]
    map: Option<PathBuf>,
    #[arg(long)]
    frames: Option<String>,
    #[arg(long)]
    resize: Option<String>,
    /// Frames per window.
    #[arg(long, default_value_t = 15)]
    window: usize,
    /// Frame step inside a window.
    #[arg(long, default_value_t = 1)]
    step: usize,
    /// Windows spread over the sequence.
    #[arg(long, default_value_t = 8)]
    anchors: usize,
    /// Pixels per window.
    #[arg(long, default_value_t = 300)]
    pixels: usize,
    #[arg(long, default_value_t = 0)]
    threads: usize,
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Blur passes (5-tap binomial, sigma 1 px each) over the images first.
    #[arg(long, default_value_t = 0)]
    blur: u32,
    /// Warp with the focal lengths scaled by this (tests whether the colour camera's
    /// intrinsics differ from the dataset's).
    #[arg(long, default_value_t = 1.0)]
    focal_scale: f32,
}

#[derive(Args)]
struct DumpStepArgs {
    #[arg(long)]
    out: PathBuf,
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Number of rays.
    #[arg(long, default_value_t = 64)]
    rays: usize,
    /// Rendering: sdf-density (Hi-Map), sdf-direct or occupancy.
    #[arg(long, default_value = "sdf-density")]
    render: String,
}

fn parse_render(s: &str) -> anyhow::Result<himap_core::field::render::RenderMode> {
    use himap_core::field::render::RenderMode::*;
    Ok(match s {
        "sdf-density" => SdfDensity,
        "sdf-direct" => SdfDirect,
        "occupancy" => Occupancy,
        other => {
            anyhow::bail!("unknown rendering '{other}': use sdf-density, sdf-direct or occupancy")
        }
    })
}

fn parse_size(s: &str) -> anyhow::Result<(u32, u32)> {
    let (w, h) = s
        .split_once('x')
        .with_context(|| format!("size '{s}': expected WxH, e.g. 320x240"))?;
    let w: u32 = w
        .trim()
        .parse()
        .with_context(|| format!("size '{s}': bad width"))?;
    let h: u32 = h
        .trim()
        .parse()
        .with_context(|| format!("size '{s}': bad height"))?;
    if w < 2 || h < 2 {
        anyhow::bail!("size '{s}': width and height must be at least 2");
    }
    Ok((w, h))
}

/// `a:b:stride`, each part optional (`10:`, `:100`, `::2`).
fn parse_frames(s: &str) -> anyhow::Result<(usize, Option<usize>, usize)> {
    let parts: Vec<&str> = s.split(':').collect();
    if parts.is_empty() || parts.len() > 3 {
        anyhow::bail!("--frames '{s}': expected start:end:stride");
    }
    let num = |p: &str, what: &str| -> anyhow::Result<Option<usize>> {
        if p.trim().is_empty() {
            Ok(None)
        } else {
            Ok(Some(
                p.trim()
                    .parse()
                    .with_context(|| format!("--frames '{s}': bad {what}"))?,
            ))
        }
    };
    let start = num(parts[0], "start")?.unwrap_or(0);
    let end = match parts.get(1) {
        Some(p) => num(p, "end")?,
        None => None,
    };
    let stride = match parts.get(2) {
        Some(p) => num(p, "stride")?.unwrap_or(1),
        None => 1,
    };
    if stride == 0 {
        anyhow::bail!("--frames '{s}': stride must be at least 1");
    }
    if let Some(e) = end {
        if e <= start {
            anyhow::bail!("--frames '{s}': end must be greater than start");
        }
    }
    Ok((start, end, stride))
}

/// Exit codes (documented in the README): 0 success, 1 a bad input or a failed run, 2 a usage
/// error (clap's), 3 a GPU device failure.
const EXIT_FAILURE: u8 = 1;
const EXIT_DEVICE: u8 = 3;

/// Prints a user-facing error as its cause chain, one line per cause, and no backtrace (even
/// with `RUST_BACKTRACE=1`: errors are values here; real bugs panic, and panics keep Rust's
/// backtrace), then exits with the code of [`exit_code`].
fn main() -> std::process::ExitCode {
    if let Some(missing) = missing_cpu_features() {
        eprintln!(
            "error: this himap was built for x86-64-v3 CPUs (.cargo/config.toml) and this CPU \
             lacks {missing}; rebuild it for any x86-64 CPU (same results, about 10 % slower \
             mapping) with: RUSTFLAGS=\"-C target-cpu=x86-64\" cargo build --release"
        );
        return std::process::ExitCode::FAILURE;
    }
    match run() {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e}");
            for cause in e.chain().skip(1) {
                eprintln!("  caused by: {cause}");
            }
            std::process::ExitCode::from(exit_code(&e))
        }
    }
}

/// The first CPU feature this binary was compiled to use that the CPU running it lacks (an
/// x86-64-v3 build on an older CPU would otherwise die of an illegal instruction).
fn missing_cpu_features() -> Option<&'static str> {
    #[cfg(target_arch = "x86_64")]
    {
        macro_rules! check {
            ($($f:tt),*) => {
                $(
                    if cfg!(target_feature = $f) && !std::arch::is_x86_feature_detected!($f) {
                        return Some($f);
                    }
                )*
            };
        }
        check!("avx", "avx2", "fma", "bmi1", "bmi2", "f16c", "lzcnt", "movbe");
    }
    None
}

/// [`EXIT_DEVICE`] when a Vulkan device error is anywhere in the chain, else [`EXIT_FAILURE`].
fn exit_code(e: &anyhow::Error) -> u8 {
    let device = e
        .chain()
        .any(|c| c.downcast_ref::<himap_vulkan::VulkanError>().is_some());
    if device {
        EXIT_DEVICE
    } else {
        EXIT_FAILURE
    }
}

fn run() -> anyhow::Result<()> {
    match Cli::parse().command {
        Command::Map(args) => map(args),
        Command::Demo(args) => demo(args),
        Command::Devices(a) => devices(&a),
        Command::Bench(args) => bench(args),
        Command::Mesh(args) => mesh(args),
        Command::TrainDemo(args) => train_demo(args),
        Command::Synth(args) => synth(args),
        Command::Eval(args) => eval(args),
        Command::WarpCheck(args) => warp_check(args),
        Command::DumpStep(args) => dump_step(args),
    }
}

/// `himap map`.
fn map(args: MapArgs) -> anyhow::Result<()> {
    let MapArgs {
        dataset,
        out,
        config,
        preset,
        backend,
        frames,
        resize,
        threads,
        print_config,
        no_preflight,
        checkpoint_every,
        resume,
        profile,
        rerun,
        rerun_save,
        rerun_mesh_every,
    } = args;
    let mut cfg = himap::config::Config::preset(&preset)?;
    for p in &config {
        cfg = himap::config::Config::from_file_over(p, &cfg)?;
    }
    if print_config {
        print!("{}", cfg.to_toml());
        return Ok(());
    }
    backend.parse::<himap::select::BackendChoice>()?;
    let (start, end, stride) = match &frames {
        Some(f) => parse_frames(f)?,
        None => (0, None, 1),
    };
    let resize = resize.as_deref().map(parse_size).transpose()?;
    let opts = himap::mapper_cli::MapOptions {
        dataset,
        out: out.clone(),
        config: cfg,
        start,
        end,
        stride,
        resize,
        threads,
        backend,
        progress: true,
        preflight: !no_preflight,
        stop_after: None,
        checkpoint_every,
        resume,
        live: himap::mapper_cli::LiveOptions {
            viewer: rerun.map(|u| (!u.is_empty()).then_some(u)),
            save: rerun_save,
            mesh_every: rerun_mesh_every,
        },
        profile,
    };
    let s = himap::mapper_cli::run_map(&opts)?;
    println!("{}", himap::mapper_cli::summary_table(&s));
    println!("outputs in {}", out.display());
    Ok(())
}

/// `himap demo`.
fn demo(args: DemoArgs) -> anyhow::Result<()> {
    let DemoArgs {
        out,
        frames,
        size,
        config,
        threads,
        backend,
    } = args;
    backend.parse::<himap::select::BackendChoice>()?;
    let cfg = match &config {
        Some(p) => himap::config::Config::from_file_over(p, &himap::config::Config::demo())?,
        None => himap::config::Config::demo(),
    };
    let size = parse_size(&size)?;
    println!(
        "synthesising a {frames}-frame {}x{} room and mapping it with the demo preset \
             (small with 20 online iterations and no early termination)",
        size.0, size.1
    );
    let (s, dir) =
        himap::mapper_cli::run_demo(out.as_deref(), cfg, frames, size, threads, &backend, true)?;
    println!("{}", himap::mapper_cli::summary_table(&s));
    println!("outputs in {}", dir.display());
    Ok(())
}

#[derive(Args)]
struct DevicesArgs {
    /// Also build every shader entry point's compute pipeline on the selected device and
    /// report each one (a driver that rejects a shader is named entry point by entry point).
    #[arg(long)]
    pipelines: bool,
    /// With --pipelines: build this SPIR-V file's entry points instead of the built-in module
    /// (narrowing down a driver's failure).
    #[arg(long, requires = "pipelines")]
    spirv: Option<std::path::PathBuf>,
    /// With --pipelines: build with the driver's optimisations disabled.
    #[arg(long, requires = "pipelines")]
    no_optimization: bool,
    /// Divide this many pairs on the selected device, with the kernels' division and with
    /// the device's own, and compare both with the CPU bit for bit.
    #[arg(long, value_name = "PAIRS")]
    divide: Option<u32>,
}

/// `himap devices`.
fn devices(a: &DevicesArgs) -> anyhow::Result<()> {
    print!("{}", himap_vulkan::describe_devices());
    if a.pipelines {
        let words = match &a.spirv {
            Some(p) => Some(himap_vulkan::read_spirv(p).map_err(anyhow::Error::msg)?),
            None => None,
        };
        print!(
            "{}",
            himap_vulkan::check_pipelines(words.as_deref(), a.no_optimization)
        );
    }
    if let Some(n) = a.divide {
        print!("{}", himap_vulkan::check_division(n));
    }
    let d = himap::select::decide(himap::select::BackendChoice::Auto);
    println!(
        "--backend auto would use: {}",
        if d.vulkan { "vulkan" } else { "cpu" }
    );
    println!("  ({})", d.reason);
    Ok(())
}

/// `himap bench`.
fn bench(args: BenchArgs) -> anyhow::Result<()> {
    let BenchArgs {
        rays,
        steps,
        fastest,
        backend,
        config,
        threads,
        profile,
    } = args;
    let opts = himap::bench::BenchOptions {
        rays,
        steps,
        backends: backend,
        configs: config,
        threads,
        profile,
        fastest,
    };
    himap::bench::run_bench(&opts, &mut std::io::stdout())?;
    Ok(())
}

/// `himap mesh`.
fn mesh(args: MeshArgs) -> anyhow::Result<()> {
    let MeshArgs {
        map,
        out,
        resolution,
        level,
        threads,
        observed,
        resize,
    } = args;
    let observed = match observed {
        Some(dataset) => Some(himap::mapper_cli::ObservedBy {
            dataset,
            resize: resize.as_deref().map(parse_size).transpose()?,
        }),
        None => None,
    };
    let (faces, level) = himap::mapper_cli::mesh_saved_map(
        &map,
        &out,
        resolution,
        level,
        threads,
        observed.as_ref(),
    )?;
    println!(
        "wrote {} ({faces} faces, level {level:.4} m)",
        out.display()
    );
    Ok(())
}

/// `himap train-demo`.
fn train_demo(args: TrainDemoArgs) -> anyhow::Result<()> {
    let TrainDemoArgs {
        steps,
        rays,
        threads,
        seed,
    } = args;
    let cfg = himap::dump::small_config(himap_core::field::render::RenderMode::SdfDensity);
    let layout = himap_core::field::model::ModelLayout::new(&cfg)?;
    println!(
            "training a {}-parameter field on an analytic sphere-in-a-box target: {steps} steps x {rays} rays",
            layout.param_count()
        );
    let start = std::time::Instant::now();
    let (first, last) = himap::train_demo::run(
        layout,
        steps,
        rays,
        threads,
        seed,
        |step, loss, psnr| println!("step {step:5}  loss {loss:.5}  PSNR {psnr:6.2} dB"),
        (steps / 10).max(1),
    )?;
    println!(
        "loss {first:.5} -> {last:.5} in {:.1} s",
        start.elapsed().as_secs_f32()
    );
    Ok(())
}

/// `himap synth`.
fn synth(args: SynthArgs) -> anyhow::Result<()> {
    let SynthArgs {
        out,
        scene,
        frames,
        width,
        height,
        seed,
    } = args;
    match scene.as_str() {
        "room" => {
            let opts = himap::synth::SynthOptions {
                frames: frames.unwrap_or(60),
                width: width.unwrap_or(160),
                height: height.unwrap_or(120),
                seed,
            };
            let s = himap::synth::write_synthetic(&out, &opts)
                .with_context(|| format!("writing the synthetic sequence to {}", out.display()))?;
            println!(
                "wrote {} frames of {}x{} to {} ({} ground-truth triangles); scene box {:?} .. {:?}",
                s.frames,
                s.intrinsics.width,
                s.intrinsics.height,
                s.out.display(),
                s.mesh_triangles,
                s.scene_box.min,
                s.scene_box.max
            );
        }
        "house" | "hall" => {
            let kind = if scene == "hall" {
                himap::synth::house::HouseKind::Hall
            } else {
                himap::synth::house::HouseKind::Rooms
            };
            let opts = himap::synth::house::HouseOptions {
                frames: frames.unwrap_or(360),
                width: width.unwrap_or(320),
                height: height.unwrap_or(240),
                seed,
                kind,
            };
            let s = himap::synth::house::write_house(&out, &opts)
                .with_context(|| format!("writing the house sequence to {}", out.display()))?;
            let (lo, hi) = s.house.interior();
            println!(
                "wrote {} frames of {}x{} of a {}-room house ({:.1} x {:.1} x {:.1} m, {:.1} m \
                 walk) to {} ({} ground-truth triangles, {:.1} % of their area seen by the \
                 frames; no scene box: the default box policy applies)",
                s.frames,
                s.intrinsics.width,
                s.intrinsics.height,
                s.house.lengths.len(),
                hi[0] - lo[0],
                hi[1] - lo[1],
                hi[2] - lo[2],
                s.path_m,
                out.display(),
                s.mesh_triangles,
                100.0 * s.mesh_seen_share,
            );
        }
        other => anyhow::bail!("unknown synthetic scene '{other}': use room, house or hall"),
    }
    Ok(())
}

/// `himap eval`.
fn eval(args: EvalArgs) -> anyhow::Result<()> {
    let EvalArgs {
        mesh,
        gt,
        json,
        samples,
        cull,
        gt_cull,
        config,
    } = args;
    use himap::eval::{Culling, EvalOptions};
    let parse = |c: &str| {
        Culling::from_name(c)
            .with_context(|| format!("unknown culling '{c}': use none, frustum or occlusion"))
    };
    let (culling, gt_culling) = (parse(&cull)?, parse(&gt_cull)?);
    let dataset = match config {
        Some(p) => himap::dataset::DatasetConfig {
            // the ground truth at the files' size, whatever size a configuration maps at
            max_width: 0,
            ..himap::config::Config::from_file(&p)?.dataset
        },
        None => Default::default(),
    };
    let opts = EvalOptions {
        n_samples: samples,
        culling,
        gt_culling,
        dataset,
        ..EvalOptions::default()
    };
    let report = himap::eval::run_eval_cli(&mesh, &gt, json.as_deref(), &opts)?;
    println!("{report}");
    Ok(())
}

/// `himap warp-check`.
fn warp_check(args: WarpCheckArgs) -> anyhow::Result<()> {
    let WarpCheckArgs {
        dataset,
        config,
        map,
        frames,
        resize,
        window,
        step,
        anchors,
        pixels,
        threads,
        seed,
        blur,
        focal_scale,
    } = args;
    let config = match config {
        Some(p) => himap::config::Config::from_file(&p)?,
        None => himap::config::Config::small(),
    };
    let mut load = himap::dataset::LoadOptions::default();
    if let Some(f) = frames {
        let (start, end, stride) = parse_frames(&f)?;
        load.start = start;
        load.end = end;
        load.stride = stride;
    }
    load.resize = resize.as_deref().map(parse_size).transpose()?;
    let opts = himap::warp_check::WarpCheckOptions {
        dataset,
        load,
        config,
        window,
        step,
        anchors,
        pixels,
        map,
        threads,
        seed,
        blur,
        focal_scale,
    };
    let (rows, total) = himap::warp_check::run(&opts)?;
    let with_map = opts.map.is_some();
    println!("{}", himap::warp_check::WarpStats::header(with_map));
    for r in &rows {
        println!("{}", r.row(&r.first.to_string()));
    }
    println!("{}", total.row("all"));
    println!("{}", total.basin_line());
    if with_map {
        println!("{}", total.sweep_line());
    }
    Ok(())
}

/// `himap dump-step`.
fn dump_step(args: DumpStepArgs) -> anyhow::Result<()> {
    let DumpStepArgs {
        out,
        seed,
        rays,
        render,
    } = args;
    let opts = DumpOptions {
        seed,
        rays,
        render_mode: parse_render(&render)?,
    };
    let loss = himap::dump::dump_step(&out, &opts).with_context(|| "dump-step failed")?;
    println!("wrote {} (loss {loss})", out.display());
    Ok(())
}
