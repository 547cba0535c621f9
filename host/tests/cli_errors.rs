//! What a user sees when `himap` fails: the cause chain and no backtrace (even with
//! `RUST_BACKTRACE=1`), and the documented exit codes (1 bad input, 2 usage, 3 device); and
//! how configuration files combine with the preset.

use std::process::Command;

fn himap(args: &[&str], env: &[(&str, &str)]) -> (i32, String) {
    let mut c = Command::new(env!("CARGO_BIN_EXE_himap"));
    c.args(args).env("RUST_BACKTRACE", "1");
    for (k, v) in env {
        c.env(k, v);
    }
    let out = c.output().unwrap();
    (
        out.status.code().unwrap_or(-1),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

/// Exit code and standard output (standard error appended when it fails).
fn himap_stdout(args: &[&str]) -> (i32, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_himap"))
        .args(args)
        .output()
        .unwrap();
    let mut text = String::from_utf8_lossy(&out.stdout).into_owned();
    if !out.status.success() {
        text.push_str(&String::from_utf8_lossy(&out.stderr));
    }
    (out.status.code().unwrap_or(-1), text)
}

#[test]
fn bad_input_prints_the_cause_chain_without_a_backtrace() {
    let dir = tempfile::tempdir().unwrap();
    let missing = dir.path().join("no-such-dataset");
    let out = dir.path().join("out");
    let (code, err) = himap(
        &[
            "map",
            missing.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
        ],
        &[],
    );
    assert_eq!(code, 1, "{err}");
    assert!(err.starts_with("error: "), "{err}");
    assert!(err.contains("no-such-dataset"), "{err}");
    assert!(!err.to_lowercase().contains("backtrace"), "{err}");
    assert!(!err.contains("anyhow::"), "{err}");
}

#[test]
fn usage_errors_exit_with_2() {
    let (code, err) = himap(&["map"], &[]);
    assert_eq!(code, 2, "{err}");
    let (code, _) = himap(&["no-such-command"], &[]);
    assert_eq!(code, 2);
}

#[test]
fn a_device_failure_exits_with_3() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("room");
    himap::synth::write_synthetic(
        &data,
        &himap::synth::SynthOptions {
            frames: 16,
            width: 32,
            height: 24,
            seed: 1,
        },
    )
    .unwrap();
    let out = dir.path().join("out");
    // No device has this name (and a machine without Vulkan fails earlier, also a device
    // failure).
    let (code, err) = himap(
        &[
            "map",
            data.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
            "--backend",
            "vulkan",
        ],
        &[("HIMAP_VULKAN_DEVICE", "no-such-device-anywhere")],
    );
    assert_eq!(code, 3, "{err}");
    assert!(err.contains("Vulkan"), "{err}");
    assert!(!err.to_lowercase().contains("backtrace"), "{err}");
}

#[test]
fn configuration_files_are_laid_over_the_preset_in_order() {
    let dir = tempfile::tempdir().unwrap();
    let a = dir.path().join("a.toml");
    let b = dir.path().join("b.toml");
    std::fs::write(&a, "[mapper]\niters = 7\nrefine_iters = 3\n").unwrap();
    std::fs::write(&b, "[mapper]\niters = 9\n").unwrap();
    let out = dir.path().join("out");
    let args = |files: &[&std::path::Path]| {
        let mut v = vec![
            "map".to_string(),
            "no-dataset".into(),
            "--out".into(),
            out.to_str().unwrap().into(),
            "--preset".into(),
            "paper".into(),
            "--print-config".into(),
        ];
        for f in files {
            v.push("--config".into());
            v.push(f.to_str().unwrap().into());
        }
        v
    };
    let run = |files: &[&std::path::Path]| {
        let v = args(files);
        let r: Vec<&str> = v.iter().map(|s| s.as_str()).collect();
        let (code, text) = himap_stdout(&r);
        assert_eq!(code, 0, "{text}");
        let c: toml::Table = toml::from_str(&text).unwrap();
        let m = c["mapper"].as_table().unwrap().clone();
        (
            m["iters"].as_integer(),
            m["refine_iters"].as_integer(),
            m["pixels"].as_integer(),
        )
    };
    // the paper preset's pixels stay; the later file's iters win, the earlier's refine stays
    let (iters, refine, pixels) = run(&[&a, &b]);
    assert_eq!((iters, refine), (Some(9), Some(3)));
    let paper = himap::config::Config::paper();
    assert_eq!(pixels, Some(paper.mapper.pixels as i64));
    assert_eq!(run(&[&b, &a]).0, Some(7));
    assert_eq!(run(&[]).0, Some(paper.mapper.iters as i64));
}
