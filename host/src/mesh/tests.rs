use std::collections::HashMap;

use super::*;

/// Checks that the mesh is a closed, consistently oriented 2-manifold: every directed edge
/// appears exactly once and its reverse exactly once (so every undirected edge has exactly
/// two faces). Returns the number of edges that violate it (0 = watertight).
fn bad_edges(m: &Mesh) -> usize {
    let mut directed: HashMap<(u32, u32), usize> = HashMap::new();
    for f in &m.faces {
        for e in 0..3 {
            *directed.entry((f[e], f[(e + 1) % 3])).or_default() += 1;
        }
    }
    directed
        .iter()
        .filter(|(&(a, b), &n)| n != 1 || directed.get(&(b, a)).copied() != Some(1))
        .count()
}

fn sphere_grid(n: usize, h: f32, r: f32) -> (Vec<f32>, [f32; 3]) {
    let o = -(n as f32 - 1.0) * 0.5 * h;
    let mut v = Vec::with_capacity(n * n * n);
    for k in 0..n {
        for j in 0..n {
            for i in 0..n {
                let p = [o + h * i as f32, o + h * j as f32, o + h * k as f32];
                v.push((p[0] * p[0] + p[1] * p[1] + p[2] * p[2]).sqrt() - r);
            }
        }
    }
    (v, [o; 3])
}

#[test]
fn marching_cubes_sphere_is_accurate_closed_and_outward() {
    let (n, h, r) = (36usize, 0.04f32, 0.5f32);
    let (vals, o) = sphere_grid(n, h, r);
    let m = marching_cubes([n; 3], o, h, &vals, 0.0);
    assert!(m.faces.len() > 1000);
    // Vertices lie on grid edges at the linearly interpolated root: |r - R| << spacing.
    let worst = m
        .vertices
        .iter()
        .map(|p| ((p[0] * p[0] + p[1] * p[1] + p[2] * p[2]).sqrt() - r).abs())
        .fold(0.0f32, f32::max);
    assert!(worst < 0.1 * h, "worst radial error {worst}");
    assert_eq!(bad_edges(&m), 0, "sphere mesh is not watertight");
    // Area and volume within 2% of the sphere's (an inscribed polyhedron: slightly less).
    let area = m.area();
    let exact_a = 4.0 * std::f64::consts::PI * (r as f64).powi(2);
    assert!(
        (area / exact_a - 1.0).abs() < 0.02,
        "area {area} vs {exact_a}"
    );
    let vol = m.signed_volume();
    let exact_v = 4.0 / 3.0 * std::f64::consts::PI * (r as f64).powi(3);
    // Positive: normals point outwards (towards positive SDF).
    assert!(
        (vol / exact_v - 1.0).abs() < 0.02,
        "volume {vol} vs {exact_v}"
    );
    // Each face normal points away from the centre.
    for f in 0..m.faces.len() {
        let [a, b, c] = m.triangle(f).map(|p| p.map(|x| x as f64));
        let nrm = cross(sub(b, a), sub(c, a));
        let centroid = [0, 1, 2].map(|k| (a[k] + b[k] + c[k]) / 3.0);
        assert!(dot(nrm, centroid) > 0.0, "face {f} points inwards");
    }
}

#[test]
fn marching_cubes_shares_one_vertex_per_cut_edge() {
    let (n, h, r) = (14usize, 0.1f32, 0.45f32);
    let (vals, o) = sphere_grid(n, h, r);
    let m = marching_cubes([n; 3], o, h, &vals, 0.0);
    let idx = |i: usize, j: usize, k: usize| vals[(k * n + j) * n + i];
    let mut cut = 0;
    for k in 0..n {
        for j in 0..n {
            for i in 0..n {
                let a = idx(i, j, k) < 0.0;
                if i + 1 < n && a != (idx(i + 1, j, k) < 0.0) {
                    cut += 1;
                }
                if j + 1 < n && a != (idx(i, j + 1, k) < 0.0) {
                    cut += 1;
                }
                if k + 1 < n && a != (idx(i, j, k + 1) < 0.0) {
                    cut += 1;
                }
            }
        }
    }
    assert_eq!(m.vertices.len(), cut);
    // A closed genus-0 surface: V - E + F = 2 with E = 3F/2.
    assert_eq!(2 * m.vertices.len() as i64 - m.faces.len() as i64, 4);
}

#[test]
fn marching_cubes_random_fields_are_watertight() {
    // Random values exercise every case, ambiguous faces included; a positive border makes
    // the surface closed, so any inconsistency between neighbouring cubes shows as a bad edge.
    let n = 12;
    for seed in 0..20u64 {
        let mut vals = vec![0.0f32; n * n * n];
        for k in 0..n {
            for j in 0..n {
                for i in 0..n {
                    let border = [i, j, k].iter().any(|&c| c == 0 || c == n - 1);
                    let id = ((k * n + j) * n + i) as u64;
                    vals[(k * n + j) * n + i] = if border {
                        1.0
                    } else {
                        unit_f64(seed, id, 0) as f32 - 0.5
                    };
                }
            }
        }
        let m = marching_cubes([n; 3], [0.0; 3], 1.0, &vals, 0.0);
        assert!(m.faces.len() > 100);
        assert_eq!(bad_edges(&m), 0, "seed {seed}");
        // Closed surfaces around inside regions with outward normals: positive volume.
        assert!(m.signed_volume() > 0.0);
    }
    // The 256 single-cube cases: a 4x4x4 grid with the cube's 8 corners in the middle and a
    // positive border; every case must give a closed, consistently oriented surface.
    for case in 0..256usize {
        let mut vals = vec![1.0f32; 64];
        for (c, off) in CORNER_OFFSETS.iter().enumerate() {
            if case >> c & 1 == 1 {
                vals[((off[2] + 1) * 4 + off[1] + 1) * 4 + off[0] + 1] = -1.0;
            }
        }
        let m = marching_cubes([4; 3], [0.0; 3], 1.0, &vals, 0.0);
        assert_eq!(bad_edges(&m), 0, "case {case}");
        assert_eq!(m.faces.is_empty(), case == 0, "case {case}");
    }
}

const CORNER_OFFSETS: [[usize; 3]; 8] = tables::CORNERS;

#[test]
fn marching_cubes_skips_nan_cubes_and_handles_tiny_grids() {
    let (n, h, r) = (10usize, 0.1f32, 0.3f32);
    let (mut vals, o) = sphere_grid(n, h, r);
    let full = marching_cubes([n; 3], o, h, &vals, 0.0);
    // A NaN at a grid vertex just outside the surface removes the 8 cubes around it.
    let (i, j, k) = (5, 5, 8); // (0.05, 0.05, 0.35): |p| = 0.357, SDF 0.057
    vals[(k * n + j) * n + i] = f32::NAN;
    let holed = marching_cubes([n; 3], o, h, &vals, 0.0);
    assert!(holed.faces.len() < full.faces.len());
    assert!(bad_edges(&holed) > 0, "a hole must leave boundary edges");
    assert!(holed
        .vertices
        .iter()
        .all(|p| p.iter().all(|x| x.is_finite())));
    // Degenerate grids give empty meshes.
    assert!(marching_cubes([1, 5, 5], [0.0; 3], 1.0, &[-1.0; 25], 0.0)
        .faces
        .is_empty());
    assert!(marching_cubes([0, 0, 0], [0.0; 3], 1.0, &[], 0.0)
        .faces
        .is_empty());
}

#[test]
fn iso_level_and_interpolation_are_exact_on_a_linear_field() {
    // f(x, y, z) = x on a 3x3x3 grid with spacing 0.5 from the origin: the iso level 0.3 is the
    // plane x = 0.3; every vertex has x = 0.3 exactly (t = 0.3 / 0.5 = 0.6 on [0, 0.5]), the
    // plane is 1 x 1 so the area is 1, and normals point towards +x (increasing values).
    let mut vals = Vec::new();
    for _k in 0..3 {
        for _j in 0..3 {
            for i in 0..3 {
                vals.push(0.5 * i as f32);
            }
        }
    }
    let m = marching_cubes([3; 3], [0.0; 3], 0.5, &vals, 0.3);
    assert_eq!(m.vertices.len(), 9);
    assert_eq!(m.faces.len(), 8);
    assert!(m.vertices.iter().all(|p| (p[0] - 0.3).abs() < 1e-6));
    assert!((m.area() - 1.0).abs() < 1e-6);
    for f in 0..m.faces.len() {
        let [a, b, c] = m.triangle(f).map(|p| p.map(|x| x as f64));
        assert!(cross(sub(b, a), sub(c, a))[0] > 0.0);
    }
}

#[test]
fn extract_mesh_matches_marching_cubes_and_colours_vertices() {
    let (n, h, r) = (20usize, 0.05f32, 0.3f32);
    let (vals, o) = sphere_grid(n, h, r);
    let reference = marching_cubes([n; 3], o, h, &vals, 0.0);
    // The box [o, o + (n - 1) h] gives exactly the same grid.
    let hi = o[0] + h * (n - 1) as f32;
    let aabb = Aabb::new(o, [hi; 3]);
    assert_eq!(extraction_dims(&aabb, h), [n; 3]);
    let calls = std::cell::Cell::new(0);
    let sdf = |p: &[[f32; 3]]| {
        calls.set(calls.get() + 1);
        p.iter()
            .map(|q| (q[0] * q[0] + q[1] * q[1] + q[2] * q[2]).sqrt() - r)
            .collect()
    };
    let color = |p: &[[f32; 3]]| p.iter().map(|q| [q[0] + 0.5, 0.25, 2.0]).collect();
    // Small batches: 3 z-slices per query.
    let m = extract_mesh_batched(aabb, h, sdf, Some(color), 3 * n * n);
    assert_eq!(calls.get(), n.div_ceil(3));
    assert_eq!(m.faces, reference.faces);
    for (a, b) in m.vertices.iter().zip(&reference.vertices) {
        for k in 0..3 {
            assert!((a[k] - b[k]).abs() < 1e-6);
        }
    }
    let cols = m.colors.as_ref().unwrap();
    for (p, c) in m.vertices.iter().zip(cols) {
        // Red = round((x + 0.5) * 255); green = round(0.25 * 255) = 64; blue clamps to 255.
        assert_eq!(c[0], (((p[0] + 0.5).clamp(0.0, 1.0)) * 255.0).round() as u8);
        assert_eq!((c[1], c[2]), (64, 255));
    }
    // The public entry point (one batch) gives the same mesh.
    let m2 = extract_mesh(aabb, h, sdf, None::<fn(&[[f32; 3]]) -> Vec<[f32; 3]>>);
    assert_eq!(m2.faces, m.faces);
    assert!(m2.colors.is_none());
}

#[test]
fn ply_round_trip_is_exact() {
    let (vals, o) = sphere_grid(8, 0.1, 0.25);
    let mut m = marching_cubes([8; 3], o, 0.1, &vals, 0.0);
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("plain.ply");
    m.write_ply(&p).unwrap();
    assert_eq!(Mesh::read_ply(&p).unwrap(), m);
    m.colors = Some(
        (0..m.vertices.len())
            .map(|i| [i as u8, 255 - i as u8, 7])
            .collect(),
    );
    let p = dir.path().join("colour.ply");
    m.write_ply(&p).unwrap();
    let back = Mesh::read_ply(&p).unwrap();
    assert_eq!(back, m);
    // Header as written (what MeshLab / Open3D parse).
    let bytes = std::fs::read(&p).unwrap();
    let text = String::from_utf8_lossy(&bytes[..300]);
    assert!(text.starts_with("ply\nformat binary_little_endian 1.0\n"));
    assert!(text.contains("property uchar red\nproperty uchar green\nproperty uchar blue\n"));
    assert!(text.contains("property list uchar int vertex_indices\nend_header\n"));
    // Size: header + 15 bytes per vertex + 13 per face.
    let header = text.find("end_header\n").unwrap() + 11;
    assert_eq!(
        bytes.len(),
        header + 15 * m.vertices.len() + 13 * m.faces.len()
    );
}

#[test]
fn ply_reads_ascii_with_quads_doubles_and_extra_elements() {
    let src = "ply\r\nformat ascii 1.0\ncomment hand written\nelement vertex 4\n\
        property double x\nproperty double y\nproperty double z\nproperty float nx\n\
        property uchar red\nproperty uchar green\nproperty uchar blue\nproperty uchar alpha\n\
        element face 2\nproperty list uchar uint vertex_indices\nproperty int flags\n\
        element edge 1\nproperty int vertex1\nproperty int vertex2\nend_header\n\
        0 0 0 1 255 0 0 255\n1 0 0 1 0 255 0 255\n1 1 0.5 1 0 0 255 255\n0 1 0 1 9 9 9 255\n\
        4 0 1 2 3 7\n3 0 2 3 1\n0 1\n";
    let m = ply::read_ply_from(src.as_bytes()).unwrap();
    assert_eq!(
        m.vertices,
        vec![
            [0.0, 0.0, 0.0],
            [1.0, 0.0, 0.0],
            [1.0, 1.0, 0.5],
            [0.0, 1.0, 0.0]
        ]
    );
    assert_eq!(
        m.colors.unwrap(),
        vec![[255, 0, 0], [0, 255, 0], [0, 0, 255], [9, 9, 9]]
    );
    // The quad is fanned into (0 1 2), (0 2 3).
    assert_eq!(m.faces, vec![[0, 1, 2], [0, 2, 3], [0, 2, 3]]);
}

#[test]
fn ply_reads_big_endian_float_colours_and_point_clouds() {
    let mut b = b"ply\nformat binary_big_endian 1.0\nelement vertex 2\nproperty float x\n\
        property float y\nproperty float z\nproperty float red\nproperty float green\n\
        property float blue\nend_header\n"
        .to_vec();
    for v in [
        1.5f32, -2.0, 3.25, 1.0, 0.5, 0.0, 0.0, 0.0, 1.0, 0.2, 0.4, 0.6,
    ] {
        b.extend_from_slice(&v.to_be_bytes());
    }
    let m = ply::read_ply_from(&b[..]).unwrap();
    assert_eq!(m.vertices, vec![[1.5, -2.0, 3.25], [0.0, 0.0, 1.0]]);
    // Float colours scale by 255: 0.5 -> 127.5 -> 128; 0.2 -> 51; 0.4 -> 102; 0.6 -> 153.
    assert_eq!(m.colors.unwrap(), vec![[255, 128, 0], [51, 102, 153]]);
    assert!(m.faces.is_empty());
}

#[test]
fn ply_errors_are_clear() {
    let err = |s: &[u8]| format!("{:#}", ply::read_ply_from(s).unwrap_err());
    assert!(err(b"plx\n").contains("not a PLY file"));
    assert!(
        err(b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\n").contains("end_header")
    );
    let trunc = b"ply\nformat binary_little_endian 1.0\nelement vertex 2\nproperty float x\n\
        property float y\nproperty float z\nend_header\n\0\0\0\0\0\0\0\0";
    assert!(err(trunc).contains("ends early"));
    let bad_idx = "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n\
        property float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n\
        0 0 0 1 0 0 0 1 0\n3 0 1 3\n";
    assert!(err(bad_idx.as_bytes()).contains("beyond the 3 vertices"));
    let no_z = "ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\n\
        end_header\n0 0\n";
    assert!(err(no_z.as_bytes()).contains("x, y or z"));
    // Counts the body cannot hold are refused before anything is sized from them.
    let huge = b"ply\nformat binary_little_endian 1.0\nelement vertex 4000000000000\n\
        property float x\nproperty float y\nproperty float z\nend_header\n\0\0\0\0";
    assert!(err(huge).contains("claims 4000000000000 entries"));
    let huge_faces = "ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\n\
        property float y\nproperty float z\nelement face 99999999999999\n\
        property list uchar int vertex_indices\nend_header\n0 0 0\n";
    assert!(err(huge_faces.as_bytes()).contains("claims 99999999999999 entries"));
    // An element without properties takes no bytes however many entries it claims.
    let empty_el = "ply\nformat ascii 1.0\nelement marker 18446744073709551615\n\
        element vertex 1\nproperty float x\nproperty float y\nproperty float z\nend_header\n\
        1 2 3\n";
    let m = ply::read_ply_from(empty_el.as_bytes()).unwrap();
    assert_eq!(m.vertices, vec![[1.0, 2.0, 3.0]]);
    let e = Mesh::read_ply(Path::new("/nonexistent/m.ply")).unwrap_err();
    assert!(format!("{e:#}").contains("/nonexistent/m.ply"));
    // Writing refuses inconsistent meshes.
    let m = Mesh {
        vertices: vec![[0.0; 3]],
        colors: None,
        faces: vec![[0, 0, 1]],
    };
    assert!(ply::write_ply_to(&m, &mut Vec::new()).is_err());
}

#[test]
fn sample_surface_is_area_weighted_uniform_and_deterministic() {
    // Two triangles in z = 0: A = (0,0),(1,0),(0,1) with area 0.5 and B = (2,0),(5,0),(2,1)
    // with area 1.5: a quarter of the samples must fall in A.
    let m = Mesh {
        vertices: vec![
            [0.0, 0.0, 0.0],
            [1.0, 0.0, 0.0],
            [0.0, 1.0, 0.0],
            [2.0, 0.0, 0.0],
            [5.0, 0.0, 0.0],
            [2.0, 1.0, 0.0],
            [9.0, 9.0, 9.0],
        ],
        colors: None,
        // A degenerate (zero-area) face must never be sampled.
        faces: vec![[0, 1, 2], [6, 6, 6], [3, 4, 5]],
    };
    let n = 40_000;
    let s = sample_surface(&m, n, 7);
    assert_eq!(s.len(), n);
    assert_eq!(s, sample_surface(&m, n, 7));
    assert_ne!(s, sample_surface(&m, n, 8));
    let in_a: Vec<_> = s.iter().filter(|p| p[0] < 1.5).collect();
    let frac = in_a.len() as f64 / n as f64;
    // Binomial std: sqrt(0.25 * 0.75 / 40000) = 0.0022; allow ~5 sigma.
    assert!((frac - 0.25).abs() < 0.011, "{frac}");
    for p in &s {
        assert_eq!(p[2], 0.0);
        let inside_a = p[0] >= 0.0 && p[1] >= 0.0 && p[0] + p[1] <= 1.0 + 1e-6;
        let inside_b = p[0] >= 2.0 && p[1] >= 0.0 && (p[0] - 2.0) / 3.0 + p[1] <= 1.0 + 1e-6;
        assert!(inside_a || inside_b, "{p:?}");
    }
    // Uniform in a triangle: the mean is the centroid (1/3, 1/3); std of each coordinate is
    // sqrt(1/18) = 0.236, so the mean of ~10000 points has std 0.0024.
    let mean = in_a
        .iter()
        .fold([0.0f64; 2], |a, p| [a[0] + p[0] as f64, a[1] + p[1] as f64]);
    let k = in_a.len() as f64;
    assert!((mean[0] / k - 1.0 / 3.0).abs() < 0.012 && (mean[1] / k - 1.0 / 3.0).abs() < 0.012);
    // No area: no samples.
    assert!(sample_surface(&Mesh::default(), 10, 0).is_empty());
}

#[test]
fn filter_faces_renumbers_and_keeps_colours() {
    let m = Mesh {
        vertices: vec![[0.0; 3], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [1.0, 1.0, 0.0]],
        colors: Some(vec![[1, 1, 1], [2, 2, 2], [3, 3, 3], [4, 4, 4]]),
        faces: vec![[0, 1, 2], [1, 3, 2]],
    };
    let f = m.filter_faces(|i| i == 1);
    assert_eq!(
        f.vertices,
        vec![[1.0, 0.0, 0.0], [1.0, 1.0, 0.0], [0.0, 1.0, 0.0]]
    );
    assert_eq!(f.colors.unwrap(), vec![[2, 2, 2], [4, 4, 4], [3, 3, 3]]);
    assert_eq!(f.faces, vec![[0, 1, 2]]);
    assert_eq!(m.bounds().unwrap(), Aabb::new([0.0; 3], [1.0, 1.0, 0.0]));
}

/// A window of the grid gives, bit for bit, the mesh of the whole grid whose values outside
/// the window are unknown (NaN): the same vertices, faces and colours, while only the window's
/// points are queried.
#[test]
fn a_window_equals_the_whole_grid_unknown_outside_it() {
    let aabb = Aabb::new([-0.5; 3], [0.5; 3]);
    let h = 0.05;
    let (lo, hi) = ([3usize, 5, 2], [15usize, 18, 21]);
    let inside = |p: &[f32; 3]| {
        (0..3).all(|a| {
            let i = ((p[a] - aabb.min[a]) / h).round() as usize;
            (lo[a]..hi[a]).contains(&i)
        })
    };
    let sphere = |p: &[f32; 3]| (p[0] * p[0] + p[1] * p[1] + p[2] * p[2]).sqrt() - 0.3;
    let queried = std::cell::Cell::new(0usize);
    let colour = |p: &[[f32; 3]]| p.iter().map(|q| q.map(|x| x + 0.5)).collect::<Vec<_>>();
    let window = extract_mesh_window(
        aabb,
        h,
        lo,
        hi,
        |p: &[[f32; 3]]| {
            queried.set(queried.get() + p.len());
            assert!(
                p.iter().all(inside),
                "a point outside the window was queried"
            );
            p.iter().map(sphere).collect()
        },
        Some(colour),
    );
    let whole = extract_mesh(
        aabb,
        h,
        |p: &[[f32; 3]]| {
            p.iter()
                .map(|q| if inside(q) { sphere(q) } else { f32::NAN })
                .collect()
        },
        Some(colour),
    );
    assert!(!window.faces.is_empty());
    assert_eq!(window, whole);
    assert_eq!(queried.get(), 12 * 13 * 19);
    // beyond the grid, the window is clamped to it; an empty window gives no mesh
    let dims = extraction_dims(&aabb, h);
    let clamped = extract_mesh_window(
        aabb,
        h,
        [0; 3],
        [usize::MAX; 3],
        |p: &[[f32; 3]]| p.iter().map(sphere).collect(),
        None::<NoColor>,
    );
    let full = extract_mesh(
        aabb,
        h,
        |p: &[[f32; 3]]| p.iter().map(sphere).collect(),
        None::<NoColor>,
    );
    assert_eq!(clamped, full);
    let empty = extract_mesh_window(
        aabb,
        h,
        dims,
        dims,
        |_: &[[f32; 3]]| -> Vec<f32> { panic!("nothing to query") },
        None::<NoColor>,
    );
    assert!(empty.faces.is_empty());
}
