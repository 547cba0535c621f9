//! Building a run's backend and its initial map, and sizing the map for its box before
//! anything is allocated.

#[allow(unused_imports)]
use super::*;

/// Builds the parallel backend for a configuration over `aabb` with image slots for `k`.
pub fn build_backend(
    config: &Config,
    aabb: Aabb,
    k: &Intrinsics,
    threads: usize,
) -> anyhow::Result<ParallelCpuBackend> {
    build_backend_at(config, aabb, k, threads, None)
}

/// [`build_backend`] whose geometric initialisation (`model.geo_init`) centres its sphere on
/// `center` (default: the box centre).
pub fn build_backend_at(
    config: &Config,
    aabb: Aabb,
    k: &Intrinsics,
    threads: usize,
    center: Option<[f32; 3]>,
) -> anyhow::Result<ParallelCpuBackend> {
    let data = initial_data(config, aabb, center)?;
    let mapper = config.mapper_config()?;
    Ok(
        ParallelCpuBackend::new(data, config.adam_config(), threads)?.with_images(ImageStore {
            width: k.width,
            height: k.height,
            slots: mapper.slots_needed(),
        }),
    )
}

/// The model a run starts from: seeded initialisation, then the geometric initialisation of
/// `model.geo_init` (its sphere centred on `center`, default the box centre).
pub fn initial_data(
    config: &Config,
    aabb: Aabb,
    center: Option<[f32; 3]>,
) -> anyhow::Result<ModelData> {
    let mc = config.model_config(aabb)?;
    let layout = ModelLayout::new(&mc).map_err(|e| anyhow::anyhow!("model: {e}"))?;
    let mut data = ModelData::new(layout, config.seed as u32)
        .map_err(|e| anyhow::anyhow!("model init: {e}"))?;
    if config.model.geo_init == crate::config::GeoInit::Sphere {
        let c = center.unwrap_or_else(|| [0, 1, 2].map(|a| 0.5 * (aabb.min[a] + aabb.max[a])));
        crate::geo_init::fit_sphere(
            &mut data,
            &crate::geo_init::SphereInit {
                center: c,
                radius: config.model.geo_init_radius,
                solid: config.model.geo_init_solid,
                iters: config.model.geo_init_iters,
                points: 4096,
                lr: 0.01,
                seed: config.seed,
            },
        );
    }
    Ok(data)
}

/// Renders a view (colour, depth, opacity per pixel, row-major).
pub fn render_view<B: Backend>(
    backend: &mut B,
    k: &Intrinsics,
    pose: &Pose,
) -> anyhow::Result<Vec<RayResult>>
where
    B::Error: std::error::Error + Send + Sync + 'static,
{
    view_results(backend, k, pose, false)
}

/// [`render_view`]'s depth and opacity (the same bits) through [`Backend::render_depth`]; the
/// colour may be 0 (the CPU skips the appearance: about twice as fast).
pub fn render_view_depth<B: Backend>(
    backend: &mut B,
    k: &Intrinsics,
    pose: &Pose,
) -> anyhow::Result<Vec<RayResult>>
where
    B::Error: std::error::Error + Send + Sync + 'static,
{
    view_results(backend, k, pose, true)
}

fn view_results<B: Backend>(
    backend: &mut B,
    k: &Intrinsics,
    pose: &Pose,
    depth_only: bool,
) -> anyhow::Result<Vec<RayResult>>
where
    B::Error: std::error::Error + Send + Sync + 'static,
{
    let n = k.width as usize * k.height as usize;
    let mut rays = vec![
        Ray {
            origin: [0.0; 3],
            dir: [0.0; 3],
            target: [0.0; 3],
            target_depth: 0.0,
        };
        n
    ];
    view_rays(k, pose, &mut rays).map_err(|e| anyhow::anyhow!("{e}"))?;
    let mut out = vec![RayResult::default(); n];
    if depth_only {
        backend.render_depth(&rays, &mut out)?;
    } else {
        backend.render(&rays, &mut out)?;
    }
    Ok(out)
}

/// Packs an RGB image into RGBA8 words.
pub fn pack_image(img: &RgbImage) -> Vec<u32> {
    img.data
        .as_chunks::<3>()
        .0
        .iter()
        .map(|c| pack_rgba8(*c))
        .collect()
}

/// Bytes the map of `aabb` takes on the CPU backend with `threads` workers: parameters and
/// Adam moments (3 x f32), and the gradient buffers (one i64 set per worker and the sum).
pub fn map_bytes(cfg: &Config, aabb: Aabb, threads: usize) -> anyhow::Result<(usize, u64, u64)> {
    let layout =
        ModelLayout::new(&cfg.model_config(aabb)?).map_err(|e| anyhow::anyhow!("model: {e}"))?;
    let workers = if threads == 0 {
        std::thread::available_parallelism().map_or(1, |n| n.get())
    } else {
        threads
    };
    let p = layout.param_count();
    Ok((p, p as u64 * 12, p as u64 * 8 * (workers as u64 + 1)))
}

/// Prints the map's memory for the box before anything is allocated, and refuses a map over
/// `scene.memory_budget_mb` with the settings that change it.
pub(super) fn check_map_memory(
    cfg: &Config,
    aabb: Aabb,
    box_src: &str,
    threads: usize,
    print: bool,
) -> anyhow::Result<()> {
    let (p, state, grads) = map_bytes(cfg, aabb, threads)?;
    let mb = |b: u64| b as f64 / 1e6;
    let total = mb(state + grads);
    let e = aabb.extent();
    if print {
        eprintln!(
            "map: {p} parameters over the {:.2} x {:.2} x {:.2} m scene box ({box_src}): {:.0} MB \
             (parameters and Adam moments {:.0} MB, gradient buffers {:.0} MB)",
            e[0],
            e[1],
            e[2],
            total,
            mb(state),
            mb(grads)
        );
    }
    if total > cfg.scene.memory_budget_mb {
        bail!(
            "the map of the {:.2} x {:.2} x {:.2} m scene box ({box_src}) needs {total:.0} MB, over \
             scene.memory_budget_mb = {:.0}: give a smaller box (scene.min, scene.max), coarser \
             grids (model.geometry.cell_sizes, model.appearance.cell_sizes) or fewer channels, \
             or raise scene.memory_budget_mb",
            e[0],
            e[1],
            e[2],
            cfg.scene.memory_budget_mb
        );
    }
    Ok(())
}
