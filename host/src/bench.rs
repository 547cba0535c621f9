//! `himap bench`: throughput of the backends at the small and the paper configuration.
//! A benchmark that prints numbers, not a timed test.

use std::time::Instant;

use himap_core::field::model::{LossConfig, ModelConfig, ModelLayout, Ray, RayResult};
use himap_core::field::render::RenderMode;
use himap_core::rng::SplitMix;
use himap_core::train::backend::{paper_adam, Backend};
use himap_core::Aabb;

use crate::backend::{ModelData, ParallelCpuBackend};

/// One measured configuration.
#[derive(Clone, Debug, serde::Serialize)]
pub struct BenchRow {
    pub backend: String,
    pub config: String,
    pub params: usize,
    /// Parameters + Adam moments (f32) + fixed-point gradients (i64), bytes.
    pub state_bytes: usize,
    pub rays: usize,
    pub samples_per_ray: u32,
    pub forward_samples_per_s: f64,
    pub train_samples_per_s: f64,
    pub train_ms_per_step: f64,
    /// CPU: the share of the training backward's sample branches skipped because every
    /// contribution rounds to 0 quanta ([`himap_core::field::negligible`]).
    pub skipped_share: Option<f64>,
}

/// Random rays from inside `aabb` (shrunk by 20%) in random directions (each component
/// uniform in [-1, 1]; normalised to unit length when `unit`).
pub fn rays_in(aabb: &Aabb, n: usize, seed: u64) -> Vec<Ray> {
    rays_in_dirs(aabb, n, seed, false)
}

fn rays_in_dirs(aabb: &Aabb, n: usize, seed: u64, unit: bool) -> Vec<Ray> {
    let mut r = SplitMix::new(seed);
    (0..n)
        .map(|_| {
            let mut o = [0.0f32; 3];
            for (a, o) in o.iter_mut().enumerate() {
                let c = 0.5 * (aabb.min[a] + aabb.max[a]);
                let h = 0.4 * (aabb.max[a] - aabb.min[a]);
                *o = c + h * (2.0 * r.unit() - 1.0);
            }
            let mut d = [
                2.0 * r.unit() - 1.0,
                2.0 * r.unit() - 1.0,
                2.0 * r.unit() - 1.0,
            ];
            if unit {
                let len = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt().max(1e-6);
                d = d.map(|x| x / len);
            }
            Ray {
                origin: o,
                dir: d,
                target: [r.unit(), r.unit(), r.unit()],
                target_depth: 0.0,
            }
        })
        .collect()
}

/// The configurations benchmarked: `small` (the dump-step model), `paper` (the paper's grids
/// and decoders over a 6 x 6 x 3 m room, 48 samples per ray) and `step` (the paper's model over
/// a 4 m cube with 64 samples per ray and unit directions: the step
/// `scripts/bench_step_torch.py` times in PyTorch).
pub fn configs() -> Vec<(&'static str, ModelConfig)> {
    let mut step = ModelConfig::paper(Aabb::new([-2.0; 3], [2.0; 3]));
    step.samples = 64;
    vec![
        ("small", crate::dump::small_config(RenderMode::SdfDensity)),
        (
            "paper (6x6x3 m room)",
            ModelConfig::paper(Aabb::new([-3.0, -3.0, -1.5], [3.0, 3.0, 1.5])),
        ),
        ("step (paper, 4 m cube)", step),
    ]
}

/// Operation count of one training sample of the paper's model (forward, backward, Adam's
/// share), the estimate of issue #12: about 35 kFLOP.
pub const FLOP_PER_TRAIN_SAMPLE: f64 = 35e3;
/// Two AVX-512 cores without fused multiply-add: about 160 GFLOP/s.
pub const PEAK_FLOPS_2_CORES: f64 = 160e9;

/// Peak resident memory of this process so far (Linux `VmHWM`), bytes.
pub fn peak_rss_bytes() -> Option<u64> {
    let s = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = s.lines().find(|l| l.starts_with("VmHWM:"))?;
    let kb: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kb * 1024)
}

/// Times `steps` renders (forward) and `steps` training steps (forward + backward + Adam) of
/// `rays` rays on `be`, after one warm-up of each: the mean time of each, or with `fastest`
/// the fastest one (side-by-side comparisons on a machine whose neighbours come and go).
fn measure<B: Backend>(
    be: &mut B,
    cfg: &ModelConfig,
    rays: usize,
    steps: usize,
    fastest: bool,
) -> anyhow::Result<(f64, f64)>
where
    B::Error: std::error::Error + Send + Sync + 'static,
{
    let steps = steps.max(1);
    let summary = |times: &[f64]| {
        if fastest {
            times.iter().copied().fold(f64::INFINITY, f64::min)
        } else {
            times.iter().sum::<f64>() / times.len() as f64
        }
    };
    let batch = rays_in_dirs(&cfg.aabb, rays, 7, cfg.samples == 64);
    let mut res = vec![RayResult::default(); rays];
    be.render(&batch, &mut res)?; // warm-up
    let mut times = Vec::with_capacity(steps);
    for _ in 0..steps {
        let t = Instant::now();
        be.render(&batch, &mut res)?;
        times.push(t.elapsed().as_secs_f64());
    }
    let fwd = summary(&times);
    let loss = LossConfig {
        lambda_color: 1.0,
        lambda_depth: 0.0,
        ray_scale: 1.0 / rays as f32,
        color_to_geometry: true,
        seed: 0,
    };
    be.train_step(&batch, &loss, &mut res)?;
    times.clear();
    for s in 0..steps {
        let l = LossConfig {
            seed: s as u32,
            ..loss
        };
        let t = Instant::now();
        be.train_step(&batch, &l, &mut res)?;
        times.push(t.elapsed().as_secs_f64());
    }
    Ok((fwd, summary(&times)))
}

fn row(
    backend: &str,
    name: &str,
    cfg: &ModelConfig,
    layout: &ModelLayout,
    rays: usize,
    extra_bytes: usize,
    (fwd, train): (f64, f64),
) -> BenchRow {
    let p = layout.param_count();
    let samples = (rays * cfg.samples as usize) as f64;
    BenchRow {
        backend: backend.to_string(),
        config: name.to_string(),
        params: p,
        state_bytes: p * (3 * 4 + 8) + extra_bytes,
        rays,
        samples_per_ray: cfg.samples,
        forward_samples_per_s: samples / fwd,
        train_samples_per_s: samples / train,
        train_ms_per_step: train * 1e3,
        skipped_share: None,
    }
}

/// Measures the multi-threaded CPU backend with `threads` threads (0 = all cores).
pub fn bench_cpu(
    name: &str,
    cfg: &ModelConfig,
    threads: usize,
    rays: usize,
    steps: usize,
    fastest: bool,
) -> anyhow::Result<BenchRow> {
    let layout = ModelLayout::new(cfg)?;
    let data = ModelData::new(layout, 1)?;
    let mut be = ParallelCpuBackend::new(data, paper_adam(), threads)?;
    let t = measure(&mut be, cfg, rays, steps, fastest)?;
    let work = be.work_bytes() - layout.param_count() * 8;
    let mut r = row(be.name(), name, cfg, &layout, rays, work, t);
    let p = be.pass_times();
    r.skipped_share = Some(p.branches_skipped as f64 / p.branches_checked.max(1) as f64);
    Ok(r)
}

/// A profiled training step: the passes' times and the wall time of the profiled steps (ms).
pub type Profile = (Vec<himap_vulkan::PassTime>, f64);

/// Measures the Vulkan backend on the selected device. The memory column adds the per-batch
/// device buffers (rays, results, sample records) to the model state. With `profile`, `steps`
/// more training steps are timed pass by pass (timestamp queries; host transfers timed on
/// the host) and returned with the wall time of those steps (ms).
pub fn bench_vulkan(
    name: &str,
    cfg: &ModelConfig,
    rays: usize,
    steps: usize,
    fastest: bool,
    profile: bool,
) -> anyhow::Result<(BenchRow, Option<Profile>)> {
    let layout = ModelLayout::new(cfg)?;
    let data = ModelData::new(layout, 1)?;
    // HIMAP_BENCH_GLOBAL_ATOMICS=1: the backward with one global atomic per contribution,
    // to compare with the workgroup-summed one the device would otherwise use.
    let options = himap_vulkan::VulkanOptions {
        global_atomics_only: std::env::var("HIMAP_BENCH_GLOBAL_ATOMICS").is_ok_and(|v| v == "1"),
        ..Default::default()
    };
    let mut be = himap_vulkan::VulkanBackend::with_options(
        layout,
        data.param_slices(),
        paper_adam(),
        options,
    )?;
    // Steps until the backend has timed both backward structures and chosen one (it
    // alternates them on its first steps), so that the timed steps run the chosen one.
    {
        let batch = rays_in_dirs(&cfg.aabb, rays, 5, cfg.samples == 64);
        let mut res = vec![RayResult::default(); rays];
        let mut s = 0;
        while be.backward_pass().0.is_none() && s < 16 {
            let loss = LossConfig {
                lambda_color: 1.0,
                lambda_depth: 0.0,
                ray_scale: 1.0 / rays as f32,
                color_to_geometry: true,
                seed: 1000 + s,
            };
            be.train_step(&batch, &loss, &mut res)?;
            s += 1;
        }
    }
    let t = measure(&mut be, cfg, rays, steps, fastest)?;
    let batch_bytes = rays * (10 + 6) * 4 + rays * cfg.samples as usize * 9 * 4;
    let mut r = row(be.name(), name, cfg, &layout, rays, batch_bytes, t);
    // the backward's structure: fixed, or chosen by timing both on the first steps
    let (chosen, ms) = be.backward_pass();
    r.backend += &match (chosen, ms) {
        (Some(c), [Some(g), Some(w)]) => format!(
            " (backward: {}; {g:.1} ms global atomics, {w:.1} ms workgroup sums)",
            c.name()
        ),
        (Some(c), _) => format!(" (backward: {})", c.name()),
        (None, _) => " (backward: still timing both)".to_string(),
    };
    if !profile {
        return Ok((r, None));
    }
    be.enable_profiling()?;
    let batch = rays_in_dirs(&cfg.aabb, rays, 7, cfg.samples == 64);
    let mut res = vec![RayResult::default(); rays];
    let steps = steps.max(1);
    let t0 = Instant::now();
    for s in 0..steps {
        let loss = LossConfig {
            lambda_color: 1.0,
            lambda_depth: 0.0,
            ray_scale: 1.0 / rays as f32,
            color_to_geometry: true,
            seed: s as u32,
        };
        be.train_step(&batch, &loss, &mut res)?;
    }
    let wall_ms = t0.elapsed().as_secs_f64() * 1e3;
    Ok((r, Some((be.profile(), wall_ms))))
}

/// The per-pass table of a profiled training step: each pass's milliseconds per step and
/// share of the step's wall time, then the time not covered by any pass (submission, waits,
/// host work between the transfers).
pub fn format_profile(passes: &[himap_vulkan::PassTime], wall_ms: f64, steps: usize) -> String {
    let steps = steps.max(1) as f64;
    let per_step = wall_ms / steps;
    let mut s = format!(
        "  per pass (timestamp queries; {:.1} ms per step over {} steps):\n",
        per_step, steps
    );
    if !passes.iter().any(|p| p.device) {
        s += "    (the device has no timestamps on its compute queue: transfers only)\n";
    }
    let mut covered = 0.0;
    for p in passes {
        let ms = p.total_ms / steps;
        covered += ms;
        s += &format!(
            "    {:<40} {:>10.3} ms {:>6.1} %{}\n",
            p.name,
            ms,
            100.0 * ms / per_step.max(1e-12),
            if p.device { "" } else { "  (host)" }
        );
    }
    let rest = (per_step - covered).max(0.0);
    s += &format!(
        "    {:<40} {:>10.3} ms {:>6.1} %\n",
        "other (submission, waits, host)",
        rest,
        100.0 * rest / per_step.max(1e-12)
    );
    s
}

/// What `himap bench` measures.
#[derive(Clone, Debug)]
pub struct BenchOptions {
    pub rays: usize,
    pub steps: usize,
    /// `cpu`, `vulkan` or `all`.
    pub backends: String,
    /// `small`, `paper` or `all`.
    pub configs: String,
    /// CPU threads (0 = all cores).
    pub threads: usize,
    /// Time the Vulkan backend's passes (`--profile`).
    pub profile: bool,
    /// Report each measurement's fastest step instead of the mean (`--fastest`).
    pub fastest: bool,
}

/// Runs the benchmark and prints the table to `out`. A backend that cannot start (no Vulkan
/// device) is reported in a line and skipped.
pub fn run_bench(opts: &BenchOptions, out: &mut dyn std::io::Write) -> anyhow::Result<()> {
    let want_cpu = matches!(opts.backends.as_str(), "cpu" | "all");
    let want_vk = matches!(opts.backends.as_str(), "vulkan" | "all");
    if !want_cpu && !want_vk {
        anyhow::bail!("--backend must be cpu, vulkan or all");
    }
    if !matches!(opts.configs.as_str(), "small" | "paper" | "step" | "all") {
        anyhow::bail!("--config must be small, paper, step or all");
    }
    writeln!(out, "{}", header())?;
    for (name, cfg) in configs() {
        if opts.configs != "all" && !name.starts_with(opts.configs.as_str()) {
            continue;
        }
        if want_cpu {
            let r = bench_cpu(
                name,
                &cfg,
                opts.threads,
                opts.rays,
                opts.steps,
                opts.fastest,
            )?;
            writeln!(out, "{}", format_row(&r))?;
            if name.starts_with("step") {
                let flop = FLOP_PER_TRAIN_SAMPLE * (r.rays * r.samples_per_ray as usize) as f64;
                let bound_ms = flop / PEAK_FLOPS_2_CORES * 1e3;
                writeln!(
                    out,
                    "  {}: {:.1} ms per step = {:.1} % of the {:.0} ms bound ({:.2} GFLOP at \
                     160 GFLOP/s); peak memory of the process {}; sample branches skipped as \
                     negligible (every contribution below half a quantum, the same sums): \
                     {:.1} %",
                    r.backend,
                    r.train_ms_per_step,
                    100.0 * bound_ms / r.train_ms_per_step,
                    bound_ms,
                    flop / 1e9,
                    peak_rss_bytes()
                        .map(|b| format!("{:.0} MB", b as f64 / 1e6))
                        .unwrap_or_else(|| "unknown".into()),
                    100.0 * r.skipped_share.unwrap_or(0.0)
                )?;
            }
        }
        if want_vk {
            match bench_vulkan(
                name,
                &cfg,
                opts.rays,
                opts.steps,
                opts.fastest,
                opts.profile,
            ) {
                Ok((r, prof)) => {
                    writeln!(out, "{}", format_row(&r))?;
                    if let Some((passes, wall)) = prof {
                        write!(out, "{}", format_profile(&passes, wall, opts.steps))?;
                    }
                }
                Err(e) => writeln!(out, "vulkan: skipped ({e:#})")?,
            }
        }
        out.flush()?;
    }
    Ok(())
}

/// One table row.
pub fn format_row(r: &BenchRow) -> String {
    format!(
        "{:<22} {:<22} {:>10} {:>9.1} MB {:>6} x {:<3} {:>12.0} {:>12.0} {:>10.1}",
        r.backend,
        r.config,
        r.params,
        r.state_bytes as f64 / 1e6,
        r.rays,
        r.samples_per_ray,
        r.forward_samples_per_s,
        r.train_samples_per_s,
        r.train_ms_per_step
    )
}

/// The table header.
pub fn header() -> String {
    format!(
        "{:<22} {:<22} {:>10} {:>12} {:>12} {:>12} {:>12} {:>10}",
        "backend",
        "config",
        "params",
        "memory",
        "rays x spr",
        "fwd smp/s",
        "train smp/s",
        "ms/step"
    )
}
