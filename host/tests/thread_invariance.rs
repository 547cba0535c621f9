//! The multi-threaded CPU backend must give the same bits as the core's single-threaded
//! reference step for any thread count: gradients, parameters, Adam state and per-ray outputs.

use himap::backend::{ModelData, ParallelCpuBackend};
use himap::dump::{nonfinite_sequence, random_rays, small_config};
use himap_core::model::{Group, LossConfig, ModelLayout, RayResult, NUM_GROUPS};
use himap_core::render::RenderMode;
use himap_core::step::{paper_adam, Backend, CpuBackend};

const STEPS: usize = 3;

struct Reference {
    params: [Vec<f32>; NUM_GROUPS],
    grads: [Vec<i64>; NUM_GROUPS],
    results: Vec<Vec<RayResult>>,
}

fn loss_for(step: usize, n: usize) -> LossConfig {
    LossConfig {
        lambda_color: 1.0,
        lambda_depth: 0.25,
        ray_scale: 1.0 / n as f32,
        color_to_geometry: step == 0,
        seed: 100 + step as u32,
    }
}

fn reference(
    layout: ModelLayout,
    data: &ModelData,
    rays: &[Vec<himap_core::model::Ray>],
) -> Reference {
    let mut params = data.params.clone();
    let mut m = data.m.clone();
    let mut v = data.v.clone();
    let mut grads: [Vec<i64>; NUM_GROUPS] = layout.group_lens().map(|n| vec![0; n]);
    let mut all = Vec::new();
    {
        let groups = himap_core::step::group_states(&mut params, &mut m, &mut v, &mut grads);
        let mut cpu = CpuBackend::new(layout, groups, paper_adam()).unwrap();
        for (s, batch) in rays.iter().enumerate() {
            let mut res = vec![RayResult::default(); batch.len()];
            cpu.train_step(batch, &loss_for(s, batch.len()), &mut res)
                .unwrap();
            all.push(res);
        }
    }
    Reference {
        params: params.0,
        grads,
        results: all,
    }
}

fn bits(v: &[f32]) -> Vec<u32> {
    v.iter().map(|x| x.to_bits()).collect()
}

#[test]
fn parallel_backend_is_bit_identical_to_reference_for_1_2_8_threads() {
    // Both rendering modes, and SDF-density with early ray termination (the parallel
    // backend's forward stops evaluating where the compositing stops; the reference
    // evaluates every sample and recomputes them in the backward).
    let cut = {
        let mut c = small_config(RenderMode::SdfDensity);
        c.min_transmittance = 0.05;
        c
    };
    let configs = [
        small_config(RenderMode::SdfDensity),
        small_config(RenderMode::Occupancy),
        cut,
    ];
    for cfg in configs {
        let mode = cfg.render_mode;
        let layout = ModelLayout::new(&cfg).unwrap();
        let data = ModelData::new(layout, 4).unwrap();
        let rays: Vec<_> = (0..STEPS).map(|s| random_rays(200, s as u64)).collect();
        let r = reference(layout, &data, &rays);
        assert!(
            r.grads[0].iter().any(|&q| q != 0),
            "reference produced no geometry gradient"
        );
        for threads in [1, 2, 8] {
            let mut be = ParallelCpuBackend::new(data.clone(), paper_adam(), threads).unwrap();
            for (s, batch) in rays.iter().enumerate() {
                let mut res = vec![RayResult::default(); batch.len()];
                be.train_step(batch, &loss_for(s, batch.len()), &mut res)
                    .unwrap();
                for (a, b) in res.iter().zip(&r.results[s]) {
                    assert_eq!(
                        bits(&a.color),
                        bits(&b.color),
                        "{threads} threads, step {s}"
                    );
                    assert_eq!(a.depth.to_bits(), b.depth.to_bits());
                    assert_eq!(a.loss.to_bits(), b.loss.to_bits());
                }
            }
            for g in Group::ALL {
                let mut grads = vec![0i64; layout.group_len(g)];
                be.read_grads(g, &mut grads).unwrap();
                assert_eq!(
                    grads,
                    r.grads[g as usize],
                    "{mode:?}: {threads} threads, gradient of {}",
                    g.name()
                );
                assert_eq!(
                    bits(&be.data().params[g as usize]),
                    bits(&r.params[g as usize]),
                    "{mode:?}: {threads} threads, parameters of {}",
                    g.name()
                );
            }
        }
    }
}

#[test]
fn demo_training_reduces_the_loss() {
    let layout = ModelLayout::new(&small_config(RenderMode::SdfDensity)).unwrap();
    let (first, last) = himap::train_demo::run(layout, 60, 256, 2, 1, |_, _, _| {}, 10).unwrap();
    assert!(last < 0.8 * first, "loss {first} -> {last}");
}

/// A step whose loss or update is not finite is rejected by the reference and the parallel
/// backend alike: parameters, Adam moments and the step count stay as before it, and the two
/// end on the same bits.
#[test]
fn nonfinite_steps_are_rejected_and_leave_the_state_as_it_was() {
    let cfg = small_config(RenderMode::SdfDensity);
    let layout = ModelLayout::new(&cfg).unwrap();
    let data = ModelData::new(layout, 6).unwrap();
    let rays = random_rays(120, 3);
    let loss = loss_for(1, rays.len());
    let adam = paper_adam();
    let lr = adam[Group::GeometryMlp].lr;
    let (mut params, mut m, mut v) = (data.params.clone(), data.m.clone(), data.v.clone());
    let mut grads: [Vec<i64>; NUM_GROUPS] = layout.group_lens().map(|n| vec![0; n]);
    let reference = {
        let groups = himap_core::step::group_states(&mut params, &mut m, &mut v, &mut grads);
        let mut cpu = CpuBackend::new(layout, groups, adam).unwrap();
        nonfinite_sequence(&mut cpu, &rays, &loss, lr).unwrap()
    };
    let key = |s: &[himap_core::step::StepStats]| -> Vec<(bool, u32, u32, u32)> {
        s.iter()
            .map(|s| (s.rejected, s.t, s.rays_hit, s.loss.to_bits()))
            .collect()
    };
    let flags: Vec<(bool, u32)> = reference.iter().map(|s| (s.rejected, s.t)).collect();
    assert_eq!(flags, vec![(false, 1), (true, 1), (true, 1), (false, 2)]);
    assert!(reference[1].loss.is_nan() && reference[2].loss.is_finite());
    assert!(params
        .iter()
        .flatten()
        .chain(m.iter().flatten())
        .all(|x| x.is_finite()));

    // The same four steps without the two rejected ones give the same state.
    let (mut p2, mut m2, mut v2) = (data.params.clone(), data.m.clone(), data.v.clone());
    let mut g2: [Vec<i64>; NUM_GROUPS] = layout.group_lens().map(|n| vec![0; n]);
    {
        let groups = himap_core::step::group_states(&mut p2, &mut m2, &mut v2, &mut g2);
        let mut cpu = CpuBackend::new(layout, groups, adam).unwrap();
        let mut res = vec![RayResult::default(); rays.len()];
        for _ in 0..2 {
            let s = cpu.train_step(&rays, &loss, &mut res).unwrap();
            assert!(!s.rejected);
        }
    }
    for g in 0..NUM_GROUPS {
        assert_eq!(
            bits(&params[g]),
            bits(&p2[g]),
            "group {g}: rejected steps changed it"
        );
        assert_eq!(bits(&m[g]), bits(&m2[g]));
        assert_eq!(bits(&v[g]), bits(&v2[g]));
    }

    for threads in [1, 2] {
        let mut par = ParallelCpuBackend::new(data.clone(), adam, threads).unwrap();
        let stats = nonfinite_sequence(&mut par, &rays, &loss, lr).unwrap();
        assert_eq!(
            key(&stats),
            key(&reference),
            "{threads} threads: step statistics"
        );
        let d = par.data();
        for g in 0..NUM_GROUPS {
            assert_eq!(
                bits(&d.params[g]),
                bits(&params[g]),
                "{threads} threads, group {g}"
            );
            assert_eq!(bits(&d.m[g]), bits(&m[g]));
            assert_eq!(bits(&d.v[g]), bits(&v[g]));
        }
    }
}
