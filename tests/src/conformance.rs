//! The backend conformance suite: every check runs a backend under test ([`Candidate`])
//! beside the core's single-threaded reference ([`himap_core::train::reference::CpuBackend`]) through the
//! [`Backend`] trait only, and asserts the same bits: per-ray and per-pixel results, step
//! statistics, fixed-point gradients, parameters and Adam moments.
//!
//! `tests/tests/conformance.rs` instantiates every check for each backend (the host's
//! parallel CPU backend with 1, 2 and 8 threads, the Vulkan backend); a new backend gets the
//! whole suite by implementing [`Candidate`].

use himap::backend::ModelData;
use himap::dump::{nonfinite_sequence, random_rays, small_config};
use himap::synth::{synth_intrinsics, synth_pose, Scene};
use himap_core::camera::{Intrinsics, Pose};
use himap_core::field::model::{
    ray_forward, Group, LossConfig, ModelConfig, ModelLayout, PerGroup, Ray, RayCache, RayResult,
    SampleScratch, NUM_GROUPS,
};
use himap_core::field::render::RenderMode;
use himap_core::gpu_abi::{pixel_result_record, ray_result_record};
use himap_core::loss::planar::PlanarConfig;
use himap_core::loss::warp::WarpConfig;
use himap_core::rng::SplitMix;
use himap_core::train::adam::AdamConfig;
use himap_core::train::backend::{paper_adam, Backend, ImageStore, MapBatch, StepStats};
use himap_core::train::pixel::{pack_rgba8, MappingLoss, PixelResult, PixelSample};
use himap_core::train::reference::{group_states, CpuBackend};
use himap_core::Aabb;

/// A backend under test.
pub trait Candidate {
    type B: Backend<Error: std::error::Error + Send + Sync + 'static>;

    /// A backend over `data`'s parameters (zero Adam moments, step 0) with image slots of
    /// `store`, or `None` (the reason printed) when this machine cannot run it.
    fn build(
        &self,
        data: &ModelData,
        adam: PerGroup<AdamConfig>,
        store: ImageStore,
    ) -> Option<Self::B>;
}

/// Whether two floats are the same bits (any NaN equals any NaN).
pub fn same(a: f32, b: f32) -> bool {
    a.to_bits() == b.to_bits() || (a.is_nan() && b.is_nan())
}

/// Asserts two float slices are the same bits, naming the first difference.
pub fn assert_same_f32(what: &str, want: &[f32], got: &[f32]) {
    assert_eq!(want.len(), got.len(), "{what}: lengths");
    let bad: Vec<usize> = (0..want.len())
        .filter(|&i| !same(want[i], got[i]))
        .collect();
    assert!(
        bad.is_empty(),
        "{what}: {} of {} values differ, first at {}: reference {:e} ({:#010x}) backend {:e} ({:#010x})",
        bad.len(),
        want.len(),
        bad[0],
        want[bad[0]],
        want[bad[0]].to_bits(),
        got[bad[0]],
        got[bad[0]].to_bits()
    );
}

/// The floats of ray results, in order (their GPU records).
pub fn result_floats(r: &[RayResult]) -> Vec<f32> {
    r.iter().flat_map(ray_result_record).collect()
}

/// The floats of pixel results (and their valid-view counts, exact as f32), in order (their
/// GPU records).
pub fn pixel_floats(r: &[PixelResult]) -> Vec<f32> {
    r.iter().flat_map(pixel_result_record).collect()
}

/// What must agree between two steps' statistics.
fn stats_key(s: &StepStats) -> (bool, u32, u32, u32) {
    // NaN payloads are not part of the contract (NVIDIA's arithmetic makes 0x7fffffff where
    // x86 makes 0xffc00000 / 0x7fc00000): any NaN loss compares as one value
    let loss = if s.loss.is_nan() {
        f32::NAN.to_bits()
    } else {
        s.loss.to_bits()
    };
    (s.rejected, s.t, s.rays_hit, loss)
}

/// The small configuration's model (seeded) and a batch of rays, two of which start outside
/// the box (one towards it, one away from it: it renders nothing).
pub fn setup_with(cfg: &ModelConfig, seed: u32, n_rays: usize) -> (ModelData, Vec<Ray>) {
    let layout = ModelLayout::new(cfg).expect("small config is valid");
    let data = ModelData::new(layout, seed).expect("init");
    let mut rays = random_rays(n_rays, seed as u64 + 100);
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

/// [`setup_with`] for the small configuration in `mode`.
pub fn setup(mode: RenderMode, seed: u32, n_rays: usize) -> (ModelData, Vec<Ray>) {
    setup_with(&small_config(mode), seed, n_rays)
}

/// Owns the reference's buffers; [`Reference::backend`] borrows them.
pub struct Reference {
    pub layout: ModelLayout,
    pub params: [Vec<f32>; NUM_GROUPS],
    pub m: [Vec<f32>; NUM_GROUPS],
    pub v: [Vec<f32>; NUM_GROUPS],
    pub grad: [Vec<i64>; NUM_GROUPS],
    pub images: Vec<u32>,
    store: ImageStore,
}

impl Reference {
    /// The reference over `data`'s parameters (zero moments) with image slots of `store`.
    pub fn new(data: &ModelData, store: ImageStore) -> Self {
        let lens = data.layout.group_lens();
        Self {
            layout: data.layout,
            params: data.params.0.clone(),
            m: lens.map(|n| vec![0.0; n]),
            v: lens.map(|n| vec![0.0; n]),
            grad: lens.map(|n| vec![0; n]),
            // with room for per-pixel depth priors after the slots
            images: vec![0; 2 * store.total_len()],
            store,
        }
    }

    /// The core's backend over these buffers.
    pub fn backend(&mut self, adam: PerGroup<AdamConfig>) -> CpuBackend<'_> {
        let groups = group_states(&mut self.params, &mut self.m, &mut self.v, &mut self.grad);
        CpuBackend::new(self.layout, groups, adam)
            .expect("cpu backend")
            .with_images(self.store, &mut self.images)
            .expect("image slots")
    }
}

/// Larger learning rates than the paper's so that a few steps move every group visibly.
pub fn test_adam() -> PerGroup<AdamConfig> {
    PerGroup([
        AdamConfig::new(0.02),
        AdamConfig::new(0.02),
        AdamConfig::new(1e-3),
        AdamConfig::new(1e-3),
        AdamConfig::new(1e-2),
    ])
}

/// A step's loss settings with both the colour and the depth term.
pub fn loss_config(seed: u32, n: usize) -> LossConfig {
    LossConfig {
        lambda_color: 1.0,
        lambda_depth: 0.5,
        ray_scale: 1.0 / n as f32,
        color_to_geometry: true,
        seed,
    }
}

/// A group's parameters, gradient and Adam moments as the backend holds them.
fn read_group<B: Backend>(b: &mut B, g: Group, len: usize) -> (Vec<f32>, Vec<i64>, [Vec<f32>; 2]) {
    let mut p = vec![0.0f32; len];
    let mut q = vec![0i64; len];
    let (mut m, mut v) = (p.clone(), p.clone());
    b.read_params(g, &mut p).unwrap();
    b.read_grads(g, &mut q).unwrap();
    b.read_adam(g, &mut m, &mut v).unwrap();
    (p, q, [m, v])
}

/// Asserts the backend holds the reference's parameters, gradients and moments.
fn assert_state<B: Backend>(what: &str, reference: &Reference, b: &mut B) {
    for g in Group::ALL {
        let i = g as usize;
        let (p, q, [m, v]) = read_group(b, g, reference.params[i].len());
        let name = g.name();
        assert_same_f32(&format!("{what}: {name} params"), &reference.params[i], &p);
        let bad = (0..q.len())
            .filter(|&k| q[k] != reference.grad[i][k])
            .count();
        assert_eq!(bad, 0, "{what}: {name}: {bad} fixed-point gradients differ");
        assert_same_f32(&format!("{what}: {name} adam m"), &reference.m[i], &m);
        assert_same_f32(&format!("{what}: {name} adam v"), &reference.v[i], &v);
    }
}

/// Every group's parameters of `a` and `b` are the same bits (labels `"{what} {group}
/// params"`).
pub fn assert_same_params<A: Backend, B: Backend>(what: &str, a: &mut A, b: &mut B) {
    for g in Group::ALL {
        let len = a.layout().group_len(g);
        let (mut p, mut q) = (vec![0.0f32; len], vec![0.0f32; len]);
        a.read_params(g, &mut p).unwrap();
        b.read_params(g, &mut q).unwrap();
        assert_same_f32(&format!("{what} {} params", g.name()), &p, &q);
    }
}

/// Renders without jitter equal the reference's in every render mode; the batch renders
/// something and the ray that misses the box renders nothing.
pub fn forward_rendering<C: Candidate>(c: &C) {
    for mode in [
        RenderMode::SdfDensity,
        RenderMode::SdfDirect,
        RenderMode::Occupancy,
    ] {
        let (data, rays) = setup(mode, 3, 300);
        let Some(mut b) = c.build(&data, paper_adam(), ImageStore::default()) else {
            return;
        };
        let mut reference = Reference::new(&data, ImageStore::default());
        let mut cpu = reference.backend(paper_adam());
        let mut rc = vec![RayResult::default(); rays.len()];
        let mut rb = rc.clone();
        cpu.render(&rays, &mut rc).unwrap();
        b.render(&rays, &mut rb).unwrap();
        assert_same_f32(
            &format!("{mode:?} render"),
            &result_floats(&rc),
            &result_floats(&rb),
        );
        assert!(rc.iter().filter(|r| r.opacity > 0.0).count() > 250);
        assert_eq!(rb.last().unwrap().opacity, 0.0);
        // The depth-only render: the same depth and opacity bits, with and without early
        // termination (the backend may skip the colour).
        for t_min in [0.0, 0.05] {
            cpu.set_min_transmittance(t_min).unwrap();
            b.set_min_transmittance(t_min).unwrap();
            cpu.render(&rays, &mut rc).unwrap();
            let mut rd = vec![RayResult::default(); rays.len()];
            b.render_depth(&rays, &mut rd).unwrap();
            let depth_opacity = |r: &[RayResult]| -> Vec<f32> {
                r.iter().flat_map(|r| [r.depth, r.opacity]).collect()
            };
            assert_same_f32(
                &format!("{mode:?} depth-only render, termination {t_min}"),
                &depth_opacity(&rc),
                &depth_opacity(&rd),
            );
        }
    }
}

/// One training step of `cfg`'s model: results, statistics, every group's gradient,
/// parameters and moments; every group receives a gradient and moves.
pub fn one_step<C: Candidate>(c: &C, cfg: &ModelConfig) {
    let (data, rays) = setup_with(cfg, 5, 200);
    let adam = test_adam();
    let Some(mut b) = c.build(&data, adam, ImageStore::default()) else {
        return;
    };
    let mut reference = Reference::new(&data, ImageStore::default());
    let loss = loss_config(9, rays.len());
    let mut rc = vec![RayResult::default(); rays.len()];
    let mut rb = rc.clone();
    let sc = reference
        .backend(adam)
        .train_step(&rays, &loss, &mut rc)
        .unwrap();
    let sb = b.train_step(&rays, &loss, &mut rb).unwrap();
    let mode = cfg.render_mode;
    assert_same_f32(
        &format!("{mode:?} step results"),
        &result_floats(&rc),
        &result_floats(&rb),
    );
    assert_eq!(stats_key(&sc), stats_key(&sb), "{mode:?} step statistics");
    for g in Group::ALL {
        let i = g as usize;
        assert!(
            reference.grad[i].iter().any(|&x| x != 0),
            "{mode:?} {}: no gradient at all (the check is vacuous)",
            g.name()
        );
        assert_ne!(
            reference.params[i],
            data.params[i],
            "{} did not move",
            g.name()
        );
    }
    assert_state(&format!("{mode:?} one step"), &reference, &mut b);
}

/// [`one_step`] with early ray termination that bites: the reference stops evaluating a
/// ray's samples where its compositing stops (for at least 20 of the rays).
pub fn one_step_with_early_termination<C: Candidate>(c: &C) {
    let mut cfg = small_config(RenderMode::SdfDensity);
    cfg.min_transmittance = 0.05;
    let (data, rays) = setup_with(&cfg, 5, 200);
    let uncut = ModelLayout::new(&small_config(RenderMode::SdfDensity)).unwrap();
    let params = data.view();
    let mut s = SampleScratch::new();
    let (mut a, mut b) = (RayCache::new(), RayCache::new());
    let cut = rays
        .iter()
        .enumerate()
        .filter(|(i, r)| {
            let i = *i as u32;
            ray_forward(&data.layout, &params, r, i, 9, true, &mut a, &mut s);
            ray_forward(&uncut, &params, r, i, 9, true, &mut b, &mut s);
            a.n < b.n
        })
        .count();
    assert!(cut >= 20, "only {cut} of {} rays were cut", rays.len());
    one_step(c, &cfg);
}

/// [`one_step`] with samples beyond `max_depth` (`far_samples` in inverse depth): the per-ray
/// sample counts differ between rays (at least 20 of them get the far samples).
pub fn one_step_with_far_samples<C: Candidate>(c: &C) {
    let mut cfg = small_config(RenderMode::SdfDensity);
    cfg.max_depth = 0.8;
    cfg.far_samples = 6;
    cfg.far_depth = 3.0;
    let (data, rays) = setup_with(&cfg, 6, 200);
    let far = rays
        .iter()
        .filter(|r| himap_core::field::model::ray_span(&data.layout, r).2 > cfg.samples as usize)
        .count();
    assert!(
        far >= 20,
        "only {far} of {} rays got far samples",
        rays.len()
    );
    one_step(c, &cfg);
}

/// `set_min_transmittance` between steps (the mapper's initialisation threshold) changes the
/// backend's compositing exactly as the reference's: the renders change, every step's
/// results and the final state agree, and thresholds outside [0, 1) are errors.
pub fn termination_threshold_between_steps<C: Candidate>(c: &C) {
    let (data, rays) = setup(RenderMode::SdfDensity, 5, 200);
    let adam = test_adam();
    let Some(mut b) = c.build(&data, adam, ImageStore::default()) else {
        return;
    };
    let mut reference = Reference::new(&data, ImageStore::default());
    let loss = loss_config(2, rays.len());
    {
        let mut uncut = vec![RayResult::default(); rays.len()];
        let mut cut = uncut.clone();
        b.render(&rays, &mut uncut).unwrap();
        b.set_min_transmittance(0.05).unwrap();
        b.render(&rays, &mut cut).unwrap();
        let differ = uncut
            .iter()
            .zip(&cut)
            .filter(|(a, b)| a.depth != b.depth)
            .count();
        assert!(differ >= 20, "only {differ} renders changed");
        let mut cpu = reference.backend(adam);
        for (step, t) in [0.0, 0.05, 0.0].into_iter().enumerate() {
            cpu.set_min_transmittance(t).unwrap();
            b.set_min_transmittance(t).unwrap();
            let mut rc = vec![RayResult::default(); rays.len()];
            let mut rb = rc.clone();
            cpu.train_step(&rays, &loss, &mut rc).unwrap();
            b.train_step(&rays, &loss, &mut rb).unwrap();
            assert_same_f32(
                &format!("step {step} results"),
                &result_floats(&rc),
                &result_floats(&rb),
            );
            assert_eq!(b.layout().config.min_transmittance, t);
        }
        assert!(cpu.set_min_transmittance(1.0).is_err());
    }
    assert!(b.set_min_transmittance(-0.1).is_err());
    assert_state("after thresholds", &reference, &mut b);
}

/// Non-finite steps (a NaN target colour, an overflowing learning rate) are rejected where
/// the reference rejects them, with the same statistics, and leave the same finite state.
pub fn nonfinite_steps_are_rejected<C: Candidate>(c: &C) {
    let (data, rays) = setup(RenderMode::SdfDensity, 8, 150);
    let adam = test_adam();
    let Some(mut b) = c.build(&data, adam, ImageStore::default()) else {
        return;
    };
    let lr = adam[Group::GeometryMlp].lr;
    let loss = loss_config(4, rays.len());
    let mut reference = Reference::new(&data, ImageStore::default());
    let sc = nonfinite_sequence(&mut reference.backend(adam), &rays, &loss, lr).unwrap();
    let sb = nonfinite_sequence(&mut b, &rays, &loss, lr).unwrap();
    let key = |s: &[StepStats]| s.iter().map(stats_key).collect::<Vec<_>>();
    assert_eq!(key(&sb), key(&sc));
    let rejected: Vec<bool> = sc.iter().map(|s| s.rejected).collect();
    assert_eq!(rejected, vec![false, true, true, false]);
    assert!(sc[1].loss.is_nan() && sc[2].loss.is_finite());
    assert!(reference
        .params
        .iter()
        .flatten()
        .chain(reference.m.iter().flatten())
        .all(|x| x.is_finite()));
    // The reference's gradient buffers hold the last accepted step's, as the backend's do.
    assert_state("after rejected steps", &reference, &mut b);
}

/// 50 training steps of the paper's model (new rays every step, the detached-colour switch,
/// a learning-rate change, a parameter overwrite with Adam reset) end on the same state.
/// On llvmpipe this diverged at step 17 before the per-sample passes (ARCHITECTURE.md).
pub fn fifty_training_steps<C: Candidate>(c: &C) {
    // 6 + 2 factorized levels, 32-wide decoders, 48 samples per ray, over a 0.64 m box so the
    // finest 2 cm levels are 32^3 (small enough for the software driver).
    let mut cfg = ModelConfig::paper(Aabb::new([-0.32; 3], [0.32; 3]));
    cfg.grid_init_std = 0.1;
    cfg.sdf_bias_init = 0.05;
    let layout = ModelLayout::new(&cfg).expect("valid config");
    let data = ModelData::new(layout, 11).expect("init");
    let adam = test_adam();
    let Some(mut b) = c.build(&data, adam, ImageStore::default()) else {
        return;
    };
    let mut reference = Reference::new(&data, ImageStore::default());
    let n = 64;
    let mut rc = vec![RayResult::default(); n];
    let mut rb = rc.clone();
    let (mut first_loss, mut last_loss) = (0.0, 0.0);
    {
        let mut cpu = reference.backend(adam);
        for step in 0..50u32 {
            let mut rays = himap::bench::rays_in(&cfg.aabb, n, 1000 + step as u64);
            for r in rays.iter_mut().step_by(2) {
                r.target_depth = 0.3;
            }
            let mut loss = loss_config(step, n);
            loss.color_to_geometry = step % 10 != 3;
            let sc = cpu.train_step(&rays, &loss, &mut rc).unwrap();
            let sb = b.train_step(&rays, &loss, &mut rb).unwrap();
            assert_eq!(stats_key(&sc), stats_key(&sb), "step {step}");
            if step == 0 {
                first_loss = sc.loss;
            }
            last_loss = sc.loss;
            if step == 25 {
                cpu.set_adam_lr(Group::AppearanceMlp, 2e-3).unwrap();
                b.set_adam_lr(Group::AppearanceMlp, 2e-3).unwrap();
                assert_eq!(b.adam_lr(Group::AppearanceMlp), 2e-3);
            }
        }
        assert!(last_loss < first_loss, "loss {first_loss} -> {last_loss}");
        let quarter = vec![0.25f32; layout.group_len(Group::GeometryMlp)];
        cpu.write_params(Group::GeometryMlp, &quarter, true)
            .unwrap();
        b.write_params(Group::GeometryMlp, &quarter, true).unwrap();
        let rays = himap::bench::rays_in(&cfg.aabb, n, 7);
        let loss = loss_config(77, n);
        cpu.train_step(&rays, &loss, &mut rc).unwrap();
        b.train_step(&rays, &loss, &mut rb).unwrap();
    }
    assert_same_f32(
        "results after reset",
        &result_floats(&rc),
        &result_floats(&rb),
    );
    for g in Group::ALL {
        assert_ne!(reference.params[g as usize], data.params[g as usize]);
    }
    assert_state("after 50 steps and a reset", &reference, &mut b);
}

/// A small synthetic window: the room of `himap demo` seen from `frames` poses at 32x24, the
/// model's box around the room, and the frames packed as RGBA8.
pub fn synthetic_window(
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

/// A mapping iteration's loss: colour, warping loss (7x7 patches), the depth prior in the
/// first steps (near-only in step 1), the detached colour in step 2, a dilated patch in the
/// even steps and, in the even steps too, a weighted term for pixels with fewer than
/// `min_views` valid views (in step 2 only from the pairs along whose epipolar line the
/// source patch has texture; in step 3 the same test on the main term's pairs).
fn mapping_loss(step: u32, n: usize) -> MappingLoss {
    let mut warp = WarpConfig::dim_slam();
    warp.min_views = 2;
    warp.margin = 2.0;
    warp.half = 3;
    // a dilated patch (samples 2 px apart) in the even steps
    warp.stride = 1 + (step + 1) % 2;
    warp.few_views_weight = if step.is_multiple_of(2) { 0.3 } else { 0.0 };
    // step 2: the texture test of those pairs
    warp.few_views_min_grad = if step == 2 { 0.05 } else { 0.0 };
    // step 3: the texture test of the main term's pairs
    warp.min_grad = if step == 3 { 0.05 } else { 0.0 };
    MappingLoss {
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
        // the planarity prior in steps 1 and 3 (their pixels come in line triplets)
        planar: if step % 2 == 1 {
            // gated in step 1, not in step 3
            PlanarConfig {
                weight: 0.5,
                edge: 10.0,
                beta: 0.05,
                gated: step == 1,
            }
        } else {
            PlanarConfig::OFF
        },
        // the per-pixel depth priors (set on every backend's slots) in steps 0 and 3
        lambda_plane: if step.is_multiple_of(3) { 0.7 } else { 0.0 },
    }
}

/// Makes pixel triples `3g..3g + 3` line triplets around their middle pixel (spacings
/// 1..=3 on either side, equal or not, as the region triplets' are; rows and columns), except
/// every fourth triple, which stays as drawn (no triplet).
fn line_triplets(pixels: &mut [PixelSample], k: &Intrinsics, rng: &mut SplitMix) {
    for (g, t) in pixels.chunks_exact_mut(3).enumerate() {
        if g % 4 == 3 {
            continue;
        }
        let s = 1 + rng.below(3);
        let s2 = if g % 3 == 0 { s } else { 1 + rng.below(3) };
        let mut mid = t[1];
        let (mut a, mut c) = (mid, mid);
        if g % 2 == 0 {
            mid.u = mid.u.clamp(s, k.width - 1 - s2);
            (a.u, c.u) = (mid.u - s, mid.u + s2);
            (a.v, c.v) = (mid.v, mid.v);
        } else {
            mid.v = mid.v.clamp(s, k.height - 1 - s2);
            (a.v, c.v) = (mid.v - s, mid.v + s2);
            (a.u, c.u) = (mid.u, mid.u);
        }
        t.copy_from_slice(&[a, mid, c]);
    }
}

/// Mapping iterations (`pixel_train`: colour L1 + DIM-SLAM warping loss through the rendered
/// depth + depth prior) over a window whose slot table is not the identity: per-pixel
/// results, statistics, and the whole state after four iterations. The candidate is handed
/// each next batch ([`Backend::map_step`]'s `next`: the Vulkan backend queues it behind the
/// current step) while the reference runs one step at a time; the second step's learning
/// rates overflow Adam, so it is rejected while the third is already queued (which must
/// still use the reference's step count), and the fourth has rates of its own.
pub fn mapping_steps<C: Candidate>(c: &C) {
    let frames = 6;
    let (data, k, poses, images) = synthetic_window(RenderMode::SdfDensity, frames);
    let adam = test_adam();
    let store = ImageStore {
        width: k.width,
        height: k.height,
        slots: frames as u32 + 2,
    };
    let Some(mut b) = c.build(&data, adam, store) else {
        return;
    };
    let mut reference = Reference::new(&data, store);
    // frame i in slot (i + 2) % slots
    let slots: Vec<u32> = (0..frames as u32).map(|i| (i + 2) % store.slots).collect();
    let mut rng = SplitMix::new(5);
    // not a multiple of 3: the last two pixels belong to no planarity triplet
    let n = 98;
    let mut any_warp = false;
    let mut any_few = false;
    // step 2: below min_views, some pixel kept its term and some lost it to the texture test
    let (mut kept_textured, mut dropped_plain) = (false, false);
    let (mut main_kept, mut main_dropped) = (false, false);
    {
        let mut cpu = reference.backend(adam);
        for (img, &slot) in images.iter().zip(&slots) {
            cpu.upload_frame(slot, img).unwrap();
            b.upload_frame(slot, img).unwrap();
        }
        // per-pixel depth priors on all but one frame: a target around 2 m on most pixels,
        // none (0) on the rest
        for (f, &slot) in slots.iter().enumerate().skip(1) {
            let prior: Vec<f32> = (0..store.slot_len())
                .map(|_| {
                    let t = 1.0 + 2.0 * rng.unit();
                    if rng.unit() < 0.8 {
                        t
                    } else {
                        0.0
                    }
                })
                .collect();
            assert!(cpu.set_depth_prior(slot, &prior).unwrap(), "frame {f}");
            assert!(b.set_depth_prior(slot, &prior).unwrap(), "frame {f}");
        }
        let steps = 4u32;
        let pixels: Vec<Vec<PixelSample>> = (0..steps)
            .map(|step| {
                let mut pixels: Vec<PixelSample> = (0..n)
                    .map(|_| PixelSample {
                        frame: (rng.unit() * frames as f32) as u32 % frames as u32,
                        u: (rng.unit() * k.width as f32) as u32 % k.width,
                        v: (rng.unit() * k.height as f32) as u32 % k.height,
                    })
                    .collect();
                if step % 2 == 1 {
                    line_triplets(&mut pixels, &k, &mut rng);
                }
                pixels
            })
            .collect();
        let batch = |step: u32| MapBatch {
            k,
            poses: &poses,
            slots: &slots,
            pixels: &pixels[step as usize],
            loss: mapping_loss(step, n),
            lr: match step {
                1 => Some([3e38; NUM_GROUPS]),
                3 => Some([0.02, 0.005, 0.001, 0.002, 0.01]),
                _ => None,
            },
        };
        for step in 0..steps {
            let next = (step + 1 < steps).then(|| batch(step + 1));
            let batch = batch(step);
            let mut rc = vec![PixelResult::default(); n];
            let mut rb = rc.clone();
            let sc = cpu.map_step(&batch, &mut rc, None).unwrap();
            let sb = b.map_step(&batch, &mut rb, next.as_ref()).unwrap();
            assert_eq!(sc.rejected, step == 1, "step {step}: rejected");
            assert_same_f32(
                &format!("step {step} pixels"),
                &pixel_floats(&rc),
                &pixel_floats(&rb),
            );
            assert_eq!(stats_key(&sc), stats_key(&sb), "step {step}");
            any_warp |= rc.iter().any(|r| r.warp_loss != 0.0);
            let min_views = batch.loss.warp.min_views;
            any_few |= rc
                .iter()
                .any(|r| r.warp_loss != 0.0 && r.warp_views < min_views);
            if batch.loss.warp.few_views_min_grad > 0.0 {
                let few = |r: &&PixelResult| r.warp_views > 0 && r.warp_views < min_views;
                kept_textured |= rc.iter().filter(few).any(|r| r.warp_loss != 0.0);
                dropped_plain |= rc.iter().filter(few).any(|r| r.warp_loss == 0.0);
            }
            if batch.loss.warp.min_grad > 0.0 {
                let main = |r: &&PixelResult| r.warp_views >= min_views;
                main_kept |= rc.iter().filter(main).any(|r| r.warp_loss != 0.0);
                main_dropped |= rc.iter().filter(main).any(|r| r.warp_loss == 0.0);
            }
        }
    }
    assert!(
        any_warp,
        "no pixel had a valid warp: the warping loss is not covered"
    );
    assert!(
        any_few,
        "no pixel had a weighted term below min_views: few_views_weight is not covered"
    );
    assert!(
        kept_textured && dropped_plain,
        "few_views_min_grad kept {kept_textured}, dropped {dropped_plain}: not covered both ways"
    );
    assert!(
        main_kept && main_dropped,
        "min_grad kept {main_kept}, dropped {main_dropped}: not covered both ways"
    );
    for g in Group::ALL {
        assert_ne!(
            reference.params[g as usize],
            data.params[g as usize],
            "{} did not move",
            g.name()
        );
    }
    assert_state("after mapping steps", &reference, &mut b);
}

/// A full image rendered by `render_view` (one ray per pixel, bin-centre samples) after a few
/// training steps equals the reference's pixel for pixel.
pub fn full_image_render<C: Candidate>(c: &C)
where
    <C::B as Backend>::Error: 'static,
{
    let (data, k, poses, _) = synthetic_window(RenderMode::SdfDensity, 2);
    let adam = test_adam();
    let Some(mut b) = c.build(&data, adam, ImageStore::default()) else {
        return;
    };
    let mut reference = Reference::new(&data, ImageStore::default());
    let mut cpu = reference.backend(adam);
    let aabb = data.layout.config.aabb;
    let n = 256;
    let mut rc = vec![RayResult::default(); n];
    let mut rb = rc.clone();
    for step in 0..3 {
        let rays = himap::bench::rays_in(&aabb, n, 300 + step);
        cpu.train_step(&rays, &loss_config(step as u32, n), &mut rc)
            .unwrap();
        b.train_step(&rays, &loss_config(step as u32, n), &mut rb)
            .unwrap();
    }
    let a = himap::mapper_cli::render_view(&mut cpu, &k, &poses[1]).unwrap();
    let r = himap::mapper_cli::render_view(&mut b, &k, &poses[1]).unwrap();
    assert_eq!(a.len(), (k.width * k.height) as usize);
    assert!(a.iter().filter(|r| r.opacity > 0.0).count() > a.len() / 2);
    assert_same_f32("full image", &result_floats(&a), &result_floats(&r));
}

/// The trait's contract on bad input: errors, never panics, and nothing changes; an empty
/// batch still takes an Adam step.
pub fn contract_errors<C: Candidate>(c: &C) {
    let (data, rays) = setup(RenderMode::SdfDensity, 1, 4);
    let (w, h) = (8u32, 6u32);
    let store = ImageStore {
        width: w,
        height: h,
        slots: 2,
    };
    let Some(mut b) = c.build(&data, paper_adam(), store) else {
        return;
    };
    assert!(!b.name().is_empty());
    assert_eq!(b.image_store(), store);
    let mut short = vec![RayResult::default(); rays.len() - 1];
    assert!(b.render(&rays, &mut short).is_err());
    assert!(b.train_step(&rays, &loss_config(0, 1), &mut short).is_err());
    let mut p = vec![0.0; 2];
    assert!(b.read_params(Group::GeometryGrid, &mut p).is_err());
    let (mut m, mut v) = (vec![0.0; 2], vec![0.0; 2]);
    assert!(b.read_adam(Group::GeometryGrid, &mut m, &mut v).is_err());
    assert!(b.write_params(Group::GeometryMlp, &p, false).is_err());
    assert!(b.set_adam_lr(Group::Beta, f32::NAN).is_err());
    assert!(b.set_adam_lr(Group::Beta, -1.0).is_err());
    assert_eq!(b.adam_lr(Group::Beta), paper_adam()[Group::Beta].lr);
    // image slots: a frame must fill one slot that exists
    let frame = vec![0xff00_0000u32; (w * h) as usize];
    assert!(b.upload_frame(2, &frame).is_err());
    assert!(b.upload_frame(0, &frame[..5]).is_err());
    b.upload_frame(1, &frame).unwrap();
    let k = Intrinsics {
        width: w,
        height: h,
        fx: 6.0,
        fy: 6.0,
        cx: 3.5,
        cy: 2.5,
    };
    let poses = [Pose::IDENTITY; 2];
    let pixels = [PixelSample {
        frame: 0,
        u: 4,
        v: 3,
    }];
    let mut res = [PixelResult::default()];
    let batch = MapBatch {
        k,
        poses: &poses,
        slots: &[0, 2],
        pixels: &pixels,
        loss: mapping_loss(0, 1),
        lr: None,
    };
    assert!(
        b.map_step(&batch, &mut res, None).is_err(),
        "slot 2 does not exist"
    );
    let batch = MapBatch {
        slots: &[0],
        ..batch
    };
    assert!(
        b.map_step(&batch, &mut res, None).is_err(),
        "slot table shorter than the window"
    );
    let batch = MapBatch {
        slots: &[0, 1],
        ..batch
    };
    assert!(
        b.map_step(&batch, &mut [], None).is_err(),
        "results of the wrong length"
    );
    let wrong_size = MapBatch {
        k: Intrinsics { width: w + 1, ..k },
        ..batch
    };
    assert!(
        b.map_step(&wrong_size, &mut res, None).is_err(),
        "intrinsics of another size"
    );
    b.read_params(Group::Beta, &mut [0.0]).unwrap();
    // nothing above took a step; an empty batch takes one
    let s = b.train_step(&[], &loss_config(0, 1), &mut []).unwrap();
    assert_eq!((s.t, s.rays_hit, s.loss, s.rejected), (1, 0, 0.0, false));
    assert!(b.map_step(&batch, &mut res, None).is_ok());
    let bad_rate = MapBatch {
        lr: Some([f32::NAN; NUM_GROUPS]),
        ..batch
    };
    assert!(
        b.map_step(&bad_rate, &mut res, None).is_err(),
        "a learning rate that is not a number"
    );
}
