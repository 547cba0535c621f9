//! Tests of the dataset loaders: small fixtures built in temporary folders (one per bad-input
//! case), hand-computed image operations, and the shared real sequences when present.

use std::path::{Path, PathBuf};

use himap_core::camera::{Intrinsics, Pose};

use super::tum::{quat_to_matrix, remap, undistort_map};
use super::*;

// ---------------------------------------------------------------------------------------------
// Fixture helpers
// ---------------------------------------------------------------------------------------------

const FW: u32 = 8;
const FH: u32 = 6;

/// Colour value of fixture frame `i` at (x, y, c), an 8-bit number.
fn fixture_rgb(i: usize, x: u32, y: u32, c: u32) -> u8 {
    ((i as u32 * 31 + x * 17 + y * 7 + c * 50) % 256) as u8
}

/// Depth value (16-bit) of fixture frame `i` at (x, y); 0 at (0, 0) (invalid).
fn fixture_depth(i: usize, x: u32, y: u32) -> u16 {
    if x == 0 && y == 0 {
        0
    } else {
        (1000 + i as u32 * 100 + x * 10 + y) as u16
    }
}

fn write_rgb_png(path: &Path, w: u32, h: u32, f: impl Fn(u32, u32, u32) -> u8) {
    let mut buf = Vec::with_capacity((3 * w * h) as usize);
    for y in 0..h {
        for x in 0..w {
            for c in 0..3 {
                buf.push(f(x, y, c));
            }
        }
    }
    image::save_buffer(path, &buf, w, h, image::ExtendedColorType::Rgb8).unwrap();
}

fn write_depth_png(path: &Path, w: u32, h: u32, f: impl Fn(u32, u32) -> u16) {
    let mut buf = Vec::with_capacity((w * h) as usize);
    for y in 0..h {
        for x in 0..w {
            buf.push(f(x, y));
        }
    }
    image::ImageBuffer::<image::Luma<u16>, Vec<u16>>::from_raw(w, h, buf)
        .unwrap()
        .save(path)
        .unwrap();
}

/// Pose of fixture frame `i`: rotation by 0.1 i rad about z, translation (i, 2i, 3i) cm.
fn fixture_pose(i: usize) -> Pose {
    let a = 0.1 * i as f32;
    let (s, c) = (a.sin(), a.cos());
    let t = 0.01 * i as f32;
    Pose {
        m: [
            [c, -s, 0.0, t],
            [s, c, 0.0, 2.0 * t],
            [0.0, 0.0, 1.0, 3.0 * t],
        ],
    }
}

fn pose_line(p: &Pose) -> String {
    let mut v = Vec::new();
    for row in &p.m {
        for x in row {
            v.push(format!("{x:.9e}"));
        }
    }
    v.extend(["0", "0", "0", "1"].map(String::from));
    v.join(" ")
}

/// A Replica-layout fixture of `n` 8x6 frames (PNG colour), camera fx = fy = 10, cx 3.5,
/// cy 2.5, depth scale 1000.
fn replica_fixture(n: usize) -> tempfile::TempDir {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path();
    std::fs::create_dir(root.join("results")).unwrap();
    let mut traj = String::new();
    for i in 0..n {
        write_rgb_png(
            &root.join(format!("results/frame{i:06}.png")),
            FW,
            FH,
            |x, y, c| fixture_rgb(i, x, y, c),
        );
        write_depth_png(
            &root.join(format!("results/depth{i:06}.png")),
            FW,
            FH,
            |x, y| fixture_depth(i, x, y),
        );
        traj.push_str(&pose_line(&fixture_pose(i)));
        traj.push('\n');
    }
    std::fs::write(root.join("traj.txt"), traj).unwrap();
    std::fs::write(
        root.join("cam_params.json"),
        r#"{"camera": {"w": 8, "h": 6, "fx": 10.0, "fy": 10.0, "cx": 3.5, "cy": 2.5, "scale": 1000.0}}"#,
    )
    .unwrap();
    dir
}

fn fixture_camera() -> Intrinsics {
    Intrinsics {
        width: FW,
        height: FH,
        fx: 10.0,
        fy: 10.0,
        cx: 3.5,
        cy: 2.5,
    }
}

fn open_default(root: &Path) -> Result<Box<dyn Dataset>, DatasetError> {
    open(root, &LoadOptions::default())
}

/// Unwraps an error, checks that its message names `file` and contains `words`.
fn expect_err<T>(r: Result<T, DatasetError>, file: &str, words: &str) -> DatasetError {
    let e = match r {
        Ok(_) => panic!("expected an error naming {file} ({words})"),
        Err(e) => e,
    };
    let msg = e.to_string();
    assert!(
        msg.contains(file) && msg.contains(words),
        "message {msg:?} should name {file:?} and say {words:?}"
    );
    e
}

fn replace_line(path: &Path, line: usize, new: &str) {
    let text = std::fs::read_to_string(path).unwrap();
    let mut lines: Vec<String> = text.lines().map(String::from).collect();
    lines[line] = new.to_string();
    std::fs::write(path, lines.join("\n") + "\n").unwrap();
}

// ---------------------------------------------------------------------------------------------
// Replica fixture: correct loading
// ---------------------------------------------------------------------------------------------

#[test]
fn replica_fixture_loads_exact_values() {
    let dir = replica_fixture(5);
    let ds = open_default(dir.path()).unwrap();
    assert_eq!(ds.len(), 5);
    assert!(ds.has_depth());
    assert_eq!(ds.intrinsics(), fixture_camera());
    assert_eq!(ds.name(), dir.path().file_name().unwrap().to_str().unwrap());
    for i in 0..5 {
        let f = ds.frame(i).unwrap();
        assert_eq!(f.index, i);
        assert_eq!((f.rgb.width, f.rgb.height), (FW, FH));
        // Poses were written with 10 significant digits: equal to f32 precision.
        for r in 0..3 {
            for c in 0..4 {
                assert!((f.pose.m[r][c] - fixture_pose(i).m[r][c]).abs() < 1e-7);
            }
        }
        assert_eq!(f.pose, ds.pose(i));
        let rgb = f.rgb.get(5, 3);
        for (c, &v) in rgb.iter().enumerate() {
            assert_eq!(v, fixture_rgb(i, 5, 3, c as u32) as f32 / 255.0);
        }
        let d = f.depth.unwrap();
        assert_eq!(d.get(0, 0), 0.0);
        // Depth value 1000 + 100 i + 10 x + y at scale 1000.
        assert_eq!(d.get(5, 3), (1053 + 100 * i) as f32 / 1000.0);
    }
    let e = expect_err(ds.frame(5), "", "out of range");
    assert!(matches!(
        e,
        DatasetError::OutOfRange {
            index: 5,
            len: 5,
            ..
        }
    ));
}

#[test]
fn saturated_depth_is_no_measurement() {
    // 0 and 65535 (7-Scenes' invalid code, a Replica writer's clip) load as 0; 65534 is a
    // distance.
    let dir = replica_fixture(1);
    write_depth_png(
        &dir.path().join("results/depth000000.png"),
        FW,
        FH,
        |x, y| match (x, y) {
            (1, 0) => u16::MAX,
            (2, 0) => u16::MAX - 1,
            _ => fixture_depth(0, x, y),
        },
    );
    let d = open_default(dir.path())
        .unwrap()
        .frame(0)
        .unwrap()
        .depth
        .unwrap();
    assert_eq!(d.get(0, 0), 0.0);
    assert_eq!(d.get(1, 0), 0.0);
    assert_eq!(d.get(2, 0), 65534.0 / 1000.0);
    assert_eq!(d.get(3, 0), 1030.0 / 1000.0);
}

#[test]
fn range_stride_and_no_depth() {
    let dir = replica_fixture(7);
    let opts = LoadOptions {
        start: 1,
        end: Some(6),
        stride: 2,
        load_depth: false,
        ..Default::default()
    };
    let ds = open(dir.path(), &opts).unwrap();
    // Frames 1, 3, 5.
    assert_eq!(ds.len(), 3);
    assert!(!ds.has_depth());
    let f = ds.frame(2).unwrap();
    assert_eq!(f.index, 5);
    assert!(f.depth.is_none());
    assert_eq!(ds.pose(1), fixture_pose(3).round_trip());
    // An end past the sequence is clamped.
    let opts = LoadOptions {
        end: Some(100),
        ..Default::default()
    };
    assert_eq!(open(dir.path(), &opts).unwrap().len(), 7);
}

trait RoundTrip {
    fn round_trip(self) -> Self;
}
impl RoundTrip for Pose {
    /// The pose as written to and parsed back from traj.txt.
    fn round_trip(self) -> Self {
        let mut p = self;
        for row in &mut p.m {
            for x in row {
                *x = format!("{x:.9e}").parse().unwrap();
            }
        }
        p
    }
}

#[test]
fn resize_and_crop_scale_intrinsics_and_images() {
    let dir = replica_fixture(2);
    let opts = LoadOptions {
        resize: Some((4, 3)),
        crop_edge: 1,
        ..Default::default()
    };
    let ds = open(dir.path(), &opts).unwrap();
    // Resize 8x6 -> 4x3: fx 10 -> 5, cx (3.5 + 0.5) / 2 - 0.5 = 1.5, cy (2.5 + 0.5) / 2 - 0.5
    // = 1.0; crop 1: 2x1, cx 0.5, cy 0.0.
    let k = ds.intrinsics();
    assert_eq!(
        (k.width, k.height, k.fx, k.fy, k.cx, k.cy),
        (2, 1, 5.0, 5.0, 0.5, 0.0)
    );
    let f = ds.frame(1).unwrap();
    assert_eq!((f.rgb.width, f.rgb.height), (2, 1));
    assert_eq!(f.intrinsics, k);
    // Output (1, 1) of the 4x3 image (kept by the crop as (0, 0)) samples source
    // ((1 + 0.5) * 2 - 0.5, (1 + 0.5) * 2 - 0.5) = (2.5, 2.5): the mean of source pixels
    // (2..3, 2..3). The fixture is affine in x and y (no wrap at these values), so the mean is
    // the value at (2.5, 2.5).
    for c in 0..3u32 {
        let mean: f32 = [(2, 2), (3, 2), (2, 3), (3, 3)]
            .iter()
            .map(|&(x, y)| fixture_rgb(1, x, y, c) as f32 / 255.0)
            .sum::<f32>()
            / 4.0;
        assert!((f.rgb.get(0, 0)[c as usize] - mean).abs() < 1e-6);
    }
    // Depth: nearest source floor((1 + 0.5) * 2) = 3 in x and y.
    assert_eq!(
        f.depth.unwrap().get(0, 0),
        fixture_depth(1, 3, 3) as f32 / 1000.0
    );
}

#[test]
fn bilinear_and_nearest_resize_hand_values() {
    // 4x1 ramp 0, 1, 2, 3 (all channels) resized to 2x1: sources at 0.5 and 2.5 -> 0.5, 2.5.
    let img = RgbImage {
        width: 4,
        height: 1,
        data: (0..4).flat_map(|x| [x as f32; 3]).collect(),
    };
    let r = img.resized(2, 1);
    assert_eq!(r.data, vec![0.5, 0.5, 0.5, 2.5, 2.5, 2.5]);
    // Upsampling 2 -> 4: sources -0.25 (clamped to 0), 0.25, 0.75, 1.25 (clamped to 1) of the
    // ramp 0, 1 -> 0, 0.25, 0.75, 1.
    let img = RgbImage {
        width: 2,
        height: 1,
        data: vec![0.0, 0.0, 0.0, 1.0, 1.0, 1.0],
    };
    let r = img.resized(4, 1);
    let red: Vec<f32> = r.data.chunks(3).map(|p| p[0]).collect();
    assert_eq!(red, vec![0.0, 0.25, 0.75, 1.0]);
    // Nearest depth 4 -> 2 picks sources floor(1.0) = 1 and floor(3.0) = 3.
    let d = DepthImage {
        width: 4,
        height: 1,
        data: vec![10.0, 11.0, 12.0, 13.0],
    };
    assert_eq!(d.resized(2, 1).data, vec![11.0, 13.0]);
    // Crop 1 of a 4x3: the middle 2x1.
    let d = DepthImage {
        width: 4,
        height: 3,
        data: (0..12).map(|x| x as f32).collect(),
    };
    assert_eq!(d.cropped(1).data, vec![5.0, 6.0]);
}

#[test]
fn camera_override_and_replica_defaults() {
    let dir = replica_fixture(2);
    // Without cam_params.json the Replica camera (1200x680) is assumed: the 8x6 images are then
    // the wrong size.
    std::fs::remove_file(dir.path().join("cam_params.json")).unwrap();
    let e = expect_err(
        open_default(dir.path()),
        "frame000000.png",
        "8x6, expected 1200x680",
    );
    assert!(matches!(e, DatasetError::ImageSize { .. }));
    // A configured camera and depth scale replace the defaults.
    let cfg = DatasetConfig {
        camera: Some(CameraConfig {
            width: 8,
            height: 6,
            fx: 7.0,
            fy: 7.0,
            cx: 3.5,
            cy: 2.5,
            distortion: None,
        }),
        depth_scale: Some(500.0),
        ..Default::default()
    };
    let ds = open_with(dir.path(), &LoadOptions::default(), &cfg).unwrap();
    assert_eq!(ds.intrinsics().fx, 7.0);
    let f = ds.frame(0).unwrap();
    assert_eq!(f.depth.unwrap().get(1, 0), 1010.0 / 500.0);
}

// ---------------------------------------------------------------------------------------------
// Replica fixture: every bad-input case is a clear error
// ---------------------------------------------------------------------------------------------

#[test]
fn missing_folder_traj_results_and_layout() {
    let dir = replica_fixture(2);
    let root = dir.path();
    expect_err(open_default(&root.join("nope")), "nope", "file not found");
    std::fs::remove_file(root.join("traj.txt")).unwrap();
    let e = expect_err(
        ReplicaDataset::open(root, &LoadOptions::default(), &DatasetConfig::default()),
        "traj.txt",
        "file not found",
    );
    assert!(matches!(e, DatasetError::Missing { .. }));
    let empty = tempfile::tempdir().unwrap();
    let e = expect_err(
        open_default(empty.path()),
        "",
        "not a recognised dataset layout",
    );
    assert_eq!(e.path(), empty.path());
    std::fs::write(empty.path().join("traj.txt"), "").unwrap();
    expect_err(open_default(empty.path()), "results", "file not found");
}

#[test]
fn missing_frame_and_depth_files() {
    let dir = replica_fixture(5);
    let root = dir.path();
    std::fs::remove_file(root.join("results/frame000002.png")).unwrap();
    // 4 frames are left with a gap; the first missing index is named.
    expect_err(open_default(root), "frame000002.png", "file not found");

    let dir = replica_fixture(5);
    let root = dir.path();
    std::fs::remove_file(root.join("results/depth000003.png")).unwrap();
    expect_err(open_default(root), "depth000003.png", "file not found");
    // Without depth the sequence opens.
    let opts = LoadOptions {
        load_depth: false,
        ..Default::default()
    };
    assert_eq!(open(root, &opts).unwrap().len(), 5);
    // A file deleted after opening is reported when the frame is read.
    let ds = open(root, &opts).unwrap();
    std::fs::remove_file(root.join("results/frame000004.png")).unwrap();
    expect_err(ds.frame(4), "frame000004.png", "file not found");
}

#[test]
fn undecodable_images() {
    let dir = replica_fixture(3);
    let root = dir.path();
    std::fs::write(root.join("results/frame000001.png"), b"this is not a png").unwrap();
    let ds = open_default(root).unwrap();
    let e = expect_err(ds.frame(1), "frame000001.png", "cannot decode image");
    assert!(matches!(e, DatasetError::Decode { .. }));
    // The first selected frame's header is checked when opening.
    std::fs::write(
        root.join("results/depth000000.png"),
        b"\x89PNG\r\n\x1a\ngarbage",
    )
    .unwrap();
    expect_err(open_default(root), "depth000000.png", "cannot decode image");
}

#[test]
fn images_of_the_wrong_size() {
    let dir = replica_fixture(3);
    let root = dir.path();
    write_rgb_png(&root.join("results/frame000002.png"), 9, 6, |_, _, _| 0);
    let ds = open_default(root).unwrap();
    let e = expect_err(ds.frame(2), "frame000002.png", "image is 9x6, expected 8x6");
    assert!(matches!(e, DatasetError::ImageSize { got_w: 9, .. }));
    write_depth_png(&root.join("results/depth000001.png"), 8, 5, |_, _| 1);
    expect_err(ds.frame(1), "depth000001.png", "image is 8x5, expected 8x6");
}

#[test]
fn depth_must_be_16_bit() {
    let dir = replica_fixture(2);
    let root = dir.path();
    write_rgb_png(&root.join("results/depth000001.png"), FW, FH, |_, _, _| 9);
    let ds = open_default(root).unwrap();
    let e = expect_err(ds.frame(1), "depth000001.png", "16-bit single-channel");
    assert!(matches!(e, DatasetError::ImageFormat { .. }));
}

#[test]
fn frame_pose_count_mismatch() {
    let dir = replica_fixture(4);
    let root = dir.path();
    let traj = root.join("traj.txt");
    let mut text = std::fs::read_to_string(&traj).unwrap();
    text.push_str(&pose_line(&Pose::IDENTITY));
    text.push('\n');
    std::fs::write(&traj, &text).unwrap();
    let e = expect_err(open_default(root), "traj.txt", "5 poses, but 4 frames");
    assert!(matches!(
        e,
        DatasetError::CountMismatch {
            frames: 4,
            poses: 5,
            ..
        }
    ));
    // Blank lines and comments are not poses.
    let lines: Vec<&str> = text.lines().take(4).collect();
    std::fs::write(&traj, format!("# c2w\n{}\n\n", lines.join("\n\n"))).unwrap();
    assert_eq!(open_default(root).unwrap().len(), 4);
}

#[test]
fn poses_must_be_finite_rigid_transforms() {
    let dir = replica_fixture(3);
    let traj = dir.path().join("traj.txt");
    // Scaled rotation on the second line.
    let mut p = Pose::IDENTITY;
    p.m[0][0] = 1.1;
    replace_line(&traj, 1, &pose_line(&p));
    let e = expect_err(
        open_default(dir.path()),
        "traj.txt:2",
        "not a finite rigid transform",
    );
    assert!(matches!(e, DatasetError::NotRigid { line: 2, .. }));
    // A reflection (determinant -1).
    let mut p = Pose::IDENTITY;
    p.m[2][2] = -1.0;
    replace_line(&traj, 1, &pose_line(&p));
    expect_err(
        open_default(dir.path()),
        "traj.txt:2",
        "not a finite rigid transform",
    );
    // NaN translation.
    let mut p = Pose::IDENTITY;
    p.m[1][3] = f32::NAN;
    replace_line(&traj, 2, &pose_line(&p));
    replace_line(&traj, 1, &pose_line(&Pose::IDENTITY));
    expect_err(
        open_default(dir.path()),
        "traj.txt:3",
        "not a finite rigid transform",
    );
    // Last row not 0 0 0 1.
    replace_line(&traj, 2, "1 0 0 0 0 1 0 0 0 0 1 0 0 0 0 2");
    expect_err(open_default(dir.path()), "traj.txt:3", "last row");
}

#[test]
fn traj_parse_errors() {
    let dir = replica_fixture(3);
    let traj = dir.path().join("traj.txt");
    replace_line(&traj, 0, "1 0 0 0 0 1 0 0 0 0 1 0 0 0 0");
    let e = expect_err(
        open_default(dir.path()),
        "traj.txt:1",
        "expected 16 numbers",
    );
    assert!(matches!(e, DatasetError::Parse { line: 1, .. }));
    replace_line(&traj, 0, "1 0 0 0 0 1 0 0 0 0 1 x 0 0 0 1");
    expect_err(open_default(dir.path()), "traj.txt:1", "not a number: 'x'");
}

#[test]
fn empty_sequences() {
    let dir = tempfile::tempdir().unwrap();
    std::fs::create_dir(dir.path().join("results")).unwrap();
    std::fs::write(dir.path().join("traj.txt"), "").unwrap();
    let e = expect_err(open_default(dir.path()), "results", "empty sequence");
    assert!(matches!(e, DatasetError::Empty { .. }));
    // A range that selects nothing.
    let dir = replica_fixture(3);
    let opts = LoadOptions {
        start: 3,
        ..Default::default()
    };
    expect_err(open(dir.path(), &opts), "", "selects none of the 3 frames");
}

#[test]
fn unknown_depth_scale() {
    let dir = replica_fixture(2);
    let params = dir.path().join("cam_params.json");
    std::fs::write(
        &params,
        r#"{"camera": {"w": 8, "h": 6, "fx": 10.0, "fy": 10.0, "cx": 3.5, "cy": 2.5}}"#,
    )
    .unwrap();
    let e = expect_err(
        open_default(dir.path()),
        "cam_params.json",
        "unknown depth scale",
    );
    assert!(matches!(e, DatasetError::UnknownDepthScale { .. }));
    // Without depth the scale is not needed; with a configured scale it is known.
    let no_depth = LoadOptions {
        load_depth: false,
        ..Default::default()
    };
    assert!(open(dir.path(), &no_depth).is_ok());
    let cfg = DatasetConfig {
        depth_scale: Some(1000.0),
        ..Default::default()
    };
    assert!(open_with(dir.path(), &LoadOptions::default(), &cfg).is_ok());
    // A scale that is not a positive number.
    std::fs::write(
        &params,
        r#"{"camera": {"w": 8, "h": 6, "fx": 10.0, "fy": 10.0, "cx": 3.5, "cy": 2.5, "scale": 0}}"#,
    )
    .unwrap();
    expect_err(
        open_default(dir.path()),
        "cam_params.json",
        "unknown depth scale",
    );
}

#[test]
fn bad_camera_files_and_options() {
    let dir = replica_fixture(2);
    let params = dir.path().join("cam_params.json");
    std::fs::write(&params, r#"{"camera": {"w": 8, "h": 6}}"#).unwrap();
    let e = expect_err(
        open_default(dir.path()),
        "cam_params.json:1",
        "missing field",
    );
    assert!(matches!(e, DatasetError::Parse { .. }));
    std::fs::write(
        &params,
        r#"{"camera": {"w": 8, "h": 6, "fx": -1.0, "fy": 10.0, "cx": 3.5, "cy": 2.5, "scale": 1}}"#,
    )
    .unwrap();
    expect_err(
        open_default(dir.path()),
        "cam_params.json",
        "invalid intrinsics",
    );
    // A size no image buffer should be made for.
    std::fs::write(
        &params,
        r#"{"camera": {"w": 4000000000, "h": 6, "fx": 10.0, "fy": 10.0, "cx": 3.5, "cy": 2.5, "scale": 1}}"#,
    )
    .unwrap();
    expect_err(
        open_default(dir.path()),
        "cam_params.json",
        "1..=16384 pixels",
    );

    let dir = replica_fixture(2);
    let opts = LoadOptions {
        stride: 0,
        ..Default::default()
    };
    expect_err(open(dir.path(), &opts), "", "stride must be at least 1");
    let opts = LoadOptions {
        crop_edge: 3,
        ..Default::default()
    };
    expect_err(
        open(dir.path(), &opts),
        "",
        "crop_edge 3 leaves nothing of a 8x6 image",
    );
}

// ---------------------------------------------------------------------------------------------
// TUM
// ---------------------------------------------------------------------------------------------

/// Unit quaternion (x, y, z, w) of a rotation matrix (Shepperd's method, f64).
fn matrix_to_quat(r: [[f64; 3]; 3]) -> [f64; 4] {
    let tr = r[0][0] + r[1][1] + r[2][2];
    let q = if tr > 0.0 {
        let s = (tr + 1.0).sqrt() * 2.0;
        [
            (r[2][1] - r[1][2]) / s,
            (r[0][2] - r[2][0]) / s,
            (r[1][0] - r[0][1]) / s,
            0.25 * s,
        ]
    } else if r[0][0] > r[1][1] && r[0][0] > r[2][2] {
        let s = (1.0 + r[0][0] - r[1][1] - r[2][2]).sqrt() * 2.0;
        [
            0.25 * s,
            (r[0][1] + r[1][0]) / s,
            (r[0][2] + r[2][0]) / s,
            (r[2][1] - r[1][2]) / s,
        ]
    } else if r[1][1] > r[2][2] {
        let s = (1.0 + r[1][1] - r[0][0] - r[2][2]).sqrt() * 2.0;
        [
            (r[0][1] + r[1][0]) / s,
            0.25 * s,
            (r[1][2] + r[2][1]) / s,
            (r[0][2] - r[2][0]) / s,
        ]
    } else {
        let s = (1.0 + r[2][2] - r[0][0] - r[1][1]).sqrt() * 2.0;
        [
            (r[0][2] + r[2][0]) / s,
            (r[1][2] + r[2][1]) / s,
            0.25 * s,
            (r[1][0] - r[0][1]) / s,
        ]
    };
    let n = q.iter().map(|x| x * x).sum::<f64>().sqrt();
    q.map(|x| x / n)
}

fn gt_line(t: f64, p: &Pose) -> String {
    let r = [0, 1, 2].map(|i| [0, 1, 2].map(|j| p.m[i][j] as f64));
    let q = matrix_to_quat(r);
    format!(
        "{t:.6} {:.9} {:.9} {:.9} {:.12} {:.12} {:.12} {:.12}",
        p.m[0][3], p.m[1][3], p.m[2][3], q[0], q[1], q[2], q[3]
    )
}

/// A small TUM fixture: `n` 8x6 frames at 30 Hz, depth and poses with timestamp jitter, a
/// decoy pose between frames, and one trailing colour frame without a pose.
fn tum_fixture(name: &str, n: usize) -> (tempfile::TempDir, PathBuf) {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path().join(name);
    std::fs::create_dir_all(root.join("rgb")).unwrap();
    std::fs::create_dir_all(root.join("depth")).unwrap();
    let mut rgb = String::from("# color images\n# file: 'fixture'\n# timestamp filename\n");
    let mut depth = String::from("# depth maps\n");
    let mut gt = String::from("# ground truth trajectory\n# timestamp tx ty tz qx qy qz qw\n");
    for i in 0..n + 1 {
        let t = 1000.0 + i as f64 / 30.0;
        let name = format!("{t:.6}.png");
        write_rgb_png(&root.join("rgb").join(&name), FW, FH, |x, y, c| {
            fixture_rgb(i, x, y, c)
        });
        rgb.push_str(&format!("{t:.6} rgb/{name}\n"));
        if i == n {
            break;
        }
        let td = t + 0.004 * ((i % 3) as f64 - 1.0);
        let dname = format!("{td:.6}.png");
        write_depth_png(&root.join("depth").join(&dname), FW, FH, |x, y| {
            fixture_depth(i, x, y)
        });
        depth.push_str(&format!("{td:.6} depth/{dname}\n"));
        gt.push_str(&gt_line(t - 0.003, &fixture_pose(i)));
        gt.push('\n');
        // A decoy half a frame later, 16.7 ms from the next frame.
        let mut decoy = fixture_pose(i);
        decoy.m[0][3] += 1.0;
        gt.push_str(&gt_line(t + 0.5 / 30.0, &decoy));
        gt.push('\n');
    }
    std::fs::write(root.join("rgb.txt"), rgb).unwrap();
    std::fs::write(root.join("depth.txt"), depth).unwrap();
    std::fs::write(root.join("groundtruth.txt"), gt).unwrap();
    (dir, root)
}

fn fixture_camera_config() -> DatasetConfig {
    let k = fixture_camera();
    DatasetConfig {
        camera: Some(CameraConfig::pinhole(&k)),
        ..Default::default()
    }
}

#[test]
fn tum_fixture_associates_by_nearest_timestamp() {
    let (_dir, root) = tum_fixture("tum_fixture", 6);
    let ds = TumDataset::open(&root, &LoadOptions::default(), &fixture_camera_config()).unwrap();
    // The trailing colour frame has neither pose nor depth within 0.02 s.
    assert_eq!(ds.len(), 6);
    assert_eq!(ds.dropped(), 1);
    assert!(ds.has_depth());
    assert!(!ds.undistorts());
    for i in 0..6 {
        let f = ds.frame(i).unwrap();
        let want = fixture_pose(i);
        for r in 0..3 {
            for c in 0..4 {
                assert!(
                    (f.pose.m[r][c] - want.m[r][c]).abs() < 1e-6,
                    "frame {i}: {:?} vs {:?}",
                    f.pose,
                    want
                );
            }
        }
        assert_eq!(f.rgb.get(2, 1)[1], fixture_rgb(i, 2, 1, 1) as f32 / 255.0);
        // TUM depth scale 5000.
        assert_eq!(
            f.depth.unwrap().get(4, 2),
            fixture_depth(i, 4, 2) as f32 / 5000.0
        );
        // Written with 6 decimals.
        assert!((ds.timestamp(i) - (1000.0 + i as f64 / 30.0)).abs() <= 5e-7);
    }
    // Through `open`, which detects the layout (the camera still comes from the config).
    let ds = open_with(&root, &LoadOptions::default(), &fixture_camera_config()).unwrap();
    assert_eq!(ds.len(), 6);
    // A tolerance below the 3 ms pose offset associates nothing.
    let cfg = DatasetConfig {
        tum_max_dt: 0.002,
        ..fixture_camera_config()
    };
    let e = expect_err(
        open_with(&root, &LoadOptions::default(), &cfg),
        "rgb.txt",
        "empty sequence",
    );
    assert!(matches!(e, DatasetError::Empty { .. }));
}

#[test]
fn tum_freiburg_camera_from_folder_name() {
    // The fixture images are 8x6, so a detected 640x480 freiburg camera is reported as a size
    // mismatch: this shows which camera was chosen.
    let (_dir, root) = tum_fixture("rgbd_dataset_freiburg2_fixture", 2);
    expect_err(
        open_default(&root),
        "rgb/1000.000000.png",
        "expected 640x480",
    );
    assert_eq!(
        detect_freiburg_k(&root),
        CameraConfig::TUM_FREIBURG2.intrinsics()
    );
    let (_dir, root) = tum_fixture("rgbd_dataset_freiburg3_x", 2);
    assert_eq!(
        detect_freiburg_k(&root),
        CameraConfig::TUM_FREIBURG3.intrinsics()
    );
    let (_dir, root) = tum_fixture("rgbd_dataset_freiburg1_x", 2);
    assert_eq!(
        detect_freiburg_k(&root),
        CameraConfig::TUM_FREIBURG1.intrinsics()
    );
    // Unknown camera.
    let (_dir, root) = tum_fixture("my_sequence", 2);
    let e = expect_err(open_default(&root), "my_sequence", "unknown camera");
    assert!(matches!(e, DatasetError::Camera { .. }));
}

fn detect_freiburg_k(root: &Path) -> Intrinsics {
    tum::detect_freiburg(root).unwrap().intrinsics()
}

#[test]
fn tum_bad_inputs() {
    let cfg = fixture_camera_config();
    let opts = LoadOptions::default();
    // Missing ground truth.
    let (_d, root) = tum_fixture("t", 3);
    std::fs::remove_file(root.join("groundtruth.txt")).unwrap();
    expect_err(
        open_with(&root, &opts, &cfg),
        "groundtruth.txt",
        "file not found",
    );
    // A quaternion that is not unit.
    let (_d, root) = tum_fixture("t", 3);
    replace_line(
        &root.join("groundtruth.txt"),
        3,
        "1000.01 0 0 0 0.5 0.5 0.5 0.9",
    );
    let e = expect_err(
        open_with(&root, &opts, &cfg),
        "groundtruth.txt:4",
        "not a finite rigid transform",
    );
    assert!(matches!(e, DatasetError::NotRigid { line: 4, .. }));
    // A non-finite translation.
    replace_line(&root.join("groundtruth.txt"), 3, "1000.01 0 inf 0 0 0 0 1");
    expect_err(
        open_with(&root, &opts, &cfg),
        "groundtruth.txt:4",
        "not a finite rigid",
    );
    // Wrong number of fields, bad timestamp.
    replace_line(&root.join("groundtruth.txt"), 3, "1000.01 0 0 0 0 0 1");
    expect_err(
        open_with(&root, &opts, &cfg),
        "groundtruth.txt:4",
        "found 7 fields",
    );
    let (_d, root) = tum_fixture("t", 3);
    replace_line(&root.join("rgb.txt"), 4, "abc rgb/x.png");
    expect_err(
        open_with(&root, &opts, &cfg),
        "rgb.txt:5",
        "not a number: 'abc'",
    );
    // A listed image that does not exist.
    let (_d, root) = tum_fixture("t", 3);
    replace_line(&root.join("depth.txt"), 2, "1000.033333 depth/missing.png");
    expect_err(
        open_with(&root, &opts, &cfg),
        "depth/missing.png",
        "file not found",
    );
    // Empty lists.
    let (_d, root) = tum_fixture("t", 3);
    std::fs::write(root.join("rgb.txt"), "# nothing\n").unwrap();
    expect_err(open_with(&root, &opts, &cfg), "rgb.txt", "no colour frames");
    // Wrong image size in a later frame.
    let (_d, root) = tum_fixture("t", 3);
    let ds = open_with(&root, &opts, &cfg).unwrap();
    let p = root.join(format!("rgb/{:.6}.png", 1000.0 + 2.0 / 30.0));
    write_rgb_png(&p, 3, 3, |_, _, _| 0);
    expect_err(ds.frame(2), "png", "image is 3x3, expected 8x6");
    // Depth scale that is not positive.
    let bad = DatasetConfig {
        depth_scale: Some(-1.0),
        ..cfg.clone()
    };
    expect_err(open_with(&root, &opts, &bad), "", "unknown depth scale");
}

#[test]
fn quaternion_conversion_hand_values() {
    // 90 degrees about z: q = (0, 0, sin 45, cos 45); R maps x -> y.
    let h = std::f64::consts::FRAC_1_SQRT_2;
    let r = quat_to_matrix([0.0, 0.0, h, h]);
    let want = [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]];
    for i in 0..3 {
        for j in 0..3 {
            assert!((r[i][j] - want[i][j]).abs() < 1e-12);
        }
    }
    // 180 degrees about x: q = (1, 0, 0, 0).
    let r = quat_to_matrix([1.0, 0.0, 0.0, 0.0]);
    assert_eq!(r, [[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]]);
    // Round trip through the test's inverse.
    for i in 0..20 {
        let p = fixture_pose(i * 3);
        let q = matrix_to_quat([0, 1, 2].map(|a| [0, 1, 2].map(|b| p.m[a][b] as f64)));
        let r = quat_to_matrix(q);
        for (row, prow) in r.iter().zip(&p.m) {
            for (x, y) in row.iter().zip(prow) {
                assert!((x - *y as f64).abs() < 1e-6);
            }
        }
    }
}

#[test]
fn undistortion_map_hand_values() {
    let k = Intrinsics {
        width: 201,
        height: 201,
        fx: 100.0,
        fy: 100.0,
        cx: 50.0,
        cy: 50.0,
    };
    let at = |map: &[[f32; 2]], u: usize, v: usize| map[v * 201 + u];
    // k1 = 0.1: pixel (150, 50) is x = 1, y = 0, r^2 = 1, radial 1.1 -> source (160, 50).
    let map = undistort_map(&k, [0.1, 0.0, 0.0, 0.0, 0.0]);
    assert_eq!(at(&map, 50, 50), [50.0, 50.0]);
    let s = at(&map, 150, 50);
    assert!((s[0] - 160.0).abs() < 1e-4 && (s[1] - 50.0).abs() < 1e-4);
    // p1 = 0.01 at (150, 150): x = y = 1, r^2 = 2; xd = 1 + 2 p1 = 1.02, yd = 1 + p1 (2 + 2)
    // = 1.04 -> (152, 154).
    let map = undistort_map(&k, [0.0, 0.0, 0.01, 0.0, 0.0]);
    let s = at(&map, 150, 150);
    assert!((s[0] - 152.0).abs() < 1e-4 && (s[1] - 154.0).abs() < 1e-4);
    // k2 = 0.1, k3 = 0.01 at (150, 50): radial 1 + 0.1 + 0.01 = 1.11 -> (161, 50).
    let map = undistort_map(&k, [0.0, 0.1, 0.0, 0.0, 0.01]);
    let s = at(&map, 150, 50);
    assert!((s[0] - 161.0).abs() < 1e-4);
    // Remap of a horizontal ramp: value = source x (bilinear is exact on a ramp); black
    // outside.
    let img = RgbImage {
        width: 201,
        height: 201,
        data: (0..201 * 201).flat_map(|i| [(i % 201) as f32; 3]).collect(),
    };
    let map = undistort_map(&k, [0.1, 0.0, 0.0, 0.0, 0.0]);
    let out = tum::remap(&img, &map);
    // (100, 50): x = 0.5, radial 1.025 -> source x 101.25.
    assert!((out.get(100, 50)[0] - 101.25).abs() < 1e-3);
    // (200, 200): x = y = 1.5, r^2 = 4.5, radial 1.45 -> source 267.5, outside -> black.
    assert_eq!(out.get(200, 200), [0.0; 3]);
}

#[test]
fn tum_undistorts_colour_only() {
    let (_dir, root) = tum_fixture("t", 2);
    let mut cfg = fixture_camera_config();
    cfg.camera.as_mut().unwrap().distortion = Some([0.05, 0.0, 0.0, 0.0, 0.0]);
    let ds = TumDataset::open(&root, &LoadOptions::default(), &cfg).unwrap();
    assert!(ds.undistorts());
    let f = ds.frame(1).unwrap();
    let map = undistort_map(&fixture_camera(), [0.05, 0.0, 0.0, 0.0, 0.0]);
    let raw = load_rgb(
        &root.join(format!("rgb/{:.6}.png", 1000.0 + 1.0 / 30.0)),
        &fixture_camera(),
    )
    .unwrap();
    assert_eq!(f.rgb, tum::remap(&raw, &map));
    assert_ne!(f.rgb, raw);
    assert_eq!(
        f.depth.unwrap().get(1, 1),
        fixture_depth(1, 1, 1) as f32 / 5000.0
    );
    // Disabled in the configuration.
    cfg.undistort = false;
    let ds = TumDataset::open(&root, &LoadOptions::default(), &cfg).unwrap();
    assert_eq!(ds.frame(1).unwrap().rgb, raw);
}

// ---------------------------------------------------------------------------------------------
// Real sequences (skipped with a message when ../shared/data is absent)
// ---------------------------------------------------------------------------------------------

fn real(name: &str) -> Option<PathBuf> {
    match shared_data_dir() {
        Ok(d) if d.join(name).is_dir() => Some(d.join(name)),
        Ok(d) => {
            eprintln!("skipping: {} not found", d.join(name).display());
            None
        }
        Err(why) => {
            eprintln!("skipping: {why}");
            None
        }
    }
}

#[test]
fn icl_livingroom_loads_and_reprojects() {
    let Some(root) = real("icl-livingroom1") else {
        return;
    };
    let ds = open_default(&root).unwrap();
    assert_eq!(ds.len(), 211);
    assert!(ds.has_depth());
    let k = ds.intrinsics();
    assert_eq!(
        (k.width, k.height, k.fx, k.fy, k.cx, k.cy),
        (640, 480, 525.0, 525.0, 319.5, 239.5)
    );
    let f0 = ds.frame(0).unwrap();
    let f10 = ds.frame(10).unwrap();
    assert_eq!((f0.rgb.width, f0.rgb.height), (640, 480));
    assert_eq!(f0.pose, Pose::IDENTITY);
    let (dz, n) = reprojection_median_dz(&f0, &f10).unwrap();
    eprintln!(
        "ICL: median |dz| frame 0 -> 10: {:.3} mm over {n} pixels",
        dz * 1e3
    );
    assert!(n > 100_000, "{n}");
    assert!(dz < 2e-3, "median |dz| {dz}");
    // Resized and cropped, the poses and scaled intrinsics still agree.
    let opts = LoadOptions {
        resize: Some((320, 240)),
        crop_edge: 8,
        ..Default::default()
    };
    let ds = open(&root, &opts).unwrap();
    assert_eq!(ds.intrinsics().width, 304);
    let (a, b) = (ds.frame(0).unwrap(), ds.frame(10).unwrap());
    let (dz, _) = reprojection_median_dz(&a, &b).unwrap();
    eprintln!("ICL 320x240 crop 8: median |dz| {:.3} mm", dz * 1e3);
    assert!(dz < 3e-3, "median |dz| {dz}");
}

#[test]
fn sevenscenes_redkitchen_loads_and_reprojects() {
    let Some(root) = real("7scenes-redkitchen") else {
        return;
    };
    let ds = open_default(&root).unwrap();
    assert_eq!(ds.len(), 250);
    let k = ds.intrinsics();
    assert_eq!(
        (k.width, k.height, k.fx, k.fy, k.cx, k.cy),
        (640, 480, 585.0, 585.0, 320.0, 240.0)
    );
    let f0 = ds.frame(0).unwrap();
    let f10 = ds.frame(10).unwrap();
    assert_eq!((f0.rgb.width, f0.rgb.height), (640, 480));
    let d = f0.depth.as_ref().unwrap();
    let holes = d.data.iter().filter(|&&z| z == 0.0).count();
    assert!(holes > 0 && holes < d.data.len() / 2, "{holes} holes");
    // Frame 214 has 3992 pixels of the invalid code 65535 (not 65.5 m): none may load as
    // a distance beyond the Kinect's range.
    let far = ds.frame(214).unwrap().depth.unwrap();
    assert!(far.data.iter().all(|&z| z < 5.0), "depth beyond 5 m");
    let (dz, n) = reprojection_median_dz(&f0, &f10).unwrap();
    eprintln!(
        "7-Scenes: median |dz| frame 0 -> 10: {:.3} mm over {n} pixels",
        dz * 1e3
    );
    assert!(n > 50_000, "{n}");
    assert!(dz < 2e-2, "median |dz| {dz}");
    // A wrong pose is detected by the same check (guards against a vacuous test).
    // 10 cm along the optical axis.
    let mut moved = f10.clone();
    for r in 0..3 {
        moved.pose.m[r][3] += 0.1 * moved.pose.m[r][2];
    }
    let (bad, _) = reprojection_median_dz(&f0, &moved).unwrap();
    assert!(bad > 3.0 * dz, "{bad} vs {dz}");
}

#[test]
fn tum_fixture_converted_from_icl_matches() {
    let Some(icl_root) = real("icl-livingroom1") else {
        return;
    };
    let icl = open_default(&icl_root).unwrap();
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path().join("icl_as_tum");
    std::fs::create_dir_all(root.join("rgb")).unwrap();
    std::fs::create_dir_all(root.join("depth")).unwrap();
    let mut rgb_txt = String::from("# color images\n# timestamp filename\n");
    let mut depth_txt = String::from("# depth maps\n# timestamp filename\n");
    let mut gt_txt = String::from("# ground truth trajectory\n# timestamp tx ty tz qx qy qz qw\n");
    let n = 12;
    for i in 0..n {
        let f = icl.frame(i).unwrap();
        let t = 1_311_868_164.0 + i as f64 / 30.0;
        // Small jitter: depth within 7 ms, pose within 5 ms of the colour timestamp.
        let jd = 0.007 * (((i * 7) % 5) as f64 / 2.0 - 1.0);
        let jg = 0.005 * (((i * 3) % 4) as f64 / 1.5 - 1.0);
        let (w, h) = (f.rgb.width, f.rgb.height);
        let rgb8 = f.rgb.to_rgb8();
        let rn = format!("rgb/{t:.6}.png");
        image::save_buffer(root.join(&rn), &rgb8, w, h, image::ExtendedColorType::Rgb8).unwrap();
        rgb_txt.push_str(&format!("{t:.6} {rn}\n"));
        let d = f.depth.as_ref().unwrap();
        let d16: Vec<u16> = d
            .data
            .iter()
            .map(|&z| {
                let v = (z * 5000.0).round();
                assert!(v <= 65535.0, "depth {z} does not fit the TUM scale");
                v as u16
            })
            .collect();
        let dn = format!("depth/{:.6}.png", t + jd);
        image::ImageBuffer::<image::Luma<u16>, Vec<u16>>::from_raw(w, h, d16)
            .unwrap()
            .save(root.join(&dn))
            .unwrap();
        depth_txt.push_str(&format!("{:.6} {dn}\n", t + jd));
        gt_txt.push_str(&gt_line(t + jg, &f.pose));
        gt_txt.push('\n');
    }
    std::fs::write(root.join("rgb.txt"), rgb_txt).unwrap();
    std::fs::write(root.join("depth.txt"), depth_txt).unwrap();
    std::fs::write(root.join("groundtruth.txt"), gt_txt).unwrap();

    let k = icl.intrinsics();
    let cfg = DatasetConfig {
        camera: Some(CameraConfig::pinhole(&k)),
        ..Default::default()
    };
    let tum = open_with(&root, &LoadOptions::default(), &cfg).unwrap();
    assert_eq!(tum.len(), n);
    assert_eq!(tum.intrinsics(), k);
    for i in 0..n {
        let a = icl.frame(i).unwrap();
        let b = tum.frame(i).unwrap();
        for r in 0..3 {
            for c in 0..4 {
                assert!(
                    (a.pose.m[r][c] - b.pose.m[r][c]).abs() < 1e-5,
                    "frame {i} pose entry ({r}, {c}): {} vs {}",
                    a.pose.m[r][c],
                    b.pose.m[r][c]
                );
            }
        }
        assert!(a.rgb == b.rgb, "frame {i}: colour differs");
        // value / 1000 and 5 value / 5000 round the same real number.
        assert!(a.depth == b.depth, "frame {i}: depth differs");
    }
    let (dz, _) = reprojection_median_dz(&tum.frame(0).unwrap(), &tum.frame(10).unwrap()).unwrap();
    eprintln!("ICL as TUM: median |dz| frame 0 -> 10: {:.3} mm", dz * 1e3);
    assert!(dz < 2e-3);
}

#[test]
fn binomial_blur_hand_values() {
    // An impulse in a 5x1 image: the horizontal pass gives the taps, the vertical pass (one
    // row, borders clamped) leaves them.
    let mut img = RgbImage::new(5, 1);
    img.data[2 * 3] = 1.0;
    let b = img.blurred(1);
    let want = [1.0, 4.0, 6.0, 4.0, 1.0].map(|x| x / 16.0);
    for (x, w) in want.iter().enumerate() {
        assert_eq!(b.get(x as u32, 0), [*w, 0.0, 0.0]);
    }
    // Clamped borders keep a constant image constant; zero passes are the identity.
    let mut c = RgbImage::new(4, 3);
    c.data.iter_mut().for_each(|x| *x = 0.375);
    assert!(c.blurred(3).data.iter().all(|&x| x == 0.375));
    assert_eq!(img.blurred(0).data, img.data);
    // Two passes: the taps convolved with themselves ([1 8 28 56 70 ...] / 256 at the centre).
    let mut wide = RgbImage::new(9, 1);
    wide.data[4 * 3 + 1] = 1.0;
    assert_eq!(wide.blurred(2).get(4, 0)[1], 70.0 / 256.0);
}

#[test]
fn depth_registered_into_another_camera_hand_values() {
    // A 4x3 depth camera with focal 2 seen from a colour camera with focal 1 and the same
    // centre pixel: colour pixel (u, v) looks along ((u - 1.5), (v - 1)) / 1, which the depth
    // camera sees at 2 * (u - 1.5) + 1.5 (rounded; half-way rounds away from zero).
    let from = Intrinsics {
        width: 4,
        height: 3,
        fx: 2.0,
        fy: 2.0,
        cx: 1.5,
        cy: 1.0,
    };
    let to = Intrinsics {
        fx: 1.0,
        fy: 1.0,
        ..from
    };
    let mut d = DepthImage::new(4, 3);
    for (i, z) in d.data.iter_mut().enumerate() {
        *z = 1.0 + i as f32;
    }
    let r = d.registered(&from, &to);
    // u = 1 -> 0.5 -> 1 (rounds up), u = 2 -> 2.5 -> 3, u = 0 -> -1.5 outside, u = 3 -> 4.5
    // outside; v = 1 -> 1, v = 0 -> -1 outside, v = 2 -> 3 outside.
    let want = [
        [0.0, 0.0, 0.0, 0.0],
        [0.0, d.get(1, 1), d.get(3, 1), 0.0],
        [0.0, 0.0, 0.0, 0.0],
    ];
    for v in 0..3 {
        for u in 0..4 {
            assert_eq!(r.get(u, v), want[v as usize][u as usize], "({u}, {v})");
        }
    }
    // The same camera is the identity.
    assert_eq!(d.registered(&from, &from).data, d.data);
}

/// A synthetic Replica-layout room of `frames` 40x30 frames (seed 0) in a temporary folder.
fn synthetic_40x30(frames: usize) -> tempfile::TempDir {
    let dir = tempfile::tempdir().unwrap();
    crate::synth::write_synthetic(
        dir.path(),
        &crate::synth::SynthOptions {
            frames,
            width: 40,
            height: 30,
            seed: 0,
        },
    )
    .unwrap();
    dir
}

#[test]
fn depth_camera_from_the_configuration_registers_every_frame() {
    let dir = synthetic_40x30(3);
    let plain = open(dir.path(), &LoadOptions::default()).unwrap();
    let k = plain.intrinsics();
    // Pretend the files' camera is the depth camera and the colour camera has 0.8 x its
    // focal length.
    let depth_camera = CameraConfig::pinhole(&k);
    let colour = CameraConfig {
        fx: 0.8 * k.fx,
        fy: 0.8 * k.fy,
        ..depth_camera
    };
    let cfg = DatasetConfig {
        camera: Some(colour),
        depth_camera: Some(depth_camera),
        ..DatasetConfig::default()
    };
    let ds = open_with(dir.path(), &LoadOptions::default(), &cfg).unwrap();
    assert_eq!(ds.intrinsics(), colour.intrinsics());
    let (a, b) = (plain.frame(1).unwrap(), ds.frame(1).unwrap());
    assert_eq!(a.rgb.data, b.rgb.data, "colour pixels are the files'");
    let want = a
        .depth
        .unwrap()
        .registered(&depth_camera.intrinsics(), &colour.intrinsics());
    assert_eq!(b.depth.unwrap().data, want.data);
    // A broken depth camera is an error naming the dataset.
    let bad = DatasetConfig {
        depth_camera: Some(CameraConfig {
            fx: -1.0,
            ..depth_camera
        }),
        ..DatasetConfig::default()
    };
    assert!(open_with(dir.path(), &LoadOptions::default(), &bad).is_err());
}

#[test]
fn depth_reprojected_into_an_offset_colour_camera() {
    let k = Intrinsics {
        width: 40,
        height: 30,
        fx: 100.0,
        fy: 100.0,
        cx: 19.5,
        cy: 14.5,
    };
    // A wall at z = 2 m with a box at z = 1 m on columns 10..=14.
    let mut d = DepthImage::new(40, 30);
    for y in 0..30 {
        for x in 0..40 {
            d.data[y * 40 + x] = if (10..=14).contains(&x) { 1.0 } else { 2.0 };
        }
    }
    // No offset: the same bits as the plain registration.
    assert_eq!(d.registered_from(&k, &k, [0.0; 3]), d.registered(&k, &k));
    // The colour camera 10 cm to the right: the wall moves fx * 0.1 / 2 = 5 px left, the box
    // 10 px; the box hides the wall behind it, and the wall's pixels the box hid from the
    // depth camera are holes.
    let r = d.registered_from(&k, &k, [0.1, 0.0, 0.0]);
    let row: Vec<f32> = (0..40).map(|x| r.get(x, 7)).collect();
    assert_eq!(row[34], 2.0, "the wall at column 39 of the depth image");
    assert_eq!(
        row[35], 0.0,
        "nothing lands right of the depth image's last column"
    );
    assert_eq!(
        &row[0..5],
        &[1.0; 5],
        "the box, 10 px left, in front of the wall"
    );
    assert_eq!(
        &row[5..10],
        &[0.0; 5],
        "the wall the box hid from the depth camera"
    );
    assert_eq!(
        row[10], 2.0,
        "the wall again from column 15 of the depth image"
    );
    // The pose moves along the camera's own axes: a camera turned 90 degrees about y
    // (its x axis along world -z) moves its centre by -0.1 along world z.
    let p = Pose {
        m: [
            [0.0, 0.0, 1.0, 1.0],
            [0.0, 1.0, 0.0, 2.0],
            [-1.0, 0.0, 0.0, 3.0],
        ],
    };
    let dir = synthetic_40x30(2);
    let cfg = DatasetConfig {
        colour_offset: Some([0.1, 0.0, 0.0]),
        ..DatasetConfig::default()
    };
    let plain = open(dir.path(), &LoadOptions::default()).unwrap();
    let ds = open_with(dir.path(), &LoadOptions::default(), &cfg).unwrap();
    let sel = Selection::new(dir.path(), 2, plain.intrinsics(), &LoadOptions::default())
        .unwrap()
        .with_colour_offset(dir.path(), Some([0.1, 0.0, 0.0]))
        .unwrap();
    let moved = sel.colour_pose(p);
    assert_eq!(moved.m[0][3], 1.0);
    assert_eq!(moved.m[1][3], 2.0);
    assert!((moved.m[2][3] - 2.9).abs() < 1e-6);
    // The loader hands out moved poses and re-projected depth, the same colour pixels.
    let (a, b) = (plain.frame(1).unwrap(), ds.frame(1).unwrap());
    assert_eq!(a.rgb.data, b.rgb.data);
    assert_eq!(b.pose, sel.colour_pose(a.pose));
    assert_eq!(ds.pose(1), b.pose);
    let k = plain.intrinsics();
    assert_eq!(
        b.depth.unwrap(),
        a.depth.unwrap().registered_from(&k, &k, [0.1, 0.0, 0.0])
    );
    // A nonsensical offset is an error naming the setting.
    let bad = DatasetConfig {
        colour_offset: Some([f32::NAN, 0.0, 0.0]),
        ..DatasetConfig::default()
    };
    let e = open_with(dir.path(), &LoadOptions::default(), &bad)
        .err()
        .expect("a NaN offset is refused");
    assert!(e.to_string().contains("colour_offset"), "{e}");
}

#[test]
fn oversized_text_files_are_refused_before_reading() {
    let dir = replica_fixture(2);
    // A sparse file: its length is over the limit, its blocks are not written.
    let f = std::fs::File::create(dir.path().join("traj.txt")).unwrap();
    f.set_len(super::MAX_TEXT_BYTES + 1).unwrap();
    drop(f);
    let e = expect_err(open_default(dir.path()), "traj.txt", "byte limit");
    assert!(matches!(e, DatasetError::TooLarge { .. }));
}

#[test]
fn max_width_resizes_wider_sequences_only() {
    let cfg = |max_width| DatasetConfig {
        max_width,
        ..DatasetConfig::default()
    };
    let k = |width, height| Intrinsics {
        width,
        height,
        fx: 600.0,
        fy: 600.0,
        cx: 599.5,
        cy: 339.5,
    };
    let none = LoadOptions::default();
    assert_eq!(
        max_width_size(k(640, 480), &none, &cfg(320)),
        Some((320, 240))
    );
    // Replica's 1200 x 680: the height in proportion, rounded
    assert_eq!(
        max_width_size(k(1200, 680), &none, &cfg(320)),
        Some((320, 181))
    );
    assert_eq!(max_width_size(k(320, 240), &none, &cfg(320)), None);
    assert_eq!(max_width_size(k(1200, 680), &none, &cfg(0)), None);
    let given = LoadOptions {
        resize: Some((600, 340)),
        ..LoadOptions::default()
    };
    assert_eq!(max_width_size(k(1200, 680), &given, &cfg(320)), None);
    // opened through the configuration: the 8 x 6 fixture at most 4 wide is 4 x 3, with the
    // intrinsics and the images of an explicit resize to 4 x 3
    let dir = replica_fixture(2);
    let capped = open_with(dir.path(), &none, &cfg(4)).unwrap();
    let explicit = open(
        dir.path(),
        &LoadOptions {
            resize: Some((4, 3)),
            ..LoadOptions::default()
        },
    )
    .unwrap();
    assert_eq!(capped.intrinsics(), explicit.intrinsics());
    assert_eq!(
        (capped.intrinsics().width, capped.intrinsics().height),
        (4, 3)
    );
    let (a, b) = (capped.frame(1).unwrap(), explicit.frame(1).unwrap());
    assert_eq!(a.rgb.data, b.rgb.data);
    assert_eq!(
        open_with(dir.path(), &none, &cfg(8)).unwrap().intrinsics(),
        fixture_camera()
    );
}

#[test]
fn replica_layout_undistorts_a_configured_distorted_camera() {
    let dir = synthetic_40x30(2);
    let plain = open(dir.path(), &LoadOptions::default()).unwrap();
    let k = plain.intrinsics();
    let dist = [0.2, -0.1, 0.001, -0.002, 0.0];
    let cfg = |undistort: bool| DatasetConfig {
        camera: Some(CameraConfig {
            distortion: Some(dist),
            ..CameraConfig::pinhole(&k)
        }),
        undistort,
        ..DatasetConfig::default()
    };
    let ds = open_with(dir.path(), &LoadOptions::default(), &cfg(true)).unwrap();
    let (a, b) = (plain.frame(1).unwrap(), ds.frame(1).unwrap());
    // The colour image is remapped through the camera's undistortion map (TUM's), depth is not.
    let want = remap(&a.rgb, &undistort_map(&k, dist));
    assert_eq!(b.rgb.data, want.data);
    assert_ne!(b.rgb.data, a.rgb.data, "the distortion moves pixels");
    assert_eq!(b.depth.unwrap().data, a.depth.unwrap().data);
    // `undistort = false` keeps the files' pixels.
    let off = open_with(dir.path(), &LoadOptions::default(), &cfg(false)).unwrap();
    assert_eq!(off.frame(1).unwrap().rgb.data, a.rgb.data);
}
