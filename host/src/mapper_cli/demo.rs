//! `himap demo`: a synthetic room mapped with the `demo` preset.

#[allow(unused_imports)]
use super::*;

/// `himap demo`: synthesises a small room (into `out`, else a temporary directory), maps it
/// with `config` and returns the summary.
pub fn run_demo(
    out: Option<&Path>,
    config: Config,
    frames: usize,
    size: (u32, u32),
    threads: usize,
    backend: &str,
    progress: bool,
) -> anyhow::Result<(MapSummary, PathBuf)> {
    let root = match out {
        Some(p) => p.to_path_buf(),
        None => std::env::temp_dir().join(format!("himap-demo-{}", std::process::id())),
    };
    let data = root.join("room");
    let synth = crate::synth::SynthOptions {
        frames,
        width: size.0,
        height: size.1,
        seed: config.seed,
    };
    crate::synth::write_synthetic(&data, &synth)
        .with_context(|| format!("writing the synthetic room to {}", data.display()))?;
    let opts = MapOptions {
        backend: backend.to_string(),
        progress,
        ..MapOptions::new(data, root.join("map"), config, threads)
    };
    let s = run_map(&opts)?;
    Ok((s, opts.out))
}
