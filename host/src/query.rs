//! What a robot's planner asks of a map, on either backend: metric signed distance to the
//! nearest surface and its gradient at a batch of points, occupancy of an axis-aligned slice,
//! colour at points, a render from any pose, and the mesh of a region.
//!
//! # Metric distances
//!
//! The field's raw value is not a distance: the renderer draws its surfaces at a level that
//! depends on beta and the sample spacing (measured from -0.45 m to +0.14 m between scenes),
//! and away from the surfaces the fitted value saturates (the geometric initialisation's target
//! is cut at `-geo_init_solid`) or drifts wherever no ray constrains it. A [`MapQuery`]
//! therefore derives distances the way nvblox derives its ESDF from a TSDF: from the surface
//! itself. It extracts the surface at the renderer's level (marching cubes over a region, the
//! mesh `himap map` writes) and answers each query with the exact Euclidean distance to the
//! nearest triangle, found through a uniform grid of buckets. The field supplies only the
//! sign (`raw - level < 0`: inside an object), so the distance is zero on the surface the
//! renderer shows, grows at one metre per metre, and is signed: positive in free space,
//! negative inside. Its gradient is the unit vector from the nearest surface point (the exact
//! gradient of a Euclidean distance wherever it is differentiable), or that face's normal on
//! the surface itself. Beyond [`QueryOptions::max_distance`] a query reports the clamped
//! distance, a zero gradient and `within_range: false`, like an ESDF's truncation.
//!
//! Every function takes the backend by `&mut` per call, so a [`MapQuery`] can live beside a
//! running [`himap_core::mapper::Mapper`] (`mapper.backend_mut()` between pushed frames). The
//! SDF and colour queries give the same bits on the CPU and Vulkan backends (conformance
//! tests), and the surface extraction and distance search are deterministic host code, so a
//! query answers the same on both.

use std::path::Path;

use anyhow::Context;
use himap_core::camera::{Intrinsics, Pose};
use himap_core::Aabb;

use crate::mapper_cli::render_view;
use crate::mesh::Mesh;
use crate::select::MapBackend;

/// Settings of a [`MapQuery`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct QueryOptions {
    /// Spacing of the marching-cubes grid the surface is extracted on (m). The distance is
    /// exact to that surface; the surface itself is within about half this of the field's.
    pub resolution: f32,
    /// The raw SDF level of the rendered surface ([`surface_level`] estimates it from views;
    /// `Config::surface_level` gives the preset's value for a trained beta).
    pub level: f32,
    /// Distances are searched up to this far (m); farther points report it, clamped.
    pub max_distance: f32,
}

impl Default for QueryOptions {
    /// 5 cm grid, level 0, 2 m range.
    fn default() -> Self {
        Self {
            resolution: 0.05,
            level: 0.0,
            max_distance: 2.0,
        }
    }
}

/// One answer of [`MapQuery::distance`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct DistanceSample {
    /// Signed distance to the nearest surface (m): positive in free space, negative inside,
    /// zero on the rendered surface; `+-max_distance` when `within_range` is false.
    pub distance: f32,
    /// Unit gradient of the distance (points away from the nearest surface on the free side);
    /// zero when `within_range` is false.
    pub gradient: [f32; 3],
    /// Whether a surface was found within `max_distance`.
    pub within_range: bool,
}

/// Exact Euclidean distance to a triangle mesh, through a uniform grid of buckets.
#[derive(Clone, Debug)]
pub struct SurfaceDistance {
    tris: Vec<[[f64; 3]; 3]>,
    normals: Vec<[f64; 3]>,
    origin: [f64; 3],
    cell: f64,
    dims: [usize; 3],
    /// Bucket `c` holds `items[starts[c]..starts[c + 1]]`.
    starts: Vec<u32>,
    items: Vec<u32>,
    max_distance: f64,
}

impl SurfaceDistance {
    /// Indexes `mesh` for distance queries up to `max_distance` (m). Degenerate faces (zero
    /// area) are kept: their distance is that to a segment or a point.
    pub fn new(mesh: &Mesh, max_distance: f32) -> Self {
        let tris: Vec<[[f64; 3]; 3]> = (0..mesh.faces.len())
            .map(|f| mesh.triangle(f).map(|p| p.map(f64::from)))
            .collect();
        let normals = tris
            .iter()
            .map(|[a, b, c]| {
                let n = cross(sub(*b, *a), sub(*c, *a));
                let l = norm(n);
                if l > 0.0 {
                    n.map(|x| x / l)
                } else {
                    [0.0; 3]
                }
            })
            .collect();
        let mut lo = [f64::INFINITY; 3];
        let mut hi = [f64::NEG_INFINITY; 3];
        let mut edge = 0.0f64;
        for t in &tris {
            for p in t {
                for a in 0..3 {
                    lo[a] = lo[a].min(p[a]);
                    hi[a] = hi[a].max(p[a]);
                }
            }
            edge = edge.max(norm(sub(t[1], t[0])));
        }
        if tris.is_empty() {
            lo = [0.0; 3];
            hi = [0.0; 3];
        }
        // Buckets of a few faces each: about 2 mesh edges wide, at most 2^21 buckets.
        let ext = [0, 1, 2].map(|a| (hi[a] - lo[a]).max(1e-6));
        let mut cell = (2.0 * edge).max(1e-3);
        while ext.iter().map(|e| (e / cell).ceil() + 1.0).product::<f64>() > (1 << 21) as f64 {
            cell *= 1.25;
        }
        let dims = ext.map(|e| ((e / cell).ceil() as usize + 1).max(1));
        let n_cells = dims[0] * dims[1] * dims[2];
        let index = |c: [usize; 3]| (c[2] * dims[1] + c[1]) * dims[0] + c[0];
        let cell_of = |p: [f64; 3]| {
            [0, 1, 2].map(|a| (((p[a] - lo[a]) / cell).floor().max(0.0) as usize).min(dims[a] - 1))
        };
        let range = |t: &[[f64; 3]; 3]| {
            let mut mn = t[0];
            let mut mx = t[0];
            for p in &t[1..] {
                for a in 0..3 {
                    mn[a] = mn[a].min(p[a]);
                    mx[a] = mx[a].max(p[a]);
                }
            }
            (cell_of(mn), cell_of(mx))
        };
        let mut counts = vec![0u32; n_cells + 1];
        for t in &tris {
            let (a, b) = range(t);
            for z in a[2]..=b[2] {
                for y in a[1]..=b[1] {
                    for x in a[0]..=b[0] {
                        counts[index([x, y, z]) + 1] += 1;
                    }
                }
            }
        }
        for c in 0..n_cells {
            counts[c + 1] += counts[c];
        }
        let starts = counts.clone();
        let mut fill = counts;
        let mut items = vec![0u32; *starts.last().unwrap_or(&0) as usize];
        for (f, t) in tris.iter().enumerate() {
            let (a, b) = range(t);
            for z in a[2]..=b[2] {
                for y in a[1]..=b[1] {
                    for x in a[0]..=b[0] {
                        let c = index([x, y, z]);
                        items[fill[c] as usize] = f as u32;
                        fill[c] += 1;
                    }
                }
            }
        }
        Self {
            tris,
            normals,
            origin: lo,
            cell,
            dims,
            starts,
            items,
            max_distance: f64::from(max_distance),
        }
    }

    /// Number of indexed faces.
    pub fn faces(&self) -> usize {
        self.tris.len()
    }

    /// The nearest surface point to `p` within `max_distance`: `(point, distance, face)`.
    pub fn nearest(&self, p: [f32; 3]) -> Option<([f64; 3], f64, usize)> {
        if self.tris.is_empty() {
            return None;
        }
        let p = p.map(f64::from);
        let home = [0, 1, 2].map(|a| {
            let c = ((p[a] - self.origin[a]) / self.cell).floor();
            c.clamp(0.0, (self.dims[a] - 1) as f64) as i64
        });
        // Distance from p to the home bucket (non-zero when p lies outside the grid).
        let outside = norm([0, 1, 2].map(|a| {
            let lo = self.origin[a] + home[a] as f64 * self.cell;
            (lo - p[a]).max(p[a] - (lo + self.cell)).max(0.0)
        }));
        let mut best: Option<([f64; 3], f64, usize)> = None;
        let max_ring = self.dims.iter().copied().max().unwrap_or(1) as i64;
        for r in 0..=max_ring {
            // Every bucket of ring r is at least (r - 1) cells (plus `outside`) away.
            let ring_min = outside.max((r - 1).max(0) as f64 * self.cell);
            let bound = best.map_or(self.max_distance, |b| b.1.min(self.max_distance));
            if ring_min > bound {
                break;
            }
            self.for_ring(home, r, |c| {
                let (s, e) = (self.starts[c] as usize, self.starts[c + 1] as usize);
                for &f in &self.items[s..e] {
                    let q = closest_on_triangle(p, &self.tris[f as usize]);
                    let d = norm(sub(p, q));
                    if best.is_none_or(|b| d < b.1 || (d == b.1 && (f as usize) < b.2)) {
                        best = Some((q, d, f as usize));
                    }
                }
            });
        }
        best.filter(|b| b.1 <= self.max_distance)
    }

    /// Calls `f` with the index of every bucket at Chebyshev distance `r` from `home`.
    fn for_ring(&self, home: [i64; 3], r: i64, mut f: impl FnMut(usize)) {
        let d = self.dims.map(|x| x as i64);
        let lo = [0, 1, 2].map(|a| (home[a] - r).max(0));
        let hi = [0, 1, 2].map(|a| (home[a] + r).min(d[a] - 1));
        for z in lo[2]..=hi[2] {
            for y in lo[1]..=hi[1] {
                let on_yz = (z - home[2]).abs() == r || (y - home[1]).abs() == r;
                let mut x = lo[0];
                while x <= hi[0] {
                    if on_yz || (x - home[0]).abs() == r {
                        f(((z * d[1] + y) * d[0] + x) as usize);
                        x += 1;
                    } else {
                        // Inside the ring on this row: only its two x ends belong to it.
                        x = (home[0] + r).max(x + 1);
                    }
                }
            }
        }
    }

    /// Signed distances for `points`, whose field values relative to the surface level are
    /// `rel` (negative: inside). See the module docs.
    pub fn signed(&self, points: &[[f32; 3]], rel: &[f32]) -> Vec<DistanceSample> {
        assert_eq!(points.len(), rel.len(), "one field value per point");
        use rayon::prelude::*;
        points
            .par_iter()
            .zip(rel.par_iter())
            .map(|(&p, &s)| {
                let sign = if s < 0.0 { -1.0 } else { 1.0 };
                match self.nearest(p) {
                    None => DistanceSample {
                        distance: (sign * self.max_distance) as f32,
                        gradient: [0.0; 3],
                        within_range: false,
                    },
                    Some((q, d, f)) => {
                        let pd = p.map(f64::from);
                        let g = if d > 1e-9 {
                            sub(pd, q).map(|x| sign * x / d)
                        } else {
                            self.normals[f]
                        };
                        DistanceSample {
                            distance: (sign * d) as f32,
                            gradient: g.map(|x| x as f32),
                            within_range: true,
                        }
                    }
                }
            })
            .collect()
    }
}

/// The closest point of triangle `t` to `p` (Voronoi regions of vertices, edges, face).
fn closest_on_triangle(p: [f64; 3], t: &[[f64; 3]; 3]) -> [f64; 3] {
    let [a, b, c] = *t;
    let ab = sub(b, a);
    let ac = sub(c, a);
    let ap = sub(p, a);
    let d1 = dot(ab, ap);
    let d2 = dot(ac, ap);
    if d1 <= 0.0 && d2 <= 0.0 {
        return a;
    }
    let bp = sub(p, b);
    let d3 = dot(ab, bp);
    let d4 = dot(ac, bp);
    if d3 >= 0.0 && d4 <= d3 {
        return b;
    }
    let vc = d1 * d4 - d3 * d2;
    if vc <= 0.0 && d1 >= 0.0 && d3 <= 0.0 {
        let v = d1 / (d1 - d3);
        return add(a, scale(ab, v));
    }
    let cp = sub(p, c);
    let d5 = dot(ab, cp);
    let d6 = dot(ac, cp);
    if d6 >= 0.0 && d5 <= d6 {
        return c;
    }
    let vb = d5 * d2 - d1 * d6;
    if vb <= 0.0 && d2 >= 0.0 && d6 <= 0.0 {
        let w = d2 / (d2 - d6);
        return add(a, scale(ac, w));
    }
    let va = d3 * d6 - d5 * d4;
    if va <= 0.0 && (d4 - d3) >= 0.0 && (d5 - d6) >= 0.0 {
        let w = (d4 - d3) / ((d4 - d3) + (d5 - d6));
        return add(b, scale(sub(c, b), w));
    }
    let denom = va + vb + vc;
    if denom.abs() < 1e-300 {
        // Degenerate (collinear) face: the nearest of its three edges.
        let seg = |u: [f64; 3], v: [f64; 3]| {
            let e = sub(v, u);
            let l = dot(e, e);
            let s = if l > 0.0 {
                (dot(sub(p, u), e) / l).clamp(0.0, 1.0)
            } else {
                0.0
            };
            add(u, scale(e, s))
        };
        let cands = [seg(a, b), seg(b, c), seg(c, a)];
        return cands
            .into_iter()
            .min_by(|x, y| norm(sub(p, *x)).total_cmp(&norm(sub(p, *y))))
            .unwrap_or(a);
    }
    let v = vb / denom;
    let w = vc / denom;
    add(a, add(scale(ab, v), scale(ac, w)))
}

fn add(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] + b[0], a[1] + b[1], a[2] + b[2]]
}
fn sub(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}
fn scale(a: [f64; 3], s: f64) -> [f64; 3] {
    a.map(|x| x * s)
}
fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}
fn cross(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}
fn norm(a: [f64; 3]) -> f64 {
    dot(a, a).sqrt()
}

/// The source of raw field values a [`MapQuery`] reads: every [`MapBackend`] (CPU or Vulkan),
/// or any batched function (an analytic field in tests).
pub trait FieldSource {
    /// Raw SDF values at world points.
    fn field_sdf(&mut self, points: &[[f32; 3]], out: &mut [f32]) -> anyhow::Result<()>;
    /// RGB in [0, 1] at world points.
    fn field_color(&mut self, points: &[[f32; 3]], out: &mut [[f32; 3]]) -> anyhow::Result<()>;
}

impl<B: MapBackend> FieldSource for B {
    fn field_sdf(&mut self, points: &[[f32; 3]], out: &mut [f32]) -> anyhow::Result<()> {
        self.query_sdf(points, out)
    }
    fn field_color(&mut self, points: &[[f32; 3]], out: &mut [[f32; 3]]) -> anyhow::Result<()> {
        self.query_color(points, out)
    }
}

/// A field given by a batched function of points (colour: mid grey).
pub struct FnField<F>(pub F);

impl<F: FnMut(&[[f32; 3]]) -> Vec<f32>> FieldSource for FnField<F> {
    fn field_sdf(&mut self, points: &[[f32; 3]], out: &mut [f32]) -> anyhow::Result<()> {
        let v = (self.0)(points);
        anyhow::ensure!(v.len() == out.len(), "the field returned the wrong count");
        out.copy_from_slice(&v);
        Ok(())
    }
    fn field_color(&mut self, _points: &[[f32; 3]], out: &mut [[f32; 3]]) -> anyhow::Result<()> {
        out.fill([0.5; 3]);
        Ok(())
    }
}

/// Cell states of an [`OccupancySlice`].
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Occupancy {
    /// Outside the query's region: the map was not extracted there.
    Unknown,
    /// Free space (signed distance > 0).
    Free,
    /// Inside an object (signed distance <= 0).
    Occupied,
}

/// An axis-aligned slice through the map: `width x height` cells (row-major, `u` fastest)
/// of spacing `resolution` starting at `origin`, in the plane `axis = offset`. The plane's
/// `u` and `v` axes are the other two world axes in increasing order (x slice: u = y, v = z).
#[derive(Clone, Debug, PartialEq)]
pub struct OccupancySlice {
    pub axis: usize,
    pub offset: f32,
    /// World position of cell (0, 0)'s centre.
    pub origin: [f32; 3],
    pub resolution: f32,
    pub width: usize,
    pub height: usize,
    pub state: Vec<Occupancy>,
    /// Signed metric distance per cell (m), as [`MapQuery::distance`].
    pub distance: Vec<f32>,
}

impl OccupancySlice {
    /// World position of cell `(u, v)`'s centre.
    pub fn cell_center(&self, u: usize, v: usize) -> [f32; 3] {
        let (ua, va) = plane_axes(self.axis);
        let mut p = self.origin;
        p[ua] += u as f32 * self.resolution;
        p[va] += v as f32 * self.resolution;
        p
    }

    /// Writes the slice as a PNG (occupied black, free white, unknown grey; v up).
    pub fn write_png(&self, path: &Path) -> anyhow::Result<()> {
        let mut img = image::GrayImage::new(self.width as u32, self.height as u32);
        for v in 0..self.height {
            for u in 0..self.width {
                let g = match self.state[v * self.width + u] {
                    Occupancy::Unknown => 128,
                    Occupancy::Free => 255,
                    Occupancy::Occupied => 0,
                };
                img.put_pixel(u as u32, (self.height - 1 - v) as u32, image::Luma([g]));
            }
        }
        img.save(path)
            .with_context(|| format!("writing {}", path.display()))
    }
}

fn plane_axes(axis: usize) -> (usize, usize) {
    match axis {
        0 => (1, 2),
        1 => (0, 2),
        _ => (0, 1),
    }
}

/// Metric queries over one extraction of a map's surface (see the module docs). Build it
/// again after the map has changed.
#[derive(Clone, Debug)]
pub struct MapQuery {
    region: Aabb,
    opts: QueryOptions,
    mesh: Mesh,
    surface: SurfaceDistance,
}

impl MapQuery {
    /// Extracts the surface of `field` at `opts.level` over `region` (coloured) and indexes it.
    pub fn build<F: FieldSource>(
        field: &mut F,
        region: Aabb,
        opts: QueryOptions,
    ) -> anyhow::Result<Self> {
        anyhow::ensure!(region.is_valid(), "query region {region:?} is not a box");
        anyhow::ensure!(
            opts.resolution > 0.0 && opts.resolution.is_finite(),
            "query resolution must be positive (got {})",
            opts.resolution
        );
        anyhow::ensure!(
            opts.max_distance > 0.0 && opts.max_distance.is_finite(),
            "query max_distance must be positive (got {})",
            opts.max_distance
        );
        let mesh = region_mesh(field, region, opts.resolution, opts.level)?;
        let surface = SurfaceDistance::new(&mesh, opts.max_distance);
        Ok(Self {
            region,
            opts,
            mesh,
            surface,
        })
    }

    /// The region the surface was extracted over.
    pub fn region(&self) -> Aabb {
        self.region
    }

    /// The settings it was built with.
    pub fn options(&self) -> QueryOptions {
        self.opts
    }

    /// The extracted surface (vertex colours from the map).
    pub fn mesh(&self) -> &Mesh {
        &self.mesh
    }

    /// Signed metric distance and its gradient at each point (see the module docs). `field`
    /// must be the map the query was built from (it gives the sign).
    pub fn distance<F: FieldSource>(
        &self,
        field: &mut F,
        points: &[[f32; 3]],
    ) -> anyhow::Result<Vec<DistanceSample>> {
        let mut rel = vec![0.0f32; points.len()];
        field.field_sdf(points, &mut rel)?;
        for r in &mut rel {
            *r -= self.opts.level;
        }
        Ok(self.surface.signed(points, &rel))
    }

    /// Occupancy and distance on the plane `axis = offset` (axis 0, 1, 2 = x, y, z) over the
    /// query's region, cells of `resolution` metres. Cells outside the region are
    /// [`Occupancy::Unknown`] (with the distance still computed).
    pub fn occupancy_slice<F: FieldSource>(
        &self,
        field: &mut F,
        axis: usize,
        offset: f32,
        resolution: f32,
    ) -> anyhow::Result<OccupancySlice> {
        anyhow::ensure!(
            axis < 3,
            "slice axis must be 0, 1 or 2 (x, y, z), got {axis}"
        );
        anyhow::ensure!(
            resolution > 0.0 && resolution.is_finite(),
            "slice resolution must be positive"
        );
        let (ua, va) = plane_axes(axis);
        let r = self.region;
        let width = ((r.max[ua] - r.min[ua]) / resolution).ceil().max(1.0) as usize;
        let height = ((r.max[va] - r.min[va]) / resolution).ceil().max(1.0) as usize;
        let mut origin = [0.0; 3];
        origin[axis] = offset;
        origin[ua] = r.min[ua] + 0.5 * resolution;
        origin[va] = r.min[va] + 0.5 * resolution;
        let mut slice = OccupancySlice {
            axis,
            offset,
            origin,
            resolution,
            width,
            height,
            state: Vec::new(),
            distance: Vec::new(),
        };
        let pts: Vec<[f32; 3]> = (0..height)
            .flat_map(|v| (0..width).map(move |u| (u, v)))
            .map(|(u, v)| slice.cell_center(u, v))
            .collect();
        let d = self.distance(field, &pts)?;
        let inside = offset >= r.min[axis] && offset <= r.max[axis];
        slice.state = pts
            .iter()
            .zip(&d)
            .map(|(p, s)| {
                let in_region = inside && p[ua] <= r.max[ua] && p[va] <= r.max[va];
                if !in_region {
                    Occupancy::Unknown
                } else if s.distance <= 0.0 {
                    Occupancy::Occupied
                } else {
                    Occupancy::Free
                }
            })
            .collect();
        slice.distance = d.iter().map(|s| s.distance).collect();
        Ok(slice)
    }
}

/// Colours (RGB in [0, 1]) of the map at world points.
pub fn color_at<F: FieldSource>(
    field: &mut F,
    points: &[[f32; 3]],
) -> anyhow::Result<Vec<[f32; 3]>> {
    let mut out = vec![[0.0; 3]; points.len()];
    field.field_color(points, &mut out)?;
    Ok(out)
}

/// The raw SDF level a surface is extracted at: one for the whole field, or one per place
/// ([`LocalLevel`]).
#[derive(Clone, Copy, Debug)]
pub enum Level<'a> {
    Global(f32),
    Local(&'a LocalLevel),
}

impl Level<'_> {
    /// The level at `p`.
    pub fn at(&self, p: [f32; 3]) -> f32 {
        match self {
            Level::Global(l) => *l,
            Level::Local(l) => l.at(p),
        }
    }
}

/// The weight of the whole map's level beside the trilinear weights of [`LocalLevel`]'s cubes.
pub const LOCAL_LEVEL_GLOBAL_WEIGHT: f32 = 0.01;

/// The renderer's surface level place by place: the median raw SDF at the rendered surface
/// points in each cube of side `cell` holding at least `min_points` of them, limited to
/// `global +- spread`, interpolated between the cubes' centres with trilinear weights over
/// the cubes that have a level (a surface on a cube's face is not pulled halfway to a free
/// cube beside it), plus [`LOCAL_LEVEL_GLOBAL_WEIGHT`] for the global level, so the level
/// returns to `global` smoothly away from the cubes. Where the field's slope near its
/// surfaces differs between rooms, one level for the whole map places some rooms' surfaces
/// centimetres off the rendered ones (ARCHITECTURE.md, issue #11).
#[derive(Clone, Debug)]
pub struct LocalLevel {
    cell: f32,
    global: f32,
    cells: std::collections::HashMap<[i32; 3], f32>,
}

impl LocalLevel {
    /// From `points` and the raw SDF at them (`sdf`, same length).
    pub fn new(
        points: &[[f32; 3]],
        sdf: &[f32],
        cell: f32,
        global: f32,
        spread: f32,
        min_points: usize,
    ) -> Self {
        let mut bins: std::collections::HashMap<[i32; 3], Vec<f32>> = Default::default();
        for (p, &s) in points.iter().zip(sdf) {
            if s.is_finite() {
                bins.entry(p.map(|x| (x / cell).floor() as i32))
                    .or_default()
                    .push(s);
            }
        }
        let cells = bins
            .into_iter()
            .filter(|(_, v)| v.len() >= min_points.max(1))
            .map(|(k, mut v)| {
                v.sort_by(f32::total_cmp);
                (k, v[v.len() / 2].clamp(global - spread, global + spread))
            })
            .collect();
        Self {
            cell,
            global,
            cells,
        }
    }

    /// Cubes with a level of their own.
    pub fn cells(&self) -> usize {
        self.cells.len()
    }

    /// The level at `p`.
    pub fn at(&self, p: [f32; 3]) -> f32 {
        let g = p.map(|x| x / self.cell - 0.5);
        let b = g.map(f32::floor);
        let f = [g[0] - b[0], g[1] - b[1], g[2] - b[2]];
        let (mut sum, mut weight) = (
            LOCAL_LEVEL_GLOBAL_WEIGHT * self.global,
            LOCAL_LEVEL_GLOBAL_WEIGHT,
        );
        for c in 0..8usize {
            let o = [c & 1, (c >> 1) & 1, (c >> 2) & 1];
            let key = [0, 1, 2].map(|a| b[a] as i32 + o[a] as i32);
            if let Some(&l) = self.cells.get(&key) {
                let w: f32 = (0..3)
                    .map(|a| if o[a] == 1 { f[a] } else { 1.0 - f[a] })
                    .product();
                sum += w * l;
                weight += w;
            }
        }
        sum / weight
    }
}

/// The mesh of `field`'s surface at `level` inside `region`, on a grid of `resolution`
/// (marching cubes, vertex colours from the map; normals towards free space).
pub fn region_mesh<F: FieldSource>(
    field: &mut F,
    region: Aabb,
    resolution: f32,
    level: f32,
) -> anyhow::Result<Mesh> {
    region_mesh_at(field, region, resolution, Level::Global(level))
}

/// [`region_mesh`] at a [`Level`] that may vary from place to place.
pub fn region_mesh_at<F: FieldSource>(
    field: &mut F,
    region: Aabb,
    resolution: f32,
    level: Level<'_>,
) -> anyhow::Result<Mesh> {
    let all = crate::mesh::extraction_dims(&region, resolution);
    region_mesh_within(
        field,
        region,
        resolution,
        level,
        ([0; 3], all),
        None::<fn([f32; 3]) -> bool>,
    )
}

/// [`region_mesh`] over the grid vertices `window` (`lo..hi` per axis, see
/// [`crate::mesh::extract_mesh_window`]) where only the grid points `within` accepts are
/// queried: the cubes touching any other point give no faces (they are marked unknown, see
/// [`crate::mesh::extract_mesh`]).
pub fn region_mesh_within<F: FieldSource, W: Fn([f32; 3]) -> bool>(
    field: &mut F,
    region: Aabb,
    resolution: f32,
    level: Level<'_>,
    window: ([usize; 3], [usize; 3]),
    within: Option<W>,
) -> anyhow::Result<Mesh> {
    let field = std::cell::RefCell::new(field);
    let err = std::cell::RefCell::new(None::<anyhow::Error>);
    let mesh = crate::mesh::extract_mesh_window(
        region,
        resolution,
        window.0,
        window.1,
        |p: &[[f32; 3]]| {
            let mut o = vec![f32::NAN; p.len()];
            let query = |p: &[[f32; 3]], o: &mut [f32]| {
                if let Err(e) = field.borrow_mut().field_sdf(p, o) {
                    err.borrow_mut().get_or_insert(e);
                }
                o.iter_mut().zip(p).for_each(|(x, q)| *x -= level.at(*q));
            };
            match &within {
                None => query(p, &mut o),
                Some(w) => {
                    let idx: Vec<usize> = (0..p.len()).filter(|&i| w(p[i])).collect();
                    let q: Vec<[f32; 3]> = idx.iter().map(|&i| p[i]).collect();
                    let mut v = vec![0.0; q.len()];
                    if !q.is_empty() {
                        query(&q, &mut v);
                    }
                    for (&i, x) in idx.iter().zip(v) {
                        o[i] = x;
                    }
                }
            }
            o
        },
        Some(|p: &[[f32; 3]]| {
            let mut o = vec![[0.0; 3]; p.len()];
            if let Err(e) = field.borrow_mut().field_color(p, &mut o) {
                err.borrow_mut().get_or_insert(e);
            }
            o
        }),
    );
    match err.into_inner() {
        Some(e) => Err(e.context("querying the field for the mesh")),
        None => Ok(mesh),
    }
}

/// A rendered view: colour (RGB in [0, 1]), depth along the optical axis normalised by the
/// opacity (0 where the opacity is below 1/2), and opacity, row-major.
#[derive(Clone, Debug, PartialEq)]
pub struct View {
    pub width: u32,
    pub height: u32,
    pub color: Vec<[f32; 3]>,
    pub depth: Vec<f32>,
    pub opacity: Vec<f32>,
}

/// Renders the map from `pose` with intrinsics `k` (bin-centre samples, no jitter).
pub fn render<B: MapBackend>(backend: &mut B, k: &Intrinsics, pose: &Pose) -> anyhow::Result<View>
where
    B::Error: std::error::Error + Send + Sync + 'static,
{
    let r = render_view(backend, k, pose)?;
    Ok(View {
        width: k.width,
        height: k.height,
        color: r.iter().map(|x| x.color).collect(),
        depth: r
            .iter()
            .map(|x| {
                if x.opacity >= 0.5 && x.depth.is_finite() {
                    x.depth / x.opacity
                } else {
                    0.0
                }
            })
            .collect(),
        opacity: r.iter().map(|x| x.opacity).collect(),
    })
}

/// The raw SDF level of the surfaces `backend` renders, estimated from up to 8 of the pushed
/// `poses` rendered at a quarter of `k`'s resolution (see
/// [`crate::mapper_cli::rendered_surface_level`]); `None` before anything renders opaque.
pub fn surface_level<B: MapBackend>(
    backend: &mut B,
    k: &Intrinsics,
    poses: &[Pose],
) -> anyhow::Result<Option<f32>>
where
    B::Error: std::error::Error + Send + Sync + 'static,
{
    let w = (k.width / 4).max(32.min(k.width));
    let h = ((k.height as u64 * w as u64) / k.width.max(1) as u64).max(1) as u32;
    crate::mapper_cli::rendered_surface_level(backend, &k.resized(w, h), poses, poses.len().min(8))
}

#[cfg(test)]
mod tests;
