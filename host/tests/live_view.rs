//! The live view's recording (`--rerun-save`, cargo feature `rerun`), read back with Rerun's
//! own decoder: every pushed frame's camera and input image, every update's render, depth and
//! metrics, the meshes, on the `frame` timeline.
#![cfg(feature = "rerun")]

use std::collections::{BTreeMap, BTreeSet};

use himap::config::Config;
use himap::mapper_cli::{run_map, LiveOptions, MapOptions};
use rerun::external::re_log_encoding::DecoderApp;
use rerun::log::{Chunk, LogMsg};

#[derive(Default, Debug)]
struct Entity {
    rows: usize,
    components: BTreeSet<String>,
    timelines: BTreeSet<String>,
}

#[test]
fn recording_holds_cameras_renders_metrics_and_meshes() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("room");
    himap::synth::write_synthetic(
        &data,
        &himap::synth::SynthOptions {
            frames: 20,
            width: 48,
            height: 36,
            seed: 3,
        },
    )
    .unwrap();
    let mut cfg: Config = himap::dump::tiny_map_config();
    cfg.mapper.init_frames = 8;
    cfg.mapper.update_every = 4;
    cfg.eval.mesh_resolution = 0.2;
    let rrd = dir.path().join("run.rrd");
    let opts = MapOptions {
        live: LiveOptions {
            viewer: None,
            save: Some(rrd.clone()),
            mesh_every: 2,
        },
        ..MapOptions::new(data, dir.path().join("out"), cfg, 2)
    };
    let s = run_map(&opts).unwrap();
    assert!(s.updates >= 3, "{} updates", s.updates);

    let mut entities: BTreeMap<String, Entity> = BTreeMap::new();
    let file = std::io::BufReader::new(std::fs::File::open(&rrd).unwrap());
    for msg in DecoderApp::decode_lazy(file) {
        if let LogMsg::ArrowMsg(_, m) = msg.unwrap() {
            let c = Chunk::from_arrow_msg(&m).unwrap();
            let e = entities.entry(c.entity_path().to_string()).or_default();
            e.rows += c.num_rows();
            e.components
                .extend(c.component_descriptors().map(|d| d.component.to_string()));
            e.timelines
                .extend(c.timelines().keys().map(|t| t.to_string()));
        }
    }
    for (k, e) in &entities {
        eprintln!("{k}: {} rows, {:?}", e.rows, e.components);
    }
    let get = |p: &str| {
        entities
            .get(p)
            .unwrap_or_else(|| panic!("no {p} in {:?}", entities.keys().collect::<Vec<_>>()))
    };
    // every pushed frame: its camera (pose and pinhole) and input image, on the frame timeline
    let cam = get("/world/camera");
    assert_eq!(cam.rows, 2 * s.frames, "{cam:?}");
    assert!(
        cam.components.iter().any(|c| c.contains("translation")),
        "{cam:?}"
    );
    assert!(
        cam.components
            .iter()
            .any(|c| c.contains("image_from_camera")),
        "{cam:?}"
    );
    assert!(cam.timelines.contains("frame"));
    assert_eq!(get("/world/camera/input").rows, s.frames);
    // every update: input, render, depth, window, keyframes, metrics
    for p in [
        "/update/input",
        "/update/render_color",
        "/update/render_depth",
        "/world/window",
        "/world/keyframes",
        "/metrics/loss",
        "/metrics/psnr_db",
    ] {
        assert_eq!(get(p).rows, s.updates, "{p}: {:?}", get(p));
    }
    // the observed mesh every 2 updates, and the final mesh.ply
    let mesh = get("/world/mesh");
    assert_eq!(mesh.rows, s.updates / 2 + 1, "{mesh:?}");
    assert!(
        mesh.components
            .iter()
            .any(|c| c.contains("triangle_indices")),
        "{mesh:?}"
    );
}
