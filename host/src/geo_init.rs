//! Geometric initialisation of the SDF before mapping (no images, no depth): the geometry grid
//! and decoder are fitted to an inverted sphere `s*(p) = max(r - |p - c|, -solid)` (positive, free
//! space, inside; the camera lives inside), centred on the first camera. This replaces the
//! near-camera "fog" of a constant output bias with one multi-view consistent surface at a
//! plausible distance, the monocular analogue
//! of the sphere initialisations of NeRF-SLAM peers and a geometric form of DIM-SLAM's constant
//! 1.5 m depth prior (which, applied per view, is not consistent between views).
//!
//! The fit is plain host code (single thread, f32 accumulation in a fixed order, the core's
//! `sdf_at` (in its fast form, `sdf_at_transposed`: the same bits) / `sdf_backward_taped` and
//! the operations of `adam_update`), so it is
//! deterministic and independent of the backend and thread count; the backend receives the
//! fitted parameters as its initial state. Adam moments of the mapping run start at zero as
//! before.

use himap_core::field::mlp::{transpose_weights, MlpScratch};
use himap_core::field::model::{
    sdf_at_transposed, sdf_backward_taped, Group, ModelGradSink, SampleScratch,
};
use himap_core::rng::SplitMix;
use himap_core::train::adam::{AdamConfig, AdamStep};

use crate::backend::{AdamHw, ModelData};

/// Settings of the sphere fit.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SphereInit {
    pub center: [f32; 3],
    /// Sphere radius (m).
    pub radius: f32,
    /// The target is cut below at `-solid` (m) outside the sphere.
    pub solid: f32,
    /// Adam iterations and points per iteration.
    pub iters: u32,
    pub points: u32,
    /// Learning rate of the grid and of the decoder.
    pub lr: f32,
    pub seed: u64,
}

struct Grads<'a> {
    grid: &'a mut [f32],
    mlp: &'a mut [f32],
}

impl ModelGradSink for Grads<'_> {
    fn add(&mut self, group: Group, i: usize, g: f32) {
        let buf = match group {
            Group::GeometryGrid => &mut *self.grid,
            Group::GeometryMlp => &mut *self.mlp,
            _ => return,
        };
        if let Some(x) = buf.get_mut(i) {
            *x += g;
        }
    }
}

/// Fits the geometry of `data` to the inverted sphere; returns the final mean squared error
/// (m^2) on the last batch.
pub fn fit_sphere(data: &mut ModelData, init: &SphereInit) -> f32 {
    let layout = data.layout;
    let aabb = layout.config.aabb;
    let gi = Group::GeometryGrid as usize;
    let mi = Group::GeometryMlp as usize;
    let (ng, nm) = (data.params[gi].len(), data.params[mi].len());
    let mut g_grid = vec![0.0f32; ng];
    let mut g_mlp = vec![0.0f32; nm];
    let (mut m_grid, mut v_grid) = (vec![0.0f32; ng], vec![0.0f32; ng]);
    let (mut m_mlp, mut v_mlp) = (vec![0.0f32; nm], vec![0.0f32; nm]);
    let mut rng = SplitMix::new(init.seed ^ 0x5EED_5A4E_0000_0001);
    let mut scratch = SampleScratch::new();
    let mut act = MlpScratch::new();
    let mut wt = vec![0.0f32; nm];
    let cfg = AdamConfig::new(init.lr);
    let n = init.points.max(1);
    let mut mse = 0.0f32;
    let mut pts = vec![[0.0f32; 3]; n as usize];
    for it in 0..init.iters {
        // Three points in four near the sphere (the cube of half side 1.5 r around the
        // centre, cut to the box), one anywhere in the box: a large box (a building, the
        // default box around the first camera) would otherwise leave the sphere with a few
        // points per iteration.
        for (j, p) in pts.iter_mut().enumerate() {
            let near = j % 4 != 3;
            for (a, x) in p.iter_mut().enumerate() {
                let (mut lo, mut hi) = (aabb.min[a], aabb.max[a]);
                if near {
                    let (l, h) = (
                        init.center[a] - 1.5 * init.radius,
                        init.center[a] + 1.5 * init.radius,
                    );
                    if l < hi && h > lo {
                        (lo, hi) = (lo.max(l), hi.min(h));
                    }
                }
                *x = lo + (hi - lo) * rng.unit();
            }
        }
        g_grid.iter_mut().for_each(|x| *x = 0.0);
        g_mlp.iter_mut().for_each(|x| *x = 0.0);
        let mut err = 0.0f32;
        {
            let params = data.view();
            // The decoder's weights transposed for the fast forward (the same bits as `sdf_at`).
            if transpose_weights(&layout.geometry_mlp, &data.params[mi], &mut wt).is_err() {
                return f32::NAN;
            }
            let mut sink = Grads {
                grid: &mut g_grid,
                mlp: &mut g_mlp,
            };
            for &p in &pts {
                let d = [
                    p[0] - init.center[0],
                    p[1] - init.center[1],
                    p[2] - init.center[2],
                ];
                // Truncated below at -solid: space not seen yet is "just solid", where
                // the renderer's gradients do not vanish, so the depth prior and the warping
                // loss can open it when a camera walks in (at -2 m, sig'(-beta s) ~ 2e-9).
                let target = (init.radius - (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt())
                    .max(-init.solid);
                let s = sdf_at_transposed(&layout, &params, &wt, p, &mut scratch, &mut act);
                let r = s - target;
                err += r * r;
                // The forward just left this point's activations in `act`: the backward of
                // `sdf_backward` without evaluating the point again (same contributions).
                sdf_backward_taped(&layout, &params, p, 2.0 * r / n as f32, &act, &mut sink);
            }
        }
        mse = err / n as f32;
        // `adam_update`'s bits with the CPU's square root (see `AdamHw`).
        let step = AdamHw::new(&AdamStep::new(&cfg, it + 1));
        for (i, p) in data.params[gi].iter_mut().enumerate() {
            step.update(p, &mut m_grid[i], &mut v_grid[i], g_grid[i]);
        }
        for (i, p) in data.params[mi].iter_mut().enumerate() {
            step.update(p, &mut m_mlp[i], &mut v_mlp[i], g_mlp[i]);
        }
    }
    mse
}

#[cfg(test)]
mod tests {
    use super::*;
    use himap_core::field::model::sdf_at;
    use himap_core::field::model::{ModelConfig, ModelLayout};
    use himap_core::Aabb;

    #[test]
    fn sphere_fit_reduces_the_error_and_is_deterministic() {
        let mut cfg = ModelConfig::paper(Aabb::new([-2.0; 3], [2.0; 3]));
        cfg.geometry_grid.levels = 3;
        cfg.geometry_grid.cell_sizes = [0.64, 0.32, 0.16, 0.0, 0.0, 0.0, 0.0, 0.0];
        let layout = ModelLayout::new(&cfg).unwrap();
        let init = SphereInit {
            center: [0.2, 0.0, -0.1],
            radius: 1.5,
            solid: 1.5,
            iters: 0,
            points: 512,
            lr: 0.01,
            seed: 3,
        };
        let mut a = ModelData::new(layout, 1).unwrap();
        let before = fit_sphere(&mut a.clone(), &SphereInit { iters: 1, ..init });
        let after = fit_sphere(&mut a, &SphereInit { iters: 150, ..init });
        assert!(after < 0.1 * before, "{before} -> {after}");
        let mut b = ModelData::new(layout, 1).unwrap();
        fit_sphere(&mut b, &SphereInit { iters: 150, ..init });
        assert_eq!(a.params, b.params);
        // inside positive (free), outside negative
        let mut s = SampleScratch::new();
        assert!(sdf_at(&layout, &a.view(), [0.2, 0.0, -0.1], &mut s) > 0.8);
        assert!(sdf_at(&layout, &a.view(), [1.9, 1.9, 1.9], &mut s) < -0.5);
    }
}
