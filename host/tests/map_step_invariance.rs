//! `map_step` (colour L1 + warping loss through the rendered depth, then Adam) of the
//! multi-threaded backend must give the same bits as the core's single-threaded reference for
//! any thread count: per-pixel outputs, gradients and parameters.

use himap::backend::{ModelData, ParallelCpuBackend};
use himap::dump::small_config;
use himap_core::camera::{Intrinsics, Pose};
use himap_core::mapping::{MappingLoss, PixelResult, PixelSample};
use himap_core::model::{Group, ModelLayout, NUM_GROUPS};
use himap_core::render::RenderMode;
use himap_core::rng::SplitMix;
use himap_core::step::{paper_adam, Backend, CpuBackend, ImageStore, MapBatch};
use himap_core::warp::WarpConfig;

const W: u32 = 48;
const H: u32 = 36;
const FRAMES: usize = 4;

fn k() -> Intrinsics {
    Intrinsics {
        width: W,
        height: H,
        fx: 40.0,
        fy: 40.0,
        cx: 23.5,
        cy: 17.5,
    }
}

fn poses() -> Vec<Pose> {
    (0..FRAMES)
        .map(|i| {
            let mut p = Pose::IDENTITY;
            p.m[0][3] = 0.05 * i as f32;
            p.m[1][3] = -0.03 * i as f32;
            p.m[2][3] = -1.8;
            p
        })
        .collect()
}

fn images() -> Vec<u32> {
    let mut r = SplitMix::new(77);
    (0..FRAMES as u32 * W * H)
        .map(|_| (r.next_u64() as u32) | 0xff00_0000)
        .collect()
}

fn batch_pixels(step: u64) -> Vec<PixelSample> {
    let mut r = SplitMix::new(1000 + step);
    (0..150)
        .map(|_| PixelSample {
            frame: r.below(FRAMES as u32),
            u: 6 + r.below(W - 12),
            v: 6 + r.below(H - 12),
        })
        .collect()
}

fn loss(step: u64) -> MappingLoss {
    let mut warp = WarpConfig::dim_slam();
    warp.half = 3;
    warp.margin = 1.0;
    warp.min_views = 1;
    MappingLoss {
        lambda_color: 0.1,
        lambda_warp: 1.0,
        color_scale: 1.0 / 150.0,
        warp_scale: 1.0 / 150.0,
        color_to_geometry: step == 0,
        seed: 7 + step as u32,
        warp,
        lambda_depth_prior: if step == 0 { 0.5 } else { 0.0 },
        depth_prior: 1.5,
        depth_prior_near: 0.0,
    }
}

fn bits(v: &[f32]) -> Vec<u32> {
    v.iter().map(|x| x.to_bits()).collect()
}

fn same(a: &PixelResult, b: &PixelResult) -> bool {
    bits(&a.color) == bits(&b.color)
        && a.depth.to_bits() == b.depth.to_bits()
        && a.color_loss.to_bits() == b.color_loss.to_bits()
        && a.warp_loss.to_bits() == b.warp_loss.to_bits()
        && a.warp_views == b.warp_views
}

#[test]
fn map_step_is_bit_identical_to_reference_for_1_2_8_threads() {
    let mut cfg = small_config(RenderMode::SdfDensity);
    cfg.sdf_bias_init = 0.05;
    let layout = ModelLayout::new(&cfg).unwrap();
    let data = ModelData::new(layout, 9).unwrap();
    let store = ImageStore {
        width: W,
        height: H,
        slots: FRAMES as u32 + 2,
    };
    let img = images();
    let poses = poses();
    // window frame i lives in slot i + 1 (slot 0 stays unused)
    let slots: Vec<u32> = (1..=FRAMES as u32).collect();
    let steps = 3u64;

    // reference
    let mut p = data.params.clone();
    let mut m = data.m.clone();
    let mut v = data.v.clone();
    let mut g: [Vec<i64>; NUM_GROUPS] = layout.group_lens().map(|n| vec![0; n]);
    let mut slot_buf = vec![0u32; store.total_len()];
    let mut ref_results = Vec::new();
    {
        let groups = himap_core::step::group_states(&mut p.0, &mut m.0, &mut v.0, &mut g);
        let mut cpu = CpuBackend::new(layout, groups, paper_adam())
            .unwrap()
            .with_images(store, &mut slot_buf)
            .unwrap();
        for f in 0..FRAMES {
            let n = (W * H) as usize;
            cpu.upload_frame(f as u32 + 1, &img[f * n..(f + 1) * n])
                .unwrap();
        }
        for s in 0..steps {
            let px = batch_pixels(s);
            let mut res = vec![PixelResult::default(); px.len()];
            let batch = MapBatch {
                k: k(),
                poses: &poses,
                slots: &slots,
                pixels: &px,
                loss: loss(s),
            };
            cpu.map_step(&batch, &mut res).unwrap();
            ref_results.push(res);
        }
    }
    let warped = ref_results[0].iter().filter(|r| r.warp_views > 0).count();
    assert!(warped > 20, "only {warped} pixels had a warp term");
    assert!(ref_results[0].iter().any(|r| r.warp_loss > 0.0));
    assert!(g[0].iter().any(|&q| q != 0), "no geometry gradient");

    for threads in [1, 2, 8] {
        let mut be = ParallelCpuBackend::new(data.clone(), paper_adam(), threads)
            .unwrap()
            .with_images(store);
        for f in 0..FRAMES {
            let n = (W * H) as usize;
            be.upload_frame(f as u32 + 1, &img[f * n..(f + 1) * n])
                .unwrap();
        }
        for s in 0..steps {
            let px = batch_pixels(s);
            let mut res = vec![PixelResult::default(); px.len()];
            let batch = MapBatch {
                k: k(),
                poses: &poses,
                slots: &slots,
                pixels: &px,
                loss: loss(s),
            };
            be.map_step(&batch, &mut res).unwrap();
            for (i, (a, b)) in res.iter().zip(&ref_results[s as usize]).enumerate() {
                assert!(
                    same(a, b),
                    "{threads} threads, step {s}, pixel {i}: {a:?} vs {b:?}"
                );
            }
        }
        for gr in Group::ALL {
            let mut q = vec![0i64; layout.group_len(gr)];
            be.read_grads(gr, &mut q).unwrap();
            assert_eq!(
                q,
                g[gr as usize],
                "{threads} threads: gradient of {}",
                gr.name()
            );
            assert_eq!(
                bits(&be.data().params[gr as usize]),
                bits(&p[gr as usize]),
                "{threads} threads: parameters of {}",
                gr.name()
            );
        }
    }
}

#[test]
fn map_step_rejects_bad_windows() {
    let layout = ModelLayout::new(&small_config(RenderMode::SdfDensity)).unwrap();
    let data = ModelData::new(layout, 1).unwrap();
    let store = ImageStore {
        width: W,
        height: H,
        slots: 2,
    };
    let mut be = ParallelCpuBackend::new(data, paper_adam(), 1)
        .unwrap()
        .with_images(store);
    assert!(be.upload_frame(2, &vec![0; (W * H) as usize]).is_err());
    assert!(be.upload_frame(0, &[0; 5]).is_err());
    let poses = poses();
    let px = batch_pixels(0);
    let mut res = vec![PixelResult::default(); px.len()];
    // slot 3 does not exist
    let slots = [0, 1, 3, 0];
    let batch = MapBatch {
        k: k(),
        poses: &poses,
        slots: &slots,
        pixels: &px,
        loss: loss(0),
    };
    assert!(be.map_step(&batch, &mut res).is_err());
    // slot table shorter than the window
    let batch = MapBatch {
        slots: &slots[..2],
        ..batch
    };
    assert!(be.map_step(&batch, &mut res).is_err());
    // results of the wrong length
    let batch = MapBatch {
        slots: &[0, 1, 1, 0],
        ..batch
    };
    assert!(be.map_step(&batch, &mut res[..3]).is_err());
    assert!(be.map_step(&batch, &mut res).is_ok());
}
