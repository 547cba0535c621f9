//! End to end on a tiny synthetic room: `run_map` writes every output and the initialisation
//! lowers the loss; a saved map loads and renders the same image bit for bit.

use himap::backend::ParallelCpuBackend;
use himap::config::Config;
use himap::mapper_cli::{
    build_backend, load_map, pack_image, render_view, run_map, save_map, MapOptions,
};
use himap::synth::{write_synthetic, SynthOptions};
use himap_core::mapper::Mapper;
use himap_core::train::backend::ImageStore;
use himap_core::train::pixel::{PixelResult, PixelSample};

fn tiny_config() -> Config {
    let mut c = himap::dump::tiny_map_config();
    // The depth prior makes more warp pairs valid as the depth grows, so the summed loss is
    // not monotone with it; this test checks the optimisation of the other terms.
    c.mapper.lambda_depth_prior = 0.0;
    // Likewise the sphere initialisation: the count of valid warp pairs (a sum) changes as
    // the surface moves from the sphere to the walls, so the total loss is not monotone.
    c.model.geo_init = himap::config::GeoInit::None;
    c.eval.renders = 2;
    c
}

#[test]
fn map_writes_all_outputs_and_the_loss_goes_down() {
    let dir = tempfile::tempdir().unwrap();
    let data = tiny_room(dir.path());
    let out = dir.path().join("out");
    let mut cfg = tiny_config();
    // Like the depth prior and the sphere (above), the weighted term of pixels below
    // `min_views` takes pixels in (from no term) as their depth moves: the summed loss of the
    // initialisation is checked without it.
    cfg.mapper.warp.few_views_weight = 0.0;
    let s = run_map(&options(data.clone(), out.clone(), cfg)).unwrap();
    // init at frame 14, one online update at 19
    assert_eq!(s.updates, 2);
    assert_eq!(s.iterations, 40 + 3);
    assert_eq!(s.scene_box_source, "scene.json");
    for f in [
        "metrics.csv",
        "summary.json",
        "mesh.ply",
        "map.safetensors",
        "metrics.png",
        "report.html",
    ] {
        assert!(out.join(f).is_file(), "{f} missing");
    }
    assert!(std::fs::read_dir(out.join("renders")).unwrap().count() >= 1);
    // the report shows the plots and every render strip
    let html = std::fs::read_to_string(out.join("report.html")).unwrap();
    assert!(html.contains("src=\"metrics.png\""));
    for e in std::fs::read_dir(out.join("renders")).unwrap() {
        let name = e.unwrap().file_name().into_string().unwrap();
        assert!(
            html.contains(&format!("renders/{name}")),
            "{name} not in the report"
        );
    }
    let png = image::open(out.join("metrics.png")).unwrap();
    assert_eq!((png.width(), png.height()), himap::mapper_cli::PLOT_SIZE);
    let csv = std::fs::read_to_string(out.join("metrics.csv")).unwrap();
    assert_eq!(csv.lines().count(), 3);
    let init: Vec<&str> = csv.lines().nth(1).unwrap().split(',').collect();
    assert_eq!(init[0..2], ["14", "init"]);
    let (first, last): (f64, f64) = (init[5].parse().unwrap(), init[6].parse().unwrap());
    assert!(last < 0.9 * first, "init loss {first} -> {last}");
    assert!(s.mean_psnr.unwrap() > 5.0 && s.mean_depth_l1_cm.is_some());
    // The final map re-rendered at frames 0 and 10 (eval.final_every = 10).
    assert_eq!(s.final_frames, 2);
    assert!(s.final_psnr.unwrap() > 5.0 && s.final_depth_l1_cm.is_some());
    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("summary.json")).unwrap()).unwrap();
    assert_eq!(json["config"]["mapper"]["init_iters"], 40);
    // A dataset with a ground-truth mesh: also the metrics against its observed part (the
    // same reconstruction samples, another truth).
    let (whole, observed) = (s.mesh.unwrap(), s.mesh_observed_gt.unwrap());
    assert_eq!(observed.n_samples, whole.n_samples);
    assert!(observed.completion_cm.is_finite() && observed.completion_cm != whole.completion_cm);
    assert!(json["mesh_observed_gt"]["completion_ratio_pct"].is_number());
    // mesh.ply on `small`'s finer grid (0.15 m / eval.mesh_refine 4), mesh_full.ply on the coarse.
    assert_eq!(s.mesh_spacing, 0.15 / 4.0);
    assert_eq!(json["mesh_spacing"].as_f64().unwrap() as f32, 0.15 / 4.0);
    assert!(s.mesh_faces > 0 && s.mesh_full_faces > 0);
    // `himap mesh --observed` on the saved map and the frames gives the run's mesh.ply.
    let again = dir.path().join("again.ply");
    let observed = himap::mapper_cli::ObservedBy {
        dataset: data,
        resize: None,
    };
    let (faces, _) = himap::mapper_cli::mesh_saved_map(
        &out.join("map.safetensors"),
        &again,
        None,
        None,
        2,
        Some(&observed),
    )
    .unwrap();
    assert!(faces > 0);
    assert_eq!(
        std::fs::read(&again).unwrap(),
        std::fs::read(out.join("mesh.ply")).unwrap()
    );
}

#[test]
fn saved_map_renders_bit_identically_after_loading() {
    let cfg = tiny_config();
    let k = himap::synth::synth_intrinsics(48, 36);
    let scene = himap::synth::Scene::generate(2);
    let aabb = scene.bounds();
    let be = build_backend(&cfg, aabb, &k, 2).unwrap();
    let mut mc = cfg.mapper_config().unwrap();
    mc.init_frames = 3;
    mc.init_iters = 5;
    mc.border = 8;
    let mut px = vec![PixelSample::default(); mc.pixels as usize];
    let mut res = vec![PixelResult::default(); mc.pixels as usize];
    let mut m = Mapper::new(be, mc, k, &mut px, &mut res).unwrap();
    let mut last = None;
    for i in 0..3 {
        let pose = himap::synth::synth_pose(&scene, i, 30);
        let (rgb, _) = scene.render(&k, &pose);
        last = m.push_frame(&pack_image(&rgb), pose).unwrap().or(last);
        if i == 2 {
            assert!(last.is_some(), "initialisation did not run");
        }
    }
    let mut be = m.into_backend();
    let view = himap::synth::synth_pose(&scene, 7, 30);
    let a = render_view(&mut be, &k, &view).unwrap();
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("map.safetensors");
    save_map(&path, &cfg, be.data()).unwrap();
    let (cfg2, data) = load_map(&path).unwrap();
    assert_eq!(cfg2, cfg);
    assert_eq!(data.t, be.data().t);
    let mut be2 = ParallelCpuBackend::new(data, cfg2.adam_config(), 1)
        .unwrap()
        .with_images(ImageStore::default());
    let b = render_view(&mut be2, &k, &view).unwrap();
    assert!(a.iter().any(|r| r.opacity > 0.0));
    for (x, y) in a.iter().zip(&b) {
        assert_eq!(x.color.map(f32::to_bits), y.color.map(f32::to_bits));
        assert_eq!(x.depth.to_bits(), y.depth.to_bits());
        assert_eq!(x.opacity.to_bits(), y.opacity.to_bits());
    }
    // not a map file: a clear error
    std::fs::write(dir.path().join("bad.safetensors"), b"hello").unwrap();
    let e = load_map(&dir.path().join("bad.safetensors")).unwrap_err();
    assert!(format!("{e:#}").contains("safetensors"), "{e:#}");
    let e = load_map(&dir.path().join("missing.safetensors")).unwrap_err();
    assert!(format!("{e:#}").contains("reading"), "{e:#}");
    // A file whose configuration asks for a far larger map than the file holds: refused
    // before the map is allocated (1 cm geometry cells over the 4 m box).
    let mut big = cfg.clone();
    big.model.geometry.cell_sizes = vec![0.01];
    let meta = std::collections::HashMap::from([
        ("himap_config".to_string(), big.to_toml()),
        ("himap_aabb".to_string(), "[[-2,-2,-2],[2,2,2]]".to_string()),
        ("adam_t".to_string(), "0".to_string()),
    ]);
    let no_tensors: Vec<(&str, safetensors::tensor::TensorView)> = Vec::new();
    let bytes = safetensors::serialize(no_tensors, Some(meta)).unwrap();
    let e = himap::mapper_cli::load_map_bytes(&bytes).unwrap_err();
    assert!(format!("{e:#}").contains("needs"), "{e:#}");
}

/// A run killed after its first mapping update keeps that update's row in `metrics.csv`
/// (written and flushed per update), and with stderr not a terminal the progress arrives as
/// plain log lines (the first of which is how this test knows when to kill it).
#[test]
fn killed_run_keeps_its_metrics_rows_and_logs_plain_lines() {
    use std::io::{BufRead, BufReader};
    use std::process::Stdio;
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("room");
    write_synthetic(
        &data,
        &SynthOptions {
            frames: 40,
            width: 64,
            height: 48,
            seed: 2,
        },
    )
    .unwrap();
    let mut cfg = tiny_config();
    // Long online updates: the run is still mapping when the test kills it.
    cfg.mapper.iters = 400;
    let cfg_path = dir.path().join("tiny.toml");
    std::fs::write(&cfg_path, cfg.to_toml()).unwrap();
    let out = dir.path().join("out");
    let mut child = map_command(&data, &out, &cfg_path)
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let mut lines = Vec::new();
    for line in BufReader::new(child.stderr.take().unwrap()).lines() {
        let line = line.unwrap();
        let first_update = line.contains("update 1 (init) at frame 14");
        lines.push(line);
        if first_update {
            break;
        }
    }
    child.kill().unwrap();
    let status = child.wait().unwrap();
    assert!(!status.success(), "the run finished before it was killed");
    assert!(
        lines
            .iter()
            .any(|l| l.contains("update 1 (init) at frame 14: PSNR")),
        "no plain update line in {lines:?}"
    );
    let csv = std::fs::read_to_string(out.join("metrics.csv")).unwrap();
    let rows: Vec<&str> = csv.lines().collect();
    assert!(rows.len() >= 2, "metrics.csv: {csv}");
    assert!(rows[0].starts_with("frame,kind,psnr"));
    assert!(rows[1].starts_with("14,init,"), "{}", rows[1]);
    assert!(!out.join("summary.json").exists());
}

/// `himap map DATA --out OUT --config CFG --backend cpu --threads 2`, stdout discarded.
fn map_command(
    data: &std::path::Path,
    out: &std::path::Path,
    cfg: &std::path::Path,
) -> std::process::Command {
    let mut c = std::process::Command::new(env!("CARGO_BIN_EXE_himap"));
    c.arg("map")
        .arg(data)
        .arg("--out")
        .arg(out)
        .arg("--config")
        .arg(cfg)
        .args(["--backend", "cpu", "--threads", "2"])
        .stdout(std::process::Stdio::null());
    c
}

fn tiny_room(dir: &std::path::Path) -> std::path::PathBuf {
    let data = dir.join("room");
    write_synthetic(
        &data,
        &SynthOptions {
            frames: 20,
            width: 64,
            height: 48,
            seed: 1,
        },
    )
    .unwrap();
    data
}

fn options(data: std::path::PathBuf, out: std::path::PathBuf, config: Config) -> MapOptions {
    MapOptions::new(data, out, config, 2)
}

/// A box whose map exceeds the memory budget is refused before anything is allocated or
/// written, with the settings to change; the estimate is what the backend allocates.
#[test]
fn map_over_the_memory_budget_is_a_clear_error() {
    let dir = tempfile::tempdir().unwrap();
    let data = tiny_room(dir.path());
    let mut cfg = tiny_config();
    cfg.scene.min = Some([-20.0, -20.0, -5.0]);
    cfg.scene.max = Some([20.0, 20.0, 5.0]);
    cfg.scene.memory_budget_mb = 100.0;
    let out = dir.path().join("out");
    let err = run_map(&options(data, out.clone(), cfg.clone())).unwrap_err();
    let msg = format!("{err:#}");
    assert!(msg.contains("scene.memory_budget_mb = 100"), "{msg}");
    assert!(
        msg.contains("scene.min") && msg.contains("cell_sizes"),
        "{msg}"
    );
    assert!(!out.join("metrics.csv").exists());
    let aabb = himap_core::Aabb::new([-20.0, -20.0, -5.0], [20.0, 20.0, 5.0]);
    let (params, state, grads) = himap::mapper_cli::map_bytes(&cfg, aabb, 2).unwrap();
    assert_eq!(state, params as u64 * 12);
    assert_eq!(grads, params as u64 * 8 * 3);
    assert!((state + grads) as f64 / 1e6 > 100.0);
}

/// Cameras outside the configured box are counted (and warned about on stderr).
#[test]
fn cameras_outside_the_box_are_counted() {
    let dir = tempfile::tempdir().unwrap();
    let data = tiny_room(dir.path());
    let mut cfg = tiny_config();
    // A box in a far corner of the room, away from the camera path.
    cfg.scene.min = Some([50.0, 50.0, 50.0]);
    cfg.scene.max = Some([51.0, 51.0, 51.0]);
    cfg.eval.final_every = 0;
    let s = run_map(&options(data, dir.path().join("out"), cfg)).unwrap();
    assert_eq!(s.frames_outside_box, 20);
    assert_eq!(s.scene_box_source, "config");
    assert_eq!(s.final_frames, 0);
    let csv = std::fs::read_to_string(dir.path().join("out/metrics.csv")).unwrap();
    let header: Vec<&str> = csv.lines().next().unwrap().split(',').collect();
    let col = header.iter().position(|&h| h == "open_rays").unwrap();
    for row in csv.lines().skip(1) {
        let v: f64 = row.split(',').nth(col).unwrap().parse().unwrap();
        // Rays from cameras far away from a small box hardly ever cross it: (almost) all
        // leave it unabsorbed.
        assert!((0.9..=1.0).contains(&v), "{row}");
    }
}

/// Every output appears whole or not at all: runs killed at moments spread over a whole run
/// (during mapping, evaluation and the saves) leave, for each file of a previous complete run
/// in the same folder, that file or a whole new one. The runs are deterministic, so a whole
/// new map, mesh or render equals the previous one byte for byte; the summary and the
/// metrics (which hold timings) must parse.
#[test]
fn outputs_are_whole_after_a_kill_at_any_moment() {
    use std::process::Stdio;
    use std::time::Instant;
    let dir = tempfile::tempdir().unwrap();
    let data = tiny_room(dir.path());
    let cfg_path = dir.path().join("tiny.toml");
    std::fs::write(&cfg_path, tiny_config().to_toml()).unwrap();
    let out = dir.path().join("out");
    let command = || {
        let mut c = map_command(&data, &out, &cfg_path);
        c.stderr(Stdio::null());
        c
    };
    let t0 = Instant::now();
    assert!(command().status().unwrap().success());
    let full = t0.elapsed();
    let names = |d: &std::path::Path| -> Vec<String> {
        let mut v: Vec<String> = std::fs::read_dir(d)
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .filter(|n| !n.starts_with(".himap-"))
            .collect();
        v.sort();
        v
    };
    let files = names(&out);
    let renders = names(&out.join("renders"));
    let bytes = |p: &std::path::Path| std::fs::read(p).unwrap();
    // The map is compared by content: its metadata is a hash map, serialised in any order.
    let map_content = |b: &[u8]| {
        let (_, meta) = safetensors::SafeTensors::read_metadata(b).unwrap();
        let t = safetensors::SafeTensors::deserialize(b).unwrap();
        let mut tensors: Vec<(String, Vec<u8>)> = t
            .tensors()
            .into_iter()
            .map(|(n, v)| (n, v.data().to_vec()))
            .collect();
        tensors.sort();
        let mut m: Vec<(String, String)> = meta
            .metadata()
            .clone()
            .unwrap_or_default()
            .into_iter()
            .collect();
        m.sort();
        (tensors, m)
    };
    let map_ref = map_content(&bytes(&out.join("map.safetensors")));
    let reference: Vec<(std::path::PathBuf, Vec<u8>)> = ["mesh.ply"]
        .iter()
        .map(|f| out.join(f))
        .chain(renders.iter().map(|r| out.join("renders").join(r)))
        .map(|p| (p.clone(), bytes(&p)))
        .collect();
    let csv_rows = std::fs::read_to_string(out.join("metrics.csv"))
        .unwrap()
        .lines()
        .count();
    for k in 0..16 {
        let mut child = command().spawn().unwrap();
        std::thread::sleep(full.mul_f64(0.1 + 0.06 * k as f64));
        let _ = child.kill();
        let _ = child.wait();
        assert_eq!(names(&out), files, "kill {k}");
        for (p, want) in &reference {
            assert!(
                bytes(p) == *want,
                "kill {k}: {} is not the previous file",
                p.display()
            );
        }
        assert!(
            map_content(&bytes(&out.join("map.safetensors"))) == map_ref,
            "kill {k}: map.safetensors is not whole"
        );
        let s: serde_json::Value =
            serde_json::from_slice(&bytes(&out.join("summary.json"))).unwrap();
        assert!(s["mesh_faces"].as_u64().unwrap() > 0, "kill {k}");
        let csv = std::fs::read_to_string(out.join("metrics.csv")).unwrap();
        let header = csv.lines().next().unwrap();
        assert!(header.starts_with("frame,kind,"), "kill {k}");
        let width = header.split(',').count();
        assert!(csv.lines().count() <= csv_rows, "kill {k}");
        for row in csv.lines().skip(1) {
            assert_eq!(row.split(',').count(), width, "kill {k}: {row}");
        }
        assert!(csv.ends_with('\n'));
    }
}

/// A broken frame late in the sequence fails the run before the first iteration (preflight),
/// naming the frame and the file; with the preflight off the run only fails at that frame.
#[test]
fn preflight_finds_a_broken_late_frame_before_mapping() {
    let dir = tempfile::tempdir().unwrap();
    let data = tiny_room(dir.path());
    let broken = data.join("results").join("frame000018.png");
    // Cut inside the PNG header: the image's size cannot be read.
    let bytes = std::fs::read(&broken).unwrap();
    std::fs::write(&broken, &bytes[..12]).unwrap();
    let out = dir.path().join("out");
    let err = run_map(&options(data.clone(), out.clone(), tiny_config())).unwrap_err();
    let msg = format!("{err:#}");
    assert!(msg.contains("preflight of frame 18 of 20"), "{msg}");
    assert!(msg.contains("frame000018.png"), "{msg}");
    assert!(!out.join("metrics.csv").exists(), "the run started mapping");
    // Without the preflight the run maps frames 0..17 (the initialisation included) first.
    let mut opts = options(data, out.clone(), tiny_config());
    opts.preflight = false;
    let err = run_map(&opts).unwrap_err();
    let msg = format!("{err:#}");
    assert!(!msg.contains("preflight"), "{msg}");
    assert!(msg.contains("frame000018.png"), "{msg}");
    let csv = std::fs::read_to_string(out.join("metrics.csv")).unwrap();
    assert!(csv.lines().nth(1).unwrap().starts_with("14,init,"), "{csv}");
}

/// Non-finite steps never reach the map: with a learning rate whose Adam step overflows
/// (`lr / (1 - beta1)` is infinite at the first step) every such step is rejected, counted in
/// `summary.json`, the learning rates are lowered after `rejected_lr_after` of them in a row,
/// and the saved map holds only finite values.
#[test]
fn nonfinite_steps_are_rejected_counted_and_never_saved() {
    let dir = tempfile::tempdir().unwrap();
    let data = tiny_room(dir.path());
    let mut cfg = tiny_config();
    cfg.adam.beta_lr = 1e38;
    cfg.mapper.rejected_lr_after = 2;
    cfg.mapper.rejected_lr_factor = 0.5;
    cfg.eval.final_every = 0;
    let out = dir.path().join("out");
    let s = run_map(&options(data, out.clone(), cfg)).unwrap();
    assert!(s.rejected_steps >= 2, "{} rejected", s.rejected_steps);
    assert!(s.lr_reductions >= 1, "{} reductions", s.lr_reductions);
    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("summary.json")).unwrap()).unwrap();
    assert_eq!(json["rejected_steps"], s.rejected_steps);
    assert_eq!(json["lr_reductions"], s.lr_reductions);
    let (_, map) = load_map(&out.join("map.safetensors")).unwrap();
    for g in 0..himap_core::field::model::NUM_GROUPS {
        let mut all = map.params[g].iter().chain(&map.m[g]).chain(&map.v[g]);
        assert!(
            all.all(|x| x.is_finite()),
            "group {g} holds non-finite values"
        );
    }
}

/// `--checkpoint-every` / `--resume`: a run stopped after 23 frames (its last checkpoint
/// after 21, one frame pending for the next update) and resumed from the checkpoint ends on the same map, bit for bit, and the same
/// metrics as the uninterrupted run; another configuration or dataset is a clear error.
#[test]
fn a_resumed_run_equals_the_uninterrupted_one() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("room");
    let synth = |path: &std::path::Path, seed| {
        write_synthetic(
            path,
            &SynthOptions {
                frames: 30,
                width: 64,
                height: 48,
                seed,
            },
        )
        .unwrap()
    };
    synth(&data, 1);
    let mut cfg = tiny_config();
    cfg.eval.final_every = 0;
    cfg.mapper.max_keyframes = 3; // the cache thins before the checkpoint
                                  // online plane priors: the resumed run must fit the same ones again (`OnlinePriors::resume`)
    cfg.mapper.lambda_plane = 1.0;
    let whole = run_map(&options(
        data.clone(),
        dir.path().join("whole"),
        cfg.clone(),
    ))
    .unwrap();

    let part = dir.path().join("part");
    let mut o = options(data.clone(), part.clone(), cfg.clone());
    o.checkpoint_every = 7;
    o.stop_after = Some(23);
    run_map(&o).unwrap();
    assert!(part.join("checkpoint.safetensors").is_file());

    let resumed = dir.path().join("resumed");
    let mut o = options(data.clone(), resumed.clone(), cfg.clone());
    o.resume = Some(part.clone());
    let s = run_map(&o).unwrap();
    assert_eq!((s.updates, s.iterations), (whole.updates, whole.iterations));
    let (_, a) = load_map(&dir.path().join("whole/map.safetensors")).unwrap();
    let (_, b) = load_map(&resumed.join("map.safetensors")).unwrap();
    assert_eq!(a.t, b.t);
    let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
    for g in 0..himap_core::field::model::NUM_GROUPS {
        assert_eq!(
            bits(&a.params[g]),
            bits(&b.params[g]),
            "group {g} parameters"
        );
        assert_eq!(bits(&a.m[g]), bits(&b.m[g]), "group {g} moments");
        assert_eq!(bits(&a.v[g]), bits(&b.v[g]), "group {g} moments");
    }
    let psnr = |s: &himap::mapper_cli::MapSummary| (s.mean_psnr.map(f64::to_bits), s.mesh_faces);
    assert_eq!(psnr(&s), psnr(&whole));
    let rows = |p: &std::path::Path| -> Vec<Vec<String>> {
        let text = std::fs::read_to_string(p.join("metrics.csv")).unwrap();
        let header: Vec<&str> = text.lines().next().unwrap().split(',').collect();
        let secs = header.iter().position(|&h| h == "seconds").unwrap();
        // every column but the update's time
        text.lines()
            .map(|l| {
                l.split(',')
                    .enumerate()
                    .filter(|(i, _)| *i != secs)
                    .map(|(_, c)| c.to_string())
                    .collect()
            })
            .collect()
    };
    assert_eq!(rows(&resumed), rows(&dir.path().join("whole")));

    // another configuration, another dataset: errors that say so
    let mut other = cfg.clone();
    other.mapper.iters += 1;
    let mut o = options(data.clone(), dir.path().join("x"), other);
    o.resume = Some(part.clone());
    let e = format!("{:#}", run_map(&o).unwrap_err());
    assert!(e.contains("another configuration"), "{e}");
    let data2 = dir.path().join("room2");
    synth(&data2, 2);
    let mut o = options(data2, dir.path().join("y"), cfg.clone());
    o.resume = Some(part.join("checkpoint.safetensors"));
    let e = format!("{:#}", run_map(&o).unwrap_err());
    assert!(e.contains("another dataset"), "{e}");
}

/// A run checkpointed at its last frame resumes into the final update and the refinement:
/// the same map, bit for bit, as the uninterrupted run. The refinement's settings
/// (`mapper.refine_*`) may differ on resume (they act after the last frame), any other
/// setting may not.
#[test]
fn a_checkpoint_at_the_last_frame_resumes_into_the_refinement() {
    let dir = tempfile::tempdir().unwrap();
    let data = tiny_room(dir.path());
    let mut cfg = tiny_config();
    cfg.eval.final_every = 0;
    cfg.mapper.refine_iters = 6;
    cfg.mapper.refine_block = 3;
    cfg.mapper.refine_window = 4;
    let whole = dir.path().join("whole");
    let mut o = options(data.clone(), whole.clone(), cfg.clone());
    o.checkpoint_every = 20;
    let w = run_map(&o).unwrap();
    assert!(whole.join("checkpoint.safetensors").is_file());

    let resumed = dir.path().join("resumed");
    let mut o = options(data.clone(), resumed.clone(), cfg.clone());
    o.resume = Some(whole.clone());
    let r = run_map(&o).unwrap();
    assert_eq!((r.updates, r.iterations), (w.updates, w.iterations));
    let (_, a) = load_map(&whole.join("map.safetensors")).unwrap();
    let (_, b) = load_map(&resumed.join("map.safetensors")).unwrap();
    let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
    for g in 0..himap_core::field::model::NUM_GROUPS {
        assert_eq!(bits(&a.params[g]), bits(&b.params[g]), "group {g}");
    }

    // another refinement: accepted, and it is what runs
    let mut other = cfg.clone();
    other.mapper.refine_iters = 3;
    let mut o = options(data.clone(), dir.path().join("other"), other);
    o.resume = Some(whole.clone());
    let r = run_map(&o).unwrap();
    assert_eq!(r.iterations, w.iterations - 3);
    // any other setting: refused
    let mut other = cfg.clone();
    other.mapper.iters += 1;
    let mut o = options(data, dir.path().join("x"), other);
    o.resume = Some(whole);
    let e = format!("{:#}", run_map(&o).unwrap_err());
    assert!(e.contains("another configuration"), "{e}");
}

/// A small synthetic room of `frames` frames under `dir` without its `scene.json`: no
/// metadata box, so mapping it places the default box around the first camera.
fn room_without_box(dir: &std::path::Path, frames: usize, seed: u64) -> std::path::PathBuf {
    let data = dir.join("room");
    write_synthetic(
        &data,
        &SynthOptions {
            frames,
            width: 64,
            height: 48,
            seed,
        },
    )
    .unwrap();
    std::fs::remove_file(data.join("scene.json")).unwrap();
    data
}

/// `scene.grow_margin_up`: a default box whose bottom lies closer to the first camera than
/// the margin grows downwards (by whole `grow_step_up`s) before the first frame, the other
/// axes keep their extent, and the run maps in it with no camera outside.
#[test]
fn the_default_box_grows_along_up() {
    let dir = tempfile::tempdir().unwrap();
    let data = room_without_box(dir.path(), 6, 2);
    let mut cfg = tiny_config();
    cfg.eval.final_every = 0;
    cfg.scene.default_horizontal = 12.0;
    cfg.scene.default_below = 0.3;
    cfg.scene.grow_margin_up = 0.8;
    cfg.scene.grow_step_up = 0.4;
    let fixed = {
        let mut c = cfg.clone();
        c.scene.grow_margin_up = 0.0;
        run_map(&options(data.clone(), dir.path().join("fixed"), c)).unwrap()
    };
    let s = run_map(&options(data.clone(), dir.path().join("up"), cfg)).unwrap();
    assert_eq!(s.frames_outside_box, 0);
    let ext = |b: &[[f32; 3]; 2], a: usize| b[1][a] - b[0][a];
    let grown: Vec<usize> = (0..3)
        .filter(|&a| (ext(&s.scene_box, a) - ext(&fixed.scene_box, a)).abs() > 1e-4)
        .collect();
    assert_eq!(grown.len(), 1, "{:?} vs {:?}", s.scene_box, fixed.scene_box);
    let a = grown[0];
    // 0.3 m below grows by two 0.4 m steps to keep 0.8 m
    assert!((ext(&s.scene_box, a) - ext(&fixed.scene_box, a) - 0.8).abs() < 1e-4);
    assert!(s.parameters > fixed.parameters);
    assert!(s.mean_psnr.is_some_and(f64::is_finite));
}

/// `scene.grow`: the default box placed around the first camera grows as the camera walks
/// (here a 1 m box around a camera circling the room), so no camera ends outside it; a run
/// stopped after a checkpoint and resumed (its backend built for the first box, the
/// checkpoint's map over a grown one) ends on the uninterrupted run's map, bit for bit.
#[test]
fn the_default_box_grows_with_the_walk_and_resumes_bit_for_bit() {
    let dir = tempfile::tempdir().unwrap();
    let data = room_without_box(dir.path(), 30, 1);
    let mut cfg = tiny_config();
    cfg.eval.final_every = 0;
    cfg.scene.default_horizontal = 1.0;
    cfg.scene.grow_margin = 0.8;
    cfg.scene.grow_step = 0.5;
    let fixed = {
        let mut c = cfg.clone();
        c.scene.grow = false;
        run_map(&options(data.clone(), dir.path().join("fixed"), c)).unwrap()
    };
    assert_eq!(fixed.scene_box_source, "default around the first camera");
    assert!(
        fixed.frames_outside_box > 0,
        "the walk must leave a 1 m box"
    );
    let whole = run_map(&options(
        data.clone(),
        dir.path().join("whole"),
        cfg.clone(),
    ))
    .unwrap();
    assert_eq!(whole.frames_outside_box, 0);
    let (lo, hi) = (whole.scene_box[0], whole.scene_box[1]);
    let (flo, fhi) = (fixed.scene_box[0], fixed.scene_box[1]);
    let grown = (0..3)
        .filter(|&a| hi[a] - lo[a] > fhi[a] - flo[a] + 0.4)
        .count();
    assert!(grown >= 1, "{:?} vs {:?}", whole.scene_box, fixed.scene_box);
    // the up axis keeps its extent
    assert!((0..3).any(|a| (hi[a] - lo[a] - (fhi[a] - flo[a])).abs() < 1e-6));
    assert!(whole.parameters > fixed.parameters);

    let part = dir.path().join("part");
    let mut o = options(data.clone(), part.clone(), cfg.clone());
    o.checkpoint_every = 7;
    o.stop_after = Some(23);
    run_map(&o).unwrap();
    let resumed = dir.path().join("resumed");
    let mut o = options(data.clone(), resumed.clone(), cfg.clone());
    o.resume = Some(part.clone());
    let s = run_map(&o).unwrap();
    assert_eq!(s.scene_box, whole.scene_box);
    let (_, a) = load_map(&dir.path().join("whole/map.safetensors")).unwrap();
    let (_, b) = load_map(&resumed.join("map.safetensors")).unwrap();
    assert_eq!(a.layout, b.layout);
    let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
    for g in 0..himap_core::field::model::NUM_GROUPS {
        assert_eq!(bits(&a.params[g]), bits(&b.params[g]), "group {g}");
        assert_eq!(bits(&a.v[g]), bits(&b.v[g]), "group {g} moments");
    }
    assert_eq!(
        s.mean_psnr.map(f64::to_bits),
        whole.mean_psnr.map(f64::to_bits)
    );
}
