//! A short training run on a built-in analytic target: a coloured sphere inside a box, seen by
//! rays from a ring of viewpoints. It needs no data and prints the loss going down; it is the
//! smallest end-to-end exercise of the field, the renderer, the losses, the gradients and Adam.

use himap_core::field::model::{Group, LossConfig, ModelLayout, Ray, RayResult};
use himap_core::rng::SplitMix;
use himap_core::train::backend::Backend;

use crate::backend::{ModelData, ParallelCpuBackend};

/// Colour and depth of the analytic target along a ray: a sphere of radius 0.45 at the origin
/// (colour varying with the surface normal), inside a cube of half-size 1 whose walls are
/// coloured per axis. Returns (colour, camera-z depth).
pub fn target(origin: [f32; 3], dir: [f32; 3]) -> ([f32; 3], f32) {
    let dot = |a: [f32; 3], b: [f32; 3]| a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
    // The rays below have |dir| = 1 and their own camera z along dir.
    let b = dot(origin, dir);
    let c = dot(origin, origin) - 0.45 * 0.45;
    let disc = b * b - c;
    if disc > 0.0 {
        let t = -b - disc.sqrt();
        if t > 0.0 {
            let p = [
                origin[0] + t * dir[0],
                origin[1] + t * dir[1],
                origin[2] + t * dir[2],
            ];
            let n = [p[0] / 0.45, p[1] / 0.45, p[2] / 0.45];
            return ([0.5 + 0.4 * n[0], 0.5 + 0.4 * n[1], 0.5 + 0.4 * n[2]], t);
        }
    }
    let mut t_exit = f32::INFINITY;
    let mut axis = 0;
    for a in 0..3 {
        if dir[a].abs() > 1e-9 {
            let t = ((if dir[a] > 0.0 { 1.0 } else { -1.0 }) - origin[a]) / dir[a];
            if t < t_exit {
                t_exit = t;
                axis = a;
            }
        }
    }
    let mut col = [0.2, 0.2, 0.2];
    col[axis] = if dir[axis] > 0.0 { 0.9 } else { 0.6 };
    (col, t_exit)
}

/// Rays from viewpoints on a ring of radius 0.8 looking roughly at the centre.
pub fn target_rays(n: usize, rng: &mut SplitMix) -> Vec<Ray> {
    (0..n)
        .map(|_| {
            let a = rng.unit() * std::f32::consts::TAU;
            let origin = [0.8 * a.cos(), 0.8 * a.sin(), 0.3 * (rng.unit() - 0.5)];
            let look = [-origin[0], -origin[1], -origin[2]];
            let mut d = [
                look[0] + 0.9 * (rng.unit() - 0.5),
                look[1] + 0.9 * (rng.unit() - 0.5),
                look[2] + 0.9 * (rng.unit() - 0.5),
            ];
            let len = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
            d = [d[0] / len, d[1] / len, d[2] / len];
            let (target, depth) = target(origin, d);
            Ray {
                origin,
                dir: d,
                target,
                target_depth: depth,
            }
        })
        .collect()
}

/// Runs `steps` training steps with `rays` rays each and reports the mean loss every
/// `report_every` steps through `report(step, loss, psnr)`. Returns the (first, last) loss
/// averaged over the first and last reporting windows.
pub fn run(
    layout: ModelLayout,
    steps: usize,
    rays: usize,
    threads: usize,
    seed: u64,
    mut report: impl FnMut(usize, f32, f32),
    report_every: usize,
) -> anyhow::Result<(f32, f32)> {
    let data = ModelData::new(layout, seed as u32)?;
    let mut adam = himap_core::train::backend::paper_adam();
    // A short run needs faster decoders than the paper's online 1e-5.
    adam[Group::GeometryMlp].lr = 1e-3;
    adam[Group::AppearanceMlp].lr = 1e-3;
    adam[Group::Beta].lr = 1e-3;
    let mut backend = ParallelCpuBackend::new(data, adam, threads)?;
    let mut rng = SplitMix::new(seed);
    let mut results = vec![RayResult::default(); rays];
    let (mut first, mut last) = (None, 0.0f32);
    let mut window = (0.0f32, 0.0f32, 0usize);
    for step in 0..steps {
        let batch = target_rays(rays, &mut rng);
        let loss = LossConfig {
            lambda_color: 1.0,
            lambda_depth: 0.0,
            ray_scale: 1.0 / rays as f32,
            color_to_geometry: true,
            seed: step as u32,
        };
        let stats = backend.train_step(&batch, &loss, &mut results)?;
        let mse: f32 = results
            .iter()
            .zip(&batch)
            .map(|(r, b)| {
                (0..3)
                    .map(|c| (r.color[c] - b.target[c]).powi(2))
                    .sum::<f32>()
            })
            .sum::<f32>()
            / (3 * rays) as f32;
        window.0 += stats.loss;
        window.1 += -10.0 * mse.log10();
        window.2 += 1;
        if (step + 1) % report_every == 0 || step + 1 == steps {
            let l = window.0 / window.2 as f32;
            report(step + 1, l, window.1 / window.2 as f32);
            if first.is_none() {
                first = Some(l);
            }
            last = l;
            window = (0.0, 0.0, 0);
        }
    }
    Ok((first.unwrap_or(last), last))
}
