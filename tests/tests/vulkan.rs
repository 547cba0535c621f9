//! What only the Vulkan backend has, against the CPU: state import, the SDF and colour
//! queries, grids split across two bindings, `himap map` end to end, its errors, and a rough
//! throughput. The checks every backend shares are in the conformance suite
//! (`tests/conformance.rs`).

use himap::backend::ParallelCpuBackend;
use himap::dump::random_rays;
use himap_core::field::model::{Group, RayResult};
use himap_core::field::render::RenderMode;
use himap_core::train::backend::{paper_adam, Backend, ImageStore};
use himap_tests::conformance::{
    assert_same_f32, assert_same_params, loss_config, result_floats, same, setup, test_adam,
    Reference,
};
use himap_tests::vulkan_or_skip;
use himap_vulkan::{BackwardPass, VulkanBackend, VulkanError, VulkanOptions};

/// Errors of the Vulkan backend carry the core's error for contract violations.
#[test]
fn contract_errors_are_core_errors() {
    let (data, rays) = setup(RenderMode::SdfDensity, 1, 4);
    let Some(mut gpu) = vulkan_or_skip(&data, paper_adam()) else {
        return;
    };
    assert!(gpu.name().starts_with("vulkan: "));
    let mut short = vec![RayResult::default(); rays.len() - 1];
    let e = gpu.render(&rays, &mut short).unwrap_err();
    assert!(matches!(e, VulkanError::Core(_)), "{e}");
    // no image store: uploads are errors, not panics
    assert_eq!(gpu.image_store().slots, 0);
    let e = gpu.upload_frame(0, &[]).unwrap_err();
    assert!(matches!(e, VulkanError::Core(_)), "{e}");
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

/// Rough throughput of `train_ray_cs` against the single-threaded CPU reference (a
/// measurement, not a check): `cargo test --release -p himap-tests --test vulkan
/// throughput -- --ignored --nocapture`.
#[test]
#[ignore = "timing only"]
fn throughput() {
    let (data, _) = setup(RenderMode::SdfDensity, 2, 0);
    let adam = test_adam();
    let Some(mut gpu) = vulkan_or_skip(&data, adam) else {
        return;
    };
    let mut reference = Reference::new(&data, ImageStore::default());
    let mut cpu = reference.backend(adam);
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

/// `himap map` of `frames` frames of a 32 x 24 synthetic room (seed 2) in `dir`, on the CPU
/// and on Vulkan (`--profile` there: steps timed one by one instead of queued, the same
/// bits): each run's summary, `metrics.csv` rows without their timings, and saved map.
/// `default_box` removes the room's `scene.json` (the box is then the default one around the
/// first camera).
fn map_on_cpu_and_vulkan(
    dir: &std::path::Path,
    frames: usize,
    default_box: bool,
    cfg: &himap::config::Config,
) -> [(
    himap::mapper_cli::MapSummary,
    Vec<String>,
    himap::backend::ModelData,
); 2] {
    let data = dir.join("room");
    himap::synth::write_synthetic(
        &data,
        &himap::synth::SynthOptions {
            frames,
            width: 32,
            height: 24,
            seed: 2,
        },
    )
    .unwrap();
    if default_box {
        std::fs::remove_file(data.join("scene.json")).unwrap();
    }
    ["cpu", "vulkan"].map(|backend| {
        let opts = himap::mapper_cli::MapOptions {
            backend: backend.into(),
            profile: backend == "vulkan",
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
        assert!(
            backend == "cpu" || s.backend.starts_with("vulkan"),
            "{}",
            s.backend
        );
        (s, rows, map)
    })
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
    // the final refinement too: 7 iterations in blocks of 3 over windows of 4 held frames
    (cfg.mapper.refine_iters, cfg.mapper.refine_block) = (7, 3);
    cfg.mapper.refine_window = 4;
    cfg.eval.mesh_resolution = 0.3;
    cfg.eval.mesh_samples = 500;
    let [(sc, rc, mc), (sg, rg, mg)] = map_on_cpu_and_vulkan(&dir, 17, false, &cfg);
    // init at frame 5, online at 10 and 15, the final update with frame 16
    assert_eq!(sc.updates, 4);
    assert_eq!(sc.iterations, 12 + 3 * 2 + 7);
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
    // (the global-atomics backward here; the conformance suite runs the workgroup-summed
    // one where the device has it)
    let options = VulkanOptions {
        max_binding_bytes: Some(part as u64 * 8),
        global_atomics_only: true,
        ..VulkanOptions::default()
    };
    let mut gpu = VulkanBackend::with_options(data.layout, params, adam, options).unwrap();
    let mut reference = Reference::new(&data, ImageStore::default());
    let mut cpu = reference.backend(adam);
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
    assert_same_params("split", &mut cpu, &mut gpu);
    for g in Group::ALL {
        let len = data.layout.group_len(g);
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
        ..VulkanOptions::default()
    };
    let e = VulkanBackend::with_options(data.layout, params, adam, tiny)
        .err()
        .expect("three parts are not supported");
    assert!(matches!(e, VulkanError::TensorTooLarge { .. }), "{e}");
}

/// Where the device has both backward structures and timestamps, the first steps time both
/// (alternating, one warm-up step each) and keep the faster; every step gives the CPU's
/// bits whichever structure it used.
#[test]
fn the_backward_structure_is_chosen_by_timing_both() {
    let (data, rays) = setup(RenderMode::SdfDensity, 5, 64);
    let adam = test_adam();
    let Some(mut gpu) = vulkan_or_skip(&data, adam) else {
        return;
    };
    let mut cpu = ParallelCpuBackend::new(data.clone(), adam, 1).unwrap();
    let n = rays.len();
    let (mut rc, mut rg) = (vec![RayResult::default(); n], vec![RayResult::default(); n]);
    assert_eq!(gpu.backward_pass().0.is_none(), gpu.workgroup_sums());
    for step in 0..9 {
        let loss = loss_config(step, n);
        let sc = cpu.train_step(&rays, &loss, &mut rc).unwrap();
        let sg = gpu.train_step(&rays, &loss, &mut rg).unwrap();
        assert_eq!((sc.t, sc.rejected), (sg.t, sg.rejected));
        assert_same_f32(
            &format!("step {step}"),
            &result_floats(&rc),
            &result_floats(&rg),
        );
    }
    assert_same_params("chosen backward:", &mut cpu, &mut gpu);
    let (chosen, ms) = gpu.backward_pass();
    eprintln!("{}: backward {chosen:?}, least ms {ms:?}", gpu.name());
    let chosen = chosen.expect("chosen after 9 steps");
    if !gpu.workgroup_sums() {
        assert_eq!(chosen, BackwardPass::GlobalAtomics);
    } else if let [Some(global), Some(sums)] = ms {
        let faster = if sums <= global {
            BackwardPass::WorkgroupSums
        } else {
            BackwardPass::GlobalAtomics
        };
        assert_eq!(chosen, faster);
    } else {
        // no timestamps on this device: the structure built for real GPUs
        assert_eq!((chosen, ms), (BackwardPass::WorkgroupSums, [None, None]));
    }
}

/// `enable_profiling` times every pass of a training step with timestamp queries (and the
/// host's transfers) without changing what the step computes.
#[test]
fn profiled_steps_name_every_pass_and_keep_the_bits() {
    let (data, rays) = setup(RenderMode::SdfDensity, 5, 64);
    let adam = test_adam();
    let Some(mut plain) = vulkan_or_skip(&data, adam) else {
        return;
    };
    let mut timed = vulkan_or_skip(&data, adam).unwrap();
    let has_timestamps = timed.enable_profiling().unwrap();
    let loss = loss_config(3, rays.len());
    let (mut ra, mut rb) = (
        vec![RayResult::default(); rays.len()],
        vec![RayResult::default(); rays.len()],
    );
    let t0 = std::time::Instant::now();
    for _ in 0..2 {
        plain.train_step(&rays, &loss, &mut ra).unwrap();
        timed.train_step(&rays, &loss, &mut rb).unwrap();
    }
    let wall_ms = t0.elapsed().as_secs_f64() * 1e3;
    assert_same_f32("results", &result_floats(&ra), &result_floats(&rb));
    assert_same_params("profiled:", &mut plain, &mut timed);
    let prof = timed.profile();
    let names: Vec<&str> = prof.iter().map(|p| p.name).collect();
    let want_host = ["upload (host)", "read back (host)"];
    for w in want_host {
        assert!(names.contains(&w), "{names:?}");
    }
    if has_timestamps {
        for w in [
            "zero gradients",
            "forward (per sample)",
            "composite and loss (per ray)",
            "backward (per sample)",
            "finiteness checks",
            "Adam",
        ] {
            let p = prof
                .iter()
                .find(|p| p.name == w)
                .unwrap_or_else(|| panic!("{w}: {names:?}"));
            assert!(p.device && p.count == 2, "{p:?}");
            assert!(p.total_ms >= 0.0);
        }
        let total: f64 = prof.iter().map(|p| p.total_ms).sum();
        assert!(
            total > 0.0 && total <= wall_ms,
            "{total} ms of {wall_ms} ms"
        );
    }
    timed.reset_profile();
    assert!(timed.profile().is_empty());
}

/// The loop canary measures how many loop iterations one invocation completes: llvmpipe cuts
/// every loop of an invocation after 65535 (a real GPU completes the canary's longest loop);
/// a mapping window whose warping pass could need more is refused with the reason instead of
/// running silently wrong, and one that fits runs.
#[test]
fn the_loop_canary_measures_the_budget_and_guards_the_warping_pass() {
    use himap_core::gpu_abi::pixel_train_loop_bound;
    use himap_core::loss::planar::PlanarConfig;
    use himap_core::loss::warp::WarpConfig;
    use himap_core::train::backend::MapBatch;
    use himap_core::train::pixel::{MappingLoss, PixelResult, PixelSample};
    use himap_tests::conformance::synthetic_window;

    let frames = 20;
    let (data, k, poses, images) = synthetic_window(RenderMode::SdfDensity, frames);
    let store = ImageStore {
        width: k.width,
        height: k.height,
        slots: frames as u32,
    };
    let Some(gpu) = vulkan_or_skip(&data, test_adam()) else {
        return;
    };
    let mut gpu = gpu.with_images(store).unwrap();
    let budget = gpu.loop_budget();
    eprintln!("{}: loop budget {budget:?}", gpu.name());
    if gpu.name().contains("llvmpipe") {
        let b = budget.expect("llvmpipe cuts loops");
        assert!((60_000..=65_535).contains(&b), "budget {b}");
    }
    for (i, img) in images.iter().enumerate() {
        gpu.upload_frame(i as u32, img).unwrap();
    }
    let slots: Vec<u32> = (0..frames as u32).collect();
    let pixels = vec![
        PixelSample {
            frame: 0,
            u: 5,
            v: 7
        };
        8
    ];
    let mut res = vec![PixelResult::default(); pixels.len()];
    let step = |gpu: &mut VulkanBackend, n: usize, res: &mut [PixelResult]| {
        let batch = MapBatch {
            k,
            poses: &poses[..n],
            slots: &slots[..n],
            pixels: &pixels,
            loss: MappingLoss {
                lambda_color: 0.1,
                lambda_warp: 1.0,
                color_scale: 0.125,
                warp_scale: 0.125,
                color_to_geometry: true,
                seed: 1,
                warp: WarpConfig::dim_slam(),
                lambda_depth_prior: 0.0,
                depth_prior: 1.5,
                depth_prior_near: 0.0,
                planar: PlanarConfig::OFF,
                lambda_plane: 0.0,
            },
            lr: None,
        };
        gpu.map_step(&batch, res, None)
    };
    match budget {
        Some(b) => {
            assert!(pixel_train_loop_bound(frames as u32) > b);
            let e = step(&mut gpu, frames, &mut res).unwrap_err();
            assert!(matches!(e, VulkanError::LoopBudget { .. }), "{e}");
            assert!(e.to_string().contains("mapping window"), "{e}");
            // the 6-frame window of the conformance tests fits
            assert!(pixel_train_loop_bound(6) <= b);
            step(&mut gpu, 6, &mut res).unwrap();
        }
        None => {
            step(&mut gpu, frames, &mut res).unwrap();
        }
    }
}

/// The workgroup-summed backward (`sample_backward_wg_cs`: decoder-weight gradients summed in
/// workgroup memory, one global atomic per weight and workgroup) gives the same gradients,
/// parameters and results as one global atomic per contribution and as the CPU, for a model
/// whose two decoders fit the workgroup memory (the small one) and for the paper's, where
/// only the geometry decoder does.
#[test]
fn workgroup_summed_backward_equals_global_atomics_and_the_cpu() {
    use himap::backend::ModelData;
    use himap_core::field::model::ModelLayout;
    use himap_core::gpu_abi::WORKGROUP_MLP_SLOTS;

    let (small, small_rays) = setup(RenderMode::SdfDensity, 9, 96);
    let paper_cfg = himap::bench::configs()
        .into_iter()
        .find(|(n, _)| n.starts_with("paper"))
        .unwrap()
        .1;
    let paper_layout = ModelLayout::new(&paper_cfg).unwrap();
    let paper = ModelData::new(paper_layout, 4).unwrap();
    let paper_rays = himap::bench::rays_in(&paper_cfg.aabb, 12, 11);
    let adam = test_adam();
    for (name, data, rays) in [
        ("small", &small, &small_rays),
        ("paper", &paper, &paper_rays),
    ] {
        let l = data.layout;
        let (geo, app) = (
            l.group_len(Group::GeometryMlp),
            l.group_len(Group::AppearanceMlp),
        );
        eprintln!("{name}: decoders {geo} + {app} weights, {WORKGROUP_MLP_SLOTS} slots");
        if vulkan_or_skip(data, adam).is_none() {
            return;
        }
        let mut wg = VulkanBackend::with_options(
            l,
            data.param_slices(),
            adam,
            VulkanOptions {
                backward: Some(BackwardPass::WorkgroupSums),
                ..VulkanOptions::default()
            },
        )
        .unwrap();
        let mut global = VulkanBackend::with_options(
            l,
            data.param_slices(),
            adam,
            VulkanOptions {
                global_atomics_only: true,
                ..VulkanOptions::default()
            },
        )
        .unwrap();
        assert!(!global.workgroup_sums());
        let mut cpu = ParallelCpuBackend::new(data.clone(), adam, 2).unwrap();
        let n = rays.len();
        let (mut rw, mut rg, mut rc) = (
            vec![RayResult::default(); n],
            vec![RayResult::default(); n],
            vec![RayResult::default(); n],
        );
        for step in 0..if name == "small" { 2 } else { 1 } {
            let loss = loss_config(step, n);
            wg.train_step(rays, &loss, &mut rw).unwrap();
            global.train_step(rays, &loss, &mut rg).unwrap();
            cpu.train_step(rays, &loss, &mut rc).unwrap();
            assert_same_f32(
                &format!("{name} results"),
                &result_floats(&rw),
                &result_floats(&rg),
            );
            assert_same_f32(
                &format!("{name} results (cpu)"),
                &result_floats(&rc),
                &result_floats(&rw),
            );
        }
        for g in Group::ALL {
            let len = l.group_len(g);
            let (mut a, mut b, mut c) = (vec![0i64; len], vec![0i64; len], vec![0i64; len]);
            wg.read_grads(g, &mut a).unwrap();
            global.read_grads(g, &mut b).unwrap();
            cpu.read_grads(g, &mut c).unwrap();
            assert_eq!(a, b, "{name} {} gradients", g.name());
            assert_eq!(c, a, "{name} {} gradients (cpu)", g.name());
            if matches!(g, Group::GeometryMlp | Group::AppearanceMlp) {
                assert!(
                    a.iter().any(|&q| q != 0),
                    "{name} {}: no gradient",
                    g.name()
                );
            }
        }
        eprintln!("{name}: workgroup sums {}", wg.workgroup_sums());
    }
}

/// The kernels' division (`math::div`, correctly rounded in SPIR-V) gives the CPU's bits on
/// the device for every kind of operand: random bit patterns (subnormals, infinities, NaNs,
/// overflowing and underflowing quotients) and the moderate values the kernels divide.
#[test]
fn the_kernels_division_equals_the_cpus() {
    let (mut a, mut b) = himap_vulkan::division_pairs(20_000);
    for (x, y) in [
        (1.0f32, 3.0f32),
        (0.0, 0.0),
        (f32::INFINITY, f32::INFINITY),
        (1.0, 0.0),
        (-0.0, 5.0),
        (f32::MIN_POSITIVE, 3.0),
        (f32::from_bits(1), 0.75),
        (f32::MAX, 0.5),
        (f32::from_bits(0x00ff_ffff), f32::from_bits(0x0080_0001)),
    ] {
        a.push(x);
        b.push(y);
    }
    let Some((q, _, _)) =
        himap_tests::vulkan_result_or_skip(himap_vulkan::divide_on_device(&a, &b))
    else {
        return;
    };
    let want: Vec<f32> = a.iter().zip(&b).map(|(x, y)| x / y).collect();
    assert_same_f32("quotients", &want, &q);
}

/// `scene.grow` on the GPU: a default box around a camera circling a room grows before
/// frames are pushed (the map resampled on the host, the backend rebuilt on the same device
/// with its image slots), and `himap map` on `--backend vulkan` writes the same metrics and
/// map, bit for bit, as on `--backend cpu`, over the same grown box.
#[test]
fn map_command_grows_the_box_on_vulkan_as_on_cpu() {
    let probe = setup(RenderMode::SdfDensity, 1, 0).0;
    if vulkan_or_skip(&probe, test_adam()).is_none() {
        return;
    }
    let dir = std::env::temp_dir().join(format!("himap-e2e-grow-{}", std::process::id()));
    // no metadata box: the default one around the first camera, small enough to grow
    let mut cfg = himap::config::Config::small();
    cfg.scene.default_horizontal = 1.0;
    cfg.scene.grow_margin = 0.8;
    cfg.scene.grow_step = 0.5;
    cfg.model.samples = 12;
    cfg.mapper.init_iters = 8;
    cfg.mapper.init_color_iters = 4;
    cfg.mapper.depth_prior_iters = 4;
    // a 6-frame window: llvmpipe's loop budget (see map_command_on_vulkan_equals_cpu)
    cfg.mapper.init_frames = 4;
    cfg.mapper.local_frames = 4;
    cfg.mapper.window_keyframes = 2;
    cfg.mapper.update_every = 2;
    cfg.mapper.iters = 2;
    cfg.mapper.pixels = 64;
    cfg.mapper.refine_iters = 0;
    cfg.eval.every = 2;
    cfg.eval.final_every = 0;
    cfg.eval.mesh_resolution = 0.3;
    cfg.eval.mesh_samples = 300;
    let [(sc, rc, mc), (sg, rg, mg)] = map_on_cpu_and_vulkan(&dir, 12, true, &cfg);
    let e = |s: &himap::mapper_cli::MapSummary| {
        [0, 1, 2].map(|a| s.scene_box[1][a] - s.scene_box[0][a])
    };
    assert!(
        e(&sc)[0] > 1.4 || e(&sc)[1] > 1.4 || e(&sc)[2] > 1.4,
        "{:?}",
        sc.scene_box
    );
    assert_eq!(sc.scene_box, sg.scene_box);
    assert_eq!(sc.frames_outside_box, 0);
    assert_eq!(sg.frames_outside_box, 0);
    assert_eq!((sc.updates, sc.iterations), (sg.updates, sg.iterations));
    assert_eq!(rc, rg, "metrics.csv differs");
    assert_eq!(mc.layout, mg.layout);
    for g in Group::ALL {
        let i = g as usize;
        assert_same_f32(&format!("map {}", g.name()), &mc.params[i], &mg.params[i]);
        assert_same_f32(&format!("moments {}", g.name()), &mc.v[i], &mg.v[i]);
    }
    let _ = std::fs::remove_dir_all(&dir);
}
