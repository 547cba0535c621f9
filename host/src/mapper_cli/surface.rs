//! The mesh a run writes: the renderer's surface level, the observed region and its
//! extraction and culling.

#[allow(unused_imports)]
use super::*;

/// The SDF level of the surfaces the field renders, estimated without ground truth: `views`
/// poses spread over the sequence are rendered at `k`; every pixel with opacity > 0.9 gives
/// the point at its rendered depth (normalised by the opacity), and the level is the median
/// SDF over these points. `None` when no pixel is opaque. Hi-Map's density proxy has no
/// `delta t`, so where the field draws its surfaces depends on beta and on the sample spacing
/// (not only on the zero crossing); this is the level `mesh.ply` is extracted at by default.
pub fn rendered_surface_level<B: MapBackend>(
    backend: &mut B,
    k: &Intrinsics,
    poses: &[Pose],
    views: usize,
) -> anyhow::Result<Option<f32>>
where
    B::Error: std::error::Error + Send + Sync + 'static,
{
    if poses.is_empty() || views == 0 {
        return Ok(None);
    }
    let mut pts = Vec::new();
    for v in 0..views {
        let pose = &poses[(v * poses.len()) / views];
        let out = render_view_depth(backend, k, pose)?;
        for (i, r) in out.iter().enumerate() {
            if r.opacity > 0.9 && r.depth > 0.0 && r.depth.is_finite() {
                let (u, w) = ((i % k.width as usize) as f32, (i / k.width as usize) as f32);
                let (o, d) = pose.ray(k, u, w);
                let t = r.depth / r.opacity;
                pts.push([o[0] + t * d[0], o[1] + t * d[1], o[2] + t * d[2]]);
            }
        }
    }
    if pts.is_empty() {
        return Ok(None);
    }
    let mut sdf = vec![0.0f32; pts.len()];
    backend.query_sdf(&pts, &mut sdf)?;
    sdf.sort_by(f32::total_cmp);
    Ok(Some(sdf[sdf.len() / 2]))
}

/// Marching cubes on the SDF of `backend` minus `level`, with vertex colours.
pub fn map_mesh<B: MapBackend>(
    backend: &mut B,
    aabb: Aabb,
    resolution: f32,
    level: f32,
) -> anyhow::Result<crate::mesh::Mesh> {
    crate::query::region_mesh(backend, aabb, resolution, level)
}

/// Views of the pushed frames [`observed_views`] renders for the observed region.
pub(super) const OBSERVED_VIEWS: usize = 96;

/// Renders the depth of up to `max_views` of `poses` (spread evenly) from the map at a
/// quarter of `k`'s resolution (at least 64 px wide); a pixel with opacity below 0.5 gets depth
/// 0 (nothing seen), others `D / O`.
pub fn observed_views<B: Backend>(
    backend: &mut B,
    k: &Intrinsics,
    poses: &[Pose],
    max_views: usize,
) -> anyhow::Result<Vec<(Intrinsics, Pose, Vec<f32>)>>
where
    B::Error: std::error::Error + Send + Sync + 'static,
{
    let w = (k.width / 4).max(64.min(k.width));
    let h = ((k.height as u64 * w as u64) / k.width.max(1) as u64).max(1) as u32;
    let lk = k.resized(w, h);
    let n = poses.len().min(max_views);
    let mut out = Vec::with_capacity(n);
    for v in 0..n {
        let pose = poses[v * poses.len() / n];
        let r = render_view_depth(backend, &lk, &pose)?;
        let d = r
            .iter()
            .map(|r| {
                if r.opacity >= 0.5 && r.depth.is_finite() {
                    r.depth / r.opacity
                } else {
                    0.0
                }
            })
            .collect();
        out.push((lk, pose, d));
    }
    Ok(out)
}

/// The box around the views' cameras and rendered surface points, grown by `margin` and cut
/// to `aabb`; `None` when it is empty.
pub fn observed_region(
    views: &[(Intrinsics, Pose, Vec<f32>)],
    aabb: Aabb,
    margin: f32,
) -> Option<Aabb> {
    let mut lo = [f32::INFINITY; 3];
    let mut hi = [f32::NEG_INFINITY; 3];
    let mut add = |p: [f32; 3]| {
        for a in 0..3 {
            lo[a] = lo[a].min(p[a]);
            hi[a] = hi[a].max(p[a]);
        }
    };
    for (k, pose, depth) in views {
        add(pose.origin());
        for (i, &d) in depth.iter().enumerate() {
            if d > 0.0 {
                let (u, v) = ((i % k.width as usize) as f32, (i / k.width as usize) as f32);
                add(pose.transform(k.direction(u, v).map(|x| x * d)));
            }
        }
    }
    let b = Aabb::new(
        [0, 1, 2].map(|a| (lo[a] - margin).max(aabb.min[a])),
        [0, 1, 2].map(|a| (hi[a] + margin).min(aabb.max[a])),
    );
    b.is_valid().then_some(b)
}

/// `himap mesh --observed`: the frames whose views cut the mesh to what they saw, as `himap
/// map` cuts `mesh.ply` (the frames the map was made from, read at the size it was made at).
#[derive(Clone, Debug)]
pub struct ObservedBy {
    pub dataset: PathBuf,
    pub resize: Option<(u32, u32)>,
}

/// `himap mesh`: extracts the mesh of a saved map at `resolution` (default: its
/// configuration's) and SDF `level` (default: [`Config::surface_level`]; with `observed`, the
/// level of the frames' renders, as `himap map`) into `out`, over the whole box or, with
/// `observed`, cut to what the frames saw ([`super::run::final_meshes`]). Returns the face
/// count and the level used.
pub fn mesh_saved_map(
    map: &Path,
    out: &Path,
    resolution: Option<f32>,
    level: Option<f32>,
    threads: usize,
    observed: Option<&ObservedBy>,
) -> anyhow::Result<(usize, f32)> {
    let (mut cfg, data) = load_map(map)?;
    let aabb = data.layout.config.aabb;
    let beta = data.params[Group::Beta as usize][0];
    let mut backend = ParallelCpuBackend::new(data, cfg.adam_config(), threads)?;
    if let Some(o) = observed {
        if let Some(l) = level {
            cfg.eval.mesh_level = Some(l);
        }
        if let Some(r) = resolution {
            cfg.eval.mesh_resolution = r;
        }
        let load = dataset::LoadOptions {
            resize: o.resize,
            load_depth: false,
            ..Default::default()
        };
        let ds = dataset::open_with(&o.dataset, &load, &cfg.dataset)?;
        let k = ds.intrinsics();
        let ek = {
            let w = ((k.width as f32 * cfg.eval.scale).round() as u32).max(1);
            let h = ((k.height as f32 * cfg.eval.scale).round() as u32).max(1);
            k.resized(w, h)
        };
        let poses: Vec<Pose> = (0..ds.len()).map(|i| ds.pose(i)).collect();
        let (_, mesh, level, _) =
            super::run::final_meshes(&mut backend, &cfg, &ek, &k, &poses, aabb, false)?;
        mesh.write_ply(out)?;
        return Ok((mesh.faces.len(), level));
    }
    let level = level.unwrap_or_else(|| cfg.surface_level(beta));
    let mesh = map_mesh(
        &mut backend,
        aabb,
        resolution.unwrap_or(cfg.eval.mesh_resolution),
        level,
    )?;
    mesh.write_ply(out)?;
    Ok((mesh.faces.len(), level))
}
