//! Mesh metrics as the paper reports them (NICE-SLAM protocol, `method-notes.md` §8.1-8.2):
//! Accuracy, Completion (cm) and Completion ratio (% of ground-truth points within 5 cm).
//!
//! Protocol of [`mesh_metrics`]:
//! 1. Sample [`EvalOptions::n_samples`] (200 000) random area-weighted points on the
//!    reconstruction ([`sample_surface`], seed `opts.seed`) and on the ground-truth mesh (seed
//!    `opts.seed + 1`, so the two sets are independent). A ground-truth point cloud is used as
//!    is, or as a random subset of `n_samples` points when it is larger.
//! 2. Nearest neighbours with a kd-tree ([`NearestNeighbours`]): Acc = mean over reconstructed points of the
//!    distance to the nearest ground-truth point; Comp = mean over ground-truth points of the
//!    distance to the nearest reconstructed point; ratio = % of ground-truth points closer than
//!    [`EvalOptions::threshold_m`] (5 cm) to the reconstruction.
//! 3. Report distances in cm.
//!
//! Not done: the ICP alignment of NICE-SLAM's script (poses are ground truth here, so the
//! reconstruction is already in the ground-truth frame).
//!
//! Without a ground-truth mesh, the ground truth is the back-projected ground-truth depth of
//! every k-th frame, voxel-downsampled ([`depth_point_cloud`]). Optional culling of the
//! reconstruction ([`cull_mesh`]): frustum (keep a face if any vertex projects inside some
//! frame, z > 0) or frustum + occlusion (a vertex counts only where it is not behind the
//! ground-truth depth by more than 3 cm). Sampling noise: two independent 200 000-point samples
//! of the same 1 m^2 surface are about 0.11 cm apart on average (the mean nearest-neighbour
//! distance of a planar Poisson process of density n / area, `0.5 / sqrt(density)`).

use std::collections::HashMap;
use std::fmt;
use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{bail, Context};
use himap_core::camera::{Intrinsics, Pose};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::mesh::{sample_surface, Mesh};

/// Errors of the mesh evaluation.
#[derive(Debug, thiserror::Error)]
pub enum EvalError {
    /// The reconstruction has no surface to sample.
    #[error("the reconstructed mesh has no surface (no faces with non-zero area)")]
    EmptyReconstruction,
    /// The ground truth has no points or no surface.
    #[error("the ground truth is empty (no points, or a mesh without area)")]
    EmptyGroundTruth,
    /// A depth map does not have `width * height` values.
    #[error("depth map {index} has {got} values, expected {expected} ({width}x{height})")]
    DepthSize {
        /// Position of the map in the input sequence.
        index: usize,
        /// Values found.
        got: usize,
        /// `width * height`.
        expected: usize,
        /// Width from the intrinsics.
        width: u32,
        /// Height from the intrinsics.
        height: u32,
    },
    /// A bad option value.
    #[error("invalid evaluation option: {0}")]
    Option(String),
}

/// The ground truth to compare against.
#[derive(Clone, Debug)]
pub enum GroundTruth {
    /// A mesh: sampled like the reconstruction.
    Mesh(Mesh),
    /// A point cloud (e.g. from [`depth_point_cloud`]): used as is, or randomly subsampled to
    /// `n_samples` points.
    Points(Vec<[f32; 3]>),
}

/// How the reconstruction is culled before sampling (see [`cull_mesh`]).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Culling {
    /// Evaluate the whole reconstruction.
    #[default]
    None,
    /// Keep faces with a vertex inside some camera frustum.
    Frustum,
    /// Keep faces with a vertex inside some frustum and not occluded in that frame (within
    /// [`EvalOptions::occlusion_eps_m`] of the ground-truth depth or in front of it).
    FrustumOcclusion,
}

impl Culling {
    /// `none`, `frustum` or `occlusion` (frustum and occlusion); `None` for any other name.
    pub fn from_name(name: &str) -> Option<Self> {
        match name {
            "none" => Some(Self::None),
            "frustum" => Some(Self::Frustum),
            "occlusion" => Some(Self::FrustumOcclusion),
            _ => None,
        }
    }
}

/// Options of the mesh evaluation.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct EvalOptions {
    /// Surface samples per mesh (200 000 in NICE-SLAM; ESLAM uses 450 000).
    pub n_samples: usize,
    /// Completion-ratio distance threshold in metres (0.05).
    pub threshold_m: f32,
    /// Sampling seed (the ground truth uses `seed + 1`).
    pub seed: u64,
    /// Culling of the reconstruction (needs camera poses: a dataset directory as ground truth).
    pub culling: Culling,
    /// Culling of a ground-truth mesh by the same frames (the "observed ground truth": the
    /// surfaces the sequence's cameras see; needs a dataset directory with `gt_mesh.ply`).
    /// A reconstruction of only the observed surfaces cannot complete what no frame saw.
    pub gt_culling: Culling,
    /// Occlusion tolerance in metres (0.03, as GO-Surf / Neural-RGBD).
    pub occlusion_eps_m: f32,
    /// Use every k-th frame for culling (2, as the Hi-Map author's benchmark).
    pub cull_stride: usize,
    /// Use every k-th frame's depth for a depth ground truth (10).
    pub gt_stride: usize,
    /// Voxel size in metres of the depth ground-truth downsampling (0.01; 0 = none).
    pub voxel_m: f32,
    /// With a dataset directory as ground truth, use its `gt_mesh.ply` when present (true)
    /// instead of the back-projected depth.
    pub prefer_gt_mesh: bool,
    /// How to read a dataset given as ground truth (its cameras, see
    /// [`crate::dataset::DatasetConfig`]).
    pub dataset: crate::dataset::DatasetConfig,
}

impl Default for EvalOptions {
    fn default() -> Self {
        Self {
            n_samples: 200_000,
            threshold_m: 0.05,
            seed: 0,
            culling: Culling::None,
            gt_culling: Culling::None,
            occlusion_eps_m: 0.03,
            cull_stride: 2,
            gt_stride: 10,
            voxel_m: 0.01,
            prefer_gt_mesh: true,
            dataset: crate::dataset::DatasetConfig::default(),
        }
    }
}

/// Mesh metrics in the paper's units.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct MeshMetrics {
    /// Mean distance from reconstructed samples to the ground truth (cm).
    pub accuracy_cm: f64,
    /// Mean distance from ground-truth points to the reconstruction (cm).
    pub completion_cm: f64,
    /// Percentage of ground-truth points within the threshold (5 cm) of the reconstruction.
    pub completion_ratio_pct: f64,
    /// Samples drawn on the reconstruction.
    pub n_samples: usize,
    /// Ground-truth points compared.
    pub n_gt_points: usize,
}

/// Leaf size of [`NearestNeighbours`].
const LEAF: usize = 12;

/// One kd-tree node: the tight bounding box of its points and either two children (`a`, `b`)
/// or, for a leaf, the range `a..b` of the reordered point array.
#[derive(Clone, Copy, Debug)]
struct KdNode {
    lo: [f32; 3],
    hi: [f32; 3],
    leaf: bool,
    a: u32,
    b: u32,
}

impl KdNode {
    /// Squared distance from `q` to the node's box (0 inside).
    #[inline]
    fn box_dist_sq(&self, q: [f32; 3]) -> f32 {
        let mut d2 = 0.0;
        for ((lo, hi), x) in self.lo.iter().zip(&self.hi).zip(&q) {
            let d = (lo - x).max(x - hi).max(0.0);
            d2 += d * d;
        }
        d2
    }
}

/// A static kd-tree over 3-D points answering nearest-neighbour distances.
///
/// Each node splits at the median of its points along the axis of largest extent and keeps
/// the tight bounding box of its points; the search prunes a subtree when the distance to its
/// box is not below the best distance so far. The boxes matter for surface samples: for a
/// query 30 cm off a plane sampled with 200k points, per-axis split-plane pruning (as in
/// kiddo 5's `ImmutableKdTree`) visits every cell within 30 cm in the plane (tens of
/// thousands of points per query, about a minute for 200k queries); with boxes, a few
/// leaves.
pub struct NearestNeighbours {
    points: Vec<[f32; 3]>,
    nodes: Vec<KdNode>,
}

impl NearestNeighbours {
    /// Builds the tree over `points` (which should be finite).
    pub fn new(points: &[[f32; 3]]) -> Self {
        let mut t = Self {
            points: points.to_vec(),
            nodes: Vec::with_capacity(2 * points.len() / LEAF + 1),
        };
        if !t.points.is_empty() {
            let mut pts = std::mem::take(&mut t.points);
            t.build(&mut pts, 0);
            t.points = pts;
        }
        t
    }

    /// Appends the subtree of `pts` (which starts at index `offset` of the point array) and
    /// returns its node index.
    fn build(&mut self, pts: &mut [[f32; 3]], offset: usize) -> u32 {
        let id = self.nodes.len() as u32;
        let (mut lo, mut hi) = ([f32::INFINITY; 3], [f32::NEG_INFINITY; 3]);
        for p in pts.iter() {
            for k in 0..3 {
                lo[k] = lo[k].min(p[k]);
                hi[k] = hi[k].max(p[k]);
            }
        }
        let leaf = pts.len() <= LEAF;
        self.nodes.push(KdNode {
            lo,
            hi,
            leaf,
            a: offset as u32,
            b: (offset + pts.len()) as u32,
        });
        if leaf {
            return id;
        }
        let mut axis = 0;
        for k in 1..3 {
            if hi[k] - lo[k] > hi[axis] - lo[axis] {
                axis = k;
            }
        }
        let mid = pts.len() / 2;
        pts.select_nth_unstable_by(mid, |p, q| p[axis].total_cmp(&q[axis]));
        let (left, right) = pts.split_at_mut(mid);
        let a = self.build(left, offset);
        let b = self.build(right, offset + mid);
        self.nodes[id as usize].a = a;
        self.nodes[id as usize].b = b;
        id
    }

    /// Squared distance from `q` to its nearest point (infinite for an empty tree).
    pub fn nearest_sq(&self, q: [f32; 3]) -> f32 {
        let mut best = f32::INFINITY;
        if !self.nodes.is_empty() {
            self.search(0, q, &mut best);
        }
        best
    }

    fn search(&self, node: u32, q: [f32; 3], best: &mut f32) {
        let n = &self.nodes[node as usize];
        if n.leaf {
            for p in &self.points[n.a as usize..n.b as usize] {
                let d = [p[0] - q[0], p[1] - q[1], p[2] - q[2]];
                let d2 = d[0] * d[0] + d[1] * d[1] + d[2] * d[2];
                if d2 < *best {
                    *best = d2;
                }
            }
            return;
        }
        let da = self.nodes[n.a as usize].box_dist_sq(q);
        let db = self.nodes[n.b as usize].box_dist_sq(q);
        let ((near, dn), (far, df)) = if da <= db {
            ((n.a, da), (n.b, db))
        } else {
            ((n.b, db), (n.a, da))
        };
        if dn < *best {
            self.search(near, q, best);
        }
        if df < *best {
            self.search(far, q, best);
        }
    }

    /// Distance (metres, f64) from each query to its nearest point, computed in parallel
    /// (infinite when the tree is empty).
    pub fn distances(&self, queries: &[[f32; 3]]) -> Vec<f64> {
        queries
            .par_iter()
            .map(|q| (self.nearest_sq(*q) as f64).sqrt())
            .collect()
    }
}

/// A deterministic random subset of `n` points (all of them when there are at most `n`).
fn subsample(points: &[[f32; 3]], n: usize, seed: u64) -> Vec<[f32; 3]> {
    if points.len() <= n {
        return points.to_vec();
    }
    // Partial Fisher-Yates shuffle over indices.
    let mut idx: Vec<u32> = (0..points.len() as u32).collect();
    for i in 0..n {
        let r = crate::mesh::unit_f64(seed, i as u64, 3);
        let j = i + ((r * (points.len() - i) as f64) as usize).min(points.len() - i - 1);
        idx.swap(i, j);
    }
    idx[..n].iter().map(|&i| points[i as usize]).collect()
}

/// Accuracy, completion and completion ratio of `rec` against `gt` (see the module
/// documentation for the protocol). Non-finite ground-truth points are ignored.
pub fn mesh_metrics(
    rec: &Mesh,
    gt: &GroundTruth,
    opts: &EvalOptions,
) -> Result<MeshMetrics, EvalError> {
    if opts.n_samples == 0 {
        return Err(EvalError::Option("n_samples must be positive".into()));
    }
    let rec_pts = sample_surface(rec, opts.n_samples, opts.seed);
    if rec_pts.is_empty() {
        return Err(EvalError::EmptyReconstruction);
    }
    let gt_pts = match gt {
        GroundTruth::Mesh(m) => sample_surface(m, opts.n_samples, opts.seed.wrapping_add(1)),
        GroundTruth::Points(p) => {
            let finite: Vec<[f32; 3]> = p
                .iter()
                .copied()
                .filter(|q| q.iter().all(|x| x.is_finite()))
                .collect();
            subsample(&finite, opts.n_samples, opts.seed.wrapping_add(1))
        }
    };
    if gt_pts.is_empty() {
        return Err(EvalError::EmptyGroundTruth);
    }
    Ok(point_metrics(&rec_pts, &gt_pts, opts.threshold_m as f64))
}

/// The metrics between two point sets (reconstruction samples, ground-truth points), in cm.
/// Both sets must be non-empty and finite.
pub fn point_metrics(rec: &[[f32; 3]], gt: &[[f32; 3]], threshold_m: f64) -> MeshMetrics {
    let (acc, comp) = rayon::join(
        || NearestNeighbours::new(gt).distances(rec),
        || NearestNeighbours::new(rec).distances(gt),
    );
    let mean = |d: &[f64]| d.iter().sum::<f64>() / d.len() as f64;
    let within = comp.iter().filter(|&&d| d < threshold_m).count();
    MeshMetrics {
        accuracy_cm: mean(&acc) * 100.0,
        completion_cm: mean(&comp) * 100.0,
        completion_ratio_pct: within as f64 / comp.len() as f64 * 100.0,
        n_samples: rec.len(),
        n_gt_points: gt.len(),
    }
}

/// Back-projects depth maps into a world point cloud, voxel-downsampled: the points falling in
/// one voxel of side `voxel` (metres; `<= 0` keeps every point) are replaced by their
/// centroid. Each item is `(depth, intrinsics, pose)`: `width * height` camera-z depths in
/// metres (row-major; `<= 0` or non-finite = no measurement), the intrinsics of that map and
/// its camera-to-world pose. Pixel (u, v) back-projects to
/// `pose * (d (u - cx) / fx, d (v - cy) / fy, d)`. The output order is deterministic
/// (sorted by voxel).
pub fn depth_point_cloud<D, I>(frames: I, voxel: f32) -> Result<Vec<[f32; 3]>, EvalError>
where
    D: AsRef<[f32]>,
    I: IntoIterator<Item = (D, Intrinsics, Pose)>,
{
    // Per voxel: coordinate sums and point count.
    type Cell = ([f64; 3], u32);
    let mut cells: HashMap<[i32; 3], Cell> = HashMap::new();
    let mut all = Vec::new();
    for (index, (depth, k, pose)) in frames.into_iter().enumerate() {
        let depth = depth.as_ref();
        let expected = k.width as usize * k.height as usize;
        if depth.len() != expected {
            return Err(EvalError::DepthSize {
                index,
                got: depth.len(),
                expected,
                width: k.width,
                height: k.height,
            });
        }
        let w = k.width as usize;
        let pts: Vec<[f32; 3]> = depth
            .par_iter()
            .enumerate()
            .filter(|(_, d)| **d > 0.0 && d.is_finite())
            .map(|(i, &d)| {
                let (u, v) = ((i % w) as f32, (i / w) as f32);
                let c = k.direction(u, v);
                pose.transform([c[0] * d, c[1] * d, d])
            })
            .collect();
        if voxel > 0.0 {
            for p in pts {
                let key = p.map(|x| (x / voxel).floor() as i32);
                let e = cells.entry(key).or_insert(([0.0; 3], 0));
                for (s, x) in e.0.iter_mut().zip(p) {
                    *s += x as f64;
                }
                e.1 += 1;
            }
        } else {
            all.extend(pts);
        }
    }
    if voxel <= 0.0 {
        return Ok(all);
    }
    let mut cells: Vec<([i32; 3], Cell)> = cells.into_iter().collect();
    cells.sort_unstable_by_key(|c| c.0);
    Ok(cells
        .into_iter()
        .map(|(_, (s, n))| s.map(|x| (x / n as f64) as f32))
        .collect())
}

/// Culls `mesh` by camera views: each item is `(intrinsics, c2w pose, optional depth map)`.
///
/// A vertex is *in the frustum* of a view when it projects inside the image
/// (0 <= u <= W - 1, 0 <= v <= H - 1) in front of the camera (z > 0). With `occlusion_eps`
/// set, a vertex is *observed* in a view when it is in the frustum and `z < depth(u, v) + eps`,
/// with (u, v) truncated to integers and the view's depth map (ground truth here; GO-Surf's
/// protocol renders the mesh's own depth instead); a view without a depth map counts as
/// unoccluded, and a pixel without depth (0) hides the vertex. A face is kept when any of its
/// vertices is in some frustum (no occlusion test) or observed in some view (with it).
/// Unreferenced vertices are removed.
pub fn cull_mesh<D, I>(mesh: &Mesh, views: I, occlusion_eps: Option<f32>) -> Mesh
where
    D: AsRef<[f32]>,
    I: IntoIterator<Item = (Intrinsics, Pose, Option<D>)>,
{
    cull_mesh_within(mesh, views, occlusion_eps, f32::INFINITY)
}

/// [`cull_mesh`] where a view sees only vertices within `max_z` of its camera (depth along
/// its optical axis): what it has farther is not counted as seen by it.
pub fn cull_mesh_within<D, I>(mesh: &Mesh, views: I, occlusion_eps: Option<f32>, max_z: f32) -> Mesh
where
    D: AsRef<[f32]>,
    I: IntoIterator<Item = (Intrinsics, Pose, Option<D>)>,
{
    let mut seen = vec![false; mesh.vertices.len()];
    for (k, pose, depth) in views {
        let depth = depth.as_ref().map(|d| d.as_ref());
        let (w, h) = (k.width as f32, k.height as f32);
        seen.par_iter_mut()
            .zip(mesh.vertices.par_iter())
            .for_each(|(s, p)| {
                if *s {
                    return;
                }
                let c = pose.inverse_transform(*p);
                // (Written so that NaN coordinates fail the tests.)
                if c[2].partial_cmp(&0.0) != Some(std::cmp::Ordering::Greater) {
                    return;
                }
                let (u, v, z) = k.project(c);
                let inside = (0.0..=w - 1.0).contains(&u) && (0.0..=h - 1.0).contains(&v);
                if !inside || z > max_z {
                    return;
                }
                *s = match (occlusion_eps, depth) {
                    (Some(eps), Some(d)) => {
                        let i = v as usize * k.width as usize + u as usize;
                        d.get(i).is_some_and(|&d| d > 0.0 && z < d + eps)
                    }
                    _ => true,
                };
            });
    }
    mesh.filter_faces(|f| mesh.faces[f].iter().any(|&i| seen[i as usize]))
}

/// What `himap eval` reports (serialisable to JSON).
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct EvalReport {
    /// The evaluated mesh file.
    pub mesh: PathBuf,
    /// The ground-truth file or dataset directory.
    pub gt: PathBuf,
    /// What the ground truth was: "mesh" (a PLY with faces, or a dataset's `gt_mesh.ply`),
    /// "points" (a PLY without faces) or "depth" (back-projected dataset depth).
    pub gt_kind: String,
    /// Faces of the reconstruction as read.
    pub faces: usize,
    /// Faces kept after culling (equal to `faces` without culling).
    pub faces_evaluated: usize,
    /// The metrics.
    pub metrics: MeshMetrics,
    /// The options used.
    pub options: EvalOptions,
    /// Wall-clock time of the whole evaluation (seconds).
    pub seconds: f64,
}

impl fmt::Display for EvalReport {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let m = &self.metrics;
        writeln!(
            f,
            "mesh {} ({} faces, {} evaluated) vs {} {}",
            self.mesh.display(),
            self.faces,
            self.faces_evaluated,
            self.gt_kind,
            self.gt.display()
        )?;
        writeln!(
            f,
            "culling: {}",
            match self.options.culling {
                Culling::None => "none (the whole reconstruction)".to_string(),
                Culling::Frustum => format!(
                    "frustum of every {}th ground-truth frame (the peers' protocol)",
                    self.options.cull_stride
                ),
                Culling::FrustumOcclusion => format!(
                    "frustum and occlusion (within {} cm of the ground-truth depth) of every \
                     {}th ground-truth frame",
                    self.options.occlusion_eps_m * 100.0,
                    self.options.cull_stride
                ),
            }
        )?;
        if self.options.gt_culling != Culling::None {
            writeln!(
                f,
                "ground truth: gt_mesh.ply culled by the same frames ({}): only what they observe",
                match self.options.gt_culling {
                    Culling::Frustum => "frustum",
                    _ => "frustum and occlusion",
                }
            )?;
        }
        writeln!(
            f,
            "Accuracy {:.2} cm | Completion {:.2} cm | Completion ratio {:.2} % (< {} cm)",
            m.accuracy_cm,
            m.completion_cm,
            m.completion_ratio_pct,
            self.options.threshold_m * 100.0
        )?;
        write!(
            f,
            "{} reconstruction samples, {} ground-truth points, {:.1} s",
            m.n_samples, m.n_gt_points, self.seconds
        )
    }
}

/// The ground truth of a dataset without `gt_mesh.ply`: its depth frames (every
/// `gt_stride`-th) back-projected and voxel-downsampled.
fn depth_truth(
    ds: &dyn crate::dataset::Dataset,
    gt: &Path,
    opts: &EvalOptions,
) -> anyhow::Result<Vec<[f32; 3]>> {
    if !ds.has_depth() {
        bail!(
            "{}: no gt_mesh.ply and no depth to build a ground truth from",
            gt.display()
        );
    }
    let frames = (0..ds.len()).step_by(opts.gt_stride).map(|i| ds.frame(i));
    let mut depth_err = None;
    let views = frames.map_while(|f| match f {
        Ok(f) => match f.depth {
            Some(d) => Some((d.data, f.intrinsics, f.pose)),
            None => {
                depth_err = Some(anyhow::anyhow!("frame {} has no depth", f.index));
                None
            }
        },
        Err(e) => {
            depth_err = Some(e.into());
            None
        }
    });
    let pts = depth_point_cloud(views, opts.voxel_m)?;
    if let Some(e) = depth_err {
        return Err(e.context(format!("reading depth of {}", gt.display())));
    }
    Ok(pts)
}

/// The reconstruction culled by the dataset's frames (every `cull_stride`-th) as
/// `opts.culling` says: by their frusta, or also by their ground-truth depth.
fn cull_by_dataset(
    rec: Mesh,
    ds: &dyn crate::dataset::Dataset,
    gt: &Path,
    culling: Culling,
    opts: &EvalOptions,
) -> anyhow::Result<Mesh> {
    Ok(match culling {
        Culling::None => rec,
        Culling::Frustum => {
            let views = (0..ds.len())
                .step_by(opts.cull_stride)
                .map(|i| (ds.intrinsics(), ds.pose(i), None::<Vec<f32>>));
            cull_mesh(&rec, views, None)
        }
        Culling::FrustumOcclusion => {
            if !ds.has_depth() {
                bail!("{}: occlusion culling needs depth", gt.display());
            }
            let mut views = Vec::new();
            for i in (0..ds.len()).step_by(opts.cull_stride) {
                let f = ds.frame(i)?;
                let d = f.depth.context("frame without depth")?;
                views.push((f.intrinsics, f.pose, Some(d.data)));
            }
            cull_mesh(&rec, views, Some(opts.occlusion_eps_m))
        }
    })
}

/// Splits every face with an edge longer than `max_edge` into 4 (midpoints), repeatedly.
pub fn subdivide(m: &Mesh, max_edge: f32) -> Mesh {
    let mut out = Mesh::default();
    let mut stack: Vec<[[f32; 3]; 3]> = (0..m.faces.len()).map(|f| m.triangle(f)).collect();
    let len = |a: [f32; 3], b: [f32; 3]| {
        ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt()
    };
    while let Some([a, b, c]) = stack.pop() {
        if len(a, b).max(len(b, c)).max(len(c, a)) <= max_edge {
            let base = out.vertices.len() as u32;
            out.vertices.extend([a, b, c]);
            out.faces.push([base, base + 1, base + 2]);
            continue;
        }
        let mid = |p: [f32; 3], q: [f32; 3]| [0, 1, 2].map(|k| 0.5 * (p[k] + q[k]));
        let (ab, bc, ca) = (mid(a, b), mid(b, c), mid(c, a));
        stack.extend([[a, ab, ca], [ab, b, bc], [ca, bc, c], [ab, bc, ca]]);
    }
    out
}

/// Longest edge (m) a ground-truth mesh's faces are split to before it is culled: faces are
/// kept by their vertices, and a wall of two huge triangles has none in any view.
const GT_CULL_EDGE_M: f32 = 0.1;

/// Evaluates a mesh file against a ground truth and builds the report (the caller prints it
/// with `Display`). `gt` is a PLY file (a mesh, or a point cloud when it has no faces) or a
/// dataset directory ([`crate::dataset::open`]): its `gt_mesh.ply` when present and
/// `opts.prefer_gt_mesh`, else the back-projection of every `opts.gt_stride`-th frame's
/// ground-truth depth ([`depth_point_cloud`], voxel `opts.voxel_m`). Culling
/// (`opts.culling`) uses every `opts.cull_stride`-th frame of the dataset and therefore needs a
/// directory. With `json`, the report is also written there (pretty-printed).
pub fn eval_report(mesh: &Path, gt: &Path, opts: &EvalOptions) -> anyhow::Result<EvalReport> {
    let t0 = Instant::now();
    if opts.cull_stride == 0 || opts.gt_stride == 0 {
        bail!("cull_stride and gt_stride must be at least 1");
    }
    let rec = Mesh::read_ply(mesh)?;
    let faces = rec.faces.len();
    let (truth, kind, rec) = if gt.is_dir() {
        let mesh_path = gt.join("gt_mesh.ply");
        let use_mesh = opts.prefer_gt_mesh && mesh_path.is_file();
        // The dataset itself is needed only for a depth ground truth or for culling.
        let ds = if !use_mesh || opts.culling != Culling::None || opts.gt_culling != Culling::None {
            Some(
                crate::dataset::open_with(
                    gt,
                    &crate::dataset::LoadOptions::default(),
                    &opts.dataset,
                )
                .with_context(|| format!("opening dataset {}", gt.display()))?,
            )
        } else {
            None
        };
        let (truth, kind) = if use_mesh {
            let m = Mesh::read_ply(&mesh_path)?;
            match (opts.gt_culling, ds.as_ref()) {
                (Culling::None, _) | (_, None) => (GroundTruth::Mesh(m), "mesh"),
                (c, Some(ds)) => (
                    GroundTruth::Mesh(cull_by_dataset(
                        subdivide(&m, GT_CULL_EDGE_M),
                        ds.as_ref(),
                        gt,
                        c,
                        opts,
                    )?),
                    "observed mesh",
                ),
            }
        } else {
            if opts.gt_culling != Culling::None {
                bail!(
                    "{}: culling the ground truth needs its gt_mesh.ply (a depth ground truth \
                     is already what the frames observed)",
                    gt.display()
                );
            }
            let ds = ds.as_ref().expect("opened above");
            (
                GroundTruth::Points(depth_truth(ds.as_ref(), gt, opts)?),
                "depth",
            )
        };
        let rec = match ds.as_ref() {
            Some(ds) => cull_by_dataset(rec, ds.as_ref(), gt, opts.culling, opts)?,
            None => rec,
        };
        (truth, kind, rec)
    } else {
        if opts.culling != Culling::None || opts.gt_culling != Culling::None {
            bail!("culling needs camera poses: pass a dataset directory as the ground truth");
        }
        let m = Mesh::read_ply(gt)?;
        if m.faces.is_empty() {
            (GroundTruth::Points(m.vertices), "points", rec)
        } else {
            (GroundTruth::Mesh(m), "mesh", rec)
        }
    };
    let faces_evaluated = rec.faces.len();
    let metrics = mesh_metrics(&rec, &truth, opts)
        .with_context(|| format!("evaluating {} against {}", mesh.display(), gt.display()))?;
    Ok(EvalReport {
        mesh: mesh.to_path_buf(),
        gt: gt.to_path_buf(),
        gt_kind: kind.to_string(),
        faces,
        faces_evaluated,
        metrics,
        options: opts.clone(),
        seconds: t0.elapsed().as_secs_f64(),
    })
}

/// `himap eval --mesh M.ply --gt (GT.ply | DATASET_DIR) [--json OUT]`: [`eval_report`], then
/// the report written to `json` as pretty JSON when given. Printing is left to the caller
/// (`println!("{report}")`).
pub fn run_eval_cli(
    mesh: &Path,
    gt: &Path,
    json: Option<&Path>,
    opts: &EvalOptions,
) -> anyhow::Result<EvalReport> {
    let report = eval_report(mesh, gt, opts)?;
    if let Some(out) = json {
        let text = serde_json::to_string_pretty(&report)?;
        crate::atomic::write_bytes_atomic(out, text.as_bytes())?;
    }
    Ok(report)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The unit square [0, 1]^2 at height z (two triangles, normal +z).
    fn square(z: f32) -> Mesh {
        Mesh {
            vertices: vec![[0.0, 0.0, z], [1.0, 0.0, z], [1.0, 1.0, z], [0.0, 1.0, z]],
            colors: None,
            faces: vec![[0, 1, 2], [0, 2, 3]],
        }
    }

    fn opts() -> EvalOptions {
        EvalOptions::default()
    }

    #[test]
    fn plane_against_itself_is_sampling_noise_only() {
        let m = mesh_metrics(&square(0.0), &GroundTruth::Mesh(square(0.0)), &opts()).unwrap();
        // Two independent 200k samples of 1 m^2: mean nearest-neighbour distance of a planar
        // Poisson process, 0.5 / sqrt(200000) m = 0.112 cm.
        assert!((m.accuracy_cm - 0.112).abs() < 0.01, "{m:?}");
        assert!((m.completion_cm - 0.112).abs() < 0.01, "{m:?}");
        assert_eq!(m.completion_ratio_pct, 100.0);
        assert_eq!((m.n_samples, m.n_gt_points), (200_000, 200_000));
        // The same samples on both sides: exactly zero.
        let p = sample_surface(&square(0.0), 1000, 3);
        let z = point_metrics(&p, &p, 0.05);
        assert_eq!(
            (z.accuracy_cm, z.completion_cm, z.completion_ratio_pct),
            (0.0, 0.0, 100.0)
        );
    }

    #[test]
    fn shifted_plane_gives_the_shift() {
        // Shift along the normal by 3 cm: every distance is sqrt(0.03^2 + r^2) with r the
        // in-plane nearest-neighbour distance (E r^2 = 1 / (pi density) = 1.6e-6 m^2), so
        // Acc = Comp = 3.000 + 0.003 cm; all ground-truth points are within 5 cm.
        let m = mesh_metrics(&square(0.03), &GroundTruth::Mesh(square(0.0)), &opts()).unwrap();
        assert!((m.accuracy_cm - 3.0).abs() < 0.02, "{m:?}");
        assert!((m.completion_cm - 3.0).abs() < 0.02, "{m:?}");
        assert_eq!(m.completion_ratio_pct, 100.0);
        // By 8 cm: nothing within 5 cm.
        let m = mesh_metrics(&square(-0.08), &GroundTruth::Mesh(square(0.0)), &opts()).unwrap();
        assert!((m.accuracy_cm - 8.0).abs() < 0.02, "{m:?}");
        assert!((m.completion_cm - 8.0).abs() < 0.02, "{m:?}");
        assert_eq!(m.completion_ratio_pct, 0.0);
    }

    #[test]
    fn half_reconstruction_has_accuracy_but_not_completion() {
        // Reconstruction: the half x < 0.5 of the ground-truth square. Accuracy is sampling
        // noise (0.112 cm); a ground-truth point at x > 0.5 is x - 0.5 from the reconstruction,
        // so Comp = 0.5 * 25 cm + 0.5 * noise (0.5 / sqrt(400000) m = 0.079 cm) = 12.54 cm and
        // the ratio is P(x < 0.55) = 55 %.
        let half = Mesh {
            vertices: vec![
                [0.0, 0.0, 0.0],
                [0.5, 0.0, 0.0],
                [0.5, 1.0, 0.0],
                [0.0, 1.0, 0.0],
            ],
            colors: None,
            faces: vec![[0, 1, 2], [0, 2, 3]],
        };
        let m = mesh_metrics(&half, &GroundTruth::Mesh(square(0.0)), &opts()).unwrap();
        assert!((m.accuracy_cm - 0.112).abs() < 0.01, "{m:?}");
        assert!((m.completion_cm - 12.54).abs() < 0.15, "{m:?}");
        assert!((m.completion_ratio_pct - 55.0).abs() < 0.5, "{m:?}");
        // Swapping the roles swaps accuracy and completion.
        let s = mesh_metrics(&square(0.0), &GroundTruth::Mesh(half), &opts()).unwrap();
        assert!((s.accuracy_cm - 12.54).abs() < 0.15, "{s:?}");
        assert_eq!(s.completion_ratio_pct, 100.0);
    }

    #[test]
    fn marching_cubes_sphere_against_analytic_surface() {
        // SDF of a sphere of radius 0.3 on a 2 cm grid; ground truth: 500k points of the exact
        // sphere (Fibonacci lattice). Expected Acc, Comp: sampling noise
        // 0.5 / sqrt(500000 / (4 pi 0.09)) m = 0.075 cm plus the marching-cubes chord error
        // (~ h^2 / (8 R) = 0.017 cm): below 0.1 * spacing = 0.2 cm.
        let (r, h) = (0.3f32, 0.02f32);
        let aabb = himap_core::Aabb::new([-0.4; 3], [0.4; 3]);
        let sdf = |p: &[[f32; 3]]| {
            p.iter()
                .map(|q| (q[0] * q[0] + q[1] * q[1] + q[2] * q[2]).sqrt() - r)
                .collect()
        };
        let mesh = crate::mesh::extract_mesh(aabb, h, sdf, None::<crate::mesh::NoColor>);
        let n = 500_000;
        let golden = std::f64::consts::PI * (3.0 - 5f64.sqrt());
        let gt: Vec<[f32; 3]> = (0..n)
            .map(|i| {
                let y = 1.0 - 2.0 * (i as f64 + 0.5) / n as f64;
                let rad = (1.0 - y * y).sqrt();
                let th = golden * i as f64;
                [rad * th.cos(), y, rad * th.sin()].map(|x| (x * r as f64) as f32)
            })
            .collect();
        let o = EvalOptions {
            n_samples: n,
            ..opts()
        };
        let m = mesh_metrics(&mesh, &GroundTruth::Points(gt), &o).unwrap();
        assert!(m.accuracy_cm < 0.1 * h as f64 * 100.0, "{m:?}");
        assert!(m.completion_cm < 0.1 * h as f64 * 100.0, "{m:?}");
        assert_eq!(m.completion_ratio_pct, 100.0);
        // And not trivially small: the noise floor is there.
        assert!(m.accuracy_cm > 0.03 && m.completion_cm > 0.03, "{m:?}");
    }

    #[test]
    fn point_ground_truth_is_subsampled_deterministically() {
        let pts: Vec<[f32; 3]> = (0..5000).map(|i| [i as f32 * 1e-3, 0.0, 0.0]).collect();
        let a = subsample(&pts, 100, 9);
        assert_eq!(a.len(), 100);
        assert_eq!(a, subsample(&pts, 100, 9));
        let mut uniq = a.clone();
        uniq.sort_by(|x, y| x[0].total_cmp(&y[0]));
        uniq.dedup();
        assert_eq!(uniq.len(), 100, "subset must not repeat points");
        assert_eq!(subsample(&pts[..50], 100, 9), pts[..50].to_vec());
    }

    #[test]
    fn empty_inputs_are_errors() {
        let e = mesh_metrics(&Mesh::default(), &GroundTruth::Mesh(square(0.0)), &opts());
        assert!(matches!(e, Err(EvalError::EmptyReconstruction)));
        let e = mesh_metrics(
            &square(0.0),
            &GroundTruth::Points(vec![[f32::NAN; 3]]),
            &opts(),
        );
        assert!(matches!(e, Err(EvalError::EmptyGroundTruth)));
        let o = EvalOptions {
            n_samples: 0,
            ..opts()
        };
        assert!(mesh_metrics(&square(0.0), &GroundTruth::Mesh(square(0.0)), &o).is_err());
    }

    fn camera() -> Intrinsics {
        Intrinsics {
            width: 8,
            height: 6,
            fx: 4.0,
            fy: 4.0,
            cx: 3.5,
            cy: 2.5,
        }
    }

    #[test]
    fn depth_back_projection_lands_on_the_surface() {
        // A camera at (1, 2, 3) looking along world -x (camera z = world -x, camera x = world
        // y, camera y = world -z... a rigid rotation), seeing the plane world x = -1 at camera
        // depth 2 everywhere except two holes.
        let pose = Pose {
            m: [
                [0.0, 0.0, -1.0, 1.0],
                [1.0, 0.0, 0.0, 2.0],
                [0.0, -1.0, 0.0, 3.0],
            ],
        };
        assert!(pose.is_rigid(1e-6));
        let k = camera();
        let mut depth = vec![2.0f32; 48];
        depth[0] = 0.0;
        depth[47] = f32::NAN;
        let pts = depth_point_cloud([(depth.clone(), k, pose)], 0.0).unwrap();
        assert_eq!(pts.len(), 46);
        // Pixel 1 is (u, v) = (1, 0): camera point 2 * ((1 - 3.5) / 4, (0 - 2.5) / 4, 1) =
        // (-1.25, -1.25, 2) -> world (1 - 2, 2 - 1.25, 3 + 1.25) = (-1, 0.75, 4.25).
        assert_eq!(pts[0], [-1.0, 0.75, 4.25]);
        for p in &pts {
            assert!((p[0] + 1.0).abs() < 1e-6);
            // Re-projecting gives an integer pixel at depth 2.
            let (u, v, z) = k.project(pose.inverse_transform(*p));
            assert!((u - u.round()).abs() < 1e-4 && (v - v.round()).abs() < 1e-4);
            assert!((z - 2.0).abs() < 1e-6);
        }
        // Voxels of 1 m: world y = 2 + (u - 3.5) / 2 in {0.25, 0.75, ..., 3.75} and
        // z = 3 - (v - 2.5) / 2 in {1.75, 2.25, ..., 4.25} fall into the voxels y in {0..3},
        // z in {1..4} (the holes' cells keep other points): 16 cells. Each output point is the
        // centroid of its cell's points, so it stays on the plane.
        let vox = depth_point_cloud([(depth.clone(), k, pose), (depth, k, pose)], 1.0).unwrap();
        assert_eq!(vox.len(), 16);
        // Cell (y 0, z 4) holds pixel (1, 0) alone ((0, 0) is a hole and v = 1 gives
        // z = 3.75), twice: its centroid is that point.
        assert!(vox.contains(&[-1.0, 0.75, 4.25]));
        for p in &vox {
            assert!((p[0] + 1.0).abs() < 1e-6);
        }
        let mut sorted = vox.clone();
        sorted.sort_by(|a, b| a.partial_cmp(b).unwrap());
        assert_eq!(sorted, vox, "output is sorted by voxel");
        let e = depth_point_cloud([(vec![1.0f32; 5], k, pose)], 0.0);
        assert!(matches!(
            e,
            Err(EvalError::DepthSize {
                got: 5,
                expected: 48,
                ..
            })
        ));
    }

    #[test]
    fn culling_by_frustum_and_occlusion() {
        // Identity camera (looking along +z). Three small triangles: A at z = 2 in view,
        // B at z = -2 (behind), C at z = 5 in view but behind the depth map's surface at 2 m.
        let k = camera();
        let tri = |x: f32, y: f32, z: f32| [[x, y, z], [x + 0.01, y, z], [x, y + 0.01, z]];
        let mut m = Mesh::default();
        for t in [tri(0.0, 0.0, 2.02), tri(0.0, 0.0, -2.0), tri(0.0, 0.0, 5.0)] {
            let base = m.vertices.len() as u32;
            m.vertices.extend(t);
            m.faces.push([base, base + 1, base + 2]);
        }
        let views = || [(k, Pose::IDENTITY, Some(vec![2.0f32; 48]))];
        let f = cull_mesh(&m, views(), None);
        assert_eq!(f.faces.len(), 2);
        assert!(f.vertices.iter().all(|p| p[2] > 0.0));
        // With occlusion: A (2.02 < 2 + 0.03) stays, C (5 > 2.03) goes.
        let o = cull_mesh(&m, views(), Some(0.03));
        assert_eq!(o.faces.len(), 1);
        assert_eq!(o.vertices[0][2], 2.02);
        // A tolerance of 1 cm hides A as well.
        assert!(cull_mesh(&m, views(), Some(0.01)).faces.is_empty());
        // Outside the image: shifted sideways beyond the frustum (u = 4 * 10 / 2 + 3.5 > 7).
        let side = Mesh {
            vertices: tri(10.0, 0.0, 2.0).to_vec(),
            colors: None,
            faces: vec![[0, 1, 2]],
        };
        assert!(cull_mesh(&side, views(), None).faces.is_empty());
        // Within a depth: without occlusion the faces at 2.02 and 5 m are seen; a view that
        // sees only to 3 m keeps the near one, one that sees to 1 m neither.
        let w = cull_mesh_within(&m, views(), None, 3.0);
        assert_eq!(w.faces.len(), 1);
        assert_eq!(w.vertices[0][2], 2.02);
        assert!(cull_mesh_within(&m, views(), None, 1.0).faces.is_empty());
        assert_eq!(cull_mesh_within(&m, views(), None, f32::INFINITY), f);
    }

    #[test]
    fn eval_cli_on_ply_files_writes_json() {
        let dir = tempfile::tempdir().unwrap();
        let (rec, gt, js) = (
            dir.path().join("rec.ply"),
            dir.path().join("gt.ply"),
            dir.path().join("r.json"),
        );
        square(0.03).write_ply(&rec).unwrap();
        square(0.0).write_ply(&gt).unwrap();
        let o = EvalOptions {
            n_samples: 50_000,
            ..opts()
        };
        let r = run_eval_cli(&rec, &gt, Some(&js), &o).unwrap();
        assert_eq!(r.gt_kind, "mesh");
        assert_eq!((r.faces, r.faces_evaluated), (2, 2));
        assert!((r.metrics.accuracy_cm - 3.0).abs() < 0.05, "{r}");
        let back: EvalReport =
            serde_json::from_str(&std::fs::read_to_string(&js).unwrap()).unwrap();
        assert_eq!(back.metrics, r.metrics);
        assert!(format!("{r}").contains("Completion ratio 100.00 %"));
        // A PLY without faces is a point cloud.
        let pc = dir.path().join("pc.ply");
        Mesh {
            vertices: vec![[0.5, 0.5, 0.0]],
            colors: None,
            faces: vec![],
        }
        .write_ply(&pc)
        .unwrap();
        let r = run_eval_cli(&rec, &pc, None, &o).unwrap();
        assert_eq!((r.gt_kind.as_str(), r.metrics.n_gt_points), ("points", 1));
        // A folder with only a gt_mesh.ply: fine without culling; a depth ground truth needs
        // a dataset there.
        let folder = dir.path().join("folder");
        std::fs::create_dir(&folder).unwrap();
        square(0.0).write_ply(&folder.join("gt_mesh.ply")).unwrap();
        let r = run_eval_cli(&rec, &folder, None, &o).unwrap();
        assert_eq!(r.gt_kind, "mesh");
        assert!((r.metrics.completion_cm - 3.0).abs() < 0.05, "{r}");
        let no_mesh = EvalOptions {
            prefer_gt_mesh: false,
            ..o.clone()
        };
        let e = run_eval_cli(&rec, &folder, None, &no_mesh).unwrap_err();
        assert!(format!("{e:#}").contains("opening dataset"), "{e:#}");
        // Culling without poses, a missing file: clear errors.
        let c = EvalOptions {
            culling: Culling::Frustum,
            ..o.clone()
        };
        let e = run_eval_cli(&rec, &gt, None, &c).unwrap_err();
        assert!(format!("{e:#}").contains("dataset directory"));
        let e = run_eval_cli(&dir.path().join("nope.ply"), &gt, None, &o).unwrap_err();
        assert!(format!("{e:#}").contains("nope.ply"));
    }

    #[test]
    fn eval_cli_on_a_synthetic_dataset() {
        let dir = tempfile::tempdir().unwrap();
        let seq = dir.path().join("seq");
        let so = crate::synth::SynthOptions {
            frames: 8,
            width: 64,
            height: 48,
            seed: 3,
        };
        crate::synth::write_synthetic(&seq, &so).unwrap();
        let gt_mesh = seq.join("gt_mesh.ply");
        let o = EvalOptions {
            n_samples: 50_000,
            gt_stride: 1,
            voxel_m: 0.02,
            ..opts()
        };
        // The dataset's own mesh: compared with its gt_mesh.ply, pure sampling noise.
        let r = run_eval_cli(&gt_mesh, &seq, None, &o).unwrap();
        assert_eq!(r.gt_kind, "mesh");
        assert!(
            r.metrics.accuracy_cm < 3.0 && r.metrics.completion_ratio_pct > 99.0,
            "{r}"
        );
        // Against the back-projected depth: every depth point lies on the mesh surface (up to
        // the 16-bit depth quantisation), so the completion is sampling noise and near-complete.
        let d = EvalOptions {
            prefer_gt_mesh: false,
            ..o.clone()
        };
        let r = run_eval_cli(&gt_mesh, &seq, None, &d).unwrap();
        assert_eq!(r.gt_kind, "depth");
        assert!(
            r.metrics.completion_cm < 3.0 && r.metrics.completion_ratio_pct > 99.0,
            "{r}"
        );
        // Culling needs a dense mesh (faces are kept by their vertices; the room's walls are
        // a few huge triangles): subdivide to edges below 10 cm. Frustum + occlusion culling
        // against the frames' depth keeps what the depth saw, so the completion stays and the
        // accuracy (unobserved surfaces far from any depth point) improves a lot.
        let dense = subdivide(&Mesh::read_ply(&gt_mesh).unwrap(), 0.1);
        let dense_path = dir.path().join("dense.ply");
        dense.write_ply(&dense_path).unwrap();
        let r = run_eval_cli(&dense_path, &seq, None, &d).unwrap();
        let c = EvalOptions {
            culling: Culling::FrustumOcclusion,
            cull_stride: 1,
            ..d.clone()
        };
        let rc = run_eval_cli(&dense_path, &seq, None, &c).unwrap();
        assert!(
            rc.faces_evaluated > 0 && rc.faces_evaluated < rc.faces,
            "{rc}"
        );
        assert!(
            rc.metrics.accuracy_cm < 0.5 * r.metrics.accuracy_cm,
            "{rc}\n{r}"
        );
        assert!(
            rc.metrics.completion_cm < r.metrics.completion_cm + 0.3,
            "{rc}\n{r}"
        );
        // (A few depth points lie in faces at the image borders whose vertices are all unseen.)
        assert!(rc.metrics.completion_ratio_pct > 98.0, "{rc}");
        // Frustum culling alone keeps at least as much as frustum + occlusion.
        let f = EvalOptions {
            culling: Culling::Frustum,
            ..c.clone()
        };
        let rf = run_eval_cli(&dense_path, &seq, None, &f).unwrap();
        assert!(rf.faces_evaluated >= rc.faces_evaluated && rf.faces_evaluated < rf.faces);

        // The observed ground truth: with the dense mesh as the dataset's gt_mesh.ply, the
        // reconstruction of exactly the observed surfaces misses the unobserved ones against
        // the whole mesh, and is complete against the mesh culled by the same frames.
        dense.write_ply(&gt_mesh).unwrap();
        let whole = run_eval_cli(&dense_path, &seq, None, &c_mesh(&c)).unwrap();
        assert_eq!(whole.gt_kind, "mesh");
        let observed = EvalOptions {
            gt_culling: Culling::FrustumOcclusion,
            ..c_mesh(&c)
        };
        let ro = run_eval_cli(&dense_path, &seq, None, &observed).unwrap();
        assert_eq!(ro.gt_kind, "observed mesh");
        assert!(
            format!("{ro}").contains("culled by the same frames"),
            "{ro}"
        );
        assert!(ro.metrics.completion_ratio_pct > 99.0, "{ro}");
        assert!(
            whole.metrics.completion_ratio_pct < ro.metrics.completion_ratio_pct - 1.0
                && whole.metrics.completion_cm > ro.metrics.completion_cm,
            "{whole}\n{ro}"
        );
        // Only a mesh ground truth can be culled.
        let e = run_eval_cli(
            &dense_path,
            &seq,
            None,
            &EvalOptions {
                prefer_gt_mesh: false,
                ..observed
            },
        )
        .unwrap_err();
        assert!(format!("{e:#}").contains("needs its gt_mesh.ply"), "{e:#}");
    }

    /// `o` with the dataset's gt_mesh.ply as the ground truth.
    fn c_mesh(o: &EvalOptions) -> EvalOptions {
        EvalOptions {
            prefer_gt_mesh: true,
            ..o.clone()
        }
    }

    #[test]
    fn kd_tree_matches_brute_force() {
        let brute = |pts: &[[f32; 3]], q: [f32; 3]| {
            pts.iter()
                .map(|p| (0..3).map(|k| (p[k] - q[k]) * (p[k] - q[k])).sum::<f32>())
                .fold(f32::INFINITY, f32::min)
        };
        let u = |i: u64, k: u64| crate::mesh::unit_f64(11, i, k) as f32;
        // A 3-D cloud, a plane with duplicated points, and all points identical.
        let cloud: Vec<[f32; 3]> = (0..3000).map(|i| [u(i, 0), u(i, 1), u(i, 2)]).collect();
        let mut plane: Vec<[f32; 3]> = (0..3000).map(|i| [u(i, 0), u(i, 1), 0.0]).collect();
        plane.extend_from_within(..500);
        let same = vec![[0.5f32, 0.5, 0.5]; 100];
        for pts in [&cloud, &plane, &same] {
            let t = NearestNeighbours::new(pts);
            let queries: Vec<[f32; 3]> = (0..500)
                .map(|i| [u(i, 5) * 1.4 - 0.2, u(i, 6) * 1.4 - 0.2, u(i, 7) - 0.5])
                .collect();
            for q in queries.iter().chain(pts.iter().take(50)) {
                assert_eq!(t.nearest_sq(*q), brute(pts, *q), "{q:?}");
            }
        }
        assert_eq!(
            NearestNeighbours::new(&[]).nearest_sq([0.0; 3]),
            f32::INFINITY
        );
    }

    /// Manual benchmark (`cargo test --release -p himap --lib bench_nearest -- --ignored
    /// --nocapture`): 200k samples of a 1 m^2 plane against 200k queries 0, 3 and 30 cm off it.
    #[test]
    #[ignore]
    fn bench_nearest_neighbours_200k() {
        let a = sample_surface(&square(0.0), 200_000, 1);
        for shift in [0.0f32, 0.03, 0.3] {
            let b = sample_surface(&square(shift), 200_000, 2);
            let t = Instant::now();
            let nn = NearestNeighbours::new(&a);
            let tb = t.elapsed();
            let t = Instant::now();
            let d = nn.distances(&b);
            let tq = t.elapsed();
            let mean = d.iter().sum::<f64>() / d.len() as f64;
            eprintln!("shift {shift} m: build {tb:?}, 200k queries {tq:?}, mean {mean:.6} m");
            assert!((mean - (shift as f64).max(0.0011)).abs() < 1e-4);
        }
    }
}
