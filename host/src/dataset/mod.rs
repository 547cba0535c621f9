//! Dataset loaders: posed RGB(-D) sequences streamed frame by frame.
//!
//! Two on-disk layouts are read:
//! - **Replica / NICE-SLAM** ([`replica`]): `results/frame%06d.{jpg,png}`,
//!   `results/depth%06d.png`, `traj.txt` (one row-major 4x4 camera-to-world matrix per line),
//!   optional `cam_params.json`. The synthetic scenes of [`crate::synth`] use it too.
//! - **TUM RGB-D** ([`tum`]): `rgb.txt`, `depth.txt`, `groundtruth.txt`, frames associated by
//!   nearest timestamp.
//!
//! [`open`] detects the layout. Poses are read and validated up front (they are small); images
//! are decoded only when [`Dataset::frame`] asks for them, so a long sequence never sits in
//! memory. Every problem with the input is a [`DatasetError`] naming the file and the problem;
//! the loaders never panic on bad input.
//!
//! Image processing order for every frame: decode at the native size (checked against the
//! camera), undistort the colour image (when the camera has distortion and it is enabled),
//! resize (bilinear colour, nearest depth), then crop `crop_edge` pixels from every border. The frame's intrinsics are
//! `native.resized(w, h).cropped(edge)` accordingly.

use std::path::{Path, PathBuf};

use himap_core::camera::{Intrinsics, Pose};
use serde::{Deserialize, Serialize};

pub mod replica;
pub mod tum;

#[cfg(test)]
mod tests;

pub use replica::ReplicaDataset;
pub use tum::TumDataset;

/// A colour image: `width * height` RGB triples in [0, 1], row-major, `data[3 * (y * width + x) + c]`.
#[derive(Clone, Debug, PartialEq)]
pub struct RgbImage {
    pub width: u32,
    pub height: u32,
    pub data: Vec<f32>,
}

impl RgbImage {
    /// A black image.
    pub fn new(width: u32, height: u32) -> Self {
        Self {
            width,
            height,
            data: vec![0.0; 3 * width as usize * height as usize],
        }
    }

    /// Pixel (x, y); panics if out of bounds (callers index inside the image).
    #[inline]
    pub fn get(&self, x: u32, y: u32) -> [f32; 3] {
        let i = 3 * (y as usize * self.width as usize + x as usize);
        [self.data[i], self.data[i + 1], self.data[i + 2]]
    }

    /// Converts 8-bit RGB bytes (`3 * width * height`, row-major) to [0, 1].
    pub fn from_rgb8(width: u32, height: u32, bytes: &[u8]) -> Self {
        Self {
            width,
            height,
            data: bytes.iter().map(|&b| b as f32 / 255.0).collect(),
        }
    }

    /// 8-bit RGB bytes (rounded, clamped to [0, 255]).
    pub fn to_rgb8(&self) -> Vec<u8> {
        self.data
            .iter()
            .map(|&x| (x.clamp(0.0, 1.0) * 255.0 + 0.5) as u8)
            .collect()
    }

    /// Bilinear resize to `width` x `height` with pixel centres kept at integer coordinates
    /// (source x = (x' + 0.5) * W / W' - 0.5, clamped to the image), matching
    /// [`Intrinsics::resized`].
    pub fn resized(&self, width: u32, height: u32) -> Self {
        let xs = bilinear_taps(self.width, width);
        let ys = bilinear_taps(self.height, height);
        let mut out = RgbImage::new(width, height);
        let w = self.width as usize;
        for (y, &(y0, y1, fy)) in ys.iter().enumerate() {
            for (x, &(x0, x1, fx)) in xs.iter().enumerate() {
                let o = 3 * (y * width as usize + x);
                for c in 0..3 {
                    let p = |yy: usize, xx: usize| self.data[3 * (yy * w + xx) + c];
                    let top = p(y0, x0) * (1.0 - fx) + p(y0, x1) * fx;
                    let bot = p(y1, x0) * (1.0 - fx) + p(y1, x1) * fx;
                    out.data[o + c] = top * (1.0 - fy) + bot * fy;
                }
            }
        }
        out
    }

    /// Removes `edge` pixels from every border (an empty image if nothing is left).
    /// `passes` rounds of the separable 5-tap binomial filter `[1 4 6 4 1] / 16` (standard
    /// deviation 1 px per pass, `sqrt(passes)` px in all), borders clamped.
    pub fn blurred(&self, passes: u32) -> Self {
        const TAPS: [f32; 5] = [1.0 / 16.0, 4.0 / 16.0, 6.0 / 16.0, 4.0 / 16.0, 1.0 / 16.0];
        let (w, h) = (self.width as i64, self.height as i64);
        let mut cur = self.clone();
        for _ in 0..passes {
            for horizontal in [true, false] {
                let src = cur.data.clone();
                for y in 0..h {
                    for x in 0..w {
                        let mut acc = [0.0f32; 3];
                        for (t, &wt) in TAPS.iter().enumerate() {
                            let o = t as i64 - 2;
                            let (sx, sy) = if horizontal {
                                ((x + o).clamp(0, w - 1), y)
                            } else {
                                (x, (y + o).clamp(0, h - 1))
                            };
                            let i = ((sy * w + sx) * 3) as usize;
                            for c in 0..3 {
                                acc[c] += wt * src[i + c];
                            }
                        }
                        let i = ((y * w + x) * 3) as usize;
                        cur.data[i..i + 3].copy_from_slice(&acc);
                    }
                }
            }
        }
        cur
    }

    pub fn cropped(&self, edge: u32) -> Self {
        let (w, h) = (
            self.width.saturating_sub(2 * edge),
            self.height.saturating_sub(2 * edge),
        );
        let mut data = Vec::with_capacity(3 * w as usize * h as usize);
        for y in 0..h {
            let start = 3 * ((y + edge) as usize * self.width as usize + edge as usize);
            data.extend_from_slice(&self.data[start..start + 3 * w as usize]);
        }
        Self {
            width: w,
            height: h,
            data,
        }
    }
}

/// A depth image in metres (camera-z, not ray length); 0 means no measurement.
/// Row-major, `data[y * width + x]`.
#[derive(Clone, Debug, PartialEq)]
pub struct DepthImage {
    pub width: u32,
    pub height: u32,
    pub data: Vec<f32>,
}

impl DepthImage {
    /// This depth image (taken by camera `from`) resampled into the pixels of camera `to`,
    /// which shares its centre and orientation: each pixel of `to` takes the nearest pixel of
    /// `from` on the same ray (z-depth is the same along it), 0 where that falls outside.
    pub fn registered(&self, from: &Intrinsics, to: &Intrinsics) -> Self {
        let mut out = DepthImage::new(to.width, to.height);
        for v in 0..to.height {
            for u in 0..to.width {
                let d = to.direction(u as f32, v as f32);
                let x = (from.fx * d[0] + from.cx).round();
                let y = (from.fy * d[1] + from.cy).round();
                if x >= 0.0 && y >= 0.0 && (x as u32) < self.width && (y as u32) < self.height {
                    out.data[(v * to.width + u) as usize] = self.get(x as u32, y as u32);
                }
            }
        }
        out
    }

    /// This depth image (taken by camera `from`) seen from camera `to`, whose centre sits at
    /// `offset` (metres) in `from`'s frame and which shares its orientation: every measured
    /// pixel is back-projected, moved into `to`'s frame and splatted to its nearest pixel
    /// there, the nearest surface winning (z-depth in `to`'s frame). Pixels nothing lands on
    /// (outside `from`'s view, or behind a near edge from `to`'s point of view) stay 0. With
    /// a zero offset this is [`Self::registered`] (the same bits).
    pub fn registered_from(&self, from: &Intrinsics, to: &Intrinsics, offset: [f32; 3]) -> Self {
        if offset == [0.0; 3] {
            return self.registered(from, to);
        }
        let mut out = DepthImage::new(to.width, to.height);
        for y in 0..self.height {
            for x in 0..self.width {
                let z = self.get(x, y);
                // a NaN or a missing (0) measurement stays out
                if z.is_nan() || z <= 0.0 {
                    continue;
                }
                let d = from.direction(x as f32, y as f32);
                let q = [z * d[0] - offset[0], z * d[1] - offset[1], z - offset[2]];
                if q[2] <= 0.0 {
                    continue;
                }
                let (u, v, _) = to.project(q);
                let (u, v) = (u.round(), v.round());
                if u >= 0.0 && v >= 0.0 && (u as u32) < to.width && (v as u32) < to.height {
                    let o = &mut out.data[(v as u32 * to.width + u as u32) as usize];
                    if *o == 0.0 || q[2] < *o {
                        *o = q[2];
                    }
                }
            }
        }
        out
    }

    /// An image with no valid measurement.
    pub fn new(width: u32, height: u32) -> Self {
        Self {
            width,
            height,
            data: vec![0.0; width as usize * height as usize],
        }
    }

    /// Depth at pixel (x, y); panics if out of bounds.
    #[inline]
    pub fn get(&self, x: u32, y: u32) -> f32 {
        self.data[y as usize * self.width as usize + x as usize]
    }

    /// Nearest-neighbour resize (never mixes depths across edges): source pixel
    /// floor((x' + 0.5) * W / W'), clamped.
    pub fn resized(&self, width: u32, height: u32) -> Self {
        let xs = nearest_taps(self.width, width);
        let ys = nearest_taps(self.height, height);
        let mut data = Vec::with_capacity(width as usize * height as usize);
        for &y in &ys {
            for &x in &xs {
                data.push(self.data[y * self.width as usize + x]);
            }
        }
        Self {
            width,
            height,
            data,
        }
    }

    /// Removes `edge` pixels from every border.
    pub fn cropped(&self, edge: u32) -> Self {
        let (w, h) = (
            self.width.saturating_sub(2 * edge),
            self.height.saturating_sub(2 * edge),
        );
        let mut data = Vec::with_capacity(w as usize * h as usize);
        for y in 0..h {
            let start = (y + edge) as usize * self.width as usize + edge as usize;
            data.extend_from_slice(&self.data[start..start + w as usize]);
        }
        Self {
            width: w,
            height: h,
            data,
        }
    }
}

fn bilinear_taps(src: u32, dst: u32) -> Vec<(usize, usize, f32)> {
    let scale = src as f64 / dst as f64;
    let last = src.saturating_sub(1) as f64;
    (0..dst)
        .map(|x| {
            let s = ((x as f64 + 0.5) * scale - 0.5).clamp(0.0, last);
            let x0 = s.floor() as usize;
            let x1 = (x0 + 1).min(last as usize);
            (x0, x1, (s - x0 as f64) as f32)
        })
        .collect()
}

fn nearest_taps(src: u32, dst: u32) -> Vec<usize> {
    let scale = src as f64 / dst as f64;
    (0..dst)
        .map(|x| (((x as f64 + 0.5) * scale).floor() as usize).min(src as usize - 1))
        .collect()
}

/// One frame of a sequence, after the [`LoadOptions`] resize and crop.
#[derive(Clone, Debug)]
pub struct Frame {
    /// Index of the frame in the source sequence (before range and stride selection).
    pub index: usize,
    pub rgb: RgbImage,
    /// Depth in metres (0 = invalid), when the dataset has depth and it was asked for.
    pub depth: Option<DepthImage>,
    /// Camera-to-world, OpenCV axes.
    pub pose: Pose,
    /// Intrinsics of `rgb` (and `depth`).
    pub intrinsics: Intrinsics,
}

/// A posed RGB(-D) sequence read frame by frame. Indices run over the selected frames
/// (`0..len()`), after the range and stride of [`LoadOptions`].
pub trait Dataset: Send + Sync {
    /// Number of selected frames.
    fn len(&self) -> usize;
    /// Whether no frame is selected (never true for an opened dataset).
    fn is_empty(&self) -> bool {
        self.len() == 0
    }
    /// Intrinsics of the delivered images (after resize and crop).
    fn intrinsics(&self) -> Intrinsics;
    /// Camera-to-world pose of selected frame `i`; panics if `i >= len()`.
    fn pose(&self, i: usize) -> Pose;
    /// Decodes selected frame `i`.
    fn frame(&self, i: usize) -> Result<Frame, DatasetError>;
    /// A short name (the folder name).
    fn name(&self) -> &str;
    /// Whether frames carry depth.
    fn has_depth(&self) -> bool;
    /// Checks selected frame `i` without decoding it: its files exist, their headers decode
    /// and give the expected size (`himap map`'s preflight).
    fn preflight(&self, i: usize) -> Result<(), DatasetError>;
}

/// Which frames to read and how to size them.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct LoadOptions {
    /// First source frame.
    pub start: usize,
    /// One past the last source frame (clamped to the sequence length); `None` = to the end.
    pub end: Option<usize>,
    /// Take every `stride`-th frame (>= 1).
    pub stride: usize,
    /// Resize to (width, height) before cropping.
    pub resize: Option<(u32, u32)>,
    /// Pixels removed from every border after resizing.
    pub crop_edge: u32,
    /// Read depth images when the dataset has them.
    pub load_depth: bool,
}

impl Default for LoadOptions {
    fn default() -> Self {
        Self {
            start: 0,
            end: None,
            stride: 1,
            resize: None,
            crop_edge: 0,
            load_depth: true,
        }
    }
}

/// On-disk layout.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum DatasetFormat {
    Replica,
    Tum,
}

/// A pinhole camera given in configuration, with optional OpenCV distortion (k1 k2 p1 p2 k3).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct CameraConfig {
    pub width: u32,
    pub height: u32,
    pub fx: f32,
    pub fy: f32,
    pub cx: f32,
    pub cy: f32,
    /// k1 k2 p1 p2 k3 of the colour camera (OpenCV model); `None` = no distortion. Colour
    /// images are undistorted onto the same pinhole camera when [`DatasetConfig::undistort`]
    /// is set, in both layouts.
    #[serde(default)]
    pub distortion: Option<[f32; 5]>,
}

impl CameraConfig {
    /// The camera of `k`, without distortion.
    pub fn pinhole(k: &Intrinsics) -> Self {
        Self {
            width: k.width,
            height: k.height,
            fx: k.fx,
            fy: k.fy,
            cx: k.cx,
            cy: k.cy,
            distortion: None,
        }
    }

    /// The pinhole part.
    pub fn intrinsics(&self) -> Intrinsics {
        Intrinsics {
            width: self.width,
            height: self.height,
            fx: self.fx,
            fy: self.fy,
            cx: self.cx,
            cy: self.cy,
        }
    }

    /// Replica's camera (NICE-SLAM configuration): 1200x680, fx = fy = 600, cx 599.5, cy 339.5.
    pub const REPLICA: CameraConfig = CameraConfig {
        width: 1200,
        height: 680,
        fx: 600.0,
        fy: 600.0,
        cx: 599.5,
        cy: 339.5,
        distortion: None,
    };

    /// TUM RGB-D freiburg1 colour camera (calibration published with the dataset).
    pub const TUM_FREIBURG1: CameraConfig = CameraConfig {
        width: 640,
        height: 480,
        fx: 517.3,
        fy: 516.5,
        cx: 318.6,
        cy: 255.3,
        distortion: Some([0.2624, -0.9531, -0.0054, 0.0026, 1.1633]),
    };

    /// TUM RGB-D freiburg2 colour camera.
    pub const TUM_FREIBURG2: CameraConfig = CameraConfig {
        width: 640,
        height: 480,
        fx: 520.9,
        fy: 521.0,
        cx: 325.1,
        cy: 249.7,
        distortion: Some([0.2312, -0.7849, -0.0033, -0.0001, 0.9172]),
    };

    /// TUM RGB-D freiburg3 colour camera (images are already undistorted).
    pub const TUM_FREIBURG3: CameraConfig = CameraConfig {
        width: 640,
        height: 480,
        fx: 535.4,
        fy: 539.2,
        cx: 320.1,
        cy: 247.6,
        distortion: None,
    };
}

/// Replica's depth scale (16-bit value per metre).
pub const REPLICA_DEPTH_SCALE: f32 = 6553.5;
/// TUM RGB-D's depth scale.
pub const TUM_DEPTH_SCALE: f32 = 5000.0;

/// Configuration that overrides what the loaders detect. `Default` detects everything.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct DatasetConfig {
    /// Force a layout instead of detecting it.
    pub format: Option<DatasetFormat>,
    /// Camera to use instead of `cam_params.json` / Replica defaults / the freiburg camera.
    /// It is the **colour** camera: mapping warps colour images through it.
    pub camera: Option<CameraConfig>,
    /// The depth images' own camera, when depth is not registered to colour (7-Scenes: the
    /// files give the depth camera, 585 px focal, and the colour camera is about 525). Each
    /// depth image is resampled into the colour camera's pixels (nearest neighbour, z kept;
    /// the two cameras are taken to share centre and orientation unless `colour_offset`
    /// says otherwise). Depth is only ground truth for evaluation, so this changes no map.
    pub depth_camera: Option<CameraConfig>,
    /// The colour camera's centre in the frame of the camera the poses and depth images
    /// belong to (metres; x right, y down, z forward), when that is another camera with the
    /// same orientation (7-Scenes: KinectFusion tracked the depth camera, and the Kinect's
    /// colour camera sits about 2 cm to its right; `scripts/colour_offset_fit.py` measures
    /// it). Mapping gets each pose moved by it (the colour camera's pose), and each depth
    /// image is re-projected into the colour camera (nearest surface per pixel; a colour
    /// camera with finer pixels than the depth camera's gets holes between the splats, which
    /// evaluation skips like any missing depth). `None`: one centre, the poses are the colour
    /// camera's.
    pub colour_offset: Option<[f32; 3]>,
    /// Depth scale (stored value per metre) to use instead of the detected one.
    pub depth_scale: Option<f32>,
    /// TUM: largest timestamp difference (s) accepted when associating colour, depth and pose.
    pub tum_max_dt: f64,
    /// Undistort colour images when the camera has distortion coefficients (TUM's freiburg
    /// cameras, or a `[dataset.camera]` with `distortion`, in either layout).
    pub undistort: bool,
    /// Widest image to map (pixels; 0, the default: the files' size): a wider sequence is
    /// resized to this width, the height in proportion (rounded), unless a size is given
    /// (`--resize`). For cameras whose frames are larger than mapping needs.
    pub max_width: u32,
}

impl Default for DatasetConfig {
    fn default() -> Self {
        Self {
            format: None,
            camera: None,
            depth_camera: None,
            colour_offset: None,
            depth_scale: None,
            tum_max_dt: 0.02,
            undistort: true,
            max_width: 0,
        }
    }
}

/// Everything that can be wrong with a dataset on disk. Each message names the file (or folder)
/// and the problem.
#[derive(Debug, thiserror::Error)]
pub enum DatasetError {
    #[error("{}: file not found", path.display())]
    Missing { path: PathBuf },
    #[error("{}: cannot read: {source}", path.display())]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("{}: cannot decode image: {msg}", path.display())]
    Decode { path: PathBuf, msg: String },
    #[error("{}: unsupported image format: {msg}", path.display())]
    ImageFormat { path: PathBuf, msg: String },
    #[error("{}: image is {got_w}x{got_h}, expected {want_w}x{want_h}", path.display())]
    ImageSize {
        path: PathBuf,
        got_w: u32,
        got_h: u32,
        want_w: u32,
        want_h: u32,
    },
    #[error("{}:{line}: {msg}", path.display())]
    Parse {
        path: PathBuf,
        line: usize,
        msg: String,
    },
    #[error("{}: {poses} poses, but {frames} frames in {}", path.display(), frames_dir.display())]
    CountMismatch {
        path: PathBuf,
        frames_dir: PathBuf,
        frames: usize,
        poses: usize,
    },
    #[error("{}:{line}: pose is not a finite rigid transform: {msg}", path.display())]
    NotRigid {
        path: PathBuf,
        line: usize,
        msg: String,
    },
    #[error("{}: empty sequence: {msg}", path.display())]
    Empty { path: PathBuf, msg: String },
    #[error("{}: unknown depth scale: {msg}", path.display())]
    UnknownDepthScale { path: PathBuf, msg: String },
    #[error("{}: camera: {msg}", path.display())]
    Camera { path: PathBuf, msg: String },
    #[error("{}: not a recognised dataset layout: {msg}", path.display())]
    UnknownLayout { path: PathBuf, msg: String },
    #[error("{}: invalid load option: {msg}", path.display())]
    InvalidOption { path: PathBuf, msg: String },
    #[error("{}: {msg}", path.display())]
    TooLarge { path: PathBuf, msg: String },
    #[error("{}: frame {index} out of range (the selection has {len} frames)", path.display())]
    OutOfRange {
        path: PathBuf,
        index: usize,
        len: usize,
    },
}

impl DatasetError {
    /// The file or folder the error is about.
    pub fn path(&self) -> &Path {
        match self {
            DatasetError::Missing { path }
            | DatasetError::Io { path, .. }
            | DatasetError::Decode { path, .. }
            | DatasetError::ImageFormat { path, .. }
            | DatasetError::ImageSize { path, .. }
            | DatasetError::Parse { path, .. }
            | DatasetError::CountMismatch { path, .. }
            | DatasetError::NotRigid { path, .. }
            | DatasetError::Empty { path, .. }
            | DatasetError::UnknownDepthScale { path, .. }
            | DatasetError::Camera { path, .. }
            | DatasetError::UnknownLayout { path, .. }
            | DatasetError::InvalidOption { path, .. }
            | DatasetError::TooLarge { path, .. }
            | DatasetError::OutOfRange { path, .. } => path,
        }
    }

    pub(crate) fn io(path: &Path, source: std::io::Error) -> Self {
        if source.kind() == std::io::ErrorKind::NotFound {
            DatasetError::Missing {
                path: path.to_path_buf(),
            }
        } else {
            DatasetError::Io {
                path: path.to_path_buf(),
                source,
            }
        }
    }
}

/// Opens the dataset at `path`, detecting its layout (`rgb.txt` = TUM, `traj.txt` or
/// `results/` = Replica), with default configuration.
pub fn open(path: &Path, opts: &LoadOptions) -> Result<Box<dyn Dataset>, DatasetError> {
    open_with(path, opts, &DatasetConfig::default())
}

/// Opens the dataset at `path` with configuration overrides.
pub fn open_with(
    path: &Path,
    opts: &LoadOptions,
    cfg: &DatasetConfig,
) -> Result<Box<dyn Dataset>, DatasetError> {
    let ds = open_as(path, opts, cfg)?;
    match max_width_size(ds.intrinsics(), opts, cfg) {
        Some(size) => open_as(
            path,
            &LoadOptions {
                resize: Some(size),
                ..opts.clone()
            },
            cfg,
        ),
        None => Ok(ds),
    }
}

/// The size [`DatasetConfig::max_width`] resizes a sequence of intrinsics `k` (as opened
/// with `opts`) to, when it applies: no explicit resize and an image wider than the limit.
pub fn max_width_size(
    k: Intrinsics,
    opts: &LoadOptions,
    cfg: &DatasetConfig,
) -> Option<(u32, u32)> {
    if opts.resize.is_some() || cfg.max_width == 0 || k.width <= cfg.max_width {
        return None;
    }
    let w = cfg.max_width;
    let h = ((k.height as f64 * w as f64 / k.width as f64).round() as u32).max(1);
    Some((w, h))
}

fn open_as(
    path: &Path,
    opts: &LoadOptions,
    cfg: &DatasetConfig,
) -> Result<Box<dyn Dataset>, DatasetError> {
    match detect_format(path, cfg)? {
        DatasetFormat::Replica => Ok(Box::new(ReplicaDataset::open(path, opts, cfg)?)),
        DatasetFormat::Tum => Ok(Box::new(TumDataset::open(path, opts, cfg)?)),
    }
}

/// The layout of the folder at `path` (or `cfg.format` when set).
pub fn detect_format(path: &Path, cfg: &DatasetConfig) -> Result<DatasetFormat, DatasetError> {
    if !path.is_dir() {
        return Err(if path.exists() {
            DatasetError::UnknownLayout {
                path: path.to_path_buf(),
                msg: "expected a folder".into(),
            }
        } else {
            DatasetError::Missing {
                path: path.to_path_buf(),
            }
        });
    }
    if let Some(f) = cfg.format {
        return Ok(f);
    }
    if path.join("rgb.txt").is_file() || path.join("groundtruth.txt").is_file() {
        Ok(DatasetFormat::Tum)
    } else if path.join("traj.txt").is_file() || path.join("results").is_dir() {
        Ok(DatasetFormat::Replica)
    } else {
        Err(DatasetError::UnknownLayout {
            path: path.to_path_buf(),
            msg: "expected traj.txt and results/ (Replica) or rgb.txt and groundtruth.txt (TUM)"
                .into(),
        })
    }
}

/// The selected source indices and the output camera, shared by the loaders.
#[derive(Clone, Debug)]
pub(crate) struct Selection {
    pub indices: Vec<usize>,
    pub native: Intrinsics,
    pub resize: Option<(u32, u32)>,
    pub crop: u32,
    pub out: Intrinsics,
    /// The depth images' own camera when they are not registered to the colour images
    /// ([`DatasetConfig::depth_camera`]).
    pub depth_camera: Option<Intrinsics>,
    /// The colour camera's centre in the pose and depth camera's frame
    /// ([`DatasetConfig::colour_offset`]; zero = the same camera).
    pub colour_offset: [f32; 3],
}

impl Selection {
    /// The source index of selected frame `i` of the dataset at `root`.
    pub fn source(&self, root: &Path, i: usize) -> Result<usize, DatasetError> {
        self.indices
            .get(i)
            .copied()
            .ok_or_else(|| DatasetError::OutOfRange {
                path: root.to_path_buf(),
                index: i,
                len: self.indices.len(),
            })
    }

    /// Validates the options against a sequence of `n` frames with camera `native`.
    pub fn new(
        root: &Path,
        n: usize,
        native: Intrinsics,
        opts: &LoadOptions,
    ) -> Result<Self, DatasetError> {
        let bad = |msg: String| DatasetError::InvalidOption {
            path: root.to_path_buf(),
            msg,
        };
        if opts.stride == 0 {
            return Err(bad("stride must be at least 1".into()));
        }
        let end = opts.end.unwrap_or(n).min(n);
        if opts.start >= end {
            return Err(DatasetError::Empty {
                path: root.to_path_buf(),
                msg: format!(
                    "frame range {}..{} selects none of the {n} frames",
                    opts.start,
                    opts.end.map_or("end".to_string(), |e| e.to_string())
                ),
            });
        }
        let indices: Vec<usize> = (opts.start..end).step_by(opts.stride).collect();
        let mut k = native;
        if let Some((w, h)) = opts.resize {
            if w == 0 || h == 0 {
                return Err(bad(format!("resize to {w}x{h}")));
            }
            k = k.resized(w, h);
        }
        if 2 * opts.crop_edge as u64 >= k.width.min(k.height) as u64 {
            return Err(bad(format!(
                "crop_edge {} leaves nothing of a {}x{} image",
                opts.crop_edge, k.width, k.height
            )));
        }
        let out = k.cropped(opts.crop_edge);
        Ok(Self {
            indices,
            native,
            resize: opts.resize,
            crop: opts.crop_edge,
            out,
            depth_camera: None,
            colour_offset: [0.0; 3],
        })
    }

    /// Sets the depth images' own camera (checked like any camera; `None` = registered).
    pub fn with_depth_camera(
        mut self,
        root: &Path,
        camera: Option<&CameraConfig>,
    ) -> Result<Self, DatasetError> {
        if let Some(c) = camera {
            let k = c.intrinsics();
            check_camera(root, &k)?;
            self.depth_camera = Some(k);
        }
        Ok(self)
    }

    /// Sets the colour camera's centre in the pose camera's frame (`None` = the same centre).
    pub fn with_colour_offset(
        mut self,
        root: &Path,
        offset: Option<[f32; 3]>,
    ) -> Result<Self, DatasetError> {
        if let Some(o) = offset {
            if o.iter().any(|c| !c.is_finite() || c.abs() > 10.0) {
                return Err(DatasetError::InvalidOption {
                    path: root.to_path_buf(),
                    msg: format!(
                        "dataset.colour_offset {o:?}: need finite metres within 10 m of the \
                         pose camera"
                    ),
                });
            }
            self.colour_offset = o;
        }
        Ok(self)
    }

    /// The colour camera's pose for a pose of the pose (and depth) camera: moved by
    /// [`DatasetConfig::colour_offset`] along the camera's own axes.
    pub fn colour_pose(&self, p: Pose) -> Pose {
        if self.colour_offset == [0.0; 3] {
            return p;
        }
        let centre = p.transform(self.colour_offset);
        let mut m = p.m;
        for (row, c) in m.iter_mut().zip(centre) {
            row[3] = c;
        }
        Pose { m }
    }

    /// The camera of the depth images on disk.
    pub fn depth_native(&self) -> &Intrinsics {
        self.depth_camera.as_ref().unwrap_or(&self.native)
    }

    /// Resize and crop a colour image decoded at the native size.
    pub fn finish_rgb(&self, img: RgbImage) -> RgbImage {
        let img = match self.resize {
            Some((w, h)) if (w, h) != (img.width, img.height) => img.resized(w, h),
            _ => img,
        };
        if self.crop > 0 {
            img.cropped(self.crop)
        } else {
            img
        }
    }

    /// Resize and crop a depth image decoded at the native size.
    pub fn finish_depth(&self, img: DepthImage) -> DepthImage {
        let img = if self.depth_camera.is_some() || self.colour_offset != [0.0; 3] {
            img.registered_from(self.depth_native(), &self.native, self.colour_offset)
        } else {
            img
        };
        let img = match self.resize {
            Some((w, h)) if (w, h) != (img.width, img.height) => img.resized(w, h),
            _ => img,
        };
        if self.crop > 0 {
            img.cropped(self.crop)
        } else {
            img
        }
    }
}

/// Checks a camera for finite, positive values.
pub(crate) fn check_camera(path: &Path, k: &Intrinsics) -> Result<(), DatasetError> {
    let ok = k.width > 0
        && k.height > 0
        && k.width <= MAX_IMAGE_SIDE
        && k.height <= MAX_IMAGE_SIDE
        && k.fx.is_finite()
        && k.fy.is_finite()
        && k.fx > 0.0
        && k.fy > 0.0
        && k.cx.is_finite()
        && k.cy.is_finite();
    if ok {
        Ok(())
    } else {
        Err(DatasetError::Camera {
            path: path.to_path_buf(),
            msg: format!(
                "invalid intrinsics {k:?} (need a size of 1..={MAX_IMAGE_SIDE} pixels a side, \
                 positive focal lengths, a finite centre)"
            ),
        })
    }
}

/// Checks a depth scale for a finite positive value.
pub(crate) fn check_depth_scale(path: &Path, s: f32) -> Result<f32, DatasetError> {
    if s.is_finite() && s > 0.0 {
        Ok(s)
    } else {
        Err(DatasetError::UnknownDepthScale {
            path: path.to_path_buf(),
            msg: format!("scale must be a positive number, got {s}"),
        })
    }
}

fn open_image(path: &Path) -> Result<image::DynamicImage, DatasetError> {
    let reader = image::ImageReader::open(path)
        .map_err(|e| DatasetError::io(path, e))?
        .with_guessed_format()
        .map_err(|e| DatasetError::io(path, e))?;
    reader.decode().map_err(|e| image_error(path, e))
}

/// Maps a decoder error: truncated or corrupt data is a decode error, other I/O failures are
/// I/O errors.
fn image_error(path: &Path, e: image::ImageError) -> DatasetError {
    match e {
        image::ImageError::IoError(io)
            if !matches!(
                io.kind(),
                std::io::ErrorKind::UnexpectedEof | std::io::ErrorKind::InvalidData
            ) =>
        {
            DatasetError::io(path, io)
        }
        other => DatasetError::Decode {
            path: path.to_path_buf(),
            msg: other.to_string(),
        },
    }
}

fn check_size(path: &Path, got: (u32, u32), want: &Intrinsics) -> Result<(), DatasetError> {
    if got != (want.width, want.height) {
        return Err(DatasetError::ImageSize {
            path: path.to_path_buf(),
            got_w: got.0,
            got_h: got.1,
            want_w: want.width,
            want_h: want.height,
        });
    }
    Ok(())
}

/// Reads only the header of an image and checks its size.
pub(crate) fn check_image_header(path: &Path, want: &Intrinsics) -> Result<(), DatasetError> {
    let dims = image::ImageReader::open(path)
        .map_err(|e| DatasetError::io(path, e))?
        .with_guessed_format()
        .map_err(|e| DatasetError::io(path, e))?
        .into_dimensions()
        .map_err(|e| image_error(path, e))?;
    check_size(path, dims, want)
}

/// Decodes a colour image (any 8/16-bit grey or colour format) and checks its size.
pub fn load_rgb(path: &Path, want: &Intrinsics) -> Result<RgbImage, DatasetError> {
    let img = open_image(path)?;
    check_size(path, (img.width(), img.height()), want)?;
    let (w, h) = (img.width(), img.height());
    Ok(match img {
        image::DynamicImage::ImageRgb8(buf) => RgbImage::from_rgb8(w, h, buf.as_raw()),
        other => RgbImage {
            width: w,
            height: h,
            data: other.into_rgb32f().into_raw(),
        },
    })
}

/// The 16-bit value that marks a depth pixel without a measurement besides 0: the saturated
/// code, which no sensor reports as a distance. 7-Scenes' Kinect frames use it for invalid
/// depth; Replica-style writers clip farther depth to it (10 m at 6553.5 per metre). The
/// measurement that found it is in ARCHITECTURE.md.
pub const DEPTH_INVALID: u16 = u16::MAX;

/// Decodes a 16-bit single-channel depth PNG, divides by `scale` (value per metre) and checks
/// its size. 0 and [`DEPTH_INVALID`] are no measurement (depth 0).
pub fn load_depth(path: &Path, scale: f32, want: &Intrinsics) -> Result<DepthImage, DatasetError> {
    let img = open_image(path)?;
    check_size(path, (img.width(), img.height()), want)?;
    match img {
        image::DynamicImage::ImageLuma16(buf) => {
            let (w, h) = buf.dimensions();
            Ok(DepthImage {
                width: w,
                height: h,
                data: buf
                    .as_raw()
                    .iter()
                    .map(|&v| match v {
                        DEPTH_INVALID => 0.0,
                        v => v as f32 / scale,
                    })
                    .collect(),
            })
        }
        other => Err(DatasetError::ImageFormat {
            path: path.to_path_buf(),
            msg: format!(
                "depth must be a 16-bit single-channel image, found {:?}",
                other.color()
            ),
        }),
    }
}

/// Parses whitespace-separated numbers of one line; `Parse` error naming the token otherwise.
pub(crate) fn parse_numbers<T: std::str::FromStr>(
    path: &Path,
    line_no: usize,
    tokens: &[&str],
) -> Result<Vec<T>, DatasetError> {
    tokens
        .iter()
        .map(|t| {
            t.parse::<T>().map_err(|_| DatasetError::Parse {
                path: path.to_path_buf(),
                line: line_no,
                msg: format!("not a number: '{t}'"),
            })
        })
        .collect()
}

/// Checks that a pose is a finite rigid transform (`Pose::is_rigid(1e-3)`).
pub(crate) fn check_pose(path: &Path, line: usize, pose: &Pose) -> Result<(), DatasetError> {
    if pose.is_rigid(1e-3) {
        Ok(())
    } else {
        Err(DatasetError::NotRigid {
            path: path.to_path_buf(),
            line,
            msg: format!(
                "rotation is not orthonormal with determinant +1, or an entry is not finite: {:?}",
                pose.m
            ),
        })
    }
}

/// Reads a text file into lines.
pub(crate) fn read_text(path: &Path) -> Result<String, DatasetError> {
    let len = std::fs::metadata(path)
        .map_err(|e| DatasetError::io(path, e))?
        .len();
    if len > MAX_TEXT_BYTES {
        return Err(DatasetError::TooLarge {
            path: path.to_path_buf(),
            msg: format!(
                "{len} bytes, over the {MAX_TEXT_BYTES}-byte limit for a dataset text file"
            ),
        });
    }
    std::fs::read_to_string(path).map_err(|e| DatasetError::io(path, e))
}

/// Largest pose, file-list or camera text file read (256 MiB: a million frames' poses take
/// about 150 MB); checked before the file is read.
pub const MAX_TEXT_BYTES: u64 = 256 << 20;

/// Largest image side accepted from a camera description (pixels), checked before any image
/// buffer is sized from it.
pub const MAX_IMAGE_SIDE: u32 = 16384;

/// The last path component, for [`Dataset::name`].
pub(crate) fn folder_name(path: &Path) -> String {
    path.canonicalize()
        .ok()
        .as_deref()
        .unwrap_or(path)
        .file_name()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_else(|| path.display().to_string())
}

/// Median |dz| (metres) and number of compared pixels when frame `src`'s depth is
/// back-projected, moved into frame `dst`'s camera and compared with `dst`'s depth there.
/// The destination depth is interpolated bilinearly in inverse depth (exact on planes) from its
/// four neighbours, which must all be valid; pixels leaving the image or the camera are skipped.
/// `None` when either frame has no depth or nothing overlaps. A check of pose/depth consistency.
pub fn reprojection_median_dz(src: &Frame, dst: &Frame) -> Option<(f64, usize)> {
    let (ds, dd) = (src.depth.as_ref()?, dst.depth.as_ref()?);
    let (ks, kd) = (&src.intrinsics, &dst.intrinsics);
    let mut errs = Vec::new();
    for v in 0..ds.height {
        for u in 0..ds.width {
            let z = ds.get(u, v);
            if z <= 0.0 {
                continue;
            }
            let d = ks.direction(u as f32, v as f32);
            let pw = src.pose.transform([d[0] * z, d[1] * z, z]);
            let pc = dst.pose.inverse_transform(pw);
            if pc[2] <= 1e-6 {
                continue;
            }
            let (x, y, zc) = kd.project(pc);
            if !(x >= 0.0 && y >= 0.0) {
                continue;
            }
            let (x0, y0) = (x.floor() as u32, y.floor() as u32);
            if x0 + 1 >= dd.width || y0 + 1 >= dd.height {
                continue;
            }
            let q = [
                dd.get(x0, y0),
                dd.get(x0 + 1, y0),
                dd.get(x0, y0 + 1),
                dd.get(x0 + 1, y0 + 1),
            ];
            if q.iter().any(|&z| z <= 0.0) {
                continue;
            }
            let (fx, fy) = ((x - x0 as f32) as f64, (y - y0 as f32) as f64);
            let inv = |z: f32| 1.0 / z as f64;
            let top = inv(q[0]) * (1.0 - fx) + inv(q[1]) * fx;
            let bot = inv(q[2]) * (1.0 - fx) + inv(q[3]) * fx;
            let zd = 1.0 / (top * (1.0 - fy) + bot * fy);
            errs.push((zc as f64 - zd).abs());
        }
    }
    if errs.is_empty() {
        return None;
    }
    let n = errs.len();
    let mid = n / 2;
    let (_, m, _) = errs.select_nth_unstable_by(mid, |a, b| a.total_cmp(b));
    Some((*m, n))
}

/// Folder of the shared real sequences used by tests: `$HIMAP_DATA_DIR`, else
/// `<workspace>/../shared/data`; `None` (with the reason) when it does not exist.
#[doc(hidden)]
pub fn shared_data_dir() -> Result<PathBuf, String> {
    let dir = match std::env::var_os("HIMAP_DATA_DIR") {
        Some(d) => PathBuf::from(d),
        None => Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared/data"),
    };
    if dir.is_dir() {
        Ok(dir)
    } else {
        Err(format!(
            "shared data folder {} not found (set HIMAP_DATA_DIR)",
            dir.display()
        ))
    }
}
