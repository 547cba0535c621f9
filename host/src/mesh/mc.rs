//! Marching cubes over a regular grid, streamed one z-slice at a time.
//!
//! Vertices lie on grid edges (linear interpolation of the values) and are shared between the
//! cubes that meet at an edge: each cut grid edge gives exactly one vertex. A corner is inside
//! when its value is below the iso level (negative SDF); triangle normals `(b - a) x (c - a)`
//! point towards increasing values, i.e. outwards from an SDF's negative inside. Cubes with a
//! NaN corner produce nothing (the mesh then has a boundary there).

use super::tables::{CORNERS, EDGES, EDGE_TABLE, TRI_TABLE};
use super::Mesh;

const NONE: u32 = u32::MAX;

/// For each cube edge: the axis it runs along and the offset of its lower grid vertex.
const fn edge_geometry() -> [(usize, [usize; 3]); 12] {
    let mut out = [(0usize, [0usize; 3]); 12];
    let mut e = 0;
    while e < 12 {
        let a = CORNERS[EDGES[e][0]];
        let b = CORNERS[EDGES[e][1]];
        let mut axis = 0;
        let mut base = [0usize; 3];
        let mut k = 0;
        while k < 3 {
            if a[k] != b[k] {
                axis = k;
            }
            base[k] = if a[k] < b[k] { a[k] } else { b[k] };
            k += 1;
        }
        out[e] = (axis, base);
        e += 1;
    }
    out
}

const EDGE_GEOMETRY: [(usize, [usize; 3]); 12] = edge_geometry();

/// Incremental marching cubes: feed the z-slices of the grid in order with
/// [`SliceMarcher::push_slice`], then take the mesh with [`SliceMarcher::finish`]. Memory is
/// two slices of values and vertex indices plus the mesh.
pub struct SliceMarcher {
    nx: usize,
    ny: usize,
    origin: [f32; 3],
    spacing: f32,
    iso: f32,
    /// Grid index of the first value of the first slice ([`SliceMarcher::offset`]).
    first: [usize; 3],
    /// Index of the next slice to be pushed.
    k: usize,
    prev: Vec<f32>,
    /// Vertex ids of the x- and y-edges of the previous and current slice ((j nx + i) 2 + axis).
    xy_prev: Vec<u32>,
    xy_cur: Vec<u32>,
    /// Vertex ids of the z-edges between the previous and the current slice.
    z_edges: Vec<u32>,
    mesh: Mesh,
}

impl SliceMarcher {
    /// A marcher for slices of `nx * ny` values (x fastest) whose grid vertex `(i, j, k)` is at
    /// `origin + spacing * (i, j, k)`.
    pub fn new(nx: usize, ny: usize, origin: [f32; 3], spacing: f32, iso: f32) -> Self {
        Self {
            nx,
            ny,
            origin,
            spacing,
            iso,
            first: [0; 3],
            k: 0,
            prev: Vec::new(),
            xy_prev: vec![NONE; nx * ny * 2],
            xy_cur: vec![NONE; nx * ny * 2],
            z_edges: vec![NONE; nx * ny],
            mesh: Mesh::default(),
        }
    }

    /// The same marcher over a window of a larger grid: the slices' value `(i, j)` of the
    /// `k`-th slice pushed is grid vertex `first + (i, j, k)`, at `origin + spacing * (first
    /// + (i, j, k))` (so the vertices of a window are those of the whole grid, bit for bit).
    pub fn offset(mut self, first: [usize; 3]) -> Self {
        self.first = first;
        self
    }

    /// Adds the next z-slice (`nx * ny` values, x fastest) and triangulates the layer of cubes
    /// between it and the previous slice.
    ///
    /// # Panics
    /// If `values.len() != nx * ny`.
    pub fn push_slice(&mut self, values: &[f32]) {
        let (nx, ny) = (self.nx, self.ny);
        assert_eq!(
            values.len(),
            nx * ny,
            "marching cubes: slice has the wrong size"
        );
        if self.k > 0 && nx >= 2 && ny >= 2 {
            self.xy_cur.fill(NONE);
            self.z_edges.fill(NONE);
            for j in 0..ny - 1 {
                for i in 0..nx - 1 {
                    self.cube(values, i, j);
                }
            }
            std::mem::swap(&mut self.xy_prev, &mut self.xy_cur);
        }
        self.prev.clear();
        self.prev.extend_from_slice(values);
        self.k += 1;
    }

    /// The mesh of all cubes seen so far.
    pub fn finish(self) -> Mesh {
        self.mesh
    }

    fn cube(&mut self, cur: &[f32], i: usize, j: usize) {
        let nx = self.nx;
        let mut v = [0.0f32; 8];
        let mut case = 0usize;
        for (c, off) in CORNERS.iter().enumerate() {
            let idx = (j + off[1]) * nx + i + off[0];
            let x = if off[2] == 0 {
                self.prev[idx]
            } else {
                cur[idx]
            };
            if x.is_nan() {
                return;
            }
            v[c] = x;
            if x < self.iso {
                case |= 1 << c;
            }
        }
        if EDGE_TABLE[case] == 0 {
            return;
        }
        let row = &TRI_TABLE[case];
        let mut t = 0;
        while t < 16 && row[t] >= 0 {
            let tri = [
                self.vertex(&v, i, j, row[t] as usize),
                self.vertex(&v, i, j, row[t + 1] as usize),
                self.vertex(&v, i, j, row[t + 2] as usize),
            ];
            self.mesh.faces.push(tri);
            t += 3;
        }
    }

    /// The shared vertex on cube edge `e` of cube `(i, j, k - 1)`, created on first use.
    fn vertex(&mut self, v: &[f32; 8], i: usize, j: usize, e: usize) -> u32 {
        let (axis, base) = EDGE_GEOMETRY[e];
        let (gi, gj) = (i + base[0], j + base[1]);
        let cell = gj * self.nx + gi;
        let slot = if axis == 2 {
            &mut self.z_edges[cell]
        } else if base[2] == 0 {
            &mut self.xy_prev[cell * 2 + axis]
        } else {
            &mut self.xy_cur[cell * 2 + axis]
        };
        if *slot != NONE {
            return *slot;
        }
        // Interpolate from the lower grid vertex of the edge to the upper one.
        let [a, b] = EDGES[e];
        let (lo, hi) = if CORNERS[a][axis] < CORNERS[b][axis] {
            (a, b)
        } else {
            (b, a)
        };
        let (vl, vh) = (v[lo], v[hi]);
        let t = (self.iso - vl) / (vh - vl);
        // Infinite values (inf / inf) give NaN: fall back to the edge midpoint.
        let t = if t.is_nan() { 0.5 } else { t.clamp(0.0, 1.0) };
        let gk = self.k - 1 + base[2];
        let f = self.first;
        let mut p = [
            self.origin[0] + self.spacing * (f[0] + gi) as f32,
            self.origin[1] + self.spacing * (f[1] + gj) as f32,
            self.origin[2] + self.spacing * (f[2] + gk) as f32,
        ];
        p[axis] += self.spacing * t;
        let id = self.mesh.vertices.len() as u32;
        self.mesh.vertices.push(p);
        *slot = id;
        id
    }
}

/// Marching cubes on a full grid of `dims[0] * dims[1] * dims[2]` values (x fastest, then y,
/// then z) whose vertex `(i, j, k)` is at `origin + spacing * (i, j, k)`. See the module
/// documentation for orientation, vertex sharing and NaN handling. A grid with fewer than 2
/// vertices along an axis gives an empty mesh.
///
/// # Panics
/// If `values.len()` is not the product of `dims`.
pub fn marching_cubes(
    dims: [usize; 3],
    origin: [f32; 3],
    spacing: f32,
    values: &[f32],
    iso: f32,
) -> Mesh {
    let slice = dims[0] * dims[1];
    assert_eq!(
        values.len(),
        slice * dims[2],
        "marching cubes: values do not match dims"
    );
    let mut m = SliceMarcher::new(dims[0], dims[1], origin, spacing, iso);
    if slice == 0 {
        return m.finish();
    }
    for s in values.chunks_exact(slice) {
        m.push_slice(s);
    }
    m.finish()
}
