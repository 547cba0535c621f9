//! Online mapping (#11.1): nothing in a run reads a frame or a pose before it is pushed, and
//! `himap map` equals the streaming API fed frame by frame.

use himap::backend::ParallelCpuBackend;
use himap::config::Config;
use himap::dataset::{self, LoadOptions};
use himap::grow::{grow_before_push, Growth};
use himap::mapper_cli::{load_map, pack_image, run_map, start_map, MapOptions};
use himap::synth::{write_synthetic, SynthOptions};
use himap_core::mapper::Mapper;
use himap_core::train::backend::ImageStore;
use himap_core::train::pixel::{PixelResult, PixelSample};

/// A tiny mapping run whose box is the default one around the first camera (the room's
/// `scene.json` is removed, as for a real sequence without metadata).
fn config() -> Config {
    let mut c = Config::small();
    c.model.samples = 12;
    c.model.geo_init_iters = 20;
    c.mapper.init_iters = 12;
    c.mapper.init_color_iters = 6;
    c.mapper.depth_prior_iters = 6;
    c.mapper.iters = 3;
    c.mapper.pixels = 128;
    c.mapper.max_keyframes = 8;
    // a short final refinement with the plane priors refreshed twice (`small`'s weight)
    c.mapper.refine_iters = 20;
    c.mapper.refine_block = 5;
    c.planes.refresh_every = 10;
    c.model.geometry.cell_sizes = vec![0.32, 0.16];
    c.model.appearance.cell_sizes = vec![0.24, 0.08];
    c.scene.default_horizontal = 6.0;
    c.eval.every = 0;
    c.eval.final_every = 0;
    c.eval.mesh_resolution = 0.2;
    c.eval.mesh_samples = 500;
    c
}

fn room(dir: &std::path::Path, name: &str) -> std::path::PathBuf {
    let data = dir.join(name);
    write_synthetic(
        &data,
        &SynthOptions {
            frames: 20,
            width: 48,
            height: 36,
            seed: 4,
        },
    )
    .unwrap();
    std::fs::remove_file(data.join("scene.json")).unwrap();
    data
}

fn options(dataset: std::path::PathBuf, out: std::path::PathBuf) -> MapOptions {
    MapOptions::new(dataset, out, config(), 2)
}

/// Replaces the pose of every frame from `from` on in the Replica `traj.txt` by a wildly
/// different rigid one (turned 90 degrees about z and moved by (3, -2, 1.5) m).
fn perturb_poses(data: &std::path::Path, from: usize) {
    let p = data.join("traj.txt");
    let text = std::fs::read_to_string(&p).unwrap();
    let mut out = String::new();
    for (i, line) in text.lines().enumerate() {
        if i < from || line.trim().is_empty() {
            out.push_str(line);
        } else {
            let m: Vec<f64> = line
                .split_whitespace()
                .map(|x| x.parse().unwrap())
                .collect();
            assert_eq!(m.len(), 16);
            // T * M with T = [Rz(90) | (3, -2, 1.5)]: rows x' = -y, y' = x.
            let mut n = m.clone();
            for c in 0..4 {
                n[c] = -m[4 + c];
                n[4 + c] = m[c];
            }
            n[3] += 3.0;
            n[7] -= 2.0;
            n[11] += 1.5;
            let s: Vec<String> = n.iter().map(|x| format!("{x:.9}")).collect();
            out.push_str(&s.join(" "));
        }
        out.push('\n');
    }
    std::fs::write(&p, out).unwrap();
}

fn params(out: &std::path::Path) -> Vec<Vec<u32>> {
    let (_, data) = load_map(&out.join("map.safetensors")).unwrap();
    data.params
        .iter()
        .chain(data.m.iter())
        .chain(data.v.iter())
        .map(|v| v.iter().map(|x| x.to_bits()).collect())
        .collect()
}

/// The map after frame N is the same bit for bit whatever the poses after N are: the scene
/// box, the initialisation, the keyframes and every update know only the frames pushed.
#[test]
fn later_poses_do_not_change_the_map_so_far() {
    let dir = tempfile::tempdir().unwrap();
    let a = room(dir.path(), "a");
    let b = room(dir.path(), "b");
    // init at frame 14 (15 frames), then frames 15 and 16 pushed; poses from 17 on differ
    perturb_poses(&b, 17);
    let run = |data: &std::path::Path, name: &str, stop: Option<usize>| {
        let out = dir.path().join(name);
        let mut o = options(data.to_path_buf(), out.clone());
        o.stop_after = stop;
        let s = run_map(&o).unwrap();
        (params(&out), s)
    };
    let (pa, sa) = run(&a, "a17", Some(17));
    let (pb, sb) = run(&b, "b17", Some(17));
    assert_eq!(sa.scene_box_source, "default around the first camera");
    assert_eq!(sa.scene_box, sb.scene_box);
    assert_eq!(sa.updates, 1);
    assert!(pa == pb, "the map after frame 16 depends on later poses");
    // ... and the perturbation does change a run that pushes those frames.
    let (fa, _) = run(&a, "a", None);
    let (fb, _) = run(&b, "b", None);
    assert!(fa != fb, "the perturbed poses were never used");
    assert!(fa != pa);
}

/// `himap map` and a caller that starts from `start_map` and pushes the frames one at a
/// time into the core `Mapper` give the same map, bit for bit.
#[test]
fn map_command_equals_the_streaming_api() {
    let dir = tempfile::tempdir().unwrap();
    let data = room(dir.path(), "room");
    let out = dir.path().join("out");
    run_map(&options(data.clone(), out.clone())).unwrap();
    let cli = params(&out);

    let cfg = config();
    let ds = dataset::open(&data, &LoadOptions::default()).unwrap();
    let k = ds.intrinsics();
    let mut started = None;
    let (mut aabb, mut axes, mut grew) = (None, [0, 2], 0);
    let mut px = vec![PixelSample::default(); cfg.mapper.pixels as usize];
    let mut res = vec![PixelResult::default(); cfg.mapper.pixels as usize];
    let mc = cfg.mapper_config().unwrap();
    let mut priors = himap::planes::OnlinePriors::default();
    for i in 0..ds.len() {
        let frame = ds.frame(i).unwrap();
        if started.is_none() {
            // The first frame's pose is all the start knows.
            let s = start_map(&cfg, &data, &frame.pose, 2, false).unwrap();
            let be = ParallelCpuBackend::new(s.data, cfg.adam_config(), 2)
                .unwrap()
                .with_images(ImageStore {
                    width: k.width,
                    height: k.height,
                    slots: mc.slots_needed(),
                });
            started = Some(Mapper::new(be, mc, k, &mut px, &mut res).unwrap());
            aabb = Some(s.aabb);
            axes = himap::grow::horizontal_axes(&frame.pose);
        }
        let m = started.as_mut().unwrap();
        // the default box grows as `himap map`'s does, before the frame is pushed
        let b = aabb.as_mut().unwrap();
        if let Growth::Grown { aabb: g, .. } =
            grow_before_push(&cfg, m, b, &axes, &frame.pose).unwrap()
        {
            *b = g;
            grew += 1;
        }
        if m.push_frame(&pack_image(&frame.rgb), frame.pose)
            .unwrap()
            .is_some()
        {
            priors.after_update(m, &cfg).unwrap();
        }
    }
    assert!(grew > 0, "the walk should grow the 6 m box");
    let mut m = started.unwrap();
    m.flush(&mut |_| {}).unwrap();
    let mut accepted = 0;
    himap::planes::refine(&mut m, &cfg, &mut |s| accepted += s.accepted, &mut |_| {}).unwrap();
    assert!(
        accepted > 0,
        "no plane prior was set: the refinement's priors are not covered"
    );
    let d = m.into_backend().into_data();
    let streamed: Vec<Vec<u32>> = d
        .params
        .iter()
        .chain(d.m.iter())
        .chain(d.v.iter())
        .map(|v| v.iter().map(|x| x.to_bits()).collect())
        .collect();
    assert!(cli == streamed, "himap map and the streaming API differ");
}
