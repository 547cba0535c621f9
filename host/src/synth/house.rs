//! A larger synthetic scene (#11.4): a house of connected rooms in a row with doors, furniture,
//! textured and plain surfaces, and a camera path of at least 25 m from one end to the other.
//!
//! World z is up, the floor's top at z = 0. Rooms `0..n` lie along +x, each `lengths[i]` long
//! (x) and `width` wide (y, from 0), `height` high, separated by walls [`WALL`] thick with one
//! door each ([`DOOR_WIDTH`] x [`DOOR_HEIGHT`]). Everything solid is an axis-aligned box (slabs,
//! walls, wall pieces around the doors, furniture) or a sphere, so rays are cast exactly. The
//! camera walks from the west room to the east room on a path that swings across each room
//! (`y = width / 2 + amplitude sin(2 pi cycles s)`), at about 1.35 m, its view swinging left and
//! right of the walking direction and pitching up and down; it starts looking back at the west
//! wall, and in every later room it turns round once to look back at the wall it came
//! through (so that the frames see most of the house: 84-90 % of the ground-truth mesh's
//! area on seeds 0-5, against 75-88 % for a walk that only looks ahead,
//! [`House::seen_share`]; the hall's walk looks ahead, [`HouseKind::looks_back`]).
//! Doors sit where the path crosses the walls, and furniture keeps
//! [`super::CAMERA_CLEARANCE`] from the path.
//!
//! The ground-truth mesh holds only the surfaces one can see from inside: every box face is
//! cut along every other solid's faces and into squares of at most [`MESH_CELL`], and a piece is
//! kept when the point 1 cm in front of its centre is free space inside the house (not in a
//! solid, not outside the outer walls).
//!
//! All arithmetic is `f32` with `himap-core`'s math, so a seed gives the same files
//! everywhere. Output of [`write_house`]: the Replica layout of [`super::write_synthetic`]
//! (`results/`, `traj.txt`, `cam_params.json`, `gt_mesh.ply`) and `house.json` (the scene and
//! the path length), but no `scene.json`: the house gives no scene box, so mapping it uses the
//! default box around the first camera, as a robot would.

use std::path::Path;

use anyhow::{bail, Context};
use himap_core::camera::{Intrinsics, Pose};
use himap_core::math::{cos, sin, sqrt};
use himap_core::rng::SplitMix;
use serde::{Deserialize, Serialize};

use super::{
    dot, look_pose, nearest_solid, normalize, push_oriented, sub, synth_intrinsics, write_sequence,
    Material, SceneBox, Sphere, TriMesh, CAMERA_CLEARANCE,
};
use crate::dataset::{DepthImage, RgbImage};

/// Wall and slab thickness (m).
pub const WALL: f32 = 0.15;
/// Door opening (m).
pub const DOOR_WIDTH: f32 = 1.2;
pub const DOOR_HEIGHT: f32 = 2.1;
/// Side of the squares of the ground-truth mesh (m).
pub const MESH_CELL: f32 = 0.1;
/// Shortest camera path (m).
pub const MIN_PATH_M: f32 = 25.0;
/// The walk's looks back ([`HousePath::look_back`], `look_width`, `look_at`): a turn of 160
/// degrees in each room after the first, centred at 35 % of the room, over a tenth of the walk
/// on either side (at most about 7 degrees per frame at 360 frames, as fast as the view's
/// swing).
pub const LOOK_BACK: f32 = 2.8;
pub const LOOK_WIDTH: f32 = 0.1;
pub const LOOK_AT: f32 = 0.35;

const TAU: f32 = core::f32::consts::TAU;
const PI: f32 = core::f32::consts::PI;

/// The walk through the house (see the module documentation); s in [0, 1].
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct HousePath {
    /// The house's room lengths and door centres (the walk goes through them).
    pub lengths: Vec<f32>,
    pub doors: Vec<f32>,
    pub x0: f32,
    pub x1: f32,
    pub y_center: f32,
    pub amplitude: f32,
    pub cycles: f32,
    pub height: f32,
    /// Swing of the view around the walking direction (radians) and its cycles over the walk.
    pub yaw_amp: f32,
    pub yaw_cycles: f32,
    /// Pitch: centre, amplitude (radians) and cycles.
    pub pitch_center: f32,
    pub pitch_amp: f32,
    pub pitch_cycles: f32,
    /// Fraction of the walk over which the initial backward look turns to the front.
    pub turn: f32,
    /// Looks back: in each room after the first, at `look_at` of the room's length, the view
    /// turns by `look_back` radians (alternately left and right) and back, over `look_width`
    /// of the walk on either side, so that the walk also sees the faces turned against its
    /// direction (the wall it came through, the furniture's backs). 0 = none (the walk of
    /// the sessions before the looks back; `house.json` files without these fields).
    #[serde(default)]
    pub look_back: f32,
    #[serde(default)]
    pub look_width: f32,
    #[serde(default)]
    pub look_at: f32,
}

impl HousePath {
    /// Room `i` with `x` in its extent (or the wall after it) and the fraction `u` of the room
    /// at `x` (clamped to [0, 1]).
    fn room_at(&self, x: f32) -> (usize, f32) {
        let mut xa = 0.0;
        for (i, &l) in self.lengths.iter().enumerate() {
            if x < xa + l + WALL || i + 1 == self.lengths.len() {
                return (i, ((x - xa) / l).clamp(0.0, 1.0));
            }
            xa += l + WALL;
        }
        (0, 0.0)
    }

    /// Camera centre at `s`: x goes from `x0` to `x1`; y follows the straight line through the
    /// doors and swings across each room with `cycles` periods, the swing fading to zero (and
    /// flat) at the walls, so the walk passes every door straight on.
    pub fn eye(&self, s: f32) -> [f32; 3] {
        let x = self.x0 + (self.x1 - self.x0) * s;
        let (i, u) = self.room_at(x);
        // The line through the doors: from the centre at the west end to door 0, ...
        let mut knots_x = vec![self.x0];
        let mut knots_y = vec![self.y_center];
        let mut xa = 0.0;
        for (j, &d) in self.doors.iter().enumerate() {
            xa += self.lengths[j];
            knots_x.push(xa + 0.5 * WALL);
            knots_y.push(d);
            xa += WALL;
        }
        knots_x.push(self.x1);
        knots_y.push(self.y_center);
        let mut base = self.y_center;
        for j in 0..knots_x.len() - 1 {
            if x >= knots_x[j] && x <= knots_x[j + 1] {
                let f = (x - knots_x[j]) / (knots_x[j + 1] - knots_x[j]);
                base = knots_y[j] + (knots_y[j + 1] - knots_y[j]) * f;
            }
        }
        let env = sin(PI * u);
        let y = base + self.amplitude * env * env * sin(TAU * self.cycles * u);
        let _ = i;
        [x, y, self.height + 0.08 * sin(TAU * 3.0 * s)]
    }

    /// Walking direction in the floor plane (unit), by a central difference.
    fn tangent(&self, s: f32) -> [f32; 2] {
        let h = 1e-3;
        let (a, b) = (self.eye((s - h).max(0.0)), self.eye((s + h).min(1.0)));
        let (dx, dy) = (b[0] - a[0], b[1] - a[1]);
        let n = sqrt(dx * dx + dy * dy);
        [dx / n, dy / n]
    }

    /// Camera-to-world pose (OpenCV axes, no roll) at `s`.
    pub fn pose(&self, s: f32) -> Pose {
        let eye = self.eye(s);
        let t = self.tangent(s);
        let back = if s < self.turn {
            let a = 1.0 - s / self.turn;
            PI * a * a * (3.0 - 2.0 * a)
        } else {
            0.0
        };
        let (look, side) = self.look(s);
        let yaw = self.yaw_amp * sin(TAU * self.yaw_cycles * s) * (1.0 - look)
            + back
            + side * self.look_back * look;
        let (cy, sy) = (cos(yaw), sin(yaw));
        let h = [cy * t[0] - sy * t[1], sy * t[0] + cy * t[1]];
        let p = self.pitch_center + self.pitch_amp * sin(TAU * self.pitch_cycles * s + 1.0);
        let (cp, sp) = (cos(p), sin(p));
        look_pose(eye, [cp * h[0], cp * h[1], sp])
    }

    /// How far the view has turned into a look back at `s` (0..1, a raised cosine around the
    /// middle of each room after the first) and to which side (+1 or -1).
    fn look(&self, s: f32) -> (f32, f32) {
        if self.look_back == 0.0 || self.look_width <= 0.0 {
            return (0.0, 1.0);
        }
        for i in 1..self.lengths.len() {
            let x = room_start(&self.lengths, i) + self.look_at * self.lengths[i];
            let c = (x - self.x0) / (self.x1 - self.x0);
            let t = (s - c) / self.look_width;
            if t.abs() < 1.0 {
                let side = if i % 2 == 1 { 1.0 } else { -1.0 };
                return (0.5 + 0.5 * cos(PI * t), side);
            }
        }
        (0.0, 1.0)
    }

    /// Length of the walk (m), summed over `steps` chords.
    pub fn length(&self, steps: usize) -> f32 {
        let mut l = 0.0;
        let mut prev = self.eye(0.0);
        for i in 1..=steps {
            let e = self.eye(i as f32 / steps as f32);
            let q = sub(e, prev);
            l += sqrt(dot(q, q));
            prev = e;
        }
        l
    }
}

/// The layouts [`House::generate_kind`] builds.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "lowercase")]
pub enum HouseKind {
    /// Three rooms of 3.5-4 x 4.2-4.8 m (at most 12.3 m long: the default 24 m box around the
    /// first camera holds it; views reach beyond 6 m only through the doors).
    #[default]
    Rooms,
    /// Two halls of 8-9 x 7.5-8.5 m, 2.8-3.2 m high, joined by a door: most views reach
    /// beyond `model.max_depth`'s 6 m, and the walk (about 17 m from end to end) leaves the
    /// default box, which grows ([`crate::grow`]).
    Hall,
}

/// A base and a span (m): a value drawn as `base + span * u`.
type Range = (f32, f32);

impl HouseKind {
    /// Rooms, and the ranges of the room lengths, the width and the height.
    fn shape(self) -> (usize, Range, Range, Range) {
        match self {
            HouseKind::Rooms => (3, (3.5, 0.5), (4.2, 0.6), (2.5, 0.2)),
            HouseKind::Hall => (2, (8.0, 1.0), (7.5, 1.0), (2.8, 0.4)),
        }
    }

    /// Whether the walk turns round in the later rooms: the rooms' does (it would miss a
    /// quarter of the house otherwise); the halls' frames already see 83 % of theirs from
    /// the walk looking ahead (a look back added one point and cost the mesh's completion).
    fn looks_back(self) -> bool {
        self == HouseKind::Rooms
    }

    /// Seeds the random stream (the rooms' salt keeps the houses of earlier sessions).
    fn salt(self) -> u64 {
        match self {
            HouseKind::Rooms => 0x4F1B_BCDC_BFA5_3E0B,
            HouseKind::Hall => 0x9E37_79B9_7F4A_7C15,
        }
    }
}

/// The house: its solids, the free interior, materials and the walk.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct House {
    /// Room lengths along x; every room spans y in [0, width], z in [0, height].
    pub lengths: Vec<f32>,
    pub width: f32,
    pub height: f32,
    /// Every solid box: slabs, walls, wall pieces around the doors, furniture.
    pub solids: Vec<SceneBox>,
    pub spheres: Vec<Sphere>,
    /// Door centres (y) in the walls between rooms i and i + 1.
    pub doors: Vec<f32>,
    pub light_dir: [f32; 3],
    pub ambient: f32,
    pub path: HousePath,
}

fn inside(p: [f32; 3], min: [f32; 3], max: [f32; 3]) -> bool {
    (0..3).all(|k| p[k] > min[k] && p[k] < max[k])
}

fn box_sdf(p: [f32; 3], b: &SceneBox) -> f32 {
    super::box_sdf(p, b.min, b.max)
}

impl House {
    /// The interior (free space and furniture) box: x from 0 to the east wall.
    pub fn interior(&self) -> ([f32; 3], [f32; 3]) {
        let x = house_length(&self.lengths);
        ([0.0, 0.0, 0.0], [x, self.width, self.height])
    }

    /// Builds the house for `seed` (deterministic).
    pub fn generate(seed: u64) -> House {
        Self::generate_kind(seed, HouseKind::Rooms)
    }

    /// Builds the house of `kind` for `seed` (deterministic).
    pub fn generate_kind(seed: u64, kind: HouseKind) -> House {
        let mut rng = SplitMix::new(seed ^ kind.salt());
        let mut unit = move || rng.unit();
        let u: &mut dyn FnMut() -> f32 = &mut unit;
        let (n, len, wid, hgt) = kind.shape();
        let lengths: Vec<f32> = (0..n).map(|_| len.0 + len.1 * u()).collect();
        let width = wid.0 + wid.1 * u();
        let height = hgt.0 + hgt.1 * u();
        let doors: Vec<f32> = (0..n - 1)
            .map(|_| 0.5 * width + 0.8 * (u() - 0.5))
            .collect();
        let path = walk(&lengths, &doors, width, kind.looks_back(), u);
        let eyes: Vec<[f32; 3]> = (0..1024).map(|i| path.eye(i as f32 / 1023.0)).collect();
        let mut solids = shell(&lengths, &doors, width, height, u);
        let structure = solids.len();
        let mut spheres: Vec<Sphere> = Vec::new();
        for i in 0..n {
            let xa = room_start(&lengths, i);
            let room = (xa, lengths[i], width);
            furnish_room(room, &eyes, structure, &mut solids, &mut spheres, u);
        }
        let light_dir = normalize([0.3 + 0.2 * u(), 0.2 + 0.2 * u(), 1.0]);
        House {
            lengths,
            width,
            height,
            solids,
            spheres,
            doors,
            light_dir,
            ambient: 0.45,
            path,
        }
    }

    /// Whether `p` is free space inside the house.
    pub fn is_free(&self, p: [f32; 3]) -> bool {
        let (lo, hi) = self.interior();
        if !inside(p, lo, hi) {
            return false;
        }
        !self.solids.iter().any(|b| inside(p, b.min, b.max))
            && !self.spheres.iter().any(|s| {
                let q = sub(p, s.center);
                dot(q, q) < s.radius * s.radius
            })
    }

    /// Nearest surface hit by the ray `o + t d` (t > 1e-4) from free space.
    pub fn intersect(&self, o: [f32; 3], d: [f32; 3]) -> Option<super::Hit<'_>> {
        let solids = self.solids.iter().map(|b| (b.min, b.max, &b.material));
        let spheres = self
            .spheres
            .iter()
            .map(|s| (s.center, s.radius, &s.material));
        let (t, normal, material) =
            nearest_solid(o, d, solids, spheres, (f32::INFINITY, [0.0; 3], None));
        Some(super::Hit {
            t,
            normal,
            material: material?,
        })
    }

    /// The share of the ground-truth mesh's area that the views see: a triangle counts as seen
    /// when its centroid projects into some view (`k`, `poses`) in front of the camera and the
    /// ray to it hits nothing more than 3 cm closer (the frustum-and-occlusion rule of the
    /// peers' culling, on exact geometry). With a walk that sees most of its house, the whole
    /// mesh and the observed one ask nearly the same of a reconstruction.
    pub fn seen_share(&self, mesh: &TriMesh, k: &Intrinsics, poses: &[Pose]) -> f64 {
        let (mut seen, mut all) = (0.0f64, 0.0f64);
        for t in &mesh.triangles {
            let [a, b, c] = t.map(|i| mesh.vertices[i as usize]);
            let u = sub(b, a);
            let v = sub(c, a);
            let x = [
                u[1] * v[2] - u[2] * v[1],
                u[2] * v[0] - u[0] * v[2],
                u[0] * v[1] - u[1] * v[0],
            ];
            let area = 0.5 * (dot(x, x) as f64).sqrt();
            all += area;
            let g = [0, 1, 2].map(|i| (a[i] + b[i] + c[i]) / 3.0);
            let visible = poses.iter().any(|pose| {
                let (pu, pv, z) = k.project(pose.inverse_transform(g));
                if z <= 1e-3
                    || !(0.0..k.width as f32 - 0.5).contains(&(pu + 0.5))
                    || !(0.0..k.height as f32 - 0.5).contains(&(pv + 0.5))
                {
                    return false;
                }
                let o = pose.origin();
                let d = sub(g, o);
                let dist = sqrt(dot(d, d));
                let dir = d.map(|e| e / dist);
                self.intersect(o, dir).is_none_or(|h| h.t >= dist - 0.03)
            });
            if visible {
                seen += area;
            }
        }
        if all > 0.0 {
            seen / all
        } else {
            0.0
        }
    }

    /// Renders colour and exact camera-z depth (0 where nothing is hit).
    pub fn render(&self, k: &Intrinsics, pose: &Pose) -> (RgbImage, DepthImage) {
        super::render_view(k, pose, self.light_dir, self.ambient, |o, d| {
            self.intersect(o, d)
        })
    }

    /// The visible surfaces (see the module documentation): box faces in squares of about
    /// [`MESH_CELL`] whose front is free space, and the spheres (64 longitudes).
    pub fn mesh(&self) -> TriMesh {
        let mut m = TriMesh::default();
        // Split coordinates along an axis within [lo, hi]: every solid's faces (so that each
        // piece is entirely seen or entirely hidden), then at most MESH_CELL apart.
        let cuts = |a: usize, lo: f32, hi: f32| -> Vec<f32> {
            let mut c: Vec<f32> = vec![lo, hi];
            for o in &self.solids {
                for x in [o.min[a], o.max[a]] {
                    if x > lo && x < hi {
                        c.push(x);
                    }
                }
            }
            c.sort_by(f32::total_cmp);
            c.dedup();
            let mut out = vec![lo];
            for w in c.windows(2) {
                let n = (((w[1] - w[0]) / MESH_CELL).ceil() as usize).max(1);
                for i in 1..=n {
                    out.push(if i == n {
                        w[1]
                    } else {
                        w[0] + (w[1] - w[0]) * i as f32 / n as f32
                    });
                }
            }
            out
        };
        for b in &self.solids {
            for k in 0..3 {
                let (a1, a2) = ((k + 1) % 3, (k + 2) % 3);
                let c1 = cuts(a1, b.min[a1], b.max[a1]);
                let c2 = cuts(a2, b.min[a2], b.max[a2]);
                for side in 0..2 {
                    let mut normal = [0.0; 3];
                    normal[k] = if side == 0 { -1.0 } else { 1.0 };
                    let plane = if side == 0 { b.min[k] } else { b.max[k] };
                    for i in 0..c1.len() - 1 {
                        for j in 0..c2.len() - 1 {
                            let at = |ii: usize, jj: usize| {
                                let mut p = [0.0; 3];
                                p[k] = plane;
                                p[a1] = c1[ii];
                                p[a2] = c2[jj];
                                p
                            };
                            let (p0, p2) = (at(i, j), at(i + 1, j + 1));
                            let mut c = [0.0; 3];
                            for a in 0..3 {
                                c[a] = 0.5 * (p0[a] + p2[a]) + 0.01 * normal[a];
                            }
                            if !self.is_free(c) {
                                continue;
                            }
                            let base = m.vertices.len() as u32;
                            m.vertices.extend([p0, at(i + 1, j), p2, at(i, j + 1)]);
                            push_oriented(&mut m, [base, base + 1, base + 2], normal);
                            push_oriented(&mut m, [base, base + 2, base + 3], normal);
                        }
                    }
                }
            }
        }
        for s in &self.spheres {
            super::add_sphere(&mut m, s.center, s.radius, super::SPHERE_SEGMENTS);
        }
        m
    }
}

/// Options of [`write_house`].
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct HouseOptions {
    pub frames: usize,
    pub width: u32,
    pub height: u32,
    pub seed: u64,
    pub kind: HouseKind,
}

/// What [`write_house`] wrote.
#[derive(Clone, Debug)]
pub struct HouseSummary {
    pub frames: usize,
    pub intrinsics: Intrinsics,
    pub house: House,
    pub poses: Vec<Pose>,
    pub path_m: f32,
    pub mesh_triangles: usize,
    /// [`House::seen_share`] of every 2nd written frame.
    pub mesh_seen_share: f64,
}

#[derive(Serialize)]
struct HouseFile<'a> {
    seed: u64,
    kind: HouseKind,
    frames: usize,
    width: u32,
    height: u32,
    path_length_m: f32,
    /// [`House::seen_share`] of the written frames (every 2nd, as the peers cull).
    mesh_seen_share: f64,
    house: &'a House,
}

/// Renders the house sequence for `opts.seed` into `out` (see the module documentation).
pub fn write_house(out: &Path, opts: &HouseOptions) -> anyhow::Result<HouseSummary> {
    if opts.frames < 2 {
        bail!("the house sequence needs at least two frames");
    }
    let house = House::generate_kind(opts.seed, opts.kind);
    let k = synth_intrinsics(opts.width, opts.height);
    let poses: Vec<Pose> = (0..opts.frames)
        .map(|i| house.path.pose(i as f32 / (opts.frames - 1) as f32))
        .collect();
    write_sequence(out, &k, &poses, |p| house.render(&k, p))?;
    let mesh = house.mesh();
    let mp = out.join("gt_mesh.ply");
    mesh.write_ply(&mp, &format!("himap synthetic house, seed {}", opts.seed))
        .with_context(|| format!("writing {}", mp.display()))?;
    let path_m = house.path.length(4096);
    let every_2nd: Vec<Pose> = poses.iter().step_by(2).copied().collect();
    let seen = house.seen_share(&mesh, &k, &every_2nd);
    let file = HouseFile {
        seed: opts.seed,
        kind: opts.kind,
        frames: opts.frames,
        width: opts.width,
        height: opts.height,
        path_length_m: path_m,
        mesh_seen_share: seen,
        house: &house,
    };
    let hp = out.join("house.json");
    std::fs::write(&hp, serde_json::to_string_pretty(&file)?)
        .with_context(|| format!("writing {}", hp.display()))?;
    Ok(HouseSummary {
        frames: opts.frames,
        intrinsics: k,
        mesh_triangles: mesh.triangles.len(),
        mesh_seen_share: seen,
        house,
        poses,
        path_m,
    })
}

/// Where room `i` starts along x (the rooms before it and their walls).
fn room_start(lengths: &[f32], i: usize) -> f32 {
    lengths[..i].iter().sum::<f32>() + WALL * i as f32
}

/// The house's inner length along x (every room and the walls between them).
fn house_length(lengths: &[f32]) -> f32 {
    lengths.iter().sum::<f32>() + WALL * (lengths.len() - 1) as f32
}

/// The walk: swings across the rooms through the doors, with enough cycles for
/// `MIN_PATH_M`.
fn walk(
    lengths: &[f32],
    doors: &[f32],
    width: f32,
    look_back: bool,
    u: &mut dyn FnMut() -> f32,
) -> HousePath {
    let total = house_length(lengths);
    let mut path = HousePath {
        lengths: lengths.to_vec(),
        doors: doors.to_vec(),
        x0: 0.7,
        x1: total - 0.7,
        y_center: 0.5 * width,
        amplitude: 0.5 * width - 0.6 - 0.4 - 0.1,
        cycles: 1.5,
        height: 1.3 + 0.1 * u(),
        yaw_amp: 0.75,
        yaw_cycles: 9.0 + 2.0 * u(),
        pitch_center: -0.2,
        pitch_amp: 0.3,
        pitch_cycles: 7.0 + 2.0 * u(),
        turn: 0.06,
        look_back: if look_back { LOOK_BACK } else { 0.0 },
        look_width: LOOK_WIDTH,
        look_at: LOOK_AT,
    };
    while path.length(4096) < MIN_PATH_M + 1.0 && path.cycles < 8.0 {
        path.cycles += 0.5;
    }
    path
}

/// The structure: ceiling, each room's floor, south and north walls (one plain and one
/// textured in a seeded order), the west end wall, and the walls between rooms with their
/// doors.
fn shell(
    lengths: &[f32],
    doors: &[f32],
    w: f32,
    h: f32,
    u: &mut dyn FnMut() -> f32,
) -> Vec<SceneBox> {
    let n = lengths.len();
    let t = WALL;
    let x1 = house_length(lengths);
    let mut solids = Vec::new();
    let plain_ceiling = super::random_material(0, u);
    solids.push(SceneBox {
        min: [-t, -t, h],
        max: [x1 + t, w + t, h + t],
        material: plain_ceiling,
    });
    for i in 0..n {
        let xa = room_start(lengths, i);
        let xb = xa + lengths[i];
        let floor_kind = if u() < 0.5 { 1 } else { 3 };
        solids.push(SceneBox {
            min: [if i == 0 { -t } else { xa - t }, -t, -t],
            max: [if i + 1 == n { xb + t } else { xb }, w + t, 0.0],
            material: super::random_material(floor_kind, u),
        });
        let plain_south = u() < 0.5;
        let kinds = if plain_south {
            [0, 1 + (u() * 3.0) as u32 % 3]
        } else {
            [1 + (u() * 3.0) as u32 % 3, 0]
        };
        solids.push(SceneBox {
            min: [xa, -t, 0.0],
            max: [xb, 0.0, h],
            material: super::random_material(kinds[0], u),
        });
        solids.push(SceneBox {
            min: [xa, w, 0.0],
            max: [xb, w + t, h],
            material: super::random_material(kinds[1], u),
        });
        if i == 0 {
            let kind = 1 + (u() * 3.0) as u32 % 3;
            solids.push(SceneBox {
                min: [-t, -t, 0.0],
                max: [0.0, w + t, h],
                material: super::random_material(kind, u),
            });
        }
        let kind = 1 + (u() * 3.0) as u32 % 3;
        let wall_mat = super::random_material(kind, u);
        if i + 1 == n {
            solids.push(SceneBox {
                min: [xb, -t, 0.0],
                max: [xb + t, w + t, h],
                material: wall_mat,
            });
        } else {
            // The wall to the next room with a door where the walk crosses it.
            let yd = doors[i];
            let (y0, y1) = (yd - 0.5 * DOOR_WIDTH, yd + 0.5 * DOOR_WIDTH);
            for (min, max) in [
                ([xb, 0.0, 0.0], [xb + t, y0, h]),
                ([xb, y1, 0.0], [xb + t, w, h]),
                ([xb, y0, DOOR_HEIGHT], [xb + t, y1, h]),
            ] {
                solids.push(SceneBox {
                    min,
                    max,
                    material: wall_mat.clone(),
                });
            }
        }
    }
    solids
}

/// Furniture of the room `(x start, length, width)`: 2 or 3 boxes and 0 to 2 spheres, clear
/// of the walk (`eyes`) and apart from the furniture so far (`solids[structure..]`).
fn furnish_room(
    (xa, len, w): (f32, f32, f32),
    eyes: &[[f32; 3]],
    structure: usize,
    solids: &mut Vec<SceneBox>,
    spheres: &mut Vec<Sphere>,
    u: &mut dyn FnMut() -> f32,
) {
    let xb = xa + len;
    let want_boxes = 2 + ((u() * 2.0) as usize).min(1);
    let want_spheres = ((u() * 3.0) as usize).min(2);
    let (mut nb, mut tries) = (0, 0);
    while nb < want_boxes && tries < 4000 {
        tries += 1;
        let hx = 0.2 + 0.4 * u();
        let hy = 0.2 + 0.4 * u();
        let hz = 0.35 + 0.6 * u();
        // Half the boxes stand against the south or north wall.
        let cx = xa + 0.05 + hx + (len - 0.1 - 2.0 * hx) * u();
        let cy = match (u() * 3.0) as u32 {
            0 => hy,
            1 => w - hy,
            _ => 0.05 + hy + (w - 0.1 - 2.0 * hy) * u(),
        };
        let b = SceneBox {
            min: [cx - hx, cy - hy, 0.0],
            max: [cx + hx, cy + hy, hz],
            material: Material::Plain { color: [0.0; 3] },
        };
        let clear = eyes.iter().all(|&e| box_sdf(e, &b) >= CAMERA_CLEARANCE);
        let apart = solids[structure..].iter().all(|o: &SceneBox| {
            let gx = (o.min[0] - b.max[0]).max(b.min[0] - o.max[0]);
            let gy = (o.min[1] - b.max[1]).max(b.min[1] - o.max[1]);
            gx.max(gy) >= 0.15
        });
        if clear && apart && b.min[0] > xa && b.max[0] < xb {
            let kind = ((u() * 4.0) as u32).min(3);
            solids.push(SceneBox {
                material: super::random_material(kind, u),
                ..b
            });
            nb += 1;
        }
    }
    let (mut ns, mut tries) = (0, 0);
    while ns < want_spheres && tries < 4000 {
        tries += 1;
        let r = 0.15 + 0.2 * u();
        let c = [
            xa + 0.1 + r + (len - 0.2 - 2.0 * r) * u(),
            0.1 + r + (w - 0.2 - 2.0 * r) * u(),
            r + (1.4 - r) * u(),
        ];
        if super::sphere_fits(c, r, eyes, solids[structure..].iter(), spheres) {
            let kind = [0, 1, 3][((u() * 3.0) as usize).min(2)];
            spheres.push(Sphere {
                center: c,
                radius: r,
                material: super::random_material(kind, u),
            });
            ns += 1;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_walk_is_long_free_and_crosses_every_door() {
        let kinds = [HouseKind::Rooms, HouseKind::Hall];
        for (seed, kind) in (0..4).flat_map(|s| kinds.map(|k| (s, k))) {
            let h = House::generate_kind(seed, kind);
            assert!(h.path.length(4096) >= MIN_PATH_M, "seed {seed}");
            assert_eq!(h.doors.len(), h.lengths.len() - 1);
            let (lo, hi) = h.interior();
            // from one end to the other
            assert!(h.path.eye(0.0)[0] < lo[0] + 1.0 && h.path.eye(1.0)[0] > hi[0] - 1.0);
            for i in 0..=2000 {
                let e = h.path.eye(i as f32 / 2000.0);
                assert!(h.is_free(e), "seed {seed}: camera in a solid at {e:?}");
                // never closer than 0.3 m to a solid (door jambs included)
                for d in [
                    [0.3, 0.0, 0.0],
                    [-0.3, 0.0, 0.0],
                    [0.0, 0.3, 0.0],
                    [0.0, -0.3, 0.0],
                ] {
                    let q = [e[0] + d[0], e[1] + d[1], e[2]];
                    assert!(h.is_free(q), "seed {seed}: {q:?} next to the path is solid");
                }
            }
            // at least two boxes of furniture per room
            let n = h.lengths.len();
            assert!(
                h.solids.len() >= 1 + 3 * n + 1 + 3 * (n - 1) + 2 * n,
                "seed {seed}"
            );
        }
    }

    #[test]
    fn renders_agree_with_the_geometry_and_the_mesh_is_only_visible_faces() {
        let h = House::generate(1);
        let k = synth_intrinsics(32, 24);
        for i in 0..5 {
            let pose = h.path.pose(i as f32 / 4.0);
            let (rgb, depth) = h.render(&k, &pose);
            assert!(depth.data.iter().all(|&d| d > 0.05 && d < 20.0));
            assert!(rgb.data.iter().all(|c| (0.0..=1.0).contains(c)));
            // the hit point is on a surface: just before it free, just after it not
            for (j, &d) in depth.data.iter().enumerate().step_by(37) {
                let (u, v) = ((j % 32) as f32, (j / 32) as f32);
                let (o, dir) = pose.ray(&k, u, v);
                let at = |t: f32| [o[0] + t * dir[0], o[1] + t * dir[1], o[2] + t * dir[2]];
                assert!(h.is_free(at(d * 0.99)));
                assert!(!h.is_free(at(d * 1.01 + 0.002)));
            }
        }
        let m = h.mesh();
        assert!(m.triangles.len() > 1000);
        // every mesh vertex lies on the border of the free space (some free point within 2 cm)
        for v in m.vertices.iter().step_by(97) {
            // (corners and edges: probe the 8 diagonal directions)
            let near_free = (0..8).any(|c| {
                let d = [0, 1, 2].map(|a| if c >> a & 1 == 1 { 0.02 } else { -0.02 });
                h.is_free([v[0] + d[0], v[1] + d[1], v[2] + d[2]])
            });
            assert!(near_free, "{v:?}");
        }
        // The visible area: the floor, walls and ceiling of every room are there, the
        // outside of the house is not (floor + ceiling >= 2 x the floor area, total below the
        // area of every box face).
        let (lo, hi) = h.interior();
        let floor = ((hi[0] - lo[0]) * (hi[1] - lo[1])) as f64;
        assert!(m.area() > 2.0 * floor * 0.95, "{} vs {floor}", m.area());
        let all: f64 = h
            .solids
            .iter()
            .map(|b| {
                let e = [0, 1, 2].map(|a| (b.max[a] - b.min[a]) as f64);
                2.0 * (e[0] * e[1] + e[1] * e[2] + e[0] * e[2])
            })
            .sum();
        assert!(m.area() < 0.7 * all);
    }

    #[test]
    fn the_walk_looks_back_and_sees_nearly_all_of_the_ground_truth_mesh() {
        // Every 4th of 360 frames at 40x30: the views overlap, so this is close to what every
        // 2nd frame at full size sees.
        let k = synth_intrinsics(40, 30);
        for seed in [0, 3, 5] {
            let h = House::generate(seed);
            let poses = |h: &House| -> Vec<Pose> {
                (0..360)
                    .step_by(4)
                    .map(|i| h.path.pose(i as f32 / 359.0))
                    .collect()
            };
            let mesh = h.mesh();
            let share = h.seen_share(&mesh, &k, &poses(&h));
            assert!(share > 0.85, "seed {seed}: {share}");
            // Looking only ahead leaves the walls the walk came through unseen.
            let mut ahead = h.clone();
            ahead.path.look_back = 0.0;
            let share_ahead = ahead.seen_share(&mesh, &k, &poses(&ahead));
            assert!(
                share_ahead + 0.03 < share,
                "seed {seed}: {share_ahead} vs {share}"
            );
            // In the middle of a look back the view faces west (-x), the way the walk came.
            let x = room_start(&h.lengths, 1) + LOOK_AT * h.lengths[1];
            let s = (x - h.path.x0) / (h.path.x1 - h.path.x0);
            let forward = h.path.pose(s).rotate([0.0, 0.0, 1.0]);
            assert!(forward[0] < -0.2, "seed {seed}: {forward:?}");
            // and seen_share is not trivially 1: the first view alone sees a small part.
            let first = h.seen_share(&mesh, &k, &poses(&h)[..1]);
            assert!(first < 0.3, "{first}");
        }
    }

    #[test]
    fn same_seed_same_house() {
        assert_eq!(House::generate(5), House::generate(5));
        assert_ne!(House::generate(5), House::generate(6));
        let h = House::generate(5);
        assert_eq!(h.path.pose(0.37).m, House::generate(5).path.pose(0.37).m);
        // The rooms' stream is the one of earlier sessions; the hall is another house.
        assert_eq!(House::generate_kind(5, HouseKind::Rooms), h);
        assert_ne!(House::generate_kind(5, HouseKind::Hall), h);
    }

    #[test]
    fn the_hall_is_larger_than_the_default_depth_limit() {
        // Halls 8-9 m long and 7.5-8.5 m wide: a good share of what the walk sees lies
        // beyond 6 m (what the hall is for), and the walk is longer than the default box's
        // half width (12 m), so mapping it grows the box.
        let h = House::generate_kind(2, HouseKind::Hall);
        let (lo, hi) = h.interior();
        assert!(hi[0] - lo[0] > 16.0 && hi[1] - lo[1] >= 7.5);
        let k = synth_intrinsics(32, 24);
        let (mut far, mut all) = (0, 0);
        for i in 0..20 {
            let (_, depth) = h.render(&k, &h.path.pose(i as f32 / 19.0));
            all += depth.data.len();
            far += depth.data.iter().filter(|&&d| d > 6.0).count();
        }
        assert!(far * 10 > all, "{far} of {all} beyond 6 m");
        assert!(h.path.eye(1.0)[0] - h.path.eye(0.0)[0] > 12.0);
    }
}
