//! Bit-for-bit conformance of the Vulkan backend with the CPU reference
//! (`himap_core::step::CpuBackend`, and the host's `ParallelCpuBackend` for queries): forward
//! rendering, every gradient buffer of a step, the Adam update (parameters and both moments),
//! all parameters after 50 training steps of the small configuration, the mapping step
//! (colour + DIM-SLAM warping loss over a window of image slots), SDF and colour queries.
//! Floats are compared by their bits (NaN equals NaN whatever its payload).
//!
//! Without a usable Vulkan device these tests print why and pass, unless
//! `HIMAP_REQUIRE_VULKAN=1` (set by CI), which makes them fail with the reason.

use himap::backend::{ModelData, ParallelCpuBackend};
use himap::dump::{nonfinite_sequence, random_rays, small_config};
use himap::synth::{synth_intrinsics, synth_pose, Scene};
use himap_core::adam::AdamConfig;
use himap_core::camera::{Intrinsics, Pose};
use himap_core::mapping::{pack_rgba8, MappingLoss, PixelResult, PixelSample};
use himap_core::model::{
    Group, LossConfig, ModelConfig, ModelLayout, PerGroup, Ray, RayResult, NUM_GROUPS,
};
use himap_core::render::RenderMode;
use himap_core::step::{group_states, paper_adam, Backend, CpuBackend, ImageStore, MapBatch};
use himap_core::warp::WarpConfig;
use himap_core::Aabb;
use himap_vulkan::{VulkanBackend, VulkanError, VulkanOptions};

/// The Vulkan backend over `data`'s parameters, or `None` (with the reason printed) when this
/// machine has no usable Vulkan device. With `HIMAP_REQUIRE_VULKAN=1` a missing device is a
/// test failure. Errors that are not about device availability always fail.
fn vulkan_or_skip(data: &ModelData, adam: PerGroup<AdamConfig>) -> Option<VulkanBackend> {
    let params = data.param_slices();
    match VulkanBackend::new(data.layout, params, adam) {
        Ok(b) => Some(b),
        Err(
            e @ (VulkanError::NoLoader(_)
            | VulkanError::ApiTooOld { .. }
            | VulkanError::Instance(_)
            | VulkanError::NoDevice
            | VulkanError::NoSuitableDevice { .. }
            | VulkanError::MissingFeature { .. }
            | VulkanError::DeviceNotFound { .. }),
        ) => {
            if std::env::var("HIMAP_REQUIRE_VULKAN").is_ok_and(|v| v == "1") {
                panic!("HIMAP_REQUIRE_VULKAN=1 but no usable Vulkan device: {e}");
            }
            eprintln!("skipping: no usable Vulkan device: {e}");
            None
        }
        Err(e) => panic!("creating the Vulkan backend failed: {e}"),
    }
}

fn same(a: f32, b: f32) -> bool {
    a.to_bits() == b.to_bits() || (a.is_nan() && b.is_nan())
}

fn assert_same_f32(what: &str, cpu: &[f32], gpu: &[f32]) {
    assert_eq!(cpu.len(), gpu.len(), "{what}: lengths");
    let bad: Vec<usize> = (0..cpu.len()).filter(|&i| !same(cpu[i], gpu[i])).collect();
    assert!(
        bad.is_empty(),
        "{what}: {} of {} values differ, first at {}: cpu {:e} ({:#010x}) gpu {:e} ({:#010x})",
        bad.len(),
        cpu.len(),
        bad[0],
        cpu[bad[0]],
        cpu[bad[0]].to_bits(),
        gpu[bad[0]],
        gpu[bad[0]].to_bits()
    );
}

fn result_floats(r: &[RayResult]) -> Vec<f32> {
    r.iter()
        .flat_map(|r| {
            [
                r.color[0], r.color[1], r.color[2], r.depth, r.opacity, r.loss,
            ]
        })
        .collect()
}

/// The small configuration's model (seeded) and a batch of rays, a few of which miss the box
/// or start outside it.
fn setup(mode: RenderMode, seed: u32, n_rays: usize) -> (ModelData, Vec<Ray>) {
    setup_with(&small_config(mode), seed, n_rays)
}

fn setup_with(cfg: &ModelConfig, seed: u32, n_rays: usize) -> (ModelData, Vec<Ray>) {
    let layout = ModelLayout::new(cfg).expect("small config is valid");
    let data = ModelData::new(layout, seed).expect("init");
    let mut rays = random_rays(n_rays, seed as u64 + 100);
    // from outside the box towards it, and away from it (renders nothing)
    rays.push(Ray {
        origin: [-3.0, 0.1, 0.2],
        dir: [1.0, 0.05, -0.02],
        target: [0.2, 0.4, 0.6],
        target_depth: 3.0,
    });
    rays.push(Ray {
        origin: [5.0, 5.0, 5.0],
        dir: [1.0, 0.0, 0.0],
        target: [0.5; 3],
        target_depth: 1.0,
    });
    (data, rays)
}

/// Owns the CPU reference's buffers; `backend()` borrows them.
struct CpuState {
    layout: ModelLayout,
    params: [Vec<f32>; NUM_GROUPS],
    m: [Vec<f32>; NUM_GROUPS],
    v: [Vec<f32>; NUM_GROUPS],
    grad: [Vec<i64>; NUM_GROUPS],
}

impl CpuState {
    fn new(data: &ModelData) -> Self {
        let lens = data.layout.group_lens();
        Self {
            layout: data.layout,
            params: data.params.0.clone(),
            m: lens.map(|n| vec![0.0; n]),
            v: lens.map(|n| vec![0.0; n]),
            grad: lens.map(|n| vec![0; n]),
        }
    }

    fn backend(&mut self, adam: PerGroup<AdamConfig>) -> CpuBackend<'_> {
        let groups = group_states(&mut self.params, &mut self.m, &mut self.v, &mut self.grad);
        CpuBackend::new(self.layout, groups, adam).expect("cpu backend")
    }
}

fn loss_config(seed: u32, n: usize) -> LossConfig {
    LossConfig {
        lambda_color: 1.0,
        lambda_depth: 0.5,
        ray_scale: 1.0 / n as f32,
        color_to_geometry: true,
        seed,
    }
}

/// Larger learning rates than the paper's so that 50 steps move every group visibly.
fn test_adam() -> PerGroup<AdamConfig> {
    PerGroup([
        AdamConfig::new(0.02),
        AdamConfig::new(0.02),
        AdamConfig::new(1e-3),
        AdamConfig::new(1e-3),
        AdamConfig::new(1e-2),
    ])
}

#[test]
fn forward_rendering_matches_cpu() {
    for mode in [
        RenderMode::SdfDensity,
        RenderMode::SdfDirect,
        RenderMode::Occupancy,
    ] {
        let (data, rays) = setup(mode, 3, 300);
        let Some(mut gpu) = vulkan_or_skip(&data, paper_adam()) else {
            return;
        };
        let mut cpu_state = CpuState::new(&data);
        let mut cpu = cpu_state.backend(paper_adam());
        let mut rc = vec![RayResult::default(); rays.len()];
        let mut rg = vec![RayResult::default(); rays.len()];
        cpu.render(&rays, &mut rc).unwrap();
        gpu.render(&rays, &mut rg).unwrap();
        assert_same_f32(
            &format!("{mode:?} render"),
            &result_floats(&rc),
            &result_floats(&rg),
        );
        // the batch renders something, and the last ray misses the box
        assert!(rc.iter().filter(|r| r.opacity > 0.0).count() > 250);
        assert_eq!(rg.last().unwrap().opacity, 0.0);
    }
}

#[test]
fn one_step_gradients_adam_and_results_match_cpu() {
    one_step(RenderMode::SdfDensity);
}

/// Occupancy mode (the DIM-SLAM-like ablation) through the same passes.
#[test]
fn one_step_occupancy_matches_cpu() {
    one_step(RenderMode::Occupancy);
}

/// Early ray termination (`ModelConfig::min_transmittance`): the CPU reference stops
/// evaluating a ray's samples where its compositing stops, the GPU evaluates every sample in
/// its per-sample pass and composites the same way; the step is the same bits.
#[test]
fn one_step_with_early_termination_matches_cpu() {
    let mut cfg = small_config(RenderMode::SdfDensity);
    cfg.min_transmittance = 0.05;
    // The cut must bite: some rays use fewer samples than the uncut field gives them.
    let (data, rays) = setup_with(&cfg, 5, 200);
    let uncut = ModelLayout::new(&small_config(RenderMode::SdfDensity)).unwrap();
    let params = data.view();
    let mut s = himap_core::model::SampleScratch::new();
    let (mut a, mut b) = (
        himap_core::model::RayCache::new(),
        himap_core::model::RayCache::new(),
    );
    let cut = rays
        .iter()
        .enumerate()
        .filter(|(i, r)| {
            let i = *i as u32;
            himap_core::model::ray_forward(&data.layout, &params, r, i, 9, true, &mut a, &mut s);
            himap_core::model::ray_forward(&uncut, &params, r, i, 9, true, &mut b, &mut s);
            a.n < b.n
        })
        .count();
    assert!(cut >= 20, "only {cut} of {} rays were cut", rays.len());
    one_step_with(RenderMode::SdfDensity, &cfg);
}

/// `set_min_transmittance` between steps (the mapper's initialisation threshold) changes the
/// GPU's compositing exactly as the CPU's: results of every step and the final parameters.
#[test]
fn termination_threshold_set_between_steps_matches_cpu() {
    let (data, rays) = setup(RenderMode::SdfDensity, 5, 200);
    let adam = test_adam();
    let Some(mut gpu) = vulkan_or_skip(&data, adam) else {
        return;
    };
    let mut cpu_state = CpuState::new(&data);
    let mut cpu = cpu_state.backend(adam);
    let loss = loss_config(2, rays.len());
    // the threshold bites: it changes the GPU's renders of this field
    let mut uncut = vec![RayResult::default(); rays.len()];
    let mut cut = uncut.clone();
    gpu.render(&rays, &mut uncut).unwrap();
    gpu.set_min_transmittance(0.05).unwrap();
    gpu.render(&rays, &mut cut).unwrap();
    let differ = uncut
        .iter()
        .zip(&cut)
        .filter(|(a, b)| a.depth != b.depth)
        .count();
    assert!(differ >= 20, "only {differ} renders changed");
    for (step, t) in [0.0, 0.05, 0.0].into_iter().enumerate() {
        cpu.set_min_transmittance(t).unwrap();
        gpu.set_min_transmittance(t).unwrap();
        let mut rc = vec![RayResult::default(); rays.len()];
        let mut rg = vec![RayResult::default(); rays.len()];
        cpu.train_step(&rays, &loss, &mut rc).unwrap();
        gpu.train_step(&rays, &loss, &mut rg).unwrap();
        assert_same_f32(
            &format!("step {step} results"),
            &result_floats(&rc),
            &result_floats(&rg),
        );
        assert_eq!(gpu.layout().config.min_transmittance, t);
    }
    assert!(cpu.set_min_transmittance(1.0).is_err() && gpu.set_min_transmittance(-0.1).is_err());
    for g in Group::ALL {
        let i = g as usize;
        let mut p = vec![0.0f32; cpu_state.params[i].len()];
        gpu.read_params(g, &mut p).unwrap();
        assert_same_f32(&format!("{} params", g.name()), &cpu_state.params[i], &p);
    }
}

fn one_step(mode: RenderMode) {
    one_step_with(mode, &small_config(mode));
}

fn one_step_with(mode: RenderMode, cfg: &ModelConfig) {
    {
        let (data, rays) = setup_with(cfg, 5, 200);
        let adam = test_adam();
        let Some(mut gpu) = vulkan_or_skip(&data, adam) else {
            return;
        };
        let mut cpu_state = CpuState::new(&data);
        let loss = loss_config(9, rays.len());
        let mut rc = vec![RayResult::default(); rays.len()];
        let mut rg = vec![RayResult::default(); rays.len()];
        let sc = cpu_state
            .backend(adam)
            .train_step(&rays, &loss, &mut rc)
            .unwrap();
        let sg = gpu.train_step(&rays, &loss, &mut rg).unwrap();
        assert_same_f32(
            &format!("{mode:?} step results"),
            &result_floats(&rc),
            &result_floats(&rg),
        );
        assert!(same(sc.loss, sg.loss), "loss {} vs {}", sc.loss, sg.loss);
        assert_eq!((sc.rays_hit, sc.t), (sg.rays_hit, sg.t));
        for g in Group::ALL {
            let i = g as usize;
            let mut grads = vec![0i64; cpu_state.grad[i].len()];
            gpu.read_grads(g, &mut grads).unwrap();
            assert!(
                cpu_state.grad[i].iter().any(|&x| x != 0),
                "{mode:?} {}: no gradient at all (test is vacuous)",
                g.name()
            );
            let bad = (0..grads.len())
                .filter(|&k| grads[k] != cpu_state.grad[i][k])
                .count();
            assert_eq!(
                bad,
                0,
                "{mode:?} {}: {bad} fixed-point gradients differ",
                g.name()
            );
            let mut p = vec![0.0f32; grads.len()];
            let (mut m, mut v) = (p.clone(), p.clone());
            gpu.read_params(g, &mut p).unwrap();
            gpu.read_adam(g, &mut m, &mut v).unwrap();
            assert_same_f32(
                &format!("{mode:?} {} params", g.name()),
                &cpu_state.params[i],
                &p,
            );
            assert_same_f32(
                &format!("{mode:?} {} adam m", g.name()),
                &cpu_state.m[i],
                &m,
            );
            assert_same_f32(
                &format!("{mode:?} {} adam v", g.name()),
                &cpu_state.v[i],
                &v,
            );
            assert_ne!(p, data.params[i], "{} did not move", g.name());
        }
    }
}

/// Non-finite steps (a NaN target colour, an overflowing learning rate) are rejected on the
/// GPU exactly where the CPU rejects them (`loss_check_cs`, `adam_check_cs`), with the same
/// statistics and the same parameters and moments afterwards.
#[test]
fn nonfinite_steps_are_rejected_like_the_cpu() {
    let (data, rays) = setup(RenderMode::SdfDensity, 8, 150);
    let adam = test_adam();
    let Some(mut gpu) = vulkan_or_skip(&data, adam) else {
        return;
    };
    let lr = adam[Group::GeometryMlp].lr;
    let loss = loss_config(4, rays.len());
    let mut cpu_state = CpuState::new(&data);
    let sc = nonfinite_sequence(&mut cpu_state.backend(adam), &rays, &loss, lr).unwrap();
    let sg = nonfinite_sequence(&mut gpu, &rays, &loss, lr).unwrap();
    let key = |s: &[himap_core::step::StepStats]| -> Vec<(bool, u32, u32, u32)> {
        s.iter()
            .map(|s| (s.rejected, s.t, s.rays_hit, s.loss.to_bits()))
            .collect()
    };
    assert_eq!(key(&sg), key(&sc));
    let rejected: Vec<bool> = sc.iter().map(|s| s.rejected).collect();
    assert_eq!(rejected, vec![false, true, true, false]);
    for g in Group::ALL {
        let i = g as usize;
        let mut p = vec![0.0f32; cpu_state.params[i].len()];
        let (mut m, mut v) = (p.clone(), p.clone());
        gpu.read_params(g, &mut p).unwrap();
        gpu.read_adam(g, &mut m, &mut v).unwrap();
        assert_same_f32(&format!("{} params", g.name()), &cpu_state.params[i], &p);
        assert_same_f32(&format!("{} adam m", g.name()), &cpu_state.m[i], &m);
        assert_same_f32(&format!("{} adam v", g.name()), &cpu_state.v[i], &v);
        assert!(p.iter().all(|x| x.is_finite()), "{}: non-finite", g.name());
    }
}

/// A resumed run on the GPU (`MapBackend::import`: parameters, Adam moments, step count)
/// continues as the CPU does from the same state.
#[test]
fn imported_state_continues_like_the_cpu() {
    use himap::select::MapBackend;
    let (data, rays) = setup(RenderMode::SdfDensity, 3, 120);
    let adam = test_adam();
    let Some(mut gpu) = vulkan_or_skip(&data, adam) else {
        return;
    };
    let loss = loss_config(7, rays.len());
    let mut res = vec![RayResult::default(); rays.len()];
    // a state with non-zero moments and step count, from the CPU
    let mut cpu = ParallelCpuBackend::new(data.clone(), adam, 2).unwrap();
    for _ in 0..3 {
        cpu.train_step(&rays, &loss, &mut res).unwrap();
    }
    let saved = cpu.export().unwrap();
    assert_eq!(saved.t, 3);
    gpu.import(&saved).unwrap();
    assert_eq!(gpu.export().unwrap().params, saved.params);
    let mut rg = vec![RayResult::default(); rays.len()];
    let sc = cpu.train_step(&rays, &loss, &mut res).unwrap();
    let sg = gpu.train_step(&rays, &loss, &mut rg).unwrap();
    assert_eq!((sc.t, sg.t), (4, 4));
    assert_same_f32("results", &result_floats(&res), &result_floats(&rg));
    let (a, b) = (cpu.export().unwrap(), gpu.export().unwrap());
    for g in Group::ALL {
        let i = g as usize;
        assert_same_f32(&format!("{} params", g.name()), &a.params[i], &b.params[i]);
        assert_same_f32(&format!("{} adam m", g.name()), &a.m[i], &b.m[i]);
        assert_same_f32(&format!("{} adam v", g.name()), &a.v[i], &b.v[i]);
    }
}

/// 50 full training steps (new rays every step, the detached-colour switch, an Adam learning
/// rate change) end on the same parameters. Before the per-sample passes this diverged at
/// step 17: llvmpipe cuts every loop short once an invocation has run 65535 loop iterations.
#[test]
fn fifty_training_steps_match_cpu_bit_for_bit() {
    // The paper's model (6 + 2 factorized levels, 32-wide decoders, 48 samples per ray) over a
    // box small enough for the software driver: 0.64 m, so the finest 2 cm levels are 32^3.
    let mut cfg = ModelConfig::paper(Aabb::new([-0.32; 3], [0.32; 3]));
    cfg.grid_init_std = 0.1;
    cfg.sdf_bias_init = 0.05;
    let layout = ModelLayout::new(&cfg).expect("valid config");
    let data = ModelData::new(layout, 11).expect("init");
    let adam = test_adam();
    let Some(mut gpu) = vulkan_or_skip(&data, adam) else {
        return;
    };
    let mut cpu_state = CpuState::new(&data);
    let mut cpu = cpu_state.backend(adam);
    let n = 64;
    let mut rc = vec![RayResult::default(); n];
    let mut rg = vec![RayResult::default(); n];
    let mut first_loss = 0.0;
    let mut last_loss = 0.0;
    for step in 0..50u32 {
        let mut rays = himap::bench::rays_in(&cfg.aabb, n, 1000 + step as u64);
        for r in rays.iter_mut().step_by(2) {
            r.target_depth = 0.3; // every other ray also has the depth term
        }
        let mut loss = loss_config(step, n);
        // exercise the detached-colour path and the write/reset path on the way
        loss.color_to_geometry = step % 10 != 3;
        let sc = cpu.train_step(&rays, &loss, &mut rc).unwrap();
        let sg = gpu.train_step(&rays, &loss, &mut rg).unwrap();
        assert!(
            same(sc.loss, sg.loss),
            "step {step}: loss {} vs {}",
            sc.loss,
            sg.loss
        );
        if step == 0 {
            first_loss = sc.loss;
        }
        last_loss = sc.loss;
        if step == 25 {
            cpu.set_adam_lr(Group::AppearanceMlp, 2e-3).unwrap();
            gpu.set_adam_lr(Group::AppearanceMlp, 2e-3).unwrap();
        }
    }
    // The rays differ per step, so compare the trend loosely: training reduces the loss.
    assert!(last_loss < first_loss, "loss {first_loss} -> {last_loss}");
    for g in Group::ALL {
        let mut c = vec![0.0f32; data.layout.group_len(g)];
        let mut p = c.clone();
        cpu.read_params(g, &mut c).unwrap();
        gpu.read_params(g, &mut p).unwrap();
        assert_same_f32(&format!("{} after 50 steps", g.name()), &c, &p);
        assert_ne!(c, data.params[g as usize]);
    }
    // Overwriting parameters with Adam reset lands on the same state too.
    let zeros = vec![0.25f32; data.layout.group_len(Group::GeometryMlp)];
    cpu.write_params(Group::GeometryMlp, &zeros, true).unwrap();
    gpu.write_params(Group::GeometryMlp, &zeros, true).unwrap();
    let rays = himap::bench::rays_in(&cfg.aabb, n, 7);
    let loss = loss_config(77, n);
    cpu.train_step(&rays, &loss, &mut rc).unwrap();
    gpu.train_step(&rays, &loss, &mut rg).unwrap();
    for g in Group::ALL {
        let mut c = vec![0.0f32; data.layout.group_len(g)];
        let mut p = c.clone();
        cpu.read_params(g, &mut c).unwrap();
        gpu.read_params(g, &mut p).unwrap();
        assert_same_f32(&format!("{} after reset + step", g.name()), &c, &p);
    }
}

#[test]
fn sdf_and_colour_queries_match_cpu() {
    let (data, _) = setup(RenderMode::SdfDensity, 13, 0);
    let Some(mut gpu) = vulkan_or_skip(&data, paper_adam()) else {
        return;
    };
    // A 41^3 lattice over a box slightly larger than the scene (points outside are clamped).
    let k = 41;
    let mut points = Vec::with_capacity(k * k * k);
    for x in 0..k {
        for y in 0..k {
            for z in 0..k {
                let c = |i: usize| -1.1 + 2.2 * i as f32 / (k - 1) as f32;
                points.push([c(x), c(y), c(z)]);
            }
        }
    }
    let cpu = ParallelCpuBackend::new(data.clone(), paper_adam(), 0).unwrap();
    let mut sc = vec![0.0f32; points.len()];
    let mut sg = sc.clone();
    cpu.sdf(&points, &mut sc);
    gpu.sdf(&points, &mut sg).unwrap();
    assert_same_f32("sdf", &sc, &sg);
    assert!(sc.iter().any(|&s| s != sc[0]));
    let mut cc = vec![[0.0f32; 3]; points.len()];
    let mut cg = cc.clone();
    cpu.color(&points, &mut cc);
    gpu.color(&points, &mut cg).unwrap();
    assert_same_f32(
        "colour",
        &cc.iter().flatten().copied().collect::<Vec<_>>(),
        &cg.iter().flatten().copied().collect::<Vec<_>>(),
    );
    // size mismatches are errors, not panics
    assert!(matches!(
        gpu.sdf(&points, &mut sg[..3]),
        Err(VulkanError::Core(_))
    ));
}

#[test]
fn backend_contract_errors() {
    let (data, rays) = setup(RenderMode::SdfDensity, 1, 4);
    let Some(mut gpu) = vulkan_or_skip(&data, paper_adam()) else {
        return;
    };
    assert!(gpu.name().starts_with("vulkan: "));
    let mut short = vec![RayResult::default(); rays.len() - 1];
    assert!(matches!(
        gpu.render(&rays, &mut short),
        Err(VulkanError::Core(_))
    ));
    let mut p = vec![0.0; 2];
    assert!(matches!(
        gpu.read_params(Group::GeometryGrid, &mut p),
        Err(VulkanError::Core(_))
    ));
    assert!(gpu.set_adam_lr(Group::Beta, f32::NAN).is_err());
    // no image store: uploads and mapping steps are errors, not panics
    assert_eq!(gpu.image_store().slots, 0);
    let e = gpu.upload_frame(0, &[]).unwrap_err();
    assert!(matches!(e, VulkanError::Core(_)), "{e}");
    // empty batches are fine and still take an Adam step, as on the CPU
    let s = gpu.train_step(&[], &loss_config(0, 1), &mut []).unwrap();
    assert_eq!((s.t, s.rays_hit, s.loss), (1, 0, 0.0));
}

/// Rough throughput of `train_ray_cs` against the single-threaded CPU reference (a
/// measurement, not a check): `cargo test --release -p himap-tests --test vulkan_conformance
/// throughput -- --ignored --nocapture`.
#[test]
#[ignore = "timing only"]
fn throughput() {
    let (data, _) = setup(RenderMode::SdfDensity, 2, 0);
    let adam = test_adam();
    let Some(mut gpu) = vulkan_or_skip(&data, adam) else {
        return;
    };
    let mut cpu_state = CpuState::new(&data);
    let mut cpu = cpu_state.backend(adam);
    let n = 4096;
    let rays = random_rays(n, 5);
    let loss = loss_config(1, n);
    let mut r = vec![RayResult::default(); n];
    let samples = (n * data.layout.config.samples as usize) as f64;
    let t0 = std::time::Instant::now();
    cpu.train_step(&rays, &loss, &mut r).unwrap();
    let cpu_s = t0.elapsed().as_secs_f64();
    gpu.train_step(&rays, &loss, &mut r).unwrap();
    let t0 = std::time::Instant::now();
    gpu.train_step(&rays, &loss, &mut r).unwrap();
    let gpu_s = t0.elapsed().as_secs_f64();
    eprintln!(
        "train step, {n} rays x {} samples: cpu {:.0} samples/s ({cpu_s:.2} s), {} {:.0} samples/s ({gpu_s:.2} s)",
        data.layout.config.samples,
        samples / cpu_s,
        gpu.name(),
        samples / gpu_s
    );
}

/// A small synthetic window: the room of `himap demo` seen from `frames` poses at 32x24, the
/// model's box around the room, and the frames packed as RGBA8.
fn synthetic_window(
    mode: RenderMode,
    frames: usize,
) -> (ModelData, Intrinsics, Vec<Pose>, Vec<Vec<u32>>) {
    let scene = Scene::generate(3);
    let k = synth_intrinsics(32, 24);
    let poses: Vec<Pose> = (0..frames).map(|i| synth_pose(&scene, i, 40)).collect();
    let images = poses
        .iter()
        .map(|p| {
            let (rgb, _) = scene.render(&k, p);
            rgb.data
                .chunks(3)
                .map(|c| pack_rgba8([c[0], c[1], c[2]]))
                .collect()
        })
        .collect();
    let mut cfg = small_config(mode);
    cfg.aabb = scene.bounds();
    let layout = ModelLayout::new(&cfg).expect("valid config");
    (ModelData::new(layout, 21).expect("init"), k, poses, images)
}

/// The mapping step (`pixel_train`: colour L1 + DIM-SLAM warping loss through the rendered
/// depth + depth prior) on the GPU equals the CPU reference bit for bit: per-pixel results,
/// every parameter after a few steps, across the colour-to-geometry and depth-prior switches.
#[test]
fn mapping_steps_match_cpu_bit_for_bit() {
    let frames = 6;
    let (data, k, poses, images) = synthetic_window(RenderMode::SdfDensity, frames);
    let adam = test_adam();
    let store = ImageStore {
        width: k.width,
        height: k.height,
        slots: frames as u32 + 2,
    };
    let Some(gpu) = vulkan_or_skip(&data, adam) else {
        return;
    };
    let mut gpu = gpu.with_images(store).expect("image slots");
    let mut cpu_state = CpuState::new(&data);
    let mut cpu_images = vec![0u32; store.total_len()];
    let mut cpu = cpu_state
        .backend(adam)
        .with_images(store, &mut cpu_images)
        .expect("cpu images");
    // frame i in slot (i + 2) % slots, so the slot table is not the identity
    let slots: Vec<u32> = (0..frames as u32).map(|i| (i + 2) % store.slots).collect();
    for (img, &slot) in images.iter().zip(&slots) {
        cpu.upload_frame(slot, img).unwrap();
        gpu.upload_frame(slot, img).unwrap();
    }
    let mut rng = himap_core::rng::SplitMix::new(5);
    let n = 96;
    let mut any_warp = false;
    for step in 0..4u32 {
        let pixels: Vec<PixelSample> = (0..n)
            .map(|_| PixelSample {
                frame: (rng.unit() * frames as f32) as u32 % frames as u32,
                u: (rng.unit() * k.width as f32) as u32 % k.width,
                v: (rng.unit() * k.height as f32) as u32 % k.height,
            })
            .collect();
        let mut warp = WarpConfig::dim_slam();
        warp.min_views = 2;
        warp.margin = 2.0;
        warp.half = 3;
        let loss = MappingLoss {
            lambda_color: 0.1,
            lambda_warp: 1.0,
            color_scale: 1.0 / n as f32,
            warp_scale: 1.0 / n as f32,
            color_to_geometry: step != 2,
            seed: 40 + step,
            warp,
            lambda_depth_prior: if step < 2 { 0.5 } else { 0.0 },
            depth_prior: 1.5,
            depth_prior_near: if step == 1 { 1.0 } else { 0.0 },
        };
        let batch = MapBatch {
            k,
            poses: &poses,
            slots: &slots,
            pixels: &pixels,
            loss,
        };
        let mut rc = vec![PixelResult::default(); n];
        let mut rg = vec![PixelResult::default(); n];
        let sc = cpu.map_step(&batch, &mut rc).unwrap();
        let sg = gpu.map_step(&batch, &mut rg).unwrap();
        for (i, (a, b)) in rc.iter().zip(&rg).enumerate() {
            let fa = [
                a.color[0],
                a.color[1],
                a.color[2],
                a.depth,
                a.opacity,
                a.color_loss,
                a.warp_loss,
            ];
            let fb = [
                b.color[0],
                b.color[1],
                b.color[2],
                b.depth,
                b.opacity,
                b.color_loss,
                b.warp_loss,
            ];
            assert_same_f32(&format!("step {step} pixel {i}"), &fa, &fb);
            assert_eq!(a.warp_views, b.warp_views, "step {step} pixel {i} views");
        }
        any_warp |= rc.iter().any(|r| r.warp_loss != 0.0);
        assert!(
            same(sc.loss, sg.loss),
            "step {step}: {} vs {}",
            sc.loss,
            sg.loss
        );
        assert_eq!((sc.rays_hit, sc.t), (sg.rays_hit, sg.t));
    }
    assert!(
        any_warp,
        "no pixel had a valid warp: the test would not cover the warping loss"
    );
    for g in Group::ALL {
        let mut c = vec![0.0f32; data.layout.group_len(g)];
        let mut p = c.clone();
        cpu.read_params(g, &mut c).unwrap();
        gpu.read_params(g, &mut p).unwrap();
        assert_same_f32(&format!("{} after mapping steps", g.name()), &c, &p);
        assert_ne!(c, data.params[g as usize], "{} did not move", g.name());
    }
    // a window that names a slot past the store is an error on both
    let bad = [0u32, 99];
    let batch = MapBatch {
        k,
        poses: &poses[..2],
        slots: &bad,
        pixels: &[],
        loss: MappingLoss {
            lambda_color: 0.1,
            lambda_warp: 1.0,
            color_scale: 1.0,
            warp_scale: 1.0,
            color_to_geometry: true,
            seed: 0,
            warp: WarpConfig::dim_slam(),
            lambda_depth_prior: 0.0,
            depth_prior: 1.5,
            depth_prior_near: 0.0,
        },
    };
    assert!(gpu.map_step(&batch, &mut []).is_err());
    assert!(cpu.map_step(&batch, &mut []).is_err());
}

/// A full image rendered by `render_view` (one ray per pixel, bin-centre samples) after a few
/// training steps is the same on both backends, pixel for pixel.
#[test]
fn full_image_render_matches_cpu() {
    let (data, k, poses, _) = synthetic_window(RenderMode::SdfDensity, 2);
    let adam = test_adam();
    let Some(mut gpu) = vulkan_or_skip(&data, adam) else {
        return;
    };
    let mut cpu_state = CpuState::new(&data);
    let mut cpu = cpu_state.backend(adam);
    let aabb = data.layout.config.aabb;
    let n = 256;
    let mut rc = vec![RayResult::default(); n];
    let mut rg = vec![RayResult::default(); n];
    for step in 0..3 {
        let rays = himap::bench::rays_in(&aabb, n, 300 + step);
        cpu.train_step(&rays, &loss_config(step as u32, n), &mut rc)
            .unwrap();
        gpu.train_step(&rays, &loss_config(step as u32, n), &mut rg)
            .unwrap();
    }
    let a = himap::mapper_cli::render_view(&mut cpu, &k, &poses[1]).unwrap();
    let b = himap::mapper_cli::render_view(&mut gpu, &k, &poses[1]).unwrap();
    assert_eq!(a.len(), (k.width * k.height) as usize);
    assert!(a.iter().filter(|r| r.opacity > 0.0).count() > a.len() / 2);
    assert_same_f32("full image", &result_floats(&a), &result_floats(&b));
}

/// End to end: `himap map` (the mapper's initialisation and an online update, evaluation,
/// mesh and saved map) on `--backend vulkan` writes the same per-update losses and the same
/// map, bit for bit, as on `--backend cpu`.
#[test]
fn map_command_on_vulkan_equals_cpu() {
    let probe = setup(RenderMode::SdfDensity, 1, 0).0;
    if vulkan_or_skip(&probe, test_adam()).is_none() {
        return;
    }
    let dir = std::env::temp_dir().join(format!("himap-e2e-{}", std::process::id()));
    let data = dir.join("room");
    himap::synth::write_synthetic(
        &data,
        &himap::synth::SynthOptions {
            frames: 17,
            width: 32,
            height: 24,
            seed: 2,
        },
    )
    .unwrap();
    let mut cfg = himap::config::Config::small();
    cfg.model.samples = 12;
    cfg.mapper.init_iters = 12;
    cfg.mapper.init_color_iters = 6;
    cfg.mapper.depth_prior_iters = 4;
    // A window of 6 frames: the warping loss runs in one invocation per pixel over every
    // window frame, and llvmpipe silently cuts the loops of an invocation past 65535
    // iterations (ARCHITECTURE.md); with the 15-frame window of `small` and a start where
    // most warp pairs are valid, a pixel's warp loss most likely passes that budget and the software
    // driver's results differ from the CPU from the 4th iteration on (issue #13: split the
    // warp pass per view / detect the budget).
    cfg.mapper.init_frames = 6;
    cfg.mapper.local_frames = 6;
    cfg.mapper.window_keyframes = 2;
    cfg.mapper.iters = 2;
    cfg.mapper.pixels = 64;
    cfg.eval.mesh_resolution = 0.3;
    cfg.eval.mesh_samples = 500;
    let run = |backend: &str| {
        let opts = himap::mapper_cli::MapOptions {
            backend: backend.into(),
            ..himap::mapper_cli::MapOptions::new(data.clone(), dir.join(backend), cfg.clone(), 2)
        };
        let s = himap::mapper_cli::run_map(&opts).unwrap();
        let csv = std::fs::read_to_string(opts.out.join("metrics.csv")).unwrap();
        // frame, kind, psnr, ssim, depth, loss_first, loss, colour, warp (drop timings)
        let rows: Vec<String> = csv
            .lines()
            .map(|l| l.split(',').take(10).collect::<Vec<_>>().join(","))
            .collect();
        let (_, map) = himap::mapper_cli::load_map(&opts.out.join("map.safetensors")).unwrap();
        (s, rows, map)
    };
    let (sc, rc, mc) = run("cpu");
    let (sg, rg, mg) = run("vulkan");
    assert!(sg.backend.starts_with("vulkan"), "{}", sg.backend);
    // init at frame 5, online at 10 and 15, the final update with frame 16
    assert_eq!(sc.updates, 4);
    assert_eq!((sc.updates, sc.iterations), (sg.updates, sg.iterations));
    assert_eq!(rc, rg, "metrics.csv differs");
    for g in Group::ALL {
        let i = g as usize;
        assert_same_f32(&format!("map {}", g.name()), &mc.params[i], &mg.params[i]);
    }
    assert_eq!(sc.mesh_faces, sg.mesh_faces);
    let _ = std::fs::remove_dir_all(&dir);
}

/// Grids larger than one storage-buffer binding are split in two parts: with the binding
/// limit forced below both grids, training steps, gradients, rendering and queries still equal
/// the CPU's bit for bit, and a group that does not fit even in two parts is a clear error.
#[test]
fn grids_split_across_two_bindings_match_cpu() {
    let (data, rays) = setup(RenderMode::SdfDensity, 6, 150);
    let lens = data.layout.group_lens();
    let (geo, app) = (lens[0], lens[1]);
    let part = geo.max(app).div_ceil(2);
    assert!(
        part < geo.min(app) && lens[2].max(lens[3]) <= part,
        "{lens:?}"
    );
    let adam = test_adam();
    let probe = vulkan_or_skip(&data, adam);
    if probe.is_none() {
        return;
    }
    drop(probe);
    let params = data.param_slices();
    let options = VulkanOptions {
        max_binding_bytes: Some(part as u64 * 8),
    };
    let mut gpu = VulkanBackend::with_options(data.layout, params, adam, options).unwrap();
    let mut cpu_state = CpuState::new(&data);
    let mut cpu = cpu_state.backend(adam);
    let n = rays.len();
    let mut rc = vec![RayResult::default(); n];
    let mut rg = vec![RayResult::default(); n];
    for step in 0..3 {
        let loss = loss_config(step, n);
        let sc = cpu.train_step(&rays, &loss, &mut rc).unwrap();
        let sg = gpu.train_step(&rays, &loss, &mut rg).unwrap();
        assert!(
            same(sc.loss, sg.loss),
            "step {step}: {} vs {}",
            sc.loss,
            sg.loss
        );
        assert_same_f32(
            "split step results",
            &result_floats(&rc),
            &result_floats(&rg),
        );
    }
    for g in Group::ALL {
        let len = data.layout.group_len(g);
        let (mut c, mut q) = (vec![0.0f32; len], vec![0.0f32; len]);
        cpu.read_params(g, &mut c).unwrap();
        gpu.read_params(g, &mut q).unwrap();
        assert_same_f32(&format!("split {} params", g.name()), &c, &q);
        let (mut gc, mut gg) = (vec![0i64; len], vec![0i64; len]);
        cpu.read_grads(g, &mut gc).unwrap();
        gpu.read_grads(g, &mut gg).unwrap();
        assert_eq!(gc, gg, "split {} gradients", g.name());
    }
    cpu.render(&rays, &mut rc).unwrap();
    gpu.render(&rays, &mut rg).unwrap();
    assert_same_f32("split render", &result_floats(&rc), &result_floats(&rg));
    // writing a split group lands in both parts
    let w: Vec<f32> = (0..geo).map(|i| (i % 7) as f32 * 0.01).collect();
    gpu.write_params(Group::GeometryGrid, &w, true).unwrap();
    let mut back = vec![0.0f32; geo];
    gpu.read_params(Group::GeometryGrid, &mut back).unwrap();
    assert_eq!(back, w);
    // a grid that needs more than two bindings is an error naming the limit
    let tiny = VulkanOptions {
        max_binding_bytes: Some((geo as u64 * 8) / 3),
    };
    let e = VulkanBackend::with_options(data.layout, params, adam, tiny)
        .err()
        .expect("three parts are not supported");
    assert!(matches!(e, VulkanError::TensorTooLarge { .. }), "{e}");
}
