//! Checkpoints of a mapping run (`himap map --checkpoint-every N`, `--resume DIR`): one
//! `checkpoint.safetensors` in the output folder, written atomically (temporary file, then
//! rename) after every N-th pushed frame. It holds the map (parameters, Adam moments and step
//! count, as `map.safetensors`) and, in its metadata, the mapper's state between frames
//! ([`himap_core::mapper::MapperState`]: local frames, keyframe cache, free image slots, frame
//! and iteration counters, the sampling generator), the learning rates (the non-finite policy
//! may have lowered them), the metrics rows so far, the configuration and the dataset's
//! identity. A resumed run re-uploads the images of the frames the mapper holds from the
//! dataset and continues bit for bit as the uninterrupted run would have.

use std::path::{Path, PathBuf};

use anyhow::{bail, Context};
use himap_core::camera::Pose;
use himap_core::field::model::NUM_GROUPS;
use himap_core::mapper::{HeldFrame, MapperState};
use serde::{Deserialize, Serialize};

use crate::backend::ModelData;
use crate::config::Config;
use crate::mapper_cli::UpdateMetrics;

/// File name of the checkpoint in the output folder.
pub const FILE: &str = "checkpoint.safetensors";
/// Metadata key of the [`RunState`] JSON.
const META: &str = "himap_checkpoint";

/// What identifies the dataset a run maps: its folder, frame count, image size and a hash
/// of the poses of the frames pushed so far (never of frames not pushed yet).
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct DatasetId {
    pub path: String,
    pub frames: usize,
    pub width: u32,
    pub height: u32,
    pub poses_hash: String,
}

impl DatasetId {
    /// The identity of `dataset` (folder) with `frames` frames of `width x height`, from the
    /// poses pushed so far.
    pub fn new(dataset: &Path, frames: usize, width: u32, height: u32, poses: &[Pose]) -> Self {
        // FNV-1a over the poses' bits
        let mut h: u64 = 0xcbf2_9ce4_8422_2325;
        for p in poses {
            for x in p.m.iter().flatten() {
                for b in x.to_bits().to_le_bytes() {
                    h = (h ^ b as u64).wrapping_mul(0x0100_0000_01b3);
                }
            }
        }
        Self {
            path: std::fs::canonicalize(dataset)
                .unwrap_or_else(|_| dataset.to_path_buf())
                .display()
                .to_string(),
            frames,
            width,
            height,
            poses_hash: format!("{h:016x}"),
        }
    }
}

/// A held frame as bits (exact through JSON).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
struct FrameBits {
    id: u32,
    slot: u32,
    pose: Vec<u32>,
}

impl FrameBits {
    fn from_core(e: &HeldFrame) -> Self {
        Self {
            id: e.id,
            slot: e.slot,
            pose: e.pose.m.iter().flatten().map(|x| x.to_bits()).collect(),
        }
    }

    fn to_core(&self) -> anyhow::Result<HeldFrame> {
        if self.pose.len() != 12 {
            bail!("a held frame's pose has {} values, not 12", self.pose.len());
        }
        let mut m = [[0.0f32; 4]; 3];
        for (k, b) in self.pose.iter().enumerate() {
            m[k / 4][k % 4] = f32::from_bits(*b);
        }
        Ok(HeldFrame {
            id: self.id,
            slot: self.slot,
            pose: Pose { m },
        })
    }
}

/// Everything of a run besides the map, as stored in the checkpoint's metadata.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct RunState {
    /// The effective configuration (TOML) and the dataset's identity at the checkpoint.
    pub config: String,
    pub dataset: DatasetId,
    local: Vec<FrameBits>,
    keyframes: Vec<FrameBits>,
    pending: usize,
    free: Vec<u32>,
    initialized: bool,
    /// Frames pushed (the next frame to push is this index of the selection).
    pub pushed: u32,
    total_iters: u32,
    rejected_steps: u32,
    rejected_run: u32,
    lr_reductions: u32,
    rng: u64,
    /// Each group's Adam learning rate (bits).
    lr_bits: Vec<u32>,
    /// The metrics rows so far and the loop's counters.
    pub rows: Vec<UpdateMetrics>,
    pub outside_box: usize,
    pub mapping_s: f64,
    /// Ids of the frames that carry an online plane prior ([`crate::planes::OnlinePriors`];
    /// none in a checkpoint written before them).
    #[serde(default)]
    pub plane_priors: Vec<u32>,
}

impl RunState {
    /// The run's state from the mapper's, the learning rates and the loop's.
    #[allow(clippy::too_many_arguments)]
    pub fn new(
        config: &Config,
        dataset: DatasetId,
        m: &MapperState,
        lrs: [f32; NUM_GROUPS],
        rows: &[UpdateMetrics],
        outside_box: usize,
        mapping_s: f64,
        plane_priors: &[u32],
    ) -> Self {
        Self {
            config: config.to_toml(),
            dataset,
            local: m.local.iter().map(FrameBits::from_core).collect(),
            keyframes: m.keyframes.iter().map(FrameBits::from_core).collect(),
            pending: m.pending,
            free: m.free.to_vec(),
            initialized: m.initialized,
            pushed: m.pushed,
            total_iters: m.total_iters,
            rejected_steps: m.rejected_steps,
            rejected_run: m.rejected_run,
            lr_reductions: m.lr_reductions,
            rng: m.rng,
            lr_bits: lrs.iter().map(|x| x.to_bits()).collect(),
            rows: rows.to_vec(),
            outside_box,
            mapping_s,
            plane_priors: plane_priors.to_vec(),
        }
    }

    /// The mapper's state (lengths checked against the module's capacities).
    pub fn mapper_state(&self) -> anyhow::Result<MapperState> {
        let too_long =
            || anyhow::anyhow!("the checkpoint's frame lists exceed the mapper's capacities");
        let frames = |list: &[FrameBits]| -> anyhow::Result<Vec<HeldFrame>> {
            list.iter().map(FrameBits::to_core).collect()
        };
        Ok(MapperState {
            local: heapless::Vec::from_slice(&frames(&self.local)?).map_err(|_| too_long())?,
            keyframes: heapless::Vec::from_slice(&frames(&self.keyframes)?)
                .map_err(|_| too_long())?,
            pending: self.pending,
            free: heapless::Vec::from_slice(&self.free).map_err(|_| too_long())?,
            initialized: self.initialized,
            pushed: self.pushed,
            total_iters: self.total_iters,
            rejected_steps: self.rejected_steps,
            rejected_run: self.rejected_run,
            lr_reductions: self.lr_reductions,
            rng: self.rng,
        })
    }

    /// The learning rates per group.
    pub fn lrs(&self) -> anyhow::Result<[f32; NUM_GROUPS]> {
        if self.lr_bits.len() != NUM_GROUPS {
            bail!(
                "the checkpoint holds {} learning rates, not {NUM_GROUPS}",
                self.lr_bits.len()
            );
        }
        Ok(std::array::from_fn(|g| f32::from_bits(self.lr_bits[g])))
    }
}

/// Writes `dir/checkpoint.safetensors` atomically.
pub fn save(dir: &Path, config: &Config, data: &ModelData, run: &RunState) -> anyhow::Result<()> {
    let json = serde_json::to_string(run)?;
    crate::mapper_cli::save_map_with(&dir.join(FILE), config, data, &[(META, json)])
}

/// The checkpoint file of `path` (a file, or a folder holding [`FILE`]).
pub fn path_of(path: &Path) -> PathBuf {
    if path.is_dir() {
        path.join(FILE)
    } else {
        path.to_path_buf()
    }
}

/// Whether a checkpoint's configuration (TOML) and a resuming run's give the same mapping:
/// equal but for the final refinement's settings (`mapper.refine_*`), which act only after
/// the last frame, so that a run checkpointed at its last frame can be refined again with
/// other settings (and the planarity prior's `mapper.planar_*` when its online weight
/// `lambda_planar` is 0: they then act only in the refinement). Both are read back as configurations first, so that a setting added
/// after the checkpoint was written, absent from it, counts as its documented default (the
/// behaviour before the setting existed).
fn same_run_config(written: &str, resuming: &str) -> bool {
    fn strip(text: &str) -> Option<toml::Table> {
        let text = match toml::from_str::<Config>(text) {
            Ok(c) => c.to_toml(),
            Err(_) => text.to_string(),
        };
        let mut t: toml::Table = toml::from_str(&text).ok()?;
        if let Some(toml::Value::Table(m)) = t.get_mut("mapper") {
            // without the online planarity prior its settings act only in the refinement
            let online_planar = m
                .get("lambda_planar")
                .and_then(|v| v.as_float())
                .is_some_and(|w| w != 0.0);
            m.retain(|k, _| {
                !k.starts_with("refine_")
                    && (online_planar || k == "lambda_planar" || !k.starts_with("planar_"))
            });
        }
        // without the online plane priors (`mapper.lambda_plane`) `[planes]` acts only in
        // the refinement
        let online_planes = t
            .get("mapper")
            .and_then(|m| m.get("lambda_plane"))
            .and_then(|v| v.as_float())
            .is_some_and(|w| w != 0.0);
        if !online_planes {
            t.remove("planes");
        }
        Some(t)
    }
    written == resuming || matches!((strip(written), strip(resuming)), (Some(a), Some(b)) if a == b)
}

/// Reads a checkpoint and checks it against the run that resumes it: the same effective
/// configuration and the same dataset (folder, frame count, image size, and the poses of
/// the frames it had pushed, from `poses_of(n)`).
pub fn load(
    path: &Path,
    config: &Config,
    dataset: &Path,
    frames: usize,
    size: (u32, u32),
    poses_of: impl FnOnce(usize) -> anyhow::Result<Vec<Pose>>,
) -> anyhow::Result<(RunState, ModelData)> {
    let file = path_of(path);
    let (_, data, meta) = crate::mapper_cli::load_map_with_meta(&file)
        .with_context(|| format!("reading the checkpoint {}", file.display()))?;
    let json = meta
        .get(META)
        .with_context(|| format!("{}: a map, not a checkpoint (no {META})", file.display()))?;
    let run: RunState = serde_json::from_str(json)
        .with_context(|| format!("{}: unreadable checkpoint state", file.display()))?;
    if !same_run_config(&run.config, &config.to_toml()) {
        bail!(
            "{} was written with another configuration; resume with the same preset and \
             --config as the interrupted run (only the final refinement's `mapper.refine_*` \
             settings may differ; `himap map --print-config` shows the effective one)",
            file.display()
        );
    }
    let pushed = run.pushed as usize;
    if pushed > frames {
        bail!(
            "{} has {pushed} frames pushed but the dataset has {frames}",
            file.display()
        );
    }
    let id = DatasetId::new(dataset, frames, size.0, size.1, &poses_of(pushed)?);
    if run.dataset != id {
        bail!(
            "{} was written for another dataset ({}, {} frames of {}x{}); this one is {} ({} \
             frames of {}x{}){}",
            file.display(),
            run.dataset.path,
            run.dataset.frames,
            run.dataset.width,
            run.dataset.height,
            id.path,
            id.frames,
            id.width,
            id.height,
            if run.dataset.poses_hash != id.poses_hash {
                ", and the poses differ"
            } else {
                ""
            }
        );
    }
    Ok((run, data))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The TOML of `c` with the line setting `mapper.key` removed, as a binary from before
    /// that setting wrote it.
    fn without(c: &Config, key: &str) -> String {
        let mut t: toml::Table = toml::from_str(&c.to_toml()).unwrap();
        let m = t.get_mut("mapper").unwrap().as_table_mut().unwrap();
        assert!(m.remove(key).is_some(), "{key} is a mapper setting");
        toml::to_string_pretty(&t).unwrap()
    }

    #[test]
    fn a_checkpoint_from_before_a_setting_resumes_with_its_default_only() {
        let small = Config::small();
        let mut old = without(&small, "online_color_to_geometry");
        for key in ["refine_color_to_geometry", "refine_lambda_color"] {
            let mut t: toml::Table = toml::from_str(&old).unwrap();
            t.get_mut("mapper")
                .unwrap()
                .as_table_mut()
                .unwrap()
                .remove(key);
            old = toml::to_string_pretty(&t).unwrap();
        }
        assert!(same_run_config(&old, &small.to_toml()));
        let mut on = small.clone();
        on.mapper.online_color_to_geometry = true;
        assert!(!same_run_config(&old, &on.to_toml()));
        assert!(!same_run_config(&small.to_toml(), &on.to_toml()));
        // the refinement's settings may differ, the online ones may not
        let mut refine = small.clone();
        refine.mapper.refine_iters += 1000;
        refine.mapper.refine_lambda_color = 3.0;
        assert!(same_run_config(&old, &refine.to_toml()));
        // the planarity prior's settings act only in the refinement when it is off online
        let mut planar = refine.clone();
        planar.mapper.refine_lambda_planar = 0.1;
        planar.mapper.planar_region_step = 0.03;
        planar.mapper.planar_spacing = 160;
        assert!(same_run_config(&old, &planar.to_toml()));
        let mut online = planar.clone();
        online.mapper.lambda_planar = 0.1;
        assert!(!same_run_config(&old, &online.to_toml()));
        let mut spacing = online.clone();
        spacing.mapper.planar_spacing = 8;
        assert!(!same_run_config(&online.to_toml(), &spacing.to_toml()));
        let mut iters = small.clone();
        iters.mapper.iters += 1;
        assert!(!same_run_config(&old, &iters.to_toml()));
        // a setting without a default stays required
        assert!(!same_run_config(
            &without(&small, "iters"),
            &small.to_toml()
        ));
    }
}
