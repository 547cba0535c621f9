//! TUM RGB-D layout:
//!
//! ```text
//! rgb.txt           "timestamp path" per line (# comments), colour images
//! depth.txt         "timestamp path", 16-bit depth PNGs, metres = value / 5000 (optional)
//! groundtruth.txt   "timestamp tx ty tz qx qy qz qw": camera-to-world, quaternion scalar-last
//! ```
//!
//! Every colour frame is associated with the ground-truth pose and (when `depth.txt` exists and
//! depth is loaded) the depth image nearest in time; frames with no partner within
//! [`DatasetConfig::tum_max_dt`] seconds (default 0.02) are dropped ([`TumDataset::dropped`]).
//! The camera comes from [`DatasetConfig::camera`], else from the folder name (`freiburg1`,
//! `freiburg2`, `freiburg3` anywhere in the path, as in `rgbd_dataset_freiburg1_desk`). When
//! the camera has distortion coefficients and [`DatasetConfig::undistort`] is set, colour
//! images are undistorted (OpenCV model k1 k2 p1 p2 k3, bilinear remap onto the same pinhole
//! camera; pixels whose source lies outside the image are black, so pair it with `crop_edge`).
//! Depth images are not undistorted.

use std::path::{Path, PathBuf};

use himap_core::camera::{Intrinsics, Pose};

use super::{
    check_camera, check_depth_scale, check_image_header, check_pose, folder_name, load_depth,
    load_rgb, parse_numbers, read_text, CameraConfig, Dataset, DatasetConfig, DatasetError, Frame,
    LoadOptions, RgbImage, Selection, TUM_DEPTH_SCALE,
};

/// One associated frame.
#[derive(Clone, Debug)]
struct Entry {
    timestamp: f64,
    rgb: PathBuf,
    depth: Option<PathBuf>,
    pose: Pose,
}

/// A TUM RGB-D sequence (see the module documentation).
#[derive(Clone, Debug)]
pub struct TumDataset {
    root: PathBuf,
    name: String,
    entries: Vec<Entry>,
    dropped: usize,
    has_depth: bool,
    depth_scale: f32,
    /// Source pixel (x, y) of every output pixel, when undistorting.
    undistort_map: Option<Vec<[f32; 2]>>,
    sel: Selection,
}

/// Parses a `timestamp path` list (`rgb.txt`, `depth.txt`); paths are relative to `root`.
pub fn read_file_list(path: &Path, root: &Path) -> Result<Vec<(f64, PathBuf)>, DatasetError> {
    parse_file_list(&read_text(path)?, path, root)
}

/// [`read_file_list`] of text already read (`path` names it in errors).
pub fn parse_file_list(
    text: &str,
    path: &Path,
    root: &Path,
) -> Result<Vec<(f64, PathBuf)>, DatasetError> {
    let mut out = Vec::new();
    for (i, line) in text.lines().enumerate() {
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let tokens: Vec<&str> = line.split_whitespace().collect();
        if tokens.len() != 2 {
            return Err(DatasetError::Parse {
                path: path.to_path_buf(),
                line: i + 1,
                msg: format!(
                    "expected 'timestamp filename', found {} fields",
                    tokens.len()
                ),
            });
        }
        let t: Vec<f64> = parse_numbers(path, i + 1, &tokens[..1])?;
        if !t[0].is_finite() {
            return Err(DatasetError::Parse {
                path: path.to_path_buf(),
                line: i + 1,
                msg: format!("timestamp is not finite: '{}'", tokens[0]),
            });
        }
        out.push((t[0], root.join(tokens[1])));
    }
    Ok(out)
}

/// Rotation matrix (row-major) of a unit quaternion (x, y, z, w).
pub fn quat_to_matrix(q: [f64; 4]) -> [[f64; 3]; 3] {
    let [x, y, z, w] = q;
    [
        [
            1.0 - 2.0 * (y * y + z * z),
            2.0 * (x * y - z * w),
            2.0 * (x * z + y * w),
        ],
        [
            2.0 * (x * y + z * w),
            1.0 - 2.0 * (x * x + z * z),
            2.0 * (y * z - x * w),
        ],
        [
            2.0 * (x * z - y * w),
            2.0 * (y * z + x * w),
            1.0 - 2.0 * (x * x + y * y),
        ],
    ]
}

/// Parses `groundtruth.txt` into (timestamp, camera-to-world pose), sorted by time. Quaternions
/// must have a norm within 1e-2 of 1 (they are then normalised).
pub fn read_groundtruth(path: &Path) -> Result<Vec<(f64, Pose)>, DatasetError> {
    parse_groundtruth(&read_text(path)?, path)
}

/// [`read_groundtruth`] of text already read (`path` names it in errors).
pub fn parse_groundtruth(text: &str, path: &Path) -> Result<Vec<(f64, Pose)>, DatasetError> {
    let mut out = Vec::new();
    for (i, line) in text.lines().enumerate() {
        let line_no = i + 1;
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let tokens: Vec<&str> = line.split_whitespace().collect();
        if tokens.len() != 8 {
            return Err(DatasetError::Parse {
                path: path.to_path_buf(),
                line: line_no,
                msg: format!(
                    "expected 'timestamp tx ty tz qx qy qz qw', found {} fields",
                    tokens.len()
                ),
            });
        }
        let v: Vec<f64> = parse_numbers(path, line_no, &tokens)?;
        if !v[0].is_finite() {
            return Err(DatasetError::Parse {
                path: path.to_path_buf(),
                line: line_no,
                msg: format!("timestamp is not finite: '{}'", tokens[0]),
            });
        }
        let q = [v[4], v[5], v[6], v[7]];
        let norm = q.iter().map(|x| x * x).sum::<f64>().sqrt();
        if norm.is_nan() || (norm - 1.0).abs() > 1e-2 {
            return Err(DatasetError::NotRigid {
                path: path.to_path_buf(),
                line: line_no,
                msg: format!("quaternion {q:?} has norm {norm}, expected 1"),
            });
        }
        let r = quat_to_matrix(q.map(|x| x / norm));
        let pose = Pose {
            m: [0, 1, 2].map(|row| {
                [
                    r[row][0] as f32,
                    r[row][1] as f32,
                    r[row][2] as f32,
                    v[1 + row] as f32,
                ]
            }),
        };
        check_pose(path, line_no, &pose)?;
        out.push((v[0], pose));
    }
    out.sort_by(|a, b| a.0.total_cmp(&b.0));
    Ok(out)
}

/// Index of the entry of `sorted` (by time) nearest to `t`, if within `max_dt`.
fn nearest<T>(sorted: &[(f64, T)], t: f64, max_dt: f64) -> Option<usize> {
    let k = sorted.partition_point(|e| e.0 < t);
    let mut best: Option<(usize, f64)> = None;
    for j in [k.wrapping_sub(1), k] {
        if let Some(e) = sorted.get(j) {
            let dt = (e.0 - t).abs();
            if dt <= max_dt && best.is_none_or(|(_, b)| dt < b) {
                best = Some((j, dt));
            }
        }
    }
    best.map(|(j, _)| j)
}

/// The freiburg camera named by a folder in `path`, if any.
pub fn detect_freiburg(path: &Path) -> Option<CameraConfig> {
    let full = path.canonicalize().unwrap_or_else(|_| path.to_path_buf());
    for comp in full.components().rev() {
        let s = comp.as_os_str().to_string_lossy().to_ascii_lowercase();
        if s.contains("freiburg1") {
            return Some(CameraConfig::TUM_FREIBURG1);
        }
        if s.contains("freiburg2") {
            return Some(CameraConfig::TUM_FREIBURG2);
        }
        if s.contains("freiburg3") {
            return Some(CameraConfig::TUM_FREIBURG3);
        }
    }
    None
}

/// Source pixel of every pixel of an undistorted image (OpenCV model, same pinhole camera).
pub fn undistort_map(k: &Intrinsics, dist: [f32; 5]) -> Vec<[f32; 2]> {
    let [k1, k2, p1, p2, k3] = dist.map(|x| x as f64);
    let (fx, fy, cx, cy) = (k.fx as f64, k.fy as f64, k.cx as f64, k.cy as f64);
    let mut map = Vec::with_capacity(k.width as usize * k.height as usize);
    for v in 0..k.height {
        for u in 0..k.width {
            let x = (u as f64 - cx) / fx;
            let y = (v as f64 - cy) / fy;
            let r2 = x * x + y * y;
            let radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3));
            let xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x);
            let yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y;
            map.push([(fx * xd + cx) as f32, (fy * yd + cy) as f32]);
        }
    }
    map
}

/// Bilinear remap of `img` through `map` (see [`undistort_map`]); sources outside the image
/// give black.
pub fn remap(img: &RgbImage, map: &[[f32; 2]]) -> RgbImage {
    let (w, h) = (img.width as usize, img.height as usize);
    let mut out = RgbImage::new(img.width, img.height);
    for (o, &[sx, sy]) in map.iter().enumerate().take(w * h) {
        if !(sx >= 0.0 && sy >= 0.0 && sx <= (w - 1) as f32 && sy <= (h - 1) as f32) {
            continue;
        }
        let (x0, y0) = (sx.floor() as usize, sy.floor() as usize);
        let (x1, y1) = ((x0 + 1).min(w - 1), (y0 + 1).min(h - 1));
        let (fx, fy) = (sx - x0 as f32, sy - y0 as f32);
        for c in 0..3 {
            let p = |y: usize, x: usize| img.data[3 * (y * w + x) + c];
            let top = p(y0, x0) * (1.0 - fx) + p(y0, x1) * fx;
            let bot = p(y1, x0) * (1.0 - fx) + p(y1, x1) * fx;
            out.data[3 * o + c] = top * (1.0 - fy) + bot * fy;
        }
    }
    out
}

/// Pairs every colour frame with the nearest pose (and depth image when `has_depth`) within
/// `max_dt` seconds; frames without one are dropped (and counted).
fn associate(
    rgb: Vec<(f64, PathBuf)>,
    gt: &[(f64, Pose)],
    depth: &[(f64, PathBuf)],
    has_depth: bool,
    max_dt: f64,
) -> (Vec<Entry>, usize) {
    let mut entries = Vec::new();
    let mut dropped = 0;
    for (t, path) in rgb {
        let Some(g) = nearest(gt, t, max_dt) else {
            dropped += 1;
            continue;
        };
        let d = if has_depth {
            match nearest(depth, t, max_dt) {
                Some(j) => Some(depth[j].1.clone()),
                None => {
                    dropped += 1;
                    continue;
                }
            }
        } else {
            None
        };
        entries.push(Entry {
            timestamp: t,
            rgb: path,
            depth: d,
            pose: gt[g].1,
        });
    }
    (entries, dropped)
}

/// The undistortion map of the camera when asked for and its coefficients are not all zero;
/// non-finite coefficients are an error.
pub(crate) fn undistortion(
    root: &Path,
    camera: &CameraConfig,
    native: &Intrinsics,
    undistort: bool,
) -> Result<Option<Vec<[f32; 2]>>, DatasetError> {
    match camera.distortion {
        Some(dist) if undistort && dist.iter().any(|&x| x != 0.0) => {
            if dist.iter().any(|x| !x.is_finite()) {
                return Err(DatasetError::Camera {
                    path: root.to_path_buf(),
                    msg: format!("distortion coefficients are not finite: {dist:?}"),
                });
            }
            Ok(Some(undistort_map(native, dist)))
        }
        _ => Ok(None),
    }
}

impl TumDataset {
    /// Opens the sequence in `root`: reads the lists and the ground truth, associates them and
    /// checks that every selected image exists and that the first one has the camera's size.
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
        let rgb_txt = root.join("rgb.txt");
        let depth_txt = root.join("depth.txt");
        let gt_txt = root.join("groundtruth.txt");
        for p in [&rgb_txt, &gt_txt] {
            if !p.is_file() {
                return Err(DatasetError::Missing { path: p.clone() });
            }
        }
        if !(cfg.tum_max_dt.is_finite() && cfg.tum_max_dt >= 0.0) {
            return Err(DatasetError::InvalidOption {
                path: root.to_path_buf(),
                msg: format!("tum_max_dt must be >= 0, got {}", cfg.tum_max_dt),
            });
        }
        let camera = match cfg.camera.or_else(|| detect_freiburg(root)) {
            Some(c) => c,
            None => {
                return Err(DatasetError::Camera {
                    path: root.to_path_buf(),
                    msg: "unknown camera: no freiburg1/2/3 in the folder name; give the camera \
                          in the configuration"
                        .into(),
                })
            }
        };
        let native = camera.intrinsics();
        check_camera(root, &native)?;
        let depth_scale = check_depth_scale(root, cfg.depth_scale.unwrap_or(TUM_DEPTH_SCALE))?;

        let rgb = read_file_list(&rgb_txt, root)?;
        let gt = read_groundtruth(&gt_txt)?;
        let has_depth = opts.load_depth && depth_txt.is_file();
        let mut depth = if has_depth {
            read_file_list(&depth_txt, root)?
        } else {
            Vec::new()
        };
        depth.sort_by(|a, b| a.0.total_cmp(&b.0));
        if rgb.is_empty() {
            return Err(DatasetError::Empty {
                path: rgb_txt,
                msg: "no colour frames listed".into(),
            });
        }
        if gt.is_empty() {
            return Err(DatasetError::Empty {
                path: gt_txt,
                msg: "no poses listed".into(),
            });
        }
        let (entries, dropped) = associate(rgb, &gt, &depth, has_depth, cfg.tum_max_dt);
        if entries.is_empty() {
            return Err(DatasetError::Empty {
                path: rgb_txt,
                msg: format!(
                    "no colour frame has a pose{} within {} s",
                    if has_depth { " and a depth image" } else { "" },
                    cfg.tum_max_dt
                ),
            });
        }
        let sel = Selection::new(root, entries.len(), native, opts)?
            .with_depth_camera(root, cfg.depth_camera.as_ref())?
            .with_colour_offset(root, cfg.colour_offset)?;
        for &i in &sel.indices {
            let e = &entries[i];
            for p in std::iter::once(&e.rgb).chain(e.depth.as_ref()) {
                if !p.is_file() {
                    return Err(DatasetError::Missing { path: p.clone() });
                }
            }
        }
        let first = &entries[sel.indices[0]];
        check_image_header(&first.rgb, &native)?;
        if let Some(d) = &first.depth {
            check_image_header(d, sel.depth_native())?;
        }
        let undistort_map = undistortion(root, &camera, &native, cfg.undistort)?;
        Ok(Self {
            root: root.to_path_buf(),
            name: folder_name(root),
            entries,
            dropped,
            has_depth,
            depth_scale,
            undistort_map,
            sel,
        })
    }

    /// Colour frames dropped because no pose (or depth) was within the time tolerance.
    pub fn dropped(&self) -> usize {
        self.dropped
    }

    /// Number of associated frames (before range and stride selection).
    pub fn source_len(&self) -> usize {
        self.entries.len()
    }

    /// Timestamp (s) of selected frame `i`'s colour image.
    pub fn timestamp(&self, i: usize) -> f64 {
        self.entries[self.sel.indices[i]].timestamp
    }

    /// Whether colour images are undistorted.
    pub fn undistorts(&self) -> bool {
        self.undistort_map.is_some()
    }

    /// The intrinsics of the images on disk.
    pub fn native_intrinsics(&self) -> Intrinsics {
        self.sel.native
    }
}

impl Dataset for TumDataset {
    fn len(&self) -> usize {
        self.sel.indices.len()
    }

    fn intrinsics(&self) -> Intrinsics {
        self.sel.out
    }

    fn pose(&self, i: usize) -> Pose {
        self.sel.colour_pose(self.entries[self.sel.indices[i]].pose)
    }

    fn frame(&self, i: usize) -> Result<Frame, DatasetError> {
        let src = self.sel.source(&self.root, i)?;
        let e = &self.entries[src];
        let mut rgb = load_rgb(&e.rgb, &self.sel.native)?;
        if let Some(map) = &self.undistort_map {
            rgb = remap(&rgb, map);
        }
        let depth = match &e.depth {
            Some(p) => Some(self.sel.finish_depth(load_depth(
                p,
                self.depth_scale,
                self.sel.depth_native(),
            )?)),
            None => None,
        };
        Ok(Frame {
            index: src,
            rgb: self.sel.finish_rgb(rgb),
            depth,
            pose: self.sel.colour_pose(e.pose),
            intrinsics: self.sel.out,
        })
    }

    fn preflight(&self, i: usize) -> Result<(), DatasetError> {
        let src = self.sel.source(&self.root, i)?;
        let e = &self.entries[src];
        check_image_header(&e.rgb, &self.sel.native)?;
        if let Some(p) = &e.depth {
            check_image_header(p, self.sel.depth_native())?;
        }
        Ok(())
    }

    fn name(&self) -> &str {
        &self.name
    }

    fn has_depth(&self) -> bool {
        self.has_depth
    }
}
