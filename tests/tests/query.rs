//! The robot-facing queries (`himap::query`) on a real map with a known distance field: the
//! geometric initialisation fits the field to an inverted sphere (free inside, radius
//! `geo_init_radius`) whose raw values are cut at `-geo_init_solid` outside, so they are not
//! distances there. The query's distances are the sphere's metric distances on the CPU backend,
//! and the Vulkan backend answers with the same bits.

use himap::backend::ParallelCpuBackend;
use himap::config::Config;
use himap::mapper_cli::initial_data;
use himap::query::{color_at, MapQuery, Occupancy, QueryOptions};
use himap_core::Aabb;
use himap_tests::vulkan_or_skip;

const CENTER: [f32; 3] = [0.3, -0.2, 0.1];

fn sphere_map() -> (Config, himap::backend::ModelData) {
    let mut cfg = Config::small();
    cfg.model.geo_init_radius = 1.2;
    let aabb = Aabb::new([-2.0, -2.0, -2.0], [2.0, 2.0, 2.0]);
    let data = initial_data(&cfg, aabb, Some(CENTER)).unwrap();
    (cfg, data)
}

fn points() -> Vec<[f32; 3]> {
    // on three rays from the centre, from 0.2 m to 2.2 m out (inside, across, outside)
    let dirs = [[1.0, 0.0, 0.0], [0.0, -0.6, 0.8], [-0.48, 0.6, -0.64]];
    let mut p = Vec::new();
    for d in dirs {
        for i in 0..=20 {
            let t = 0.2 + 0.1 * i as f32;
            p.push([0, 1, 2].map(|a| CENTER[a] + t * d[a]));
        }
    }
    p
}

fn radius(p: [f32; 3]) -> f32 {
    let d = [0, 1, 2].map(|a| p[a] - CENTER[a]);
    (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt()
}

#[test]
fn distances_of_the_initial_sphere_are_metric_and_equal_on_both_backends() {
    let (cfg, data) = sphere_map();
    let region = Aabb::new(CENTER.map(|x| x - 1.6), CENTER.map(|x| x + 1.6));
    let opts = QueryOptions {
        resolution: 0.05,
        level: 0.0,
        max_distance: 1.0,
    };
    let mut cpu = ParallelCpuBackend::new(data.clone(), cfg.adam_config(), 2).unwrap();
    let q = MapQuery::build(&mut cpu, region, opts).unwrap();
    let pts = points();
    let d = q.distance(&mut cpu, &pts).unwrap();
    // the fitted surface's radius, from the extracted mesh
    let m = q.mesh();
    assert!(m.faces.len() > 1000, "{} faces", m.faces.len());
    let r_mesh = m.vertices.iter().map(|v| radius(*v)).sum::<f32>() / m.vertices.len() as f32;
    assert!((r_mesh - 1.2).abs() < 0.05, "fitted radius {r_mesh}");
    let mut raw = vec![0.0f32; pts.len()];
    use himap::select::MapBackend;
    cpu.query_sdf(&pts, &mut raw).unwrap();
    for ((p, s), raw) in pts.iter().zip(&d).zip(&raw) {
        let truth = r_mesh - radius(*p); // positive inside (free space)
        if truth.abs() > 0.97 {
            // near or beyond the 1 m range (the surface's own error decides the edge)
            assert!(truth.abs() < 1.03 || !s.within_range, "{p:?}: {s:?}");
            continue;
        }
        assert!(s.within_range, "{p:?}");
        assert!(
            (s.distance - truth).abs() < 0.03,
            "{p:?}: distance {} vs {truth} (raw field {raw})",
            s.distance
        );
        if truth.abs() > 0.1 {
            // free side inside: the gradient points to the centre
            let inward: f32 = (0..3)
                .map(|a| (CENTER[a] - p[a]) / radius(*p) * s.gradient[a])
                .sum();
            assert!(inward > 0.95, "{p:?}: {:?}", s.gradient);
        }
    }
    // the raw field is not metric out there (cut at -solid), the query's distance is
    let far = pts
        .iter()
        .zip(&d)
        .zip(&raw)
        .find(|((p, _), _)| radius(**p) > 2.0)
        .unwrap();
    assert!(*far.1 > -0.5 && far.0 .1.distance < -0.75, "{far:?}");

    // occupancy: the centre's plane is free inside the sphere, occupied outside it
    let s = q.occupancy_slice(&mut cpu, 2, CENTER[2], 0.1).unwrap();
    let mut seen = [0usize; 3];
    for v in 0..s.height {
        for u in 0..s.width {
            let p = s.cell_center(u, v);
            let st = s.state[v * s.width + u];
            let truth = r_mesh - radius(p);
            if truth > 0.05 {
                assert_eq!(st, Occupancy::Free, "{p:?}");
                seen[0] += 1;
            } else if truth < -0.05 && st != Occupancy::Unknown {
                assert_eq!(st, Occupancy::Occupied, "{p:?}");
                seen[1] += 1;
            }
        }
    }
    assert!(seen[0] > 100 && seen[1] > 100, "{seen:?}");

    let colors = color_at(&mut cpu, &pts).unwrap();
    assert!(colors.iter().flatten().all(|c| c.is_finite()));

    let Some(mut gpu) = vulkan_or_skip(&data, cfg.adam_config()) else {
        return;
    };
    let qg = MapQuery::build(&mut gpu, region, opts).unwrap();
    assert_eq!(
        qg.mesh(),
        q.mesh(),
        "the surfaces differ between the backends"
    );
    let dg = qg.distance(&mut gpu, &pts).unwrap();
    assert_eq!(dg, d, "the distances differ between the backends");
    let sg = qg.occupancy_slice(&mut gpu, 2, CENTER[2], 0.1).unwrap();
    assert_eq!(sg, s);
    let cg = color_at(&mut gpu, &pts).unwrap();
    let bits = |c: &[[f32; 3]]| c.iter().flatten().map(|x| x.to_bits()).collect::<Vec<_>>();
    assert_eq!(bits(&cg), bits(&colors));
}
