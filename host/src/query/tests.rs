use super::*;

fn lcg(state: &mut u64) -> f64 {
    *state = state
        .wrapping_mul(6364136223846793005)
        .wrapping_add(1442695040888963407);
    ((*state >> 11) as f64) / ((1u64 << 53) as f64)
}

fn random_points(n: usize, lo: f32, hi: f32, seed: u64) -> Vec<[f32; 3]> {
    let mut s = seed;
    (0..n)
        .map(|_| [0; 3].map(|_| lo + (hi - lo) * lcg(&mut s) as f32))
        .collect()
}

/// Brute force: the minimum over dense barycentric samples of the triangle.
fn sampled_distance(p: [f64; 3], t: &[[f64; 3]; 3]) -> f64 {
    let n = 200;
    let mut best = f64::INFINITY;
    for i in 0..=n {
        for j in 0..=(n - i) {
            let (u, v) = (i as f64 / n as f64, j as f64 / n as f64);
            let q = add(
                t[0],
                add(scale(sub(t[1], t[0]), u), scale(sub(t[2], t[0]), v)),
            );
            best = best.min(norm(sub(p, q)));
        }
    }
    best
}

#[test]
fn closest_point_on_a_triangle_matches_dense_sampling() {
    let tris = [
        [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]],
        [[0.2, -0.3, 0.5], [1.1, 0.4, -0.2], [-0.5, 0.9, 0.3]],
        // very obtuse
        [[0.0, 0.0, 0.0], [2.0, 0.0, 0.0], [1.0, 0.05, 0.0]],
    ];
    let mut s = 7u64;
    for t in &tris {
        for _ in 0..200 {
            let p = [0; 3].map(|_| -1.5 + 3.5 * lcg(&mut s));
            let q = closest_on_triangle(p, t);
            let d = norm(sub(p, q));
            let b = sampled_distance(p, t);
            // dense sampling is an upper bound within its spacing (<= 2/200 of an edge)
            assert!(
                d <= b + 1e-12,
                "closest point farther than a sample: {d} > {b}"
            );
            assert!(b - d < 0.012, "closest point too near: {d} vs sampled {b}");
        }
    }
    // a degenerate (collinear) face is a segment
    let seg = [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [2.0, 0.0, 0.0]];
    let q = closest_on_triangle([1.5, 1.0, 0.0], &seg);
    assert!((norm(sub(q, [1.5, 0.0, 0.0]))) < 1e-12, "{q:?}");
}

fn sphere_mesh(c: [f32; 3], r: f32, res: f32) -> Mesh {
    let aabb = Aabb::new(c.map(|x| x - r - 2.0 * res), c.map(|x| x + r + 2.0 * res));
    crate::mesh::extract_mesh(
        aabb,
        res,
        |p: &[[f32; 3]]| {
            p.iter()
                .map(|q| {
                    let d = [0, 1, 2].map(|a| q[a] - c[a]);
                    (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt() - r
                })
                .collect()
        },
        None::<fn(&[[f32; 3]]) -> Vec<[f32; 3]>>,
    )
}

#[test]
fn bucket_search_equals_brute_force_inside_outside_and_far() {
    let mesh = sphere_mesh([0.3, -0.2, 0.5], 0.6, 0.1);
    let sd = SurfaceDistance::new(&mesh, 1.5);
    assert!(sd.faces() > 100);
    // points inside, near, outside the grid and beyond the range
    for p in random_points(400, -2.5, 3.0, 11) {
        let pd = p.map(f64::from);
        let (mut best, mut bf) = (f64::INFINITY, usize::MAX);
        for f in 0..mesh.faces.len() {
            let t = mesh.triangle(f).map(|v| v.map(f64::from));
            let d = norm(sub(pd, closest_on_triangle(pd, &t)));
            if d < best {
                (best, bf) = (d, f);
            }
        }
        match sd.nearest(p) {
            Some((_, d, f)) => {
                assert!(best <= 1.5);
                assert_eq!(d, best, "point {p:?}: face {f} vs brute force {bf}");
            }
            None => assert!(best > 1.5, "point {p:?} has a face at {best} within range"),
        }
    }
    let empty = SurfaceDistance::new(&Mesh::default(), 1.0);
    assert!(empty.nearest([0.0; 3]).is_none());
}

fn length(p: [f32; 3], c: [f32; 3]) -> f32 {
    let d = [0, 1, 2].map(|a| p[a] - c[a]);
    (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt()
}

/// A field whose zero set is a sphere but whose values are not distances: quadratic, shifted
/// by a level, and saturated outside (as a fitted field is). The query's distances are the
/// sphere's metric distances, their gradients the unit radial vectors.
#[test]
fn distances_are_metric_for_a_non_metric_field() {
    let c = [0.1f32, 0.2, -0.1];
    let r = 0.8f32;
    let level = -0.3f32;
    let raw = move |p: &[[f32; 3]]| -> Vec<f32> {
        p.iter()
            .map(|q| {
                let l = length(*q, c);
                (0.25 * (l * l - r * r)).min(0.05) + level
            })
            .collect()
    };
    let mut field = FnField(raw);
    let region = Aabb::new(c.map(|x| x - 1.2), c.map(|x| x + 1.2));
    let opts = QueryOptions {
        resolution: 0.05,
        level,
        max_distance: 1.0,
    };
    let q = MapQuery::build(&mut field, region, opts).unwrap();
    assert!(q.mesh().faces.len() > 1000);
    let pts = random_points(500, -1.4, 1.6, 3);
    let d = q.distance(&mut field, &pts).unwrap();
    let mut checked = 0;
    for (p, s) in pts.iter().zip(&d) {
        let truth = length(*p, c) - r;
        if truth.abs() > 1.0 + 0.01 {
            assert!(!s.within_range, "{p:?}: {s:?}, truth {truth}");
            assert_eq!(s.distance.abs(), 1.0);
            assert_eq!(s.gradient, [0.0; 3]);
            continue;
        }
        if truth.abs() < 0.99 {
            assert!(s.within_range);
            // marching cubes' chords at 5 cm on a 0.8 m sphere: under 1 mm, plus vertex error
            assert!(
                (s.distance - truth).abs() < 3e-3,
                "{p:?}: {} vs {truth}",
                s.distance
            );
            let l = length(*p, c);
            let radial = [0, 1, 2].map(|a| (p[a] - c[a]) / l);
            let cos: f32 = (0..3).map(|a| radial[a] * s.gradient[a]).sum();
            assert!(cos > 0.99, "{p:?}: gradient {:?}", s.gradient);
            checked += 1;
        }
    }
    assert!(checked > 150, "{checked}");
    // the gradient is the distance's own: central differences agree
    let h = 1e-3f32;
    for p in random_points(40, -0.6, 0.8, 5) {
        let s = q.distance(&mut field, &[p]).unwrap()[0];
        if !s.within_range || s.distance.abs() < 0.02 {
            continue;
        }
        for a in 0..3 {
            let (mut pp, mut pm) = (p, p);
            pp[a] += h;
            pm[a] -= h;
            let dd = q.distance(&mut field, &[pp, pm]).unwrap();
            let fd = (dd[0].distance - dd[1].distance) / (2.0 * h);
            assert!(
                (fd - s.gradient[a]).abs() < 0.02,
                "{p:?} axis {a}: {fd} vs {:?}",
                s.gradient
            );
        }
    }
}

#[test]
fn occupancy_slice_through_a_sphere() {
    let c = [0.0f32, 0.0, 0.0];
    let r = 0.5f32;
    let mut field = FnField(move |p: &[[f32; 3]]| p.iter().map(|q| length(*q, c) - r).collect());
    let region = Aabb::new([-1.0, -1.0, -0.8], [1.0, 1.0, 0.8]);
    let q = MapQuery::build(&mut field, region, QueryOptions::default()).unwrap();
    let s = q.occupancy_slice(&mut field, 2, 0.0, 0.1).unwrap();
    assert_eq!((s.width, s.height), (20, 20));
    assert_eq!(s.cell_center(0, 0), [-0.95, -0.95, 0.0]);
    for v in 0..s.height {
        for u in 0..s.width {
            let p = s.cell_center(u, v);
            let truth = length(p, c) - r;
            let st = s.state[v * s.width + u];
            if truth < -0.01 {
                assert_eq!(st, Occupancy::Occupied, "{p:?}");
            } else if truth > 0.01 {
                assert_eq!(st, Occupancy::Free, "{p:?}");
            }
        }
    }
    // a plane outside the region is unknown everywhere
    let out = q.occupancy_slice(&mut field, 0, 3.0, 0.25).unwrap();
    assert!(out.state.iter().all(|s| *s == Occupancy::Unknown));
    assert!(q.occupancy_slice(&mut field, 3, 0.0, 0.1).is_err());
    let dir = tempfile::tempdir().unwrap();
    s.write_png(&dir.path().join("slice.png")).unwrap();
    let img = image::open(dir.path().join("slice.png"))
        .unwrap()
        .to_luma8();
    // the centre is occupied (black), a corner free (white); v grows upwards
    assert_eq!(img.get_pixel(10, 10).0[0], 0);
    assert_eq!(img.get_pixel(0, 0).0[0], 255);
}

#[test]
fn bad_settings_are_errors() {
    let mut field = FnField(|p: &[[f32; 3]]| vec![1.0; p.len()]);
    let region = Aabb::new([0.0; 3], [1.0; 3]);
    let bad_res = QueryOptions {
        resolution: 0.0,
        ..QueryOptions::default()
    };
    assert!(MapQuery::build(&mut field, region, bad_res).is_err());
    let bad_box = Aabb::new([0.0; 3], [0.0, 1.0, 1.0]);
    assert!(MapQuery::build(&mut field, bad_box, QueryOptions::default()).is_err());
    // a field with no surface gives clamped, out-of-range answers (free everywhere)
    let q = MapQuery::build(&mut field, region, QueryOptions::default()).unwrap();
    let d = q.distance(&mut field, &[[0.5; 3]]).unwrap()[0];
    assert_eq!(d.distance, 2.0);
    assert!(!d.within_range);
}

/// Hand-computed cases: a cube's level is the median of its points' SDF, limited to the
/// spread around the global level; between cube centres it is interpolated; a cube with too
/// few points takes the global level.
#[test]
fn local_level_is_the_cubes_median_within_the_spread() {
    // cube [0, 1)^3: SDF 0.1, 0.2, 0.3 (median 0.2); cube [1, 2) x [0, 1)^2: 0.9 (limited to
    // 0.1 + 0.5); cube [-1, 0) x [0, 1)^2: one point only.
    let pts = [
        [0.5, 0.5, 0.5],
        [0.2, 0.5, 0.5],
        [0.7, 0.5, 0.5],
        [1.5, 0.5, 0.5],
        [1.6, 0.5, 0.5],
        [1.7, 0.5, 0.5],
        [-0.5, 0.5, 0.5],
    ];
    let sdf = [0.2, 0.1, 0.3, 0.9, 0.9, 0.9, 5.0];
    let l = LocalLevel::new(&pts, &sdf, 1.0, 0.1, 0.5, 2);
    assert_eq!(l.cells(), 2);
    let close = |a: f32, b: f32| (a - b).abs() < 1e-6;
    let g = LOCAL_LEVEL_GLOBAL_WEIGHT;
    let blend = |pairs: &[(f32, f32)]| {
        let (s, w) = pairs
            .iter()
            .fold((g * 0.1, g), |(s, w), &(wi, li)| (s + wi * li, w + wi));
        s / w
    };
    // at a centre: the cube's level, and a little of the global one
    assert!(
        close(l.at([0.5, 0.5, 0.5]), blend(&[(1.0, 0.2)])),
        "{}",
        l.at([0.5; 3])
    );
    assert!(close(l.at([1.5, 0.5, 0.5]), blend(&[(1.0, 0.6)])));
    // halfway between the two centres
    assert!(close(
        l.at([1.0, 0.5, 0.5]),
        blend(&[(0.5, 0.2), (0.5, 0.6)])
    ));
    // the sparse cube's centre and a place far from every cube: the global level
    assert!(close(l.at([-0.5, 0.5, 0.5]), 0.1));
    assert!(close(l.at([10.0, 10.0, 10.0]), 0.1));
    // a quarter of the way from the first centre towards the empty cube above it: the free
    // cube does not dilute the level
    assert!(close(l.at([0.5, 0.75, 0.5]), blend(&[(0.75, 0.2)])));
    // the global level as a Level
    assert!(close(Level::Global(0.3).at([1.5, 0.5, 0.5]), 0.3));
}

/// A field whose level near its surface drifts along x (as the trained maps' rooms differ),
/// with the rendered surface on the plane z = 0: one level for the whole field leaves the
/// mesh up to 8 cm off the plane at the ends; the level per cube keeps it within 2.5 cm (at
/// the region's corners the last cubes' level extends beyond their centres).
#[test]
fn local_level_follows_a_level_that_varies_across_the_field() {
    let region = Aabb::new([-2.0, -0.5, -0.5], [2.0, 0.5, 0.5]);
    let raw = |p: [f32; 3]| p[2] + 0.1 + 0.1 * (p[0] / 2.0).clamp(-1.0, 1.0);
    let mut field = FnField(|p: &[[f32; 3]]| p.iter().map(|&q| raw(q)).collect::<Vec<f32>>());
    // "rendered" points on the plane, every 5 cm
    let mut pts = Vec::new();
    for i in 0..80 {
        for j in 0..20 {
            pts.push([
                -2.0 + 0.05 * i as f32 + 0.025,
                -0.5 + 0.05 * j as f32 + 0.025,
                0.0,
            ]);
        }
    }
    let sdf: Vec<f32> = pts.iter().map(|&p| raw(p)).collect();
    let mut sorted = sdf.clone();
    sorted.sort_by(f32::total_cmp);
    let global = sorted[sorted.len() / 2];
    let off = |m: &Mesh| m.vertices.iter().map(|v| v[2].abs()).fold(0.0f32, f32::max);
    let one = region_mesh(&mut field, region, 0.05, global).unwrap();
    let local = LocalLevel::new(&pts, &sdf, 0.5, global, 0.2, 10);
    let many = region_mesh_at(&mut field, region, 0.05, Level::Local(&local)).unwrap();
    assert!(!one.faces.is_empty() && !many.faces.is_empty());
    assert!(off(&one) > 0.07, "one level: {}", off(&one));
    let worst =
        many.vertices.iter().fold(
            [0.0f32; 3],
            |a, v| if v[2].abs() > a[2].abs() { *v } else { a },
        );
    assert!(
        off(&many) < 0.025,
        "a level per cube: {} at {:?}",
        off(&many),
        worst
    );
}
