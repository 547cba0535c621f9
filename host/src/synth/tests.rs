//! Tests of the synthetic scenes: hand-computed renders and distances, agreement between the
//! ray caster, the SDF and the mesh, determinism, and a round trip through the Replica loader.

use std::path::Path;

use himap_core::camera::{Intrinsics, Pose};

use super::*;
use crate::dataset::{self, LoadOptions};

fn plain(c: f32) -> Material {
    Material::Plain { color: [c; 3] }
}

/// Room [-2, 2] x [-1.5, 1.5] x [0, 2.6], plain walls with grey levels 0.1 .. 0.6, light from
/// straight above, ambient 0.35, no objects.
fn hand_scene() -> Scene {
    Scene {
        room_min: [-2.0, -1.5, 0.0],
        room_max: [2.0, 1.5, 2.6],
        walls: [
            plain(0.1),
            plain(0.2),
            plain(0.3),
            plain(0.4),
            plain(0.5),
            plain(0.6),
        ],
        boxes: vec![],
        spheres: vec![],
        light_dir: [0.0, 0.0, 1.0],
        ambient: 0.35,
        path: Scene::generate(0).path,
    }
}

/// Camera at (0, 0, 1) looking along +x: right = -y, down = -z.
fn looking_along_x() -> Pose {
    Pose {
        m: [
            [0.0, 0.0, 1.0, 0.0],
            [-1.0, 0.0, 0.0, 0.0],
            [0.0, -1.0, 0.0, 1.0],
        ],
    }
}

#[test]
fn render_hand_values() {
    let scene = hand_scene();
    let k = Intrinsics {
        width: 101,
        height: 101,
        fx: 25.0,
        fy: 25.0,
        cx: 50.0,
        cy: 50.0,
    };
    let pose = looking_along_x();
    assert!(pose.is_rigid(1e-6));
    let (rgb, depth) = scene.render(&k, &pose);
    // Centre: the x = 2 wall at depth 2; its normal (-1, 0, 0) is perpendicular to the light,
    // so only the ambient term: 0.35 * 0.2.
    assert_eq!(depth.get(50, 50), 2.0);
    assert!((rgb.get(50, 50)[0] - 0.35 * 0.2).abs() < 1e-6);
    // Pixel (0, 50): camera direction (-2, 0, 1) -> world (1, 2, 0); y reaches 1.5 at t = 0.75
    // (before x reaches 2 at t = 2): the y = max wall (0.4), ambient only.
    assert!((depth.get(0, 50) - 0.75).abs() < 1e-6);
    assert!((rgb.get(0, 50)[1] - 0.35 * 0.4).abs() < 1e-6);
    // Pixel (50, 100): camera (0, 2, 1) -> world (1, 0, -2): the floor z = 0 at t = 0.5, lit
    // head-on (n.l = 1): full albedo 0.5.
    assert!((depth.get(50, 100) - 0.5).abs() < 1e-6);
    assert!((rgb.get(50, 100)[2] - 0.5).abs() < 1e-6);
    // Pixel (50, 0): camera (0, -2, 1) -> world (1, 0, 2): the ceiling z = 2.6 at t = 0.8,
    // facing away from the light: ambient only, 0.35 * 0.6.
    assert!((depth.get(50, 0) - 0.8).abs() < 1e-6);
    assert!((rgb.get(50, 0)[0] - 0.35 * 0.6).abs() < 1e-6);

    // A sphere of radius 0.5 at (1.5, 0, 1): the ray from (0, 0, 1) along +x hits it at
    // t = 1.0 with normal (-1, 0, 0). A thin box at x in [0.8, 0.9] in front of it is nearer:
    // t = 0.8.
    let mut scene = hand_scene();
    scene.spheres.push(Sphere {
        center: [1.5, 0.0, 1.0],
        radius: 0.5,
        material: plain(0.9),
    });
    let hit = scene.intersect([0.0, 0.0, 1.0], [1.0, 0.0, 0.0]).unwrap();
    assert!((hit.t - 1.0).abs() < 1e-6);
    assert!((hit.normal[0] + 1.0).abs() < 1e-6);
    scene.boxes.push(SceneBox {
        min: [0.8, -0.1, 0.0],
        max: [0.9, 0.1, 2.0],
        material: plain(0.7),
    });
    let hit = scene.intersect([0.0, 0.0, 1.0], [1.0, 0.0, 0.0]).unwrap();
    assert!((hit.t - 0.8).abs() < 1e-6);
    assert_eq!(hit.normal, [-1.0, 0.0, 0.0]);
    assert_eq!(*hit.material, plain(0.7));
    // Rays from outside the room hit nothing.
    assert!(scene.intersect([3.0, 0.0, 1.0], [-1.0, 0.0, 0.0]).is_none());
}

#[test]
fn sdf_hand_values() {
    let mut scene = hand_scene();
    // Empty room: distance to the nearest wall.
    assert_eq!(scene_sdf(&scene, [0.0, 0.0, 1.0]), 1.0); // floor at 1.0
    assert_eq!(scene_sdf(&scene, [1.5, 0.0, 1.3]), 0.5); // x = 2 wall
    assert!((scene_sdf(&scene, [0.0, 0.0, 2.9]) + 0.3).abs() < 1e-6); // above the ceiling
                                                                      // Outside a corner: -(distance to the corner) = -sqrt(0.3^2 + 0.4^2) = -0.5.
    assert!((scene_sdf(&scene, [2.3, 1.9, 1.0]) + 0.5).abs() < 1e-6);
    scene.spheres.push(Sphere {
        center: [1.0, 0.0, 1.0],
        radius: 0.25,
        material: plain(0.5),
    });
    assert_eq!(scene_sdf(&scene, [0.0, 0.0, 1.0]), 0.75);
    assert_eq!(scene_sdf(&scene, [1.0, 0.0, 1.0]), -0.25);
    scene.boxes.push(SceneBox {
        min: [-0.5, 0.5, 0.0],
        max: [0.5, 1.0, 1.0],
        material: plain(0.5),
    });
    // (0, 0, 0.5): 0.5 from the box's y = 0.5 face and from the floor.
    assert_eq!(scene_sdf(&scene, [0.0, 0.0, 0.5]), 0.5);
    // (0, 0.1, 0.6): box face 0.4 away.
    assert!((scene_sdf(&scene, [0.0, 0.1, 0.6]) - 0.4).abs() < 1e-6);
    // Diagonal from the box edge (0.5, 0.5, 1.0) + (0.3, -0.4, 0.0): 0.5.
    assert!((box_sdf([0.8, 0.1, 1.0], [-0.5, 0.5, 0.0], [0.5, 1.0, 1.0]) - 0.5).abs() < 1e-6);
}

#[test]
fn generated_scenes_are_well_formed() {
    for seed in 0..30 {
        let s = Scene::generate(seed);
        let ext = s.bounds().extent();
        assert!((3.6..=4.4).contains(&ext[0]) && (2.8..=3.4).contains(&ext[1]));
        assert!((2.5..=2.8).contains(&ext[2]));
        assert!(
            (2..=4).contains(&s.boxes.len()),
            "seed {seed}: {} boxes",
            s.boxes.len()
        );
        assert!((1..=3).contains(&s.spheres.len()), "seed {seed}");
        // Textureless and textured surfaces both present.
        let plain_walls = s
            .walls
            .iter()
            .filter(|m| matches!(m, Material::Plain { .. }))
            .count();
        // One of the four walls and the ceiling.
        assert_eq!(plain_walls, 2, "seed {seed}");
        for b in &s.boxes {
            for k in 0..3 {
                assert!(b.min[k] >= s.room_min[k] && b.max[k] <= s.room_max[k]);
            }
        }
        for sp in &s.spheres {
            for k in 0..3 {
                assert!(sp.center[k] - sp.radius >= s.room_min[k]);
                assert!(sp.center[k] + sp.radius <= s.room_max[k]);
            }
        }
        // The camera path keeps its distance from every surface and moves smoothly.
        let poses: Vec<Pose> = (0..60).map(|i| synth_pose(&s, i, 60)).collect();
        for (i, p) in poses.iter().enumerate() {
            assert!(p.is_rigid(1e-5));
            let d = scene_sdf(&s, p.origin());
            assert!(d >= CAMERA_CLEARANCE - 1e-3, "seed {seed} frame {i}: {d}");
            if i > 0 {
                let a = poses[i - 1].origin();
                let b = p.origin();
                let step =
                    ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt();
                assert!(step < 0.2, "seed {seed} frame {i}: step {step}");
            }
        }
    }
    assert_ne!(Scene::generate(1), Scene::generate(2));
    assert_eq!(Scene::generate(5), Scene::generate(5));
}

/// Sphere tracing with the SDF along pixel rays gives the ray caster's depth.
#[test]
fn sdf_agrees_with_ray_casting() {
    for seed in [0u64, 3, 11] {
        let scene = Scene::generate(seed);
        let k = synth_intrinsics(64, 48);
        for f in [0usize, 17, 41] {
            let pose = synth_pose(&scene, f, 60);
            let (_, depth) = scene.render(&k, &pose);
            for v in (0..48).step_by(3) {
                for u in (0..64).step_by(3) {
                    let z = depth.get(u, v);
                    assert!(z > 0.0, "every ray hits the closed room");
                    let (o, d) = pose.ray(&k, u as f32, v as f32);
                    let len = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
                    // March in units of t (the SDF is a distance along the unit direction).
                    let mut t = 0.0f32;
                    for _ in 0..400 {
                        let p = [o[0] + t * d[0], o[1] + t * d[1], o[2] + t * d[2]];
                        let s = scene_sdf(&scene, p);
                        if s < 1e-5 {
                            break;
                        }
                        t += s / len;
                    }
                    assert!(
                        (t - z).abs() < 1e-3 * z.max(1.0),
                        "seed {seed} frame {f} pixel ({u}, {v}): sdf {t} vs cast {z}"
                    );
                    let hit = [o[0] + z * d[0], o[1] + z * d[1], o[2] + z * d[2]];
                    assert!(scene_sdf(&scene, hit).abs() < 2e-5);
                }
            }
        }
    }
}

/// The SDF has unit gradient in the free space (central differences, h = 1e-3, in f64 of f32
/// evaluations; away from the medial axes where the nearest surface switches).
#[test]
fn sdf_has_unit_gradient() {
    let scene = Scene::generate(4);
    let mut rng = himap_core::rng::SplitMix::new(9);
    let h = 1e-3f32;
    let (mut n, mut good) = (0, 0);
    while n < 2000 {
        let p = [0, 1, 2]
            .map(|k| scene.room_min[k] + (scene.room_max[k] - scene.room_min[k]) * rng.unit());
        let s = scene_sdf(&scene, p);
        if s < 0.02 {
            continue;
        }
        n += 1;
        let mut g2 = 0.0f64;
        for k in 0..3 {
            let (mut a, mut b) = (p, p);
            a[k] += h;
            b[k] -= h;
            let g = (scene_sdf(&scene, a) as f64 - scene_sdf(&scene, b) as f64) / (2.0 * h as f64);
            g2 += g * g;
        }
        if (g2.sqrt() - 1.0).abs() < 1e-2 {
            good += 1;
        }
    }
    assert!(good >= 1900, "{good} of {n} points with |grad| = 1");
}

/// Per-primitive signed distance (free space positive) and normal-side check for the mesh test.
fn primitive_distances(scene: &Scene, p: [f32; 3]) -> Vec<f32> {
    let mut d = vec![-box_sdf(p, scene.room_min, scene.room_max)];
    d.extend(scene.boxes.iter().map(|b| box_sdf(p, b.min, b.max)));
    d.extend(scene.spheres.iter().map(|s| {
        let q = [p[0] - s.center[0], p[1] - s.center[1], p[2] - s.center[2]];
        (q[0] * q[0] + q[1] * q[1] + q[2] * q[2]).sqrt() - s.radius
    }));
    d
}

#[test]
fn mesh_lies_on_the_surfaces_facing_free_space() {
    let scene = Scene::generate(2);
    let mesh = scene.mesh(SPHERE_SEGMENTS);
    for v in &mesh.vertices {
        let d = primitive_distances(&scene, *v);
        assert!(
            d.iter().any(|x| x.abs() < 1e-5),
            "vertex {v:?} off every surface"
        );
    }
    for t in &mesh.triangles {
        let [a, b, c] = t.map(|i| mesh.vertices[i as usize]);
        let centroid = [0, 1, 2].map(|k| (a[k] + b[k] + c[k]) / 3.0);
        let e1 = [0, 1, 2].map(|k| b[k] - a[k]);
        let e2 = [0, 1, 2].map(|k| c[k] - a[k]);
        let n = [
            e1[1] * e2[2] - e1[2] * e2[1],
            e1[2] * e2[0] - e1[0] * e2[2],
            e1[0] * e2[1] - e1[1] * e2[0],
        ];
        let len = (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt();
        let off = [0, 1, 2].map(|k| centroid[k] + 5e-3 * n[k] / len);
        let dc = primitive_distances(&scene, centroid);
        let doff = primitive_distances(&scene, off);
        // Some primitive has the centroid on its surface (within the sphere chord error) and
        // the normal pointing to its outside.
        assert!(
            dc.iter()
                .zip(&doff)
                .any(|(c, o)| c.abs() < 1e-3 && *o > 4e-3),
            "triangle {t:?} not on a surface facing free space"
        );
    }
    // Area: room inside + boxes without their bottoms + spheres (the tessellation is slightly
    // smaller than 4 pi r^2: chords of pi / 32 rad in both directions lose about
    // 2 * (pi / 32)^2 / 6 ~ 0.3 %; allow 0.5 %).
    let e = scene.bounds().extent().map(|x| x as f64);
    let mut area = 2.0 * (e[0] * e[1] + e[0] * e[2] + e[1] * e[2]);
    for b in &scene.boxes {
        let s = [0, 1, 2].map(|k| (b.max[k] - b.min[k]) as f64);
        area += s[0] * s[1] + 2.0 * (s[0] * s[2] + s[1] * s[2]);
    }
    let sphere_area: f64 = scene
        .spheres
        .iter()
        .map(|s| 4.0 * std::f64::consts::PI * (s.radius as f64).powi(2))
        .sum();
    let got = mesh.area();
    assert!(got <= area + sphere_area + 1e-6);
    assert!(
        got >= area + 0.995 * sphere_area,
        "{got} vs {}",
        area + sphere_area
    );
}

fn read_all(dir: &Path) -> Vec<(String, Vec<u8>)> {
    let mut out = Vec::new();
    for sub in ["", "results"] {
        let mut names: Vec<_> = std::fs::read_dir(dir.join(sub))
            .unwrap()
            .map(|e| e.unwrap().path())
            .filter(|p| p.is_file())
            .collect();
        names.sort();
        for p in names {
            let rel = p.strip_prefix(dir).unwrap().display().to_string();
            out.push((rel, std::fs::read(&p).unwrap()));
        }
    }
    out
}

#[test]
fn deterministic_for_a_seed() {
    let opts = SynthOptions {
        frames: 6,
        width: 48,
        height: 36,
        seed: 7,
    };
    let (a, b, c) = (
        tempfile::tempdir().unwrap(),
        tempfile::tempdir().unwrap(),
        tempfile::tempdir().unwrap(),
    );
    write_synthetic(a.path(), &opts).unwrap();
    write_synthetic(b.path(), &opts).unwrap();
    write_synthetic(c.path(), &SynthOptions { seed: 8, ..opts }).unwrap();
    let (fa, fb, fc) = (read_all(a.path()), read_all(b.path()), read_all(c.path()));
    // 6 colour + 6 depth + traj, cam_params, gt_mesh, scene.
    assert_eq!(fa.len(), 16);
    assert_eq!(fa, fb);
    let names: Vec<_> = fa.iter().map(|f| f.0.clone()).collect();
    assert_eq!(names, fc.iter().map(|f| f.0.clone()).collect::<Vec<_>>());
    for (x, y) in fa.iter().zip(&fc) {
        if x.0 != "cam_params.json" {
            assert_ne!(x.1, y.1, "{} is the same for seeds 7 and 8", x.0);
        }
    }
}

#[test]
fn loads_through_replica_loader_and_reprojects() {
    let dir = tempfile::tempdir().unwrap();
    let summary = write_synthetic(dir.path(), &SynthOptions::default()).unwrap();
    assert_eq!(summary.frames, 60);
    let ds = dataset::open(dir.path(), &LoadOptions::default()).unwrap();
    assert_eq!(ds.len(), 60);
    assert!(ds.has_depth());
    let k = ds.intrinsics();
    assert_eq!(k, summary.intrinsics);
    assert_eq!((k.width, k.height, k.cx, k.cy), (160, 120, 79.5, 59.5));
    // 70 degrees: 2 atan(80 / fx).
    let hfov = 2.0 * (80.0 / k.fx as f64).atan();
    assert!((hfov.to_degrees() - 70.0).abs() < 1e-3);
    let frames: Vec<_> = (0..60).map(|i| ds.frame(i).unwrap()).collect();
    for (i, f) in frames.iter().enumerate() {
        assert_eq!(f.pose, summary.poses[i]);
        let d = f.depth.as_ref().unwrap();
        assert!(d.data.iter().all(|&z| z > 0.3 && z < 6.0), "frame {i}");
        // Depth exact up to the 16-bit quantisation (1 / 6553.5 m).
        let (_, exact) = summary.scene.render(&k, &f.pose);
        for (a, b) in d.data.iter().zip(&exact.data) {
            assert!((a - b).abs() <= 0.5 / 6553.5 + 1e-6);
        }
    }
    // Colour images are not flat.
    let rgb = &frames[0].rgb;
    let mean = rgb.data.iter().sum::<f32>() / rgb.data.len() as f32;
    let var = rgb.data.iter().map(|x| (x - mean).powi(2)).sum::<f32>() / rgb.data.len() as f32;
    assert!(var > 1e-3, "variance {var}");
    for (a, b) in [(0, 1), (0, 5), (10, 20), (30, 33), (59, 0)] {
        let (dz, n) = dataset::reprojection_median_dz(&frames[a], &frames[b]).unwrap();
        assert!(n > 2000, "{a} -> {b}: {n} pixels");
        assert!(dz < 1e-3, "{a} -> {b}: median |dz| {dz}");
    }
    // scene.json reads back.
    let (scene, bounds) = read_scene_json(&dir.path().join("scene.json")).unwrap();
    assert_eq!(scene, summary.scene);
    assert_eq!(bounds, summary.scene_box);
}

#[test]
fn ply_reads_back() {
    let dir = tempfile::tempdir().unwrap();
    let scene = Scene::generate(3);
    let mesh = scene.mesh(16);
    let path = dir.path().join("m.ply");
    mesh.write_ply(&path, "test").unwrap();
    let mut f = std::io::BufReader::new(std::fs::File::open(&path).unwrap());
    let ply = ply_rs::parser::Parser::<ply_rs::ply::DefaultElement>::new()
        .read_ply(&mut f)
        .unwrap();
    let verts = &ply.payload["vertex"];
    let faces = &ply.payload["face"];
    assert_eq!(verts.len(), mesh.vertices.len());
    assert_eq!(faces.len(), mesh.triangles.len());
    for (e, v) in verts.iter().zip(&mesh.vertices) {
        for (k, name) in ["x", "y", "z"].iter().enumerate() {
            assert_eq!(e[*name], ply_rs::ply::Property::Float(v[k]));
        }
    }
    for (e, t) in faces.iter().zip(&mesh.triangles) {
        assert_eq!(
            e["vertex_indices"],
            ply_rs::ply::Property::ListInt(t.iter().map(|&i| i as i32).collect())
        );
    }
}

#[test]
fn bad_options_are_errors() {
    let dir = tempfile::tempdir().unwrap();
    let o = SynthOptions {
        frames: 0,
        ..Default::default()
    };
    assert!(write_synthetic(dir.path(), &o).is_err());
    let o = SynthOptions {
        width: 1,
        ..Default::default()
    };
    assert!(write_synthetic(dir.path(), &o).is_err());
}
