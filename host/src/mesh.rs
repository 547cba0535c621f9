//! Triangle meshes: the [`Mesh`] type, PLY files ([`ply`]), marching cubes ([`mc`]), mesh
//! extraction from a batched SDF query ([`extract_mesh`]) and area-weighted surface sampling
//! ([`sample_surface`]).
//!
//! Orientation convention: triangles are counter-clockwise seen from outside, so the normal
//! `(b - a) x (c - a)` of face `[a, b, c]` points outwards; for meshes from marching cubes on an
//! SDF that is towards increasing SDF (out of the negative inside), and a closed surface has a
//! positive [`Mesh::signed_volume`].

pub mod mc;
pub mod ply;
pub mod tables;

use std::path::Path;

use himap_core::Aabb;
use rayon::prelude::*;

pub use mc::{marching_cubes, SliceMarcher};

#[cfg(test)]
mod tests;

/// An indexed triangle mesh with optional 8-bit vertex colours.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Mesh {
    /// Vertex positions (metres, world frame).
    pub vertices: Vec<[f32; 3]>,
    /// One RGB colour per vertex, when present.
    pub colors: Option<Vec<[u8; 3]>>,
    /// Triangles as indices into `vertices`, counter-clockwise seen from outside.
    pub faces: Vec<[u32; 3]>,
}

impl Mesh {
    /// Reads a PLY file (ASCII or binary; see [`ply`]).
    pub fn read_ply(path: &Path) -> anyhow::Result<Mesh> {
        ply::read_ply(path)
    }

    /// Writes the mesh as a binary little-endian PLY file (with colours when present).
    pub fn write_ply(&self, path: &Path) -> anyhow::Result<()> {
        ply::write_ply(self, path)
    }

    /// The three corner positions of face `f`.
    #[inline]
    pub fn triangle(&self, f: usize) -> [[f32; 3]; 3] {
        self.faces[f].map(|i| self.vertices[i as usize])
    }

    /// Area of face `f` (computed in f64).
    pub fn face_area(&self, f: usize) -> f64 {
        let [a, b, c] = self.triangle(f).map(|p| p.map(|x| x as f64));
        0.5 * norm(cross(sub(b, a), sub(c, a)))
    }

    /// Total surface area.
    pub fn area(&self) -> f64 {
        (0..self.faces.len()).map(|f| self.face_area(f)).sum()
    }

    /// Signed volume enclosed by the surface (divergence theorem; positive for a closed mesh
    /// with outward normals, meaningless for an open one).
    pub fn signed_volume(&self) -> f64 {
        let mut v = 0.0;
        for f in 0..self.faces.len() {
            let [a, b, c] = self.triangle(f).map(|p| p.map(|x| x as f64));
            v += dot(a, cross(b, c)) / 6.0;
        }
        v
    }

    /// Axis-aligned bounds of the vertices, `None` for a mesh without vertices.
    pub fn bounds(&self) -> Option<Aabb> {
        let first = *self.vertices.first()?;
        let (mut lo, mut hi) = (first, first);
        for v in &self.vertices {
            for k in 0..3 {
                lo[k] = lo[k].min(v[k]);
                hi[k] = hi[k].max(v[k]);
            }
        }
        Some(Aabb::new(lo, hi))
    }

    /// A copy keeping only the faces for which `keep(face index)` is true, with unreferenced
    /// vertices (and their colours) removed and indices renumbered.
    pub fn filter_faces(&self, mut keep: impl FnMut(usize) -> bool) -> Mesh {
        let mut map = vec![u32::MAX; self.vertices.len()];
        let mut out = Mesh {
            colors: self.colors.as_ref().map(|_| Vec::new()),
            ..Default::default()
        };
        for (fi, f) in self.faces.iter().enumerate() {
            if !keep(fi) {
                continue;
            }
            let nf = f.map(|i| {
                let m = &mut map[i as usize];
                if *m == u32::MAX {
                    *m = out.vertices.len() as u32;
                    out.vertices.push(self.vertices[i as usize]);
                    if let (Some(oc), Some(c)) = (out.colors.as_mut(), self.colors.as_ref()) {
                        oc.push(c[i as usize]);
                    }
                }
                *m
            });
            out.faces.push(nf);
        }
        out
    }
}

#[inline]
fn sub(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

#[inline]
fn cross(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

#[inline]
fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

#[inline]
fn norm(a: [f64; 3]) -> f64 {
    dot(a, a).sqrt()
}

/// SplitMix64 finaliser.
#[inline]
fn mix64(mut z: u64) -> u64 {
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// Uniform in [0, 1) with 53 random bits, a pure function of (seed, i, k).
#[inline]
pub(crate) fn unit_f64(seed: u64, i: u64, k: u64) -> f64 {
    let h = mix64(
        mix64(seed ^ 0x2545_F491_4F6C_DD1D).wrapping_add(i.wrapping_mul(0x9E37_79B9_7F4A_7C15))
            ^ k.wrapping_mul(0xD1B5_4A32_D192_ED03),
    );
    (h >> 11) as f64 * (1.0 / (1u64 << 53) as f64)
}

/// `n` random points on the surface of `mesh`, uniformly distributed by area (a face is chosen
/// with probability proportional to its area, then a uniform point inside it), like
/// `trimesh.sample.sample_surface`. Deterministic for a `seed` (point `i` depends only on
/// `seed`, `i` and the mesh, whatever the thread count). Returns an empty vector when the mesh
/// has no area.
pub fn sample_surface(mesh: &Mesh, n: usize, seed: u64) -> Vec<[f32; 3]> {
    let nf = mesh.faces.len();
    let mut cdf = Vec::with_capacity(nf);
    let mut total = 0.0f64;
    for f in 0..nf {
        let a = mesh.face_area(f);
        total += if a.is_finite() { a } else { 0.0 };
        cdf.push(total);
    }
    // (Also catches a NaN total.)
    if total.partial_cmp(&0.0) != Some(std::cmp::Ordering::Greater) {
        return Vec::new();
    }
    (0..n)
        .into_par_iter()
        .map(|i| {
            let i = i as u64;
            let x = unit_f64(seed, i, 0) * total;
            let f = cdf.partition_point(|&c| c <= x).min(nf - 1);
            let [a, b, c] = mesh.triangle(f).map(|p| p.map(|x| x as f64));
            let r1 = unit_f64(seed, i, 1).sqrt();
            let r2 = unit_f64(seed, i, 2);
            let (wa, wb, wc) = (1.0 - r1, r1 * (1.0 - r2), r1 * r2);
            [0, 1, 2].map(|k| (wa * a[k] + wb * b[k] + wc * c[k]) as f32)
        })
        .collect()
}

/// The type to name for "no colour query" in [`extract_mesh`]: `None::<NoColor>`.
pub type NoColor = fn(&[[f32; 3]]) -> Vec<[f32; 3]>;

/// Most points per SDF or colour query in [`extract_mesh`].
pub const EXTRACT_BATCH: usize = 1 << 20;

/// The grid [`extract_mesh`] samples: vertex counts per axis for a box and a resolution
/// (`ceil(extent / resolution) + 1`, at least 2), starting at `aabb.min` with spacing
/// `resolution` (the last vertex may lie up to one `resolution` beyond `aabb.max`).
pub fn extraction_dims(aabb: &Aabb, resolution: f32) -> [usize; 3] {
    let e = aabb.extent();
    [0, 1, 2].map(|k| ((e[k] / resolution - 1e-4).ceil().max(1.0) as usize) + 1)
}

/// Extracts the zero level set of an SDF inside `aabb` by marching cubes on a grid of spacing
/// `resolution` (see [`extraction_dims`]). `sdf` answers batched queries (one value per
/// point; NaN marks an unknown value and removes the cubes touching it); it is called
/// slab by slab along z with at most [`EXTRACT_BATCH`] points (at least one z-slice), so memory
/// stays bounded by two slices plus the mesh. When `color` is given it is queried at the
/// vertices (RGB in [0, 1], batched the same way) and stored as 8-bit vertex colours.
/// Orientation: normals point towards positive SDF (see [`mc`]).
///
/// # Panics
/// If `aabb` is not a valid box, `resolution` is not positive and finite, or a query returns
/// the wrong number of values.
pub fn extract_mesh<S, C>(aabb: Aabb, resolution: f32, sdf: S, color: Option<C>) -> Mesh
where
    S: Fn(&[[f32; 3]]) -> Vec<f32>,
    C: Fn(&[[f32; 3]]) -> Vec<[f32; 3]>,
{
    extract_mesh_batched(aabb, resolution, sdf, color, EXTRACT_BATCH)
}

/// [`extract_mesh`] over the grid vertices `lo..hi` (per axis, clamped to
/// [`extraction_dims`]) of the grid [`extract_mesh`] samples: the same points and vertices bit
/// for bit, and the faces of the cubes inside the window in the same order. Where every point
/// outside the window would be unknown (NaN), the mesh equals [`extract_mesh`]'s.
pub fn extract_mesh_window<S, C>(
    aabb: Aabb,
    resolution: f32,
    lo: [usize; 3],
    hi: [usize; 3],
    sdf: S,
    color: Option<C>,
) -> Mesh
where
    S: Fn(&[[f32; 3]]) -> Vec<f32>,
    C: Fn(&[[f32; 3]]) -> Vec<[f32; 3]>,
{
    extract_window_batched(aabb, resolution, Some((lo, hi)), sdf, color, EXTRACT_BATCH)
}

/// [`extract_mesh`] with at most `batch` points per query (at least one z-slice).
pub(crate) fn extract_mesh_batched<S, C>(
    aabb: Aabb,
    resolution: f32,
    sdf: S,
    color: Option<C>,
    batch: usize,
) -> Mesh
where
    S: Fn(&[[f32; 3]]) -> Vec<f32>,
    C: Fn(&[[f32; 3]]) -> Vec<[f32; 3]>,
{
    extract_window_batched(aabb, resolution, None, sdf, color, batch)
}

fn extract_window_batched<S, C>(
    aabb: Aabb,
    resolution: f32,
    window: Option<([usize; 3], [usize; 3])>,
    sdf: S,
    color: Option<C>,
    batch: usize,
) -> Mesh
where
    S: Fn(&[[f32; 3]]) -> Vec<f32>,
    C: Fn(&[[f32; 3]]) -> Vec<[f32; 3]>,
{
    assert!(aabb.is_valid(), "extract_mesh: invalid box {aabb:?}");
    assert!(
        resolution > 0.0 && resolution.is_finite(),
        "extract_mesh: bad resolution {resolution}"
    );
    let dims = extraction_dims(&aabb, resolution);
    let (lo, hi) = window.unwrap_or(([0; 3], dims));
    let hi = [0, 1, 2].map(|a| hi[a].min(dims[a]));
    let lo = [0, 1, 2].map(|a| lo[a].min(hi[a]));
    let [nx, ny, nz] = [0, 1, 2].map(|a| hi[a] - lo[a]);
    let slice = nx * ny;
    if slice * nz == 0 {
        return Mesh::default();
    }
    let slab = (batch / slice).max(1);
    let o = aabb.min;
    let mut marcher = SliceMarcher::new(nx, ny, o, resolution, 0.0).offset(lo);
    let mut pts = Vec::with_capacity(slice * slab.min(nz));
    let mut k0 = 0;
    while k0 < nz {
        let k1 = (k0 + slab).min(nz);
        pts.clear();
        for k in lo[2] + k0..lo[2] + k1 {
            for j in lo[1]..hi[1] {
                for i in lo[0]..hi[0] {
                    pts.push([
                        o[0] + resolution * i as f32,
                        o[1] + resolution * j as f32,
                        o[2] + resolution * k as f32,
                    ]);
                }
            }
        }
        let vals = sdf(&pts);
        assert_eq!(
            vals.len(),
            pts.len(),
            "extract_mesh: SDF query returned the wrong count"
        );
        for s in vals.chunks_exact(slice) {
            marcher.push_slice(s);
        }
        k0 = k1;
    }
    let mut mesh = marcher.finish();
    if let Some(color) = color {
        let mut cols = Vec::with_capacity(mesh.vertices.len());
        for chunk in mesh.vertices.chunks(batch.max(1)) {
            let c = color(chunk);
            assert_eq!(
                c.len(),
                chunk.len(),
                "extract_mesh: colour query returned the wrong count"
            );
            cols.extend(
                c.iter()
                    .map(|c| c.map(|x| (x.clamp(0.0, 1.0) * 255.0).round() as u8)),
            );
        }
        mesh.colors = Some(cols);
    }
    mesh
}
