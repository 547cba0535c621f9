//! Replica / NICE-SLAM layout:
//!
//! ```text
//! results/frame%06d.jpg (or .png)   colour, 8-bit
//! results/depth%06d.png             16-bit depth; metres = value / scale; 0 and 65535 = no measurement
//! traj.txt                          one row-major 4x4 camera-to-world matrix per line (OpenCV axes)
//! cam_params.json                   optional {"camera": {"w", "h", "fx", "fy", "cx", "cy", "scale"}}
//! ```
//!
//! Camera: [`DatasetConfig::camera`] if given, else `cam_params.json`, else Replica's camera
//! ([`CameraConfig::REPLICA`], depth scale 6553.5). Depth scale: [`DatasetConfig::depth_scale`],
//! else `cam_params.json`'s `scale`, else 6553.5 when there is no `cam_params.json`. A
//! `cam_params.json` without `scale` is an error when depth is loaded. A sequence without any
//! depth image has no depth (`has_depth() == false`). A configured camera with `distortion`
//! has its colour images undistorted as TUM's are ([`DatasetConfig::undistort`]).

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use himap_core::camera::{Intrinsics, Pose};
use serde::Deserialize;

use super::tum::{remap, undistortion};
use super::{
    check_camera, check_depth_scale, check_image_header, check_pose, folder_name, load_depth,
    load_rgb, parse_numbers, read_text, CameraConfig, Dataset, DatasetConfig, DatasetError, Frame,
    LoadOptions, Selection, REPLICA_DEPTH_SCALE,
};

/// A Replica-layout sequence (see the module documentation).
#[derive(Clone, Debug)]
pub struct ReplicaDataset {
    root: PathBuf,
    name: String,
    /// Source pixel (x, y) of every output pixel, when the configured camera has distortion
    /// coefficients (and [`DatasetConfig::undistort`]): colour images are undistorted as TUM's.
    undistort_map: Option<Vec<[f32; 2]>>,
    /// Colour file of every source frame.
    frames: Vec<PathBuf>,
    /// Depth file of every source frame (empty when the sequence has no depth or it is not
    /// loaded).
    depths: Vec<PathBuf>,
    /// Pose of every source frame.
    poses: Vec<Pose>,
    depth_scale: f32,
    sel: Selection,
}

#[derive(Deserialize)]
struct CamParamsFile {
    camera: CamParams,
}

#[derive(Deserialize)]
struct CamParams {
    w: u32,
    h: u32,
    fx: f32,
    fy: f32,
    cx: f32,
    cy: f32,
    #[serde(default)]
    scale: Option<f32>,
}

/// Parses `traj.txt`: one row-major 4x4 camera-to-world matrix per non-empty line (`#` starts a
/// comment line). Every pose must be a finite rigid transform with last row 0 0 0 1.
pub fn read_traj(path: &Path) -> Result<Vec<Pose>, DatasetError> {
    parse_traj(&read_text(path)?, path)
}

/// [`read_traj`] of text already read (`path` names it in errors).
pub fn parse_traj(text: &str, path: &Path) -> Result<Vec<Pose>, DatasetError> {
    let mut poses = Vec::new();
    for (i, line) in text.lines().enumerate() {
        let line_no = i + 1;
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let tokens: Vec<&str> = line.split_whitespace().collect();
        if tokens.len() != 16 {
            return Err(DatasetError::Parse {
                path: path.to_path_buf(),
                line: line_no,
                msg: format!(
                    "expected 16 numbers (a row-major 4x4 matrix), found {}",
                    tokens.len()
                ),
            });
        }
        let v: Vec<f32> = parse_numbers(path, line_no, &tokens)?;
        let last = [v[12], v[13], v[14], v[15]];
        let expect = [0.0, 0.0, 0.0, 1.0];
        if last
            .iter()
            .zip(expect)
            .any(|(a, b)| a.is_nan() || (a - b).abs() > 1e-3)
        {
            return Err(DatasetError::NotRigid {
                path: path.to_path_buf(),
                line: line_no,
                msg: format!("last row is {last:?}, expected [0, 0, 0, 1]"),
            });
        }
        let pose = Pose {
            m: [
                [v[0], v[1], v[2], v[3]],
                [v[4], v[5], v[6], v[7]],
                [v[8], v[9], v[10], v[11]],
            ],
        };
        check_pose(path, line_no, &pose)?;
        poses.push(pose);
    }
    Ok(poses)
}

/// Parses `cam_params.json` (`{"camera": {w, h, fx, fy, cx, cy, scale}}`): the camera, checked
/// like every camera ([`check_camera`]), and the depth scale if given (checked positive).
pub fn parse_cam_params(
    text: &str,
    path: &Path,
) -> Result<(Intrinsics, Option<f32>), DatasetError> {
    let p: CamParamsFile = serde_json::from_str(text).map_err(|e| DatasetError::Parse {
        path: path.to_path_buf(),
        line: e.line(),
        msg: format!("expected {{\"camera\": {{w, h, fx, fy, cx, cy, scale}}}}: {e}"),
    })?;
    let p = p.camera;
    let k = Intrinsics {
        width: p.w,
        height: p.h,
        fx: p.fx,
        fy: p.fy,
        cx: p.cx,
        cy: p.cy,
    };
    check_camera(path, &k)?;
    let scale = p.scale.map(|s| check_depth_scale(path, s)).transpose()?;
    Ok((k, scale))
}

/// Files by frame index.
type IndexMap = BTreeMap<usize, PathBuf>;

/// Colour and depth files of `results/`, by index.
fn list_results(results: &Path) -> Result<(IndexMap, IndexMap), DatasetError> {
    let mut frames = BTreeMap::new();
    let mut depths = BTreeMap::new();
    let entries = std::fs::read_dir(results).map_err(|e| DatasetError::io(results, e))?;
    for entry in entries {
        let entry = entry.map_err(|e| DatasetError::io(results, e))?;
        let name = entry.file_name();
        let Some(name) = name.to_str() else { continue };
        let Some((stem, ext)) = name.rsplit_once('.') else {
            continue;
        };
        let ext = ext.to_ascii_lowercase();
        let (map, digits) = if let Some(d) = stem.strip_prefix("frame") {
            if !matches!(ext.as_str(), "jpg" | "jpeg" | "png") {
                continue;
            }
            (&mut frames, d)
        } else if let Some(d) = stem.strip_prefix("depth") {
            if ext != "png" {
                continue;
            }
            (&mut depths, d)
        } else {
            continue;
        };
        if digits.is_empty() || !digits.bytes().all(|b| b.is_ascii_digit()) {
            continue;
        }
        let Ok(index) = digits.parse::<usize>() else {
            continue;
        };
        let path = entry.path();
        // Two files for one index (frame000001.jpg and .png): keep the first by name, so the
        // choice does not depend on the directory order.
        map.entry(index)
            .and_modify(|p: &mut PathBuf| {
                if path < *p {
                    *p = path.clone();
                }
            })
            .or_insert(path);
    }
    Ok((frames, depths))
}

/// Turns an index map into a contiguous list 0..n, or names the first missing file.
fn contiguous(
    map: &IndexMap,
    n: usize,
    results: &Path,
    prefix: &str,
    ext: &str,
) -> Result<Vec<PathBuf>, DatasetError> {
    (0..n)
        .map(|i| {
            map.get(&i).cloned().ok_or_else(|| DatasetError::Missing {
                path: results.join(format!("{prefix}{i:06}.{ext}")),
            })
        })
        .collect()
}

/// The sequence's camera (the configuration's, else `cam_params.json`'s, else Replica's), its
/// depth scale when known, and the path of `cam_params.json` (for errors).
fn camera_and_depth_scale(
    root: &Path,
    cfg: &DatasetConfig,
) -> Result<(Intrinsics, Option<f32>, PathBuf), DatasetError> {
    let params_path = root.join("cam_params.json");
    let params = if params_path.is_file() {
        Some(parse_cam_params(&read_text(&params_path)?, &params_path)?)
    } else {
        None
    };
    let (native, camera_source) = if let Some(c) = &cfg.camera {
        (c.intrinsics(), root.to_path_buf())
    } else if let Some((k, _)) = &params {
        (*k, params_path.clone())
    } else {
        (CameraConfig::REPLICA.intrinsics(), root.to_path_buf())
    };
    check_camera(&camera_source, &native)?;
    let depth_scale = match (cfg.depth_scale, &params) {
        (Some(s), _) => Some(check_depth_scale(root, s)?),
        (None, Some((_, scale))) => *scale,
        (None, None) => Some(REPLICA_DEPTH_SCALE),
    };
    Ok((native, depth_scale, params_path))
}

/// The depth image of every selected frame (`depth%06d.png` in `results`), indexed by frame
/// (empty paths for the frames not selected).
fn depth_files(
    depth_map: &IndexMap,
    results: &Path,
    n: usize,
    selected: &[usize],
) -> Result<Vec<PathBuf>, DatasetError> {
    let mut depths = vec![PathBuf::new(); n];
    for &i in selected {
        depths[i] = depth_map
            .get(&i)
            .cloned()
            .ok_or_else(|| DatasetError::Missing {
                path: results.join(format!("depth{i:06}.png")),
            })?;
    }
    Ok(depths)
}

impl ReplicaDataset {
    /// Opens the sequence in `root`; reads and validates `traj.txt` and the camera, checks that
    /// every selected image exists and that the first one has the camera's size.
    pub fn open(
        root: &Path,
        opts: &LoadOptions,
        cfg: &DatasetConfig,
    ) -> Result<Self, DatasetError> {
        if !root.is_dir() {
            return Err(DatasetError::Missing {
                path: root.to_path_buf(),
            });
        }
        let traj = root.join("traj.txt");
        let results = root.join("results");
        if !traj.is_file() {
            return Err(DatasetError::Missing { path: traj });
        }
        if !results.is_dir() {
            return Err(DatasetError::Missing { path: results });
        }

        let (native, depth_scale, params_path) = camera_and_depth_scale(root, cfg)?;

        // Files and poses.
        let (frame_map, depth_map) = list_results(&results)?;
        let n = frame_map.len();
        if n == 0 {
            return Err(DatasetError::Empty {
                path: results,
                msg: "no frame%06d.jpg or .png colour images".into(),
            });
        }
        let frame_ext = frame_map[frame_map.keys().next().unwrap_or(&0)]
            .extension()
            .and_then(|e| e.to_str())
            .unwrap_or("jpg")
            .to_string();
        let frames = contiguous(&frame_map, n, &results, "frame", &frame_ext)?;
        let poses = read_traj(&traj)?;
        if poses.len() != n {
            return Err(DatasetError::CountMismatch {
                path: traj,
                frames_dir: results,
                frames: n,
                poses: poses.len(),
            });
        }
        let sel = Selection::new(root, n, native, opts)?
            .with_depth_camera(root, cfg.depth_camera.as_ref())?
            .with_colour_offset(root, cfg.colour_offset)?;

        let load_depth = opts.load_depth && !depth_map.is_empty();
        let (depths, depth_scale) = if load_depth {
            let Some(scale) = depth_scale else {
                return Err(DatasetError::UnknownDepthScale {
                    path: params_path,
                    msg: "no \"scale\" in \"camera\"; add it or set the depth scale in the \
                          configuration"
                        .into(),
                });
            };
            (depth_files(&depth_map, &results, n, &sel.indices)?, scale)
        } else {
            (Vec::new(), depth_scale.unwrap_or(REPLICA_DEPTH_SCALE))
        };

        let undistort_map = match &cfg.camera {
            Some(c) => undistortion(root, c, &native, cfg.undistort)?,
            None => None,
        };
        let first = sel.indices[0];
        check_image_header(&frames[first], &native)?;
        if load_depth {
            check_image_header(&depths[first], sel.depth_native())?;
        }
        Ok(Self {
            root: root.to_path_buf(),
            name: folder_name(root),
            frames,
            depths,
            poses,
            depth_scale,
            undistort_map,
            sel,
        })
    }

    /// Number of frames in the source sequence (before selection).
    pub fn source_len(&self) -> usize {
        self.frames.len()
    }

    /// Depth scale in use (16-bit value per metre).
    pub fn depth_scale(&self) -> f32 {
        self.depth_scale
    }

    /// Source index of selected frame `i`.
    pub fn source_index(&self, i: usize) -> usize {
        self.sel.indices[i]
    }

    /// The intrinsics of the images on disk.
    pub fn native_intrinsics(&self) -> Intrinsics {
        self.sel.native
    }
}

impl Dataset for ReplicaDataset {
    fn len(&self) -> usize {
        self.sel.indices.len()
    }

    fn intrinsics(&self) -> Intrinsics {
        self.sel.out
    }

    fn pose(&self, i: usize) -> Pose {
        self.sel.colour_pose(self.poses[self.sel.indices[i]])
    }

    fn frame(&self, i: usize) -> Result<Frame, DatasetError> {
        let src = self.sel.source(&self.root, i)?;
        let mut rgb = load_rgb(&self.frames[src], &self.sel.native)?;
        if let Some(map) = &self.undistort_map {
            rgb = remap(&rgb, map);
        }
        let depth = if self.has_depth() {
            let d = load_depth(&self.depths[src], self.depth_scale, self.sel.depth_native())?;
            Some(self.sel.finish_depth(d))
        } else {
            None
        };
        Ok(Frame {
            index: src,
            rgb: self.sel.finish_rgb(rgb),
            depth,
            pose: self.sel.colour_pose(self.poses[src]),
            intrinsics: self.sel.out,
        })
    }

    fn preflight(&self, i: usize) -> Result<(), DatasetError> {
        let src = self.sel.source(&self.root, i)?;
        check_image_header(&self.frames[src], &self.sel.native)?;
        if self.has_depth() {
            check_image_header(&self.depths[src], self.sel.depth_native())?;
        }
        Ok(())
    }

    fn name(&self) -> &str {
        &self.name
    }

    fn has_depth(&self) -> bool {
        !self.depths.is_empty()
    }
}
