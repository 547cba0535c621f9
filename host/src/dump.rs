//! `himap dump-step`: one training step of a small model on random rays against a synthetic
//! target, written with every input, output and gradient as named safetensors tensors, so that
//! an outside autograd implementation can recompute the loss and the gradients from the file
//! alone. The tensor names and the formulas are documented in the README ("Cross-checking a
//! training step").

use std::collections::HashMap;
use std::path::Path;

use anyhow::Context;
use himap_core::field::grid::{GridConfig, GridKind, GridLayout, MAX_LEVELS};
use himap_core::field::model::{
    Group, LossConfig, ModelConfig, ModelLayout, Ray, RayCache, RayResult, SampleScratch,
};
use himap_core::field::render::RenderMode;
use himap_core::rng::SplitMix;
use himap_core::train::backend::Backend;
use himap_core::train::reference::CpuBackend;
use himap_core::Aabb;
use safetensors::tensor::{Dtype, TensorView};
use serde_json::json;

use crate::backend::ModelData;

/// Options of `dump-step`.
#[derive(Clone, Debug)]
pub struct DumpOptions {
    pub seed: u64,
    pub rays: usize,
    pub render_mode: RenderMode,
}

impl Default for DumpOptions {
    fn default() -> Self {
        Self {
            seed: 0,
            rays: 64,
            render_mode: RenderMode::SdfDensity,
        }
    }
}

/// The small configuration used by `dump-step` (and tests): a 2 m cube, geometry 3 levels
/// (0.5, 0.25, 0.125 m, 2 channels), appearance 2 levels (0.5, 0.25 m, 4 channels), decoders
/// with 16 hidden units and two hidden layers, 16 samples per ray.
pub fn small_config(render_mode: RenderMode) -> ModelConfig {
    let aabb = Aabb::new([-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]);
    let mut geo = GridConfig::hi_map_geometry();
    geo.levels = 3;
    geo.cell_sizes = [0.5, 0.25, 0.125, 0.0, 0.0, 0.0, 0.0, 0.0];
    let mut app = GridConfig::hi_map_appearance();
    app.channels = 4;
    app.cell_sizes = [0.5, 0.25, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0];
    ModelConfig {
        aabb,
        geometry_grid: geo,
        appearance_grid: app,
        hidden: 16,
        hidden_layers: 2,
        dual_path: true,
        render_mode,
        samples: 16,
        beta_init: 10.0,
        // Larger than the paper's 0.01 so that the grids carry signal through the decoders in
        // a single step (the cross-check wants non-trivial gradients everywhere).
        grid_init_std: 0.1,
        sdf_bias_init: 0.3,
        max_depth: 0.0,
        far_samples: 0,
        far_depth: 0.0,
        min_transmittance: 0.0,
    }
}

/// A mapping configuration small enough for end-to-end tests on 64x48 synthetic rooms:
/// `small` with 12 samples per ray, 40 initialisation iterations (20 with colour to the
/// geometry), 3 online iterations of 128 pixels, 8 keyframes, and a coarse, sparse mesh
/// evaluation (0.15 m grid, `mesh.ply` again at 3.75 cm, 2000 samples). Tests change what
/// they exercise on top of it.
pub fn tiny_map_config() -> crate::config::Config {
    let mut c = crate::config::Config::small();
    c.model.samples = 12;
    c.mapper.init_iters = 40;
    c.mapper.init_color_iters = 20;
    c.mapper.iters = 3;
    c.mapper.pixels = 128;
    c.mapper.max_keyframes = 8;
    c.mapper.refine_iters = 0;
    c.eval.mesh_resolution = 0.15;
    c.eval.mesh_samples = 2000;
    c
}

/// Random rays from inside the box towards random directions, with synthetic targets.
pub fn random_rays(n: usize, seed: u64) -> Vec<Ray> {
    let mut rng = SplitMix::new(seed ^ 0x5E_ED0F_7A75);
    let mut u = |lo: f32, hi: f32| lo + (hi - lo) * rng.unit();
    (0..n)
        .map(|_| {
            let origin = [u(-0.5, 0.5), u(-0.5, 0.5), u(-0.5, 0.5)];
            let dir = [u(-1.0, 1.0), u(-1.0, 1.0), u(-1.0, 1.0)];
            Ray {
                origin,
                dir,
                target: [u(0.0, 1.0), u(0.0, 1.0), u(0.0, 1.0)],
                target_depth: u(0.2, 1.0),
            }
        })
        .collect()
}

/// The non-finite-step sequence the backends' rejection tests run (four train steps over
/// `rays`, [`LossConfig`] as in `loss`): a finite step; the same rays with one target colour
/// NaN (the loss is not finite); the finite rays with the geometry decoder's learning rate at
/// 1e38 (`lr / (1 - beta1^t)` overflows, so the update is not finite), the rate then set back
/// to `lr`; a finite step. Returns each step's statistics; a backend must reject steps 2
/// and 3 and leave every parameter, moment and the step count as they were.
pub fn nonfinite_sequence<B: Backend>(
    backend: &mut B,
    rays: &[Ray],
    loss: &LossConfig,
    lr: f32,
) -> Result<Vec<himap_core::train::backend::StepStats>, B::Error> {
    let mut res = vec![RayResult::default(); rays.len()];
    let mut stats = vec![backend.train_step(rays, loss, &mut res)?];
    let mut poisoned = rays.to_vec();
    poisoned[rays.len() / 2].target[1] = f32::NAN;
    stats.push(backend.train_step(&poisoned, loss, &mut res)?);
    backend.set_adam_lr(Group::GeometryMlp, 1e38)?;
    stats.push(backend.train_step(rays, loss, &mut res)?);
    backend.set_adam_lr(Group::GeometryMlp, lr)?;
    stats.push(backend.train_step(rays, loss, &mut res)?);
    Ok(stats)
}

fn grid_json(l: &GridLayout) -> serde_json::Value {
    let levels: Vec<_> = (0..l.levels as usize)
        .map(|i| {
            let lv = &l.level[i];
            json!({"res": lv.res, "offset": lv.offset, "plane_offsets": lv.plane_offsets,
                   "line_offsets": lv.line_offsets, "count": lv.count})
        })
        .collect();
    json!({
        "kind": match l.kind { GridKind::Factorized => "factorized", GridKind::Dense => "dense" },
        "levels": levels, "channels": l.channels, "param_count": l.param_count,
    })
}

fn f32_bytes(v: &[f32]) -> Vec<u8> {
    v.iter().flat_map(|x| x.to_le_bytes()).collect()
}

fn i64_bytes(v: &[i64]) -> Vec<u8> {
    v.iter().flat_map(|x| x.to_le_bytes()).collect()
}

/// Runs the step and writes the file. Returns the loss.
pub fn dump_step(out: &Path, opts: &DumpOptions) -> anyhow::Result<f32> {
    let cfg = small_config(opts.render_mode);
    let layout = ModelLayout::new(&cfg).context("building the small model layout")?;
    let data = ModelData::new(layout, opts.seed as u32)?;
    let initial = data.clone();
    let rays = random_rays(opts.rays, opts.seed);
    let loss = LossConfig {
        lambda_color: 1.0,
        lambda_depth: 0.5,
        ray_scale: 1.0 / rays.len() as f32,
        color_to_geometry: true,
        seed: opts.seed as u32 ^ 0xA5A5,
    };

    // The single-threaded reference backend over copies of the buffers.
    let mut params = data.params.clone();
    let mut m = data.m.clone();
    let mut v = data.v.clone();
    let lens = layout.group_lens();
    let mut grads: [Vec<i64>; 5] = lens.map(|n| vec![0; n]);
    let groups =
        himap_core::train::reference::group_states(&mut params, &mut m, &mut v, &mut grads);
    let mut backend = CpuBackend::new(layout, groups, himap_core::train::backend::paper_adam())?;
    let mut results = vec![RayResult::default(); rays.len()];
    let stats = backend.train_step(&rays, &loss, &mut results)?;

    let (t_all, w_all, n_all) = ray_samples(&layout, &initial, &rays, loss.seed);
    let s = cfg.samples as usize;

    let n = rays.len();
    let mut tensors: Vec<(String, Dtype, Vec<usize>, Vec<u8>)> = Vec::new();
    let mut push_f32 = |name: &str, shape: Vec<usize>, data: &[f32]| {
        tensors.push((name.to_string(), Dtype::F32, shape, f32_bytes(data)))
    };
    for g in Group::ALL {
        let gi = g as usize;
        push_f32(
            &format!("params.{}", g.name()),
            vec![lens[gi]],
            &initial.params[gi],
        );
        push_f32(
            &format!("params_after.{}", g.name()),
            vec![lens[gi]],
            backend.params(g),
        );
        let gf: Vec<f32> = backend
            .grads(g)
            .iter()
            .map(|&q| himap_core::train::fixed::from_fixed(q))
            .collect();
        push_f32(&format!("grad.{}", g.name()), vec![lens[gi]], &gf);
    }
    let flat = |f: &dyn Fn(&Ray) -> [f32; 3]| -> Vec<f32> { rays.iter().flat_map(f).collect() };
    push_f32("rays.origin", vec![n, 3], &flat(&|r| r.origin));
    push_f32("rays.dir", vec![n, 3], &flat(&|r| r.dir));
    push_f32("target.color", vec![n, 3], &flat(&|r| r.target));
    push_f32(
        "target.depth",
        vec![n],
        &rays.iter().map(|r| r.target_depth).collect::<Vec<_>>(),
    );
    push_f32("samples.t", vec![n, s], &t_all);
    push_f32("render.weights", vec![n, s], &w_all);
    push_f32(
        "render.color",
        vec![n, 3],
        &results.iter().flat_map(|r| r.color).collect::<Vec<_>>(),
    );
    push_f32(
        "render.depth",
        vec![n],
        &results.iter().map(|r| r.depth).collect::<Vec<_>>(),
    );
    push_f32(
        "render.opacity",
        vec![n],
        &results.iter().map(|r| r.opacity).collect::<Vec<_>>(),
    );
    push_f32(
        "loss.per_ray",
        vec![n],
        &results.iter().map(|r| r.loss).collect::<Vec<_>>(),
    );
    push_f32("loss", vec![1], &[stats.loss]);
    for g in Group::ALL {
        tensors.push((
            format!("grad_fixed.{}", g.name()),
            Dtype::I64,
            vec![lens[g as usize]],
            i64_bytes(backend.grads(g)),
        ));
    }
    tensors.push((
        "samples.count".into(),
        Dtype::I64,
        vec![n],
        i64_bytes(&n_all),
    ));

    let config = config_json(&cfg, &layout, &loss);
    write_tensors(out, &tensors, &config.to_string())?;
    Ok(stats.loss)
}

/// Per-ray sample depths, rendering weights (`samples` slots per ray) and sample counts of the
/// step's forward, recomputed from the initial parameters with the step's seed (the forward
/// is pure).
fn ray_samples(
    layout: &ModelLayout,
    initial: &ModelData,
    rays: &[Ray],
    seed: u32,
) -> (Vec<f32>, Vec<f32>, Vec<i64>) {
    let s = layout.config.samples as usize;
    let mut t_all = vec![0f32; rays.len() * s];
    let mut w_all = vec![0f32; rays.len() * s];
    let mut n_all = vec![0i64; rays.len()];
    let view = initial.view();
    let mut cache = Box::new(RayCache::new());
    let mut scratch = Box::new(SampleScratch::new());
    for (i, ray) in rays.iter().enumerate() {
        himap_core::field::model::ray_forward(
            layout,
            &view,
            ray,
            i as u32,
            seed,
            true,
            &mut cache,
            &mut scratch,
        );
        n_all[i] = cache.n as i64;
        for k in 0..cache.n {
            t_all[i * s + k] = cache.t[k];
            w_all[i * s + k] = cache.out.weights[k];
        }
    }
    (t_all, w_all, n_all)
}

/// The file's `himap_config` metadata: the model's shapes and the step's loss settings.
fn config_json(cfg: &ModelConfig, layout: &ModelLayout, loss: &LossConfig) -> serde_json::Value {
    json!({
        "aabb": {"min": cfg.aabb.min, "max": cfg.aabb.max},
        "geometry_grid": grid_json(&layout.geometry_grid),
        "appearance_grid": grid_json(&layout.appearance_grid),
        "geometry_mlp": {"n_in": layout.geometry_mlp.n_in, "hidden": layout.geometry_mlp.hidden,
            "hidden_layers": layout.geometry_mlp.hidden_layers, "n_out": layout.geometry_mlp.n_out},
        "appearance_mlp": {"n_in": layout.appearance_mlp.n_in, "hidden": layout.appearance_mlp.hidden,
            "hidden_layers": layout.appearance_mlp.hidden_layers, "n_out": layout.appearance_mlp.n_out},
        "dual_path": cfg.dual_path,
        "render_mode": format!("{:?}", cfg.render_mode),
        "samples": cfg.samples,
        "lambda_color": loss.lambda_color,
        "lambda_depth": loss.lambda_depth,
        "ray_scale": loss.ray_scale,
        "color_to_geometry": loss.color_to_geometry,
        "fixed_point_frac_bits": himap_core::train::fixed::FRAC_BITS,
        "max_levels": MAX_LEVELS,
    })
}

/// Writes the tensors with the configuration as metadata, atomically.
fn write_tensors(
    out: &Path,
    tensors: &[(String, Dtype, Vec<usize>, Vec<u8>)],
    config: &str,
) -> anyhow::Result<()> {
    let mut meta = HashMap::new();
    meta.insert("himap_config".to_string(), config.to_string());
    meta.insert("format".to_string(), "himap-dump-step-v1".to_string());
    let views: Vec<(String, TensorView<'_>)> = tensors
        .iter()
        .map(|(name, dt, shape, bytes)| {
            Ok((name.clone(), TensorView::new(*dt, shape.clone(), bytes)?))
        })
        .collect::<Result<_, safetensors::SafeTensorError>>()?;
    let bytes = safetensors::serialize(views, Some(meta))
        .with_context(|| format!("serialising {}", out.display()))?;
    crate::atomic::write_bytes_atomic(out, &bytes)?;
    Ok(())
}
