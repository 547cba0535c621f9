//! What a user sees when `himap` fails: the cause chain and no backtrace (even with
//! `RUST_BACKTRACE=1`), and the documented exit codes (1 bad input, 2 usage, 3 device).

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
