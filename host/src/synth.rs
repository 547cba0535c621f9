//! Synthetic scenes: a procedurally built room (seeded) rendered analytically by ray casting,
//! written as a Replica-layout sequence with exact depth and a ground-truth mesh.
//!
//! The room is an axis-aligned box of about 4 x 3 x 2.6 m (world z up, floor at z = 0, centred
//! on x = y = 0) holding 2 to 4 boxes standing on the floor and 1 to 3 spheres. Surfaces carry
//! analytic textures of the world position (checkerboard, smooth stripes, smooth value noise) or
//! a plain colour (textureless); shading is Lambertian from a fixed light direction plus an
//! ambient term, so colours do not depend on the view. The camera orbits the room's centre
//! once over the sequence on an ellipse, looking at a point above the centre whose height
//! oscillates (the view pitches between about -35 and +15 degrees) with a small vertical
//! wobble of the camera itself. Objects keep at least [`CAMERA_CLEARANCE`] from the path.
//!
//! Every number is computed in `f32` with the vendored math of `himap-core`, so the output is
//! bit-for-bit deterministic for a seed (and independent of the platform's libm).
//!
//! Output of [`write_synthetic`]:
//! ```text
//! results/frame%06d.png   8-bit colour
//! results/depth%06d.png   16-bit depth, metres = value / 6553.5 (camera z; 0 = no hit)
//! traj.txt                row-major 4x4 camera-to-world per line (OpenCV axes)
//! cam_params.json         {"camera": {w, h, fx, fy, cx, cy, scale}}, ~70 deg horizontal FOV
//! gt_mesh.ply             binary PLY of the surfaces (room inside, boxes, tessellated spheres)
//! scene.json              {"seed", "frames", "width", "height", "scene_box": {min, max}, "scene"}
//! ```

use std::io::Write;
use std::path::{Path, PathBuf};

use anyhow::{bail, Context};
use himap_core::camera::{Intrinsics, Pose};
use himap_core::math::{cos, floor, sin, sqrt};
use himap_core::rng::{hash3, SplitMix};
use himap_core::Aabb;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::dataset::{DepthImage, RgbImage, DEPTH_INVALID, REPLICA_DEPTH_SCALE};

/// Smallest distance between the camera path and any object surface (metres).
pub const CAMERA_CLEARANCE: f32 = 0.5;
/// Horizontal field of view of the synthetic camera (degrees).
pub const HFOV_DEG: f32 = 70.0;
/// Longitude segments of the tessellated spheres in the ground-truth mesh (latitude: half).
/// The chord error is at most r (1 - cos(pi / 64)) ~ 1.2e-3 r.
pub const SPHERE_SEGMENTS: u32 = 64;

const TAU: f32 = core::f32::consts::TAU;

/// Surface colour as a function of the world position.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "lowercase")]
pub enum Material {
    /// A single colour (textureless).
    Plain { color: [f32; 3] },
    /// A 3D checkerboard of cubes of side `size`, shifted by `offset` (so that cell borders do
    /// not coincide with the axis-aligned faces).
    Checker {
        a: [f32; 3],
        b: [f32; 3],
        size: f32,
        offset: [f32; 3],
    },
    /// Smooth stripes: mix(a, b, 0.5 + 0.5 sin(2 pi p.dir / period)); `dir` is a unit vector.
    Stripes {
        a: [f32; 3],
        b: [f32; 3],
        period: f32,
        dir: [f32; 3],
    },
    /// Smooth value noise (two octaves, feature size `scale`): mix(a, b, n(p)), n contrast-
    /// stretched to [0, 1].
    Noise {
        a: [f32; 3],
        b: [f32; 3],
        scale: f32,
        seed: u32,
    },
}

fn mix(a: [f32; 3], b: [f32; 3], t: f32) -> [f32; 3] {
    [
        a[0] + (b[0] - a[0]) * t,
        a[1] + (b[1] - a[1]) * t,
        a[2] + (b[2] - a[2]) * t,
    ]
}

/// Value at an integer lattice point, in [0, 1).
fn lattice(seed: u32, i: [i32; 3]) -> f32 {
    let a = (i[0] as u32).wrapping_mul(73_856_093) ^ (i[1] as u32).wrapping_mul(19_349_663);
    (hash3(seed, a, i[2] as u32) >> 8) as f32 * (1.0 / 16_777_216.0)
}

/// Trilinear value noise with smoothstep weights, in [0, 1).
fn value_noise(seed: u32, q: [f32; 3]) -> f32 {
    let fl = [floor(q[0]), floor(q[1]), floor(q[2])];
    let i = [fl[0] as i32, fl[1] as i32, fl[2] as i32];
    let f = [q[0] - fl[0], q[1] - fl[1], q[2] - fl[2]];
    let w = f.map(|x| x * x * (3.0 - 2.0 * x));
    let mut acc = 0.0;
    for corner in 0..8 {
        let d = [corner & 1, (corner >> 1) & 1, (corner >> 2) & 1];
        let mut weight = 1.0;
        for a in 0..3 {
            weight *= if d[a] == 1 { w[a] } else { 1.0 - w[a] };
        }
        acc += weight * lattice(seed, [i[0] + d[0], i[1] + d[1], i[2] + d[2]]);
    }
    acc
}

impl Material {
    /// Albedo at world position `p`, each channel in [0, 1].
    pub fn albedo(&self, p: [f32; 3]) -> [f32; 3] {
        match *self {
            Material::Plain { color } => color,
            Material::Checker { a, b, size, offset } => {
                let mut parity = 0i64;
                for k in 0..3 {
                    parity += floor((p[k] + offset[k]) / size) as i64;
                }
                if parity & 1 == 0 {
                    a
                } else {
                    b
                }
            }
            Material::Stripes { a, b, period, dir } => {
                let s = p[0] * dir[0] + p[1] * dir[1] + p[2] * dir[2];
                mix(a, b, 0.5 + 0.5 * sin(TAU * s / period))
            }
            Material::Noise { a, b, scale, seed } => {
                let q = p.map(|x| x / scale);
                let q2 = q.map(|x| 2.03 * x + 17.1);
                let n = 0.65 * value_noise(seed, q) + 0.35 * value_noise(seed ^ 0x51ED, q2);
                // The sum concentrates around 0.5: stretch it.
                mix(a, b, ((n - 0.5) * 2.5 + 0.5).clamp(0.0, 1.0))
            }
        }
    }
}

/// A seeded material of `kind`: 0 plain, 1 checker, 2 stripes, 3 noise (textures mix a dark
/// and a light colour, so they always have contrast).
fn random_material(kind: u32, u: &mut dyn FnMut() -> f32) -> Material {
    // Colours with channels in [lo, lo + span).
    let colour = |lo: f32, span: f32, u: &mut dyn FnMut() -> f32| {
        [lo + span * u(), lo + span * u(), lo + span * u()]
    };
    let a = colour(0.05, 0.45, u);
    let b = colour(0.5, 0.45, u);
    match kind {
        0 => Material::Plain {
            color: colour(0.15, 0.8, u),
        },
        1 => Material::Checker {
            a,
            b,
            size: 0.2 + 0.3 * u(),
            offset: [u(), u(), u()].map(|x| 0.05 + 0.9 * x),
        },
        2 => {
            let th = TAU * u();
            let ph = (u() - 0.5) * 2.0;
            Material::Stripes {
                a,
                b,
                period: 0.15 + 0.25 * u(),
                dir: normalize([cos(th), sin(th), ph]),
            }
        }
        _ => Material::Noise {
            a,
            b,
            scale: 0.15 + 0.35 * u(),
            seed: (u() * 16_777_216.0) as u32,
        },
    }
}

/// A box standing in the room.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SceneBox {
    pub min: [f32; 3],
    pub max: [f32; 3],
    pub material: Material,
}

/// A sphere in the room.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Sphere {
    pub center: [f32; 3],
    pub radius: f32,
    pub material: Material,
}

/// The camera path: an ellipse around (0, 0) at `height` (+ `wobble` sin(4 pi s)), looking at
/// (0, 0, `target_height` + `target_amp` sin(4 pi s + `target_phase`)), s in [0, 1) is the
/// fraction of the orbit.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CameraPath {
    pub radii: [f32; 2],
    pub height: f32,
    pub wobble: f32,
    /// Angle of the camera at s = 0 (radians).
    pub phase: f32,
    pub target_height: f32,
    pub target_amp: f32,
    pub target_phase: f32,
}

impl CameraPath {
    /// Camera centre at orbit fraction `s`.
    pub fn eye(&self, s: f32) -> [f32; 3] {
        let a = TAU * s + self.phase;
        [
            self.radii[0] * cos(a),
            self.radii[1] * sin(a),
            self.height + self.wobble * sin(2.0 * TAU * s),
        ]
    }

    /// Camera-to-world pose (OpenCV axes) at orbit fraction `s`, looking at the target with the
    /// world z axis up (no roll).
    pub fn pose(&self, s: f32) -> Pose {
        let eye = self.eye(s);
        let target = [
            0.0,
            0.0,
            self.target_height + self.target_amp * sin(2.0 * TAU * s + self.target_phase),
        ];
        look_pose(eye, normalize(sub(target, eye)))
    }
}

/// A synthetic room scene. Solids are everything outside the room box, the boxes and the
/// spheres; the camera lives in the free space inside the room.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Scene {
    pub room_min: [f32; 3],
    pub room_max: [f32; 3],
    /// Materials of the room faces: x = min, x = max, y = min, y = max, floor, ceiling.
    pub walls: [Material; 6],
    pub boxes: Vec<SceneBox>,
    pub spheres: Vec<Sphere>,
    /// Unit vector pointing towards the (directional) light.
    pub light_dir: [f32; 3],
    /// Ambient fraction of the shading: colour = albedo (ambient + (1 - ambient) max(0, n.l)).
    pub ambient: f32,
    pub path: CameraPath,
}

/// A ray-surface intersection.
#[derive(Clone, Copy, Debug)]
pub struct Hit<'a> {
    /// Ray parameter (camera-z depth for rays from [`Pose::ray`]).
    pub t: f32,
    /// Unit normal, pointing into the free space.
    pub normal: [f32; 3],
    pub material: &'a Material,
}

/// A triangle mesh.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct TriMesh {
    pub vertices: Vec<[f32; 3]>,
    pub triangles: Vec<[u32; 3]>,
}

fn sub(a: [f32; 3], b: [f32; 3]) -> [f32; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

fn dot(a: [f32; 3], b: [f32; 3]) -> f32 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

fn cross(a: [f32; 3], b: [f32; 3]) -> [f32; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

/// The camera-to-world pose at `eye` looking along the unit vector `f`, world z up: x (right)
/// = forward x up, y (down) = forward x right, z = forward (OpenCV axes).
fn look_pose(eye: [f32; 3], f: [f32; 3]) -> Pose {
    let r = normalize(cross(f, [0.0, 0.0, 1.0]));
    let d = cross(f, r);
    Pose {
        m: [
            [r[0], d[0], f[0], eye[0]],
            [r[1], d[1], f[1], eye[1]],
            [r[2], d[2], f[2], eye[2]],
        ],
    }
}

fn normalize(a: [f32; 3]) -> [f32; 3] {
    let n = sqrt(dot(a, a));
    [a[0] / n, a[1] / n, a[2] / n]
}

/// Exact signed distance to an axis-aligned box (negative inside).
pub fn box_sdf(p: [f32; 3], min: [f32; 3], max: [f32; 3]) -> f32 {
    let mut outside = 0.0f32;
    let mut inside = f32::NEG_INFINITY;
    for k in 0..3 {
        let c = 0.5 * (min[k] + max[k]);
        let h = 0.5 * (max[k] - min[k]);
        let q = (p[k] - c).abs() - h;
        let qp = q.max(0.0);
        outside += qp * qp;
        inside = inside.max(q);
    }
    sqrt(outside) + inside.min(0.0)
}

/// Analytic signed distance to the scene's surfaces: positive in the free space inside the
/// room, negative inside solids (the walls' outside, boxes, spheres). Exact in the free space
/// (the minimum of exact distances to the solids), a bound inside solids.
pub fn scene_sdf(scene: &Scene, p: [f32; 3]) -> f32 {
    let mut d = -box_sdf(p, scene.room_min, scene.room_max);
    for b in &scene.boxes {
        d = d.min(box_sdf(p, b.min, b.max));
    }
    for s in &scene.spheres {
        let q = sub(p, s.center);
        d = d.min(sqrt(dot(q, q)) - s.radius);
    }
    d
}

/// Smallest ray parameter accepted as a hit.
const T_MIN: f32 = 1e-4;

impl Scene {
    /// Builds the room for `seed` (deterministic).
    pub fn generate(seed: u64) -> Scene {
        let mut rng = SplitMix::new(seed ^ 0x6A09_E667_F3BC_C908);
        let mut u = move || rng.unit();
        let size = [3.6 + 0.8 * u(), 2.8 + 0.6 * u(), 2.5 + 0.3 * u()];
        let room_min = [-0.5 * size[0], -0.5 * size[1], 0.0];
        let room_max = [0.5 * size[0], 0.5 * size[1], size[2]];
        let path = CameraPath {
            radii: [0.3 * size[0], 0.3 * size[1]],
            height: 1.3 + 0.2 * u(),
            wobble: 0.1,
            phase: TAU * u(),
            target_height: 1.05,
            target_amp: 0.6,
            target_phase: TAU * u(),
        };

        let textured = |kind: u32, u: &mut dyn FnMut() -> f32| random_material(kind, u);
        // Walls: one of each kind in a seeded order; floor textured; ceiling plain.
        let mut kinds = [0u32, 1, 2, 3];
        for i in (1..4).rev() {
            let j = ((u() * (i + 1) as f32) as usize).min(i);
            kinds.swap(i, j);
        }
        let floor_kind = if u() < 0.5 { 1 } else { 3 };
        let walls = [
            textured(kinds[0], &mut u),
            textured(kinds[1], &mut u),
            textured(kinds[2], &mut u),
            textured(kinds[3], &mut u),
            textured(floor_kind, &mut u),
            textured(0, &mut u),
        ];

        let eyes: Vec<[f32; 3]> = (0..256).map(|i| path.eye(i as f32 / 256.0)).collect();
        let n_boxes = 2 + ((u() * 3.0) as usize).min(2);
        let n_spheres = 1 + ((u() * 3.0) as usize).min(2);
        let mut boxes: Vec<SceneBox> = Vec::new();
        let mut tries = 0;
        while boxes.len() < n_boxes && tries < 5000 {
            tries += 1;
            let h = [0.15 + 0.3 * u(), 0.15 + 0.3 * u(), 0.3 + 0.9 * u()];
            let mut c = [0.0; 2];
            for k in 0..2 {
                let lo = room_min[k] + 0.05 + h[k];
                let hi = room_max[k] - 0.05 - h[k];
                c[k] = lo + (hi - lo) * u();
            }
            let min = [c[0] - h[0], c[1] - h[1], 0.0];
            let max = [c[0] + h[0], c[1] + h[1], h[2]];
            let clear = eyes
                .iter()
                .all(|&e| box_sdf(e, min, max) >= CAMERA_CLEARANCE);
            let apart = boxes.iter().all(|o| {
                let gx = (o.min[0] - max[0]).max(min[0] - o.max[0]);
                let gy = (o.min[1] - max[1]).max(min[1] - o.max[1]);
                gx.max(gy) >= 0.1
            });
            if clear && apart {
                let kind = (u() * 4.0) as u32;
                boxes.push(SceneBox {
                    min,
                    max,
                    material: textured(kind.min(3), &mut u),
                });
            }
        }
        let mut spheres: Vec<Sphere> = Vec::new();
        tries = 0;
        while spheres.len() < n_spheres && tries < 5000 {
            tries += 1;
            let r = 0.12 + 0.2 * u();
            let mut c = [0.0; 3];
            for k in 0..2 {
                let lo = room_min[k] + 0.05 + r;
                let hi = room_max[k] - 0.05 - r;
                c[k] = lo + (hi - lo) * u();
            }
            c[2] = r + (1.6 - r) * u();
            if sphere_fits(c, r, &eyes, boxes.iter(), &spheres) {
                let kind = [0, 1, 3][((u() * 3.0) as usize).min(2)];
                spheres.push(Sphere {
                    center: c,
                    radius: r,
                    material: textured(kind, &mut u),
                });
            }
        }
        let light_dir = normalize([0.3 + 0.2 * u(), 0.2 + 0.2 * u(), 1.0]);
        Scene {
            room_min,
            room_max,
            walls,
            boxes,
            spheres,
            light_dir,
            ambient: 0.45,
            path,
        }
    }

    /// The room box (every surface lies in it); use it, with a small margin, as the mapping
    /// bound.
    pub fn bounds(&self) -> Aabb {
        Aabb::new(self.room_min, self.room_max)
    }

    /// Nearest surface hit by the ray o + t d (t > 1e-4; `d` need not be normalised). `None`
    /// when `o` is not strictly inside the room.
    pub fn intersect(&self, o: [f32; 3], d: [f32; 3]) -> Option<Hit<'_>> {
        // Room, from the inside: the first face the ray leaves through.
        let mut best_t = f32::INFINITY;
        let mut best_n = [0.0; 3];
        let mut best_m = &self.walls[0];
        for k in 0..3 {
            if !(o[k] > self.room_min[k] && o[k] < self.room_max[k]) {
                return None;
            }
            let (t, face) = if d[k] > 0.0 {
                ((self.room_max[k] - o[k]) / d[k], 2 * k + 1)
            } else if d[k] < 0.0 {
                ((self.room_min[k] - o[k]) / d[k], 2 * k)
            } else {
                continue;
            };
            if t < best_t {
                best_t = t;
                best_n = [0.0; 3];
                best_n[k] = if d[k] > 0.0 { -1.0 } else { 1.0 };
                best_m = &self.walls[face];
            }
        }
        let solids = self.boxes.iter().map(|b| (b.min, b.max, &b.material));
        let spheres = self
            .spheres
            .iter()
            .map(|s| (s.center, s.radius, &s.material));
        let (best_t, best_n, best_m) =
            nearest_solid(o, d, solids, spheres, (best_t, best_n, Some(best_m)));
        match best_m {
            Some(material) if best_t.is_finite() && best_t > T_MIN => Some(Hit {
                t: best_t,
                normal: best_n,
                material,
            }),
            _ => None,
        }
    }

    /// Shaded colour of a hit of the ray o + t d.
    pub fn shade(&self, o: [f32; 3], d: [f32; 3], hit: &Hit<'_>) -> [f32; 3] {
        let p = [
            o[0] + hit.t * d[0],
            o[1] + hit.t * d[1],
            o[2] + hit.t * d[2],
        ];
        lambert(
            hit.material.albedo(p),
            hit.normal,
            self.light_dir,
            self.ambient,
        )
    }

    /// Renders colour and exact camera-z depth (0 where nothing is hit).
    pub fn render(&self, k: &Intrinsics, pose: &Pose) -> (RgbImage, DepthImage) {
        render_view(k, pose, self.light_dir, self.ambient, |o, d| {
            self.intersect(o, d)
        })
    }

    /// Ground-truth triangle mesh: the inside of the room (normals inward), the boxes (outward;
    /// the bottom face is left out when it stands on the floor) and the spheres tessellated
    /// with `segments` longitudes and `segments / 2` latitudes (outward normals,
    /// counter-clockwise winding seen from the free space).
    pub fn mesh(&self, segments: u32) -> TriMesh {
        let mut m = TriMesh::default();
        add_box(&mut m, self.room_min, self.room_max, true, false);
        for b in &self.boxes {
            let on_floor = b.min[2] <= self.room_min[2] + 1e-6;
            add_box(&mut m, b.min, b.max, false, on_floor);
        }
        for s in &self.spheres {
            add_sphere(&mut m, s.center, s.radius, segments.max(4));
        }
        m
    }
}

/// The nearest hit of `o + t d` (`T_MIN < t < best.0`) on boxes entered from outside and on
/// spheres, over `best` (t, normal into the free space, material).
fn nearest_solid<'a>(
    o: [f32; 3],
    d: [f32; 3],
    boxes: impl Iterator<Item = ([f32; 3], [f32; 3], &'a Material)>,
    spheres: impl Iterator<Item = ([f32; 3], f32, &'a Material)>,
    best: (f32, [f32; 3], Option<&'a Material>),
) -> (f32, [f32; 3], Option<&'a Material>) {
    let (mut best_t, mut best_n, mut best_m) = best;
    for (min, max, material) in boxes {
        let mut t0 = f32::NEG_INFINITY;
        let mut t1 = f32::INFINITY;
        let mut axis = 0;
        let mut ok = true;
        for k in 0..3 {
            if d[k] == 0.0 {
                if o[k] < min[k] || o[k] > max[k] {
                    ok = false;
                    break;
                }
                continue;
            }
            let inv = 1.0 / d[k];
            let (mut ta, mut tb) = ((min[k] - o[k]) * inv, (max[k] - o[k]) * inv);
            if ta > tb {
                core::mem::swap(&mut ta, &mut tb);
            }
            if ta > t0 {
                t0 = ta;
                axis = k;
            }
            t1 = t1.min(tb);
        }
        if ok && t0 <= t1 && t0 > T_MIN && t0 < best_t {
            best_t = t0;
            best_n = [0.0; 3];
            best_n[axis] = if d[axis] > 0.0 { -1.0 } else { 1.0 };
            best_m = Some(material);
        }
    }
    for (center, radius, material) in spheres {
        let oc = sub(o, center);
        let a = dot(d, d);
        let hb = dot(oc, d);
        let c = dot(oc, oc) - radius * radius;
        let disc = hb * hb - a * c;
        if disc < 0.0 {
            continue;
        }
        let t = (-hb - sqrt(disc)) / a;
        if t > T_MIN && t < best_t {
            best_t = t;
            let p = [o[0] + t * d[0], o[1] + t * d[1], o[2] + t * d[2]];
            best_n = normalize(sub(p, center));
            best_m = Some(material);
        }
    }
    (best_t, best_n, best_m)
}

/// Whether a sphere at `c` of radius `r` keeps [`CAMERA_CLEARANCE`] from every camera centre
/// in `eyes` and 0.1 m from every box and sphere already placed.
fn sphere_fits<'a>(
    c: [f32; 3],
    r: f32,
    eyes: &[[f32; 3]],
    mut boxes: impl Iterator<Item = &'a SceneBox>,
    spheres: &[Sphere],
) -> bool {
    let clear = eyes.iter().all(|&e| {
        let q = sub(e, c);
        sqrt(dot(q, q)) - r >= CAMERA_CLEARANCE
    });
    clear
        && boxes.all(|b| box_sdf(c, b.min, b.max) - r >= 0.1)
        && spheres.iter().all(|s| {
            let q = sub(s.center, c);
            sqrt(dot(q, q)) - r - s.radius >= 0.1
        })
}

/// Renders colour (Lambertian, see [`lambert`]) and exact camera-z depth (0 where nothing is
/// hit) of every pixel's ray through `intersect`.
fn render_view<'a>(
    k: &Intrinsics,
    pose: &Pose,
    light_dir: [f32; 3],
    ambient: f32,
    intersect: impl Fn([f32; 3], [f32; 3]) -> Option<Hit<'a>>,
) -> (RgbImage, DepthImage) {
    let mut rgb = RgbImage::new(k.width, k.height);
    let mut depth = DepthImage::new(k.width, k.height);
    for v in 0..k.height {
        for u in 0..k.width {
            let (o, d) = pose.ray(k, u as f32, v as f32);
            if let Some(hit) = intersect(o, d) {
                let i = (v * k.width + u) as usize;
                depth.data[i] = hit.t;
                let p = [
                    o[0] + hit.t * d[0],
                    o[1] + hit.t * d[1],
                    o[2] + hit.t * d[2],
                ];
                let c = lambert(hit.material.albedo(p), hit.normal, light_dir, ambient);
                rgb.data[3 * i..3 * i + 3].copy_from_slice(&c);
            }
        }
    }
    (rgb, depth)
}

/// Lambertian shading of `albedo` with normal `n`: `albedo (ambient + (1 - ambient) max(0, n.l))`.
fn lambert(albedo: [f32; 3], n: [f32; 3], light_dir: [f32; 3], ambient: f32) -> [f32; 3] {
    let s = ambient + (1.0 - ambient) * dot(n, light_dir).max(0.0);
    albedo.map(|a| (a * s).clamp(0.0, 1.0))
}

/// Pushes triangle (a, b, c), reordered so that its normal points along `towards`.
fn push_oriented(m: &mut TriMesh, mut tri: [u32; 3], towards: [f32; 3]) {
    let [a, b, c] = tri.map(|i| m.vertices[i as usize]);
    if dot(cross(sub(b, a), sub(c, a)), towards) < 0.0 {
        tri.swap(1, 2);
    }
    m.triangles.push(tri);
}

fn add_box(m: &mut TriMesh, min: [f32; 3], max: [f32; 3], inward: bool, skip_bottom: bool) {
    for k in 0..3 {
        for side in 0..2 {
            if skip_bottom && k == 2 && side == 0 {
                continue;
            }
            let (b, c) = ((k + 1) % 3, (k + 2) % 3);
            let base = m.vertices.len() as u32;
            for (lb, lc) in [(0, 0), (1, 0), (1, 1), (0, 1)] {
                let mut p = [0.0; 3];
                p[k] = if side == 0 { min[k] } else { max[k] };
                p[b] = if lb == 0 { min[b] } else { max[b] };
                p[c] = if lc == 0 { min[c] } else { max[c] };
                m.vertices.push(p);
            }
            let mut n = [0.0; 3];
            n[k] = if (side == 1) != inward { 1.0 } else { -1.0 };
            push_oriented(m, [base, base + 1, base + 2], n);
            push_oriented(m, [base, base + 2, base + 3], n);
        }
    }
}

fn add_sphere(m: &mut TriMesh, c: [f32; 3], r: f32, segments: u32) {
    let n_lon = segments;
    let n_lat = (segments / 2).max(2);
    let base = m.vertices.len() as u32;
    m.vertices.push([c[0], c[1], c[2] + r]);
    for i in 1..n_lat {
        let th = core::f32::consts::PI * i as f32 / n_lat as f32;
        for j in 0..n_lon {
            let ph = TAU * j as f32 / n_lon as f32;
            m.vertices.push([
                c[0] + r * sin(th) * cos(ph),
                c[1] + r * sin(th) * sin(ph),
                c[2] + r * cos(th),
            ]);
        }
    }
    m.vertices.push([c[0], c[1], c[2] - r]);
    let south = m.vertices.len() as u32 - 1;
    let ring = |i: u32, j: u32| base + 1 + (i - 1) * n_lon + (j % n_lon);
    let out = |m: &TriMesh, t: [u32; 3]| {
        let [a, b, cc] = t.map(|i| m.vertices[i as usize]);
        sub(
            [
                (a[0] + b[0] + cc[0]) / 3.0,
                (a[1] + b[1] + cc[1]) / 3.0,
                (a[2] + b[2] + cc[2]) / 3.0,
            ],
            c,
        )
    };
    for j in 0..n_lon {
        let t = [base, ring(1, j), ring(1, j + 1)];
        let n = out(m, t);
        push_oriented(m, t, n);
        let t = [south, ring(n_lat - 1, j), ring(n_lat - 1, j + 1)];
        let n = out(m, t);
        push_oriented(m, t, n);
        for i in 1..n_lat - 1 {
            let q = [
                ring(i, j),
                ring(i, j + 1),
                ring(i + 1, j + 1),
                ring(i + 1, j),
            ];
            for t in [[q[0], q[1], q[2]], [q[0], q[2], q[3]]] {
                let n = out(m, t);
                push_oriented(m, t, n);
            }
        }
    }
}

impl TriMesh {
    /// Total surface area.
    pub fn area(&self) -> f64 {
        self.triangles
            .iter()
            .map(|t| {
                let [a, b, c] = t.map(|i| self.vertices[i as usize].map(|x| x as f64));
                let u = [b[0] - a[0], b[1] - a[1], b[2] - a[2]];
                let v = [c[0] - a[0], c[1] - a[1], c[2] - a[2]];
                let x = [
                    u[1] * v[2] - u[2] * v[1],
                    u[2] * v[0] - u[0] * v[2],
                    u[0] * v[1] - u[1] * v[0],
                ];
                0.5 * (x[0] * x[0] + x[1] * x[1] + x[2] * x[2]).sqrt()
            })
            .sum()
    }

    /// Writes a binary little-endian PLY (`float x, y, z`; `list uchar int vertex_indices`).
    pub fn write_ply(&self, path: &Path, comment: &str) -> std::io::Result<()> {
        let mut w = std::io::BufWriter::new(std::fs::File::create(path)?);
        write!(
            w,
            "ply\nformat binary_little_endian 1.0\ncomment {}\nelement vertex {}\n\
             property float x\nproperty float y\nproperty float z\nelement face {}\n\
             property list uchar int vertex_indices\nend_header\n",
            comment.replace('\n', " "),
            self.vertices.len(),
            self.triangles.len()
        )?;
        for v in &self.vertices {
            for x in v {
                w.write_all(&x.to_le_bytes())?;
            }
        }
        for t in &self.triangles {
            w.write_all(&[3u8])?;
            for &i in t {
                w.write_all(&(i as i32).to_le_bytes())?;
            }
        }
        w.flush()
    }
}

/// Options of [`write_synthetic`].
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(default)]
pub struct SynthOptions {
    /// Number of frames (one orbit of the room over the sequence).
    pub frames: usize,
    pub width: u32,
    pub height: u32,
    /// Scene and path seed.
    pub seed: u64,
}

impl Default for SynthOptions {
    fn default() -> Self {
        Self {
            frames: 60,
            width: 160,
            height: 120,
            seed: 0,
        }
    }
}

/// What [`write_synthetic`] wrote.
#[derive(Clone, Debug)]
pub struct SynthSummary {
    pub out: PathBuf,
    pub frames: usize,
    pub intrinsics: Intrinsics,
    /// The room box (see [`Scene::bounds`]).
    pub scene_box: Aabb,
    pub scene: Scene,
    /// Camera-to-world pose of every frame (as written to `traj.txt`).
    pub poses: Vec<Pose>,
    /// Triangles in `gt_mesh.ply`.
    pub mesh_triangles: usize,
}

/// Camera of a synthetic sequence: square pixels, [`HFOV_DEG`] horizontally, centred
/// (cx = (w - 1) / 2, cy = (h - 1) / 2).
pub fn synth_intrinsics(width: u32, height: u32) -> Intrinsics {
    // tan(35 degrees).
    let f = 0.5 * width as f32 / 0.700_207_5;
    Intrinsics {
        width,
        height,
        fx: f,
        fy: f,
        cx: 0.5 * (width as f32 - 1.0),
        cy: 0.5 * (height as f32 - 1.0),
    }
}

/// Pose of frame `i` of `frames` (orbit fraction i / frames).
pub fn synth_pose(scene: &Scene, i: usize, frames: usize) -> Pose {
    scene.path.pose(i as f32 / frames.max(1) as f32)
}

#[derive(Serialize)]
struct SceneFile<'a> {
    seed: u64,
    frames: usize,
    width: u32,
    height: u32,
    scene_box: SceneBoxJson,
    scene: &'a Scene,
}

#[derive(Serialize, Deserialize)]
struct SceneBoxJson {
    min: [f32; 3],
    max: [f32; 3],
}

/// Reads `scene.json` written by [`write_synthetic`]: the scene and its box.
pub fn read_scene_json(path: &Path) -> anyhow::Result<(Scene, Aabb)> {
    #[derive(Deserialize)]
    struct File {
        scene_box: SceneBoxJson,
        scene: Scene,
    }
    let text =
        std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
    let f: File =
        serde_json::from_str(&text).with_context(|| format!("parsing {}", path.display()))?;
    Ok((f.scene, Aabb::new(f.scene_box.min, f.scene_box.max)))
}

/// Writes a posed sequence in the Replica layout: `results/frame%06d.png` and
/// `depth%06d.png` of `render(pose)` for every pose (in parallel), `traj.txt` and
/// `cam_params.json`.
fn write_sequence(
    out: &Path,
    k: &Intrinsics,
    poses: &[Pose],
    render: impl Fn(&Pose) -> (RgbImage, DepthImage) + Sync,
) -> anyhow::Result<()> {
    let results = out.join("results");
    std::fs::create_dir_all(&results).with_context(|| format!("creating {}", results.display()))?;
    (0..poses.len())
        .into_par_iter()
        .try_for_each(|i| -> anyhow::Result<()> {
            let (rgb, depth) = render(&poses[i]);
            let rgb8 = rgb.to_rgb8();
            let depth16: Vec<u16> = depth
                .data
                .iter()
                .map(|&t| {
                    let v = t * REPLICA_DEPTH_SCALE + 0.5;
                    if t > 0.0 && v < DEPTH_INVALID as f32 {
                        v as u16
                    } else {
                        0
                    }
                })
                .collect();
            let fp = results.join(format!("frame{i:06}.png"));
            image::save_buffer(
                &fp,
                &rgb8,
                k.width,
                k.height,
                image::ExtendedColorType::Rgb8,
            )
            .with_context(|| format!("writing {}", fp.display()))?;
            let dp = results.join(format!("depth{i:06}.png"));
            let img = image::ImageBuffer::<image::Luma<u16>, Vec<u16>>::from_raw(
                k.width, k.height, depth16,
            )
            .context("depth buffer size")?;
            img.save(&dp)
                .with_context(|| format!("writing {}", dp.display()))?;
            Ok(())
        })?;

    let mut traj = String::new();
    for p in poses {
        let mut vals: Vec<String> = Vec::with_capacity(16);
        for row in &p.m {
            for x in row {
                vals.push(format!("{x:.9e}"));
            }
        }
        for x in [0.0f32, 0.0, 0.0, 1.0] {
            vals.push(format!("{x:.9e}"));
        }
        traj.push_str(&vals.join(" "));
        traj.push('\n');
    }
    let tp = out.join("traj.txt");
    std::fs::write(&tp, traj).with_context(|| format!("writing {}", tp.display()))?;

    let cam = serde_json::json!({
        "camera": {
            "w": k.width, "h": k.height, "fx": k.fx, "fy": k.fy, "cx": k.cx, "cy": k.cy,
            "scale": REPLICA_DEPTH_SCALE,
        }
    });
    let cp = out.join("cam_params.json");
    std::fs::write(&cp, serde_json::to_string_pretty(&cam)?)
        .with_context(|| format!("writing {}", cp.display()))?;
    Ok(())
}

/// Renders a synthetic sequence for `opts.seed` into `out` (created if needed) in the Replica
/// layout, with `gt_mesh.ply` and `scene.json` (see the module documentation).
pub fn write_synthetic(out: &Path, opts: &SynthOptions) -> anyhow::Result<SynthSummary> {
    if opts.frames == 0 {
        bail!("synthetic sequence needs at least one frame");
    }
    if opts.width < 2 || opts.height < 2 || opts.width > 16384 || opts.height > 16384 {
        bail!(
            "synthetic image size {}x{} is out of range (2..=16384)",
            opts.width,
            opts.height
        );
    }
    let scene = Scene::generate(opts.seed);
    let k = synth_intrinsics(opts.width, opts.height);
    let poses: Vec<Pose> = (0..opts.frames)
        .map(|i| synth_pose(&scene, i, opts.frames))
        .collect();
    write_sequence(out, &k, &poses, |p| scene.render(&k, p))?;

    let mesh = scene.mesh(SPHERE_SEGMENTS);
    let mp = out.join("gt_mesh.ply");
    mesh.write_ply(&mp, &format!("himap synthetic room, seed {}", opts.seed))
        .with_context(|| format!("writing {}", mp.display()))?;

    let bounds = scene.bounds();
    let file = SceneFile {
        seed: opts.seed,
        frames: opts.frames,
        width: opts.width,
        height: opts.height,
        scene_box: SceneBoxJson {
            min: bounds.min,
            max: bounds.max,
        },
        scene: &scene,
    };
    let sp = out.join("scene.json");
    std::fs::write(&sp, serde_json::to_string_pretty(&file)?)
        .with_context(|| format!("writing {}", sp.display()))?;

    Ok(SynthSummary {
        out: out.to_path_buf(),
        frames: opts.frames,
        intrinsics: k,
        scene_box: bounds,
        scene,
        poses,
        mesh_triangles: mesh.triangles.len(),
    })
}

pub mod house;

#[cfg(test)]
mod tests;
