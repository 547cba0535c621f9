//! The multi-threaded CPU backend must give the same bits as the core's single-threaded
//! reference step for any thread count: gradients, parameters, Adam state and per-ray outputs.

use himap::backend::{ModelData, ParallelCpuBackend};
use himap::dump::{random_rays, small_config};
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
        params,
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
