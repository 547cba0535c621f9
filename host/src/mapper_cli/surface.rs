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
    level: crate::query::Level<'_>,
) -> anyhow::Result<crate::mesh::Mesh> {
    crate::query::region_mesh_at(backend, aabb, resolution, level)
}

/// Rendered surface points a cube needs for a level of its own in [`local_surface_level`].
pub const LOCAL_LEVEL_POINTS: usize = 200;

/// The renderer's surface level place by place ([`crate::query::LocalLevel`]) from the
/// views' rendered surface points (`surface`, one per 1 cm voxel): cubes of side `cell`, each
/// at most `spread` from the whole map's level `global`.
pub fn local_surface_level<B: MapBackend>(
    backend: &mut B,
    surface: &SeenSurface,
    cell: f32,
    global: f32,
    spread: f32,
) -> anyhow::Result<crate::query::LocalLevel> {
    let pts: Vec<[f32; 3]> = surface.points().collect();
    let mut sdf = vec![0.0f32; pts.len()];
    backend.query_sdf(&pts, &mut sdf)?;
    Ok(crate::query::LocalLevel::new(
        &pts,
        &sdf,
        cell,
        global,
        spread,
        LOCAL_LEVEL_POINTS,
    ))
}

/// How many coarse cells around a seen face [`refined_mesh`] extracts again (measured in
/// ARCHITECTURE.md: 2 keeps what extracting the whole region finely finds).
pub const REFINE_REACH: usize = 2;

/// The spacing [`refined_mesh`] extracts `seen` (a mesh on a grid of `resolution`) at:
/// `resolution / refine`, or coarser so that the finer mesh has about `max_faces` (its faces
/// grow as the squared ratio of the spacings); `None` when that is not finer than
/// `resolution` or `seen` is empty.
pub fn refined_spacing(
    seen: &crate::mesh::Mesh,
    resolution: f32,
    refine: u32,
    max_faces: usize,
) -> Option<f32> {
    if refine <= 1 || seen.faces.is_empty() {
        return None;
    }
    let by_faces = resolution as f64 * (seen.faces.len() as f64 / max_faces.max(1) as f64).sqrt();
    let s = (resolution as f64 / refine as f64).max(by_faces) as f32;
    (s < 0.99 * resolution).then_some(s)
}

/// The surface of `field` at `level` extracted again on a grid of `spacing` over `region`,
/// only in the cells of the `resolution` grid over `region` (origin `region.min`) around the
/// vertices of `seen` (a mesh extracted on that grid): each vertex's cell and those up to
/// [`REFINE_REACH`] cells away along each axis, so a level set that moves, or a thin part the
/// coarse grid missed, stays inside. Every other grid point is never queried and its cubes
/// give no faces.
pub fn refined_mesh<F: crate::query::FieldSource>(
    field: &mut F,
    region: Aabb,
    resolution: f32,
    seen: &crate::mesh::Mesh,
    spacing: f32,
    level: crate::query::Level<'_>,
) -> anyhow::Result<crate::mesh::Mesh> {
    let dims = crate::mesh::extraction_dims(&region, resolution).map(|n| n - 1);
    let o = region.min;
    let cell = |p: [f32; 3]| -> [usize; 3] {
        [0, 1, 2].map(|a| {
            let c = ((p[a] - o[a]) / resolution).floor();
            c.clamp(0.0, (dims[a] - 1) as f32) as usize
        })
    };
    let index = |c: [usize; 3]| c[0] + dims[0] * (c[1] + dims[1] * c[2]);
    let mut active = vec![false; dims[0] * dims[1] * dims[2]];
    // The active cells' index box: the finer grid is walked only over it, with a finer point
    // to spare on each side (every point outside it lies in an inactive cell). A culled or
    // extracted mesh has no unreferenced vertices, so every vertex is a seen face's.
    let (mut cmin, mut cmax) = ([usize::MAX; 3], [0usize; 3]);
    for v in &seen.vertices {
        let c = cell(*v);
        let lo = c.map(|x| x.saturating_sub(REFINE_REACH));
        let hi = [0, 1, 2].map(|a| (c[a] + REFINE_REACH).min(dims[a] - 1));
        for z in lo[2]..=hi[2] {
            for y in lo[1]..=hi[1] {
                for x in lo[0]..=hi[0] {
                    active[index([x, y, z])] = true;
                }
            }
        }
        for a in 0..3 {
            cmin[a] = cmin[a].min(lo[a]);
            cmax[a] = cmax[a].max(hi[a]);
        }
    }
    if cmin[0] == usize::MAX {
        return Ok(crate::mesh::Mesh::default());
    }
    let ratio = resolution as f64 / spacing as f64;
    let lo = cmin.map(|c| ((c as f64 * ratio).floor() as usize).saturating_sub(1));
    let hi = cmax.map(|c| ((c + 1) as f64 * ratio).ceil() as usize + 2);
    crate::query::region_mesh_within(
        field,
        region,
        spacing,
        level,
        (lo, hi),
        Some(|p: [f32; 3]| active[index(cell(p))]),
    )
}

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

/// The surface points the views rendered (each pixel's depth back-projected, at most `max_z`
/// from its camera along the optical axis; [`crate::eval::depth_point_cloud`] at 1 cm, as
/// views overlap), in cubic buckets of side `radius` so that [`SeenSurface::near`] looks at
/// 27 buckets.
pub struct SeenSurface {
    radius: f32,
    buckets: std::collections::HashMap<[i32; 3], Vec<[f32; 3]>>,
}

impl SeenSurface {
    pub fn new(
        views: &[(Intrinsics, Pose, Vec<f32>)],
        radius: f32,
        max_z: f32,
    ) -> anyhow::Result<Self> {
        let radius = radius.max(1e-3);
        let within = |d: &[f32]| -> Vec<f32> {
            d.iter()
                .map(|&z| if z <= max_z { z } else { 0.0 })
                .collect()
        };
        let cloud = crate::eval::depth_point_cloud(
            views.iter().map(|(k, p, d)| (within(d), *k, *p)),
            0.01,
        )?;
        let mut buckets: std::collections::HashMap<[i32; 3], Vec<[f32; 3]>> =
            std::collections::HashMap::new();
        for p in cloud {
            buckets
                .entry(p.map(|x| (x / radius).floor() as i32))
                .or_default()
                .push(p);
        }
        Ok(Self { radius, buckets })
    }

    /// The rendered surface points (in no particular order).
    pub fn points(&self) -> impl Iterator<Item = [f32; 3]> + '_ {
        self.buckets.values().flatten().copied()
    }

    /// Whether a rendered surface point lies within the radius of `p`.
    pub fn near(&self, p: [f32; 3]) -> bool {
        let r2 = self.radius * self.radius;
        let key = p.map(|x| (x / self.radius).floor() as i32);
        (-1..=1).any(|dx| {
            (-1..=1).any(|dy| {
                (-1..=1).any(|dz| {
                    self.buckets
                        .get(&[key[0] + dx, key[1] + dy, key[2] + dz])
                        .is_some_and(|b| {
                            b.iter().any(|q| {
                                let d = [q[0] - p[0], q[1] - p[1], q[2] - p[2]];
                                d[0] * d[0] + d[1] * d[1] + d[2] * d[2] <= r2
                            })
                        })
                })
            })
        })
    }

    /// `mesh` cut to the faces with a vertex near the rendered surface (unreferenced vertices
    /// removed).
    pub fn cull(&self, mesh: &crate::mesh::Mesh) -> crate::mesh::Mesh {
        use rayon::prelude::*;
        let seen: Vec<bool> = mesh.vertices.par_iter().map(|&p| self.near(p)).collect();
        mesh.filter_faces(|f| mesh.faces[f].iter().any(|&i| seen[i as usize]))
    }
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
            cfg.eval.mesh_refine = 1;
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
        let (_, mesh, level, _, _) =
            super::run::final_meshes(&mut backend, &cfg, &ek, &k, &poses, aabb, false)?;
        mesh.write_ply(out)?;
        return Ok((mesh.faces.len(), level));
    }
    let level = level.unwrap_or_else(|| cfg.surface_level(beta));
    let mesh = map_mesh(
        &mut backend,
        aabb,
        resolution.unwrap_or(cfg.eval.mesh_resolution),
        crate::query::Level::Global(level),
    )?;
    mesh.write_ply(out)?;
    Ok((mesh.faces.len(), level))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::query::{region_mesh, FnField};

    /// A floor 0.5 m below a camera looking level (identity pose, y down), seen at grazing
    /// angles 2-5 m ahead; the view rendered it 3 cm higher than the mesh's level set lies.
    /// Along the rays that is 12-30 cm, beyond an 8 cm margin in depth everywhere, but in
    /// space the mesh is 3-6 cm from the rendered points: [`SeenSurface`] keeps the whole
    /// floor, drops a second floor 0.5 m below it (hidden) and everything outside the
    /// frustum or beyond `max_z`.
    #[test]
    fn seen_surface_keeps_grazing_surfaces_near_the_rendered_points() {
        let k = Intrinsics {
            width: 400,
            height: 300,
            fx: 500.0,
            fy: 500.0,
            cx: 199.5,
            cy: 149.5,
        };
        let depth: Vec<f32> = (0..k.width * k.height)
            .map(|i| {
                let b = ((i / k.width) as f32 - k.cy) / k.fy;
                if b > 0.0 && 0.47 / b < 50.0 {
                    0.47 / b
                } else {
                    0.0
                }
            })
            .collect();
        let views = vec![(k, Pose::IDENTITY, depth)];
        // quads of 5 cm over x in [x0, x0 + 1], z in [2, 5], at height y
        let mut mesh = crate::mesh::Mesh::default();
        let mut floor = |x0: f32, y: f32| {
            let first = mesh.vertices.len() as u32;
            let (nx, nz) = (21u32, 61u32);
            for j in 0..nz {
                for i in 0..nx {
                    mesh.vertices
                        .push([x0 + 0.05 * i as f32, y, 2.0 + 0.05 * j as f32]);
                }
            }
            for j in 0..nz - 1 {
                for i in 0..nx - 1 {
                    let a = first + j * nx + i;
                    mesh.faces.push([a, a + 1, a + nx]);
                    mesh.faces.push([a + 1, a + nx + 1, a + nx]);
                }
            }
            2 * (nx - 1) as usize * (nz - 1) as usize
        };
        let seen_floor = floor(-0.5, 0.5);
        floor(-0.5, 1.0); // hidden below the seen one
        floor(20.0, 0.5); // outside the frustum
        let kept = SeenSurface::new(&views, 0.08, f32::INFINITY)
            .unwrap()
            .cull(&mesh);
        assert_eq!(kept.faces.len(), seen_floor);
        assert!(kept.vertices.iter().all(|v| v[1] == 0.5 && v[0] < 1.0));
        // a margin in depth keeps none of it
        let by_depth = crate::eval::cull_mesh_within(
            &mesh,
            views.iter().map(|(k, p, d)| (*k, *p, Some(d.as_slice()))),
            Some(0.08),
            f32::INFINITY,
        );
        assert!(by_depth.faces.is_empty());
        // what a view has beyond max_z is not counted as seen
        let near = SeenSurface::new(&views, 0.08, 3.0).unwrap().cull(&mesh);
        assert!(near.vertices.iter().all(|v| v[2] <= 3.15 && v[1] == 0.5));
        assert!(!near.faces.is_empty());
    }

    #[test]
    fn refined_spacing_is_the_finer_grid_within_the_face_budget() {
        let mesh = |faces: usize| crate::mesh::Mesh {
            vertices: vec![[0.0; 3]; 3],
            faces: vec![[0, 1, 2]; faces],
            colors: None,
        };
        // 4 cm / 4 = 1 cm while 1000 faces * 16 stay under the budget
        assert_eq!(refined_spacing(&mesh(1000), 0.04, 4, 2_000_000), Some(0.01));
        // 355 020 seen faces * (4 / s)^2 = 2 M: s = 4 cm * sqrt(0.17751) = 1.6853 cm
        let s = refined_spacing(&mesh(355_020), 0.04, 4, 2_000_000).unwrap();
        assert!((s - 0.016_853).abs() < 1e-6, "{s}");
        // at the budget already, refining off, nothing seen: the coarse grid
        assert_eq!(refined_spacing(&mesh(2_000_000), 0.04, 4, 2_000_000), None);
        assert_eq!(refined_spacing(&mesh(1000), 0.04, 1, 2_000_000), None);
        assert_eq!(refined_spacing(&mesh(0), 0.04, 4, 2_000_000), None);
    }

    /// A sphere of radius 0.5 extracted at 10 cm, its upper half kept as "seen", extracted again
    /// at 2.5 cm: the finer faces lie nearer the sphere, cover the seen half, reach at most
    /// [`REFINE_REACH`] + 1 coarse cells below it, and only grid points near it were queried.
    #[test]
    fn refined_mesh_is_finer_only_around_the_seen_faces() {
        let region = Aabb::new([-1.0; 3], [1.0; 3]);
        let sphere = |p: &[[f32; 3]]| -> Vec<f32> {
            p.iter()
                .map(|q| (q[0] * q[0] + q[1] * q[1] + q[2] * q[2]).sqrt() - 0.5)
                .collect()
        };
        let coarse = region_mesh(&mut FnField(sphere), region, 0.1, 0.0).unwrap();
        let seen = coarse.filter_faces(|f| {
            coarse.faces[f]
                .iter()
                .all(|&v| coarse.vertices[v as usize][2] > 0.0)
        });
        assert!(!seen.faces.is_empty());
        let queried = std::cell::Cell::new(0usize);
        let fine = refined_mesh(
            &mut FnField(|p: &[[f32; 3]]| {
                queried.set(queried.get() + p.len());
                sphere(p)
            }),
            region,
            0.1,
            &seen,
            0.025,
            crate::query::Level::Global(0.0),
        )
        .unwrap();
        let radius_err = |m: &crate::mesh::Mesh| {
            m.vertices
                .iter()
                .map(|v| ((v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt() - 0.5).abs())
                .fold(0.0f32, f32::max)
        };
        assert!(radius_err(&fine) < radius_err(&seen) / 2.0);
        assert!(radius_err(&fine) < 0.005, "{}", radius_err(&fine));
        for v in &seen.vertices {
            let near = fine
                .vertices
                .iter()
                .any(|w| (0..3).map(|a| (v[a] - w[a]).powi(2)).sum::<f32>() < 0.05f32.powi(2));
            assert!(near, "no finer surface near the seen vertex {v:?}");
        }
        let lowest = fine.vertices.iter().map(|v| v[2]).fold(f32::MAX, f32::min);
        let seen_lowest = seen.vertices.iter().map(|v| v[2]).fold(f32::MAX, f32::min);
        assert!(
            lowest >= seen_lowest - 0.1 * (REFINE_REACH + 1) as f32,
            "{lowest}"
        );
        assert!(
            lowest < seen_lowest,
            "the reach extends below the seen faces"
        );
        let full = 81usize.pow(3);
        assert!(queried.get() < full / 2, "{} of {full}", queried.get());
    }
}
