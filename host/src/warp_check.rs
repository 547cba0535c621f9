//! `himap warp-check`: does the warping loss find the true depth on a dataset?
//!
//! Issue #11's diagnostic. For pixels with ground-truth depth, the DIM-SLAM warping loss
//! ([`himap_core::loss::warp::warp_pixel`], the mapper's configuration) is evaluated along the
//! pixel's ray at depths `gt * s` for `s` log-spaced over `[1/2, 2]`. Where its minimum is
//! not at the ground truth, the loss itself (patch, validity, exposure) fails and no schedule
//! of the optimiser can recover the geometry. With a saved map, the loss at the map's rendered
//! depth is compared with the loss at the ground truth for the same pixels.
//!
//! Windows are consecutive frames (the mapper's local window): `window` frames ending at each
//! anchor, `step` apart. Source pixels are drawn from every frame of the window, at least
//! `mapper.border` pixels inside the image. Everything here reads ground truth: it is an
//! evaluation tool, never part of mapping.

use std::path::PathBuf;

use anyhow::Context;
use himap_core::camera::{Intrinsics, Pose};
use himap_core::field::model::{Ray, RayResult};
use himap_core::loss::warp::{warp_pixel, FrameImages, PackedImages, WarpConfig};
use himap_core::rng::SplitMix;
use himap_core::train::backend::Backend;

use crate::backend::ParallelCpuBackend;
use crate::config::Config;
use crate::dataset::{self, LoadOptions};

/// What to measure.
#[derive(Clone, Debug)]
pub struct WarpCheckOptions {
    pub dataset: PathBuf,
    pub load: LoadOptions,
    /// Mapper configuration (warp settings, border, the dataset's cameras); the map's own
    /// when `map` is given.
    pub config: Config,
    /// Frames per window.
    pub window: usize,
    /// Frame step inside a window.
    pub step: usize,
    /// Number of windows, spread evenly over the sequence.
    pub anchors: usize,
    /// Source pixels per window.
    pub pixels: usize,
    /// A saved map whose rendered depth is compared with the ground truth.
    pub map: Option<PathBuf>,
    pub threads: usize,
    pub seed: u64,
    /// Passes of a 5-tap binomial blur (sigma 1 px each) over the colour images first.
    pub blur: u32,
    /// Warps with the focal lengths scaled by this (1 = the dataset's camera): a colour
    /// camera whose true intrinsics differ from the file's shows up as a lower centre
    /// residual at another scale.
    pub focal_scale: f32,
}

impl WarpCheckOptions {
    /// The defaults of `himap warp-check` for a dataset (the `small` preset's warp settings,
    /// 8 windows of 15 consecutive frames, 300 pixels each).
    pub fn new(dataset: PathBuf) -> Self {
        Self {
            dataset,
            load: LoadOptions::default(),
            config: Config::small(),
            window: 15,
            step: 1,
            anchors: 8,
            pixels: 300,
            map: None,
            threads: 0,
            seed: 0,
            blur: 0,
            focal_scale: 1.0,
        }
    }
}

/// Scale factors of the depth sweep: 1 and 96 log-spaced values over [1/2, 2].
fn sweep() -> Vec<f32> {
    let n = 96;
    let mut s: Vec<f32> = (0..=n)
        .map(|i| (2f64.ln() * (2.0 * i as f64 / n as f64 - 1.0)).exp() as f32)
        .collect();
    s[n / 2] = 1.0;
    s
}

/// Depth scales at which the direction of the loss gradient is checked.
pub const BASIN_SCALES: [f32; 6] = [0.5, 0.67, 0.8, 1.25, 1.5, 2.0];

/// Per-window (or total) statistics.
#[derive(Clone, Debug, Default)]
pub struct WarpStats {
    /// First frame index (selected frames) of the window, `usize::MAX` for a total.
    pub first: usize,
    /// Sampled pixels with ground-truth depth.
    pub sampled: usize,
    /// Pixels with at least `min_views` valid pairs at the ground-truth depth.
    pub valid: usize,
    /// Pixels whose sweep minimum lies within 5 % / 10 % of the ground truth.
    pub within5: usize,
    pub within10: usize,
    /// |argmin / gt - 1| of every valid pixel.
    pub rel_err: Vec<f32>,
    /// Pixels whose gradient points towards the ground truth from 0.8 gt and from 1.25 gt.
    pub basin: usize,
    /// Pixels whose gradient points towards the ground truth from `gt * BASIN_SCALES[i]`.
    pub towards: [usize; BASIN_SCALES.len()],
    /// Centre-pixel smooth-L1 residual per valid pair at the ground truth (mean over pixels).
    pub centre_residual: f64,
    /// With a map: pixels valid at both depths, those where the truth scores lower, and the
    /// sums of the losses and of |rendered - gt|.
    pub both: usize,
    pub gt_lower: usize,
    pub loss_gt: f64,
    pub loss_rendered: f64,
    pub depth_err: f64,
    /// Valid pixels on plain surfaces (the grey standard deviation of their dense 11x11
    /// neighbourhood below [`PLAIN_STD`]) and those of them whose minimum lies within 5 %.
    pub plain: usize,
    pub plain_within5: usize,
    /// With a map: pixels (valid at both depths) whose rendered depth is off by
    /// [`FAR_ERROR`] or more, and those of them where the truth scores lower.
    pub far: usize,
    pub far_gt_lower: usize,
    /// With a map: the loss swept along the ray around the rendered depth (0.5x..2x); the
    /// summed error of the sweep's minimum (|argmin - gt|) over the pixels valid at both,
    /// and, for the confident ones (minimum below [`SWEEP_CONFIDENT`] times the loss at the
    /// rendered depth), their count and summed errors of the map and of the sweep.
    pub sweep_err: f64,
    pub confident: usize,
    pub confident_map_err: f64,
    pub confident_sweep_err: f64,
}

/// The sweep's minimum counts as confident below this share of the loss at the rendered depth.
pub const SWEEP_CONFIDENT: f32 = 0.7;

/// A rendered depth this far from the truth (metres) counts as a gross error.
pub const FAR_ERROR: f32 = 0.5;

/// Grey-level standard deviation (colours in [0, 1]) under which a pixel's 11x11
/// neighbourhood counts as plain.
pub const PLAIN_STD: f32 = 0.02;

/// The standard deviation of the grey level (mean of the channels) over the dense 11x11
/// neighbourhood of `(u, v)` in frame `f` (clamped at the border).
fn grey_std(images: &PackedImages<'_>, f: usize, u: u32, v: u32) -> f32 {
    let (w, h) = (images.width as i32, images.height as i32);
    let (mut s, mut s2, mut n) = (0.0f64, 0.0f64, 0.0f64);
    for dy in -5..=5 {
        for dx in -5..=5 {
            let x = (u as i32 + dx).clamp(0, w - 1) as u32;
            let y = (v as i32 + dy).clamp(0, h - 1) as u32;
            let t = images.texel(f, x, y);
            let g = ((t[0] + t[1] + t[2]) / 3.0) as f64;
            s += g;
            s2 += g * g;
            n += 1.0;
        }
    }
    let m = s / n;
    ((s2 / n - m * m).max(0.0)).sqrt() as f32
}

impl WarpStats {
    fn add(&mut self, o: &WarpStats) {
        self.sampled += o.sampled;
        self.valid += o.valid;
        self.within5 += o.within5;
        self.within10 += o.within10;
        self.rel_err.extend_from_slice(&o.rel_err);
        self.basin += o.basin;
        for (a, b) in self.towards.iter_mut().zip(o.towards) {
            *a += b;
        }
        self.centre_residual += o.centre_residual;
        self.both += o.both;
        self.gt_lower += o.gt_lower;
        self.loss_gt += o.loss_gt;
        self.loss_rendered += o.loss_rendered;
        self.depth_err += o.depth_err;
        self.plain += o.plain;
        self.plain_within5 += o.plain_within5;
        self.far += o.far;
        self.far_gt_lower += o.far_gt_lower;
        self.sweep_err += o.sweep_err;
        self.confident += o.confident;
        self.confident_map_err += o.confident_map_err;
        self.confident_sweep_err += o.confident_sweep_err;
    }

    /// With a map: what a sweep of the loss around the rendered depth would give (the mean
    /// depth error of the sweep's minimum against the map's, and for the confident pixels).
    pub fn sweep_line(&self) -> String {
        let n = self.both.max(1) as f64;
        let c = self.confident.max(1) as f64;
        format!(
            "sweep around the map's depth: error {:.1} cm (map {:.1} cm); confident {:.1} % of \
             pixels: map {:.1} cm, sweep {:.1} cm",
            100.0 * self.sweep_err / n,
            100.0 * self.depth_err / n,
            100.0 * self.confident as f64 / n,
            100.0 * self.confident_map_err / c,
            100.0 * self.confident_sweep_err / c,
        )
    }

    fn median_rel(&self) -> f32 {
        let mut v = self.rel_err.clone();
        if v.is_empty() {
            return f32::NAN;
        }
        let mid = v.len() / 2;
        *v.select_nth_unstable_by(mid, |a, b| a.total_cmp(b)).1
    }

    /// One table row.
    pub fn row(&self, label: &str) -> String {
        let pct = |a: usize, b: usize| {
            if b == 0 {
                "-".to_string()
            } else {
                format!("{:.1}", 100.0 * a as f64 / b as f64)
            }
        };
        let mut s = format!(
            "{label:>8} {:>6} {:>6} {:>7} {:>7} {:>8.3} {:>7} {:>8.4} {:>6} {:>7}",
            self.sampled,
            pct(self.valid, self.sampled),
            pct(self.within5, self.valid),
            pct(self.within10, self.valid),
            self.median_rel(),
            pct(self.basin, self.valid),
            self.centre_residual / self.valid.max(1) as f64,
            pct(self.plain, self.valid),
            pct(self.plain_within5, self.plain),
        );
        if self.both > 0 {
            let n = self.both as f64;
            s += &format!(
                " {:>7} {:>8.4} {:>8.4} {:>7.1} {:>5} {:>7}",
                pct(self.gt_lower, self.both),
                self.loss_gt / n,
                self.loss_rendered / n,
                100.0 * self.depth_err / n,
                pct(self.far, self.both),
                pct(self.far_gt_lower, self.far),
            );
        }
        s
    }

    /// Share (%) of the valid pixels whose gradient points towards the truth at each of
    /// [`BASIN_SCALES`].
    pub fn basin_line(&self) -> String {
        let mut s = String::from("gradient towards the truth from");
        for (k, n) in BASIN_SCALES.iter().zip(self.towards) {
            s += &format!(
                "  {k} gt: {:.1} %",
                100.0 * n as f64 / self.valid.max(1) as f64
            );
        }
        s
    }

    /// The table header matching [`WarpStats::row`].
    pub fn header(with_map: bool) -> String {
        let mut s = format!(
            "{:>8} {:>6} {:>6} {:>7} {:>7} {:>8} {:>7} {:>8} {:>6} {:>7}",
            "frames",
            "pixels",
            "valid%",
            "argmin5",
            "argmin10",
            "med_rel",
            "basin%",
            "centre",
            "plain%",
            "plain5"
        );
        if with_map {
            s += &format!(
                " {:>7} {:>8} {:>8} {:>7} {:>5} {:>7}",
                "gt<map%", "loss_gt", "loss_map", "dl1_cm", "far%", "far_gt<"
            );
        }
        s
    }
}

/// Runs the check; returns the per-window statistics and the total.
pub fn run(opts: &WarpCheckOptions) -> anyhow::Result<(Vec<WarpStats>, WarpStats)> {
    let (config, mut backend) = match &opts.map {
        Some(p) => {
            let (cfg, data) = crate::mapper_cli::load_map(p)?;
            let b = ParallelCpuBackend::new(data, cfg.adam_config(), opts.threads)?;
            (cfg, Some(b))
        }
        None => (opts.config.clone(), None),
    };
    let mut load = opts.load.clone();
    load.load_depth = true;
    let ds = dataset::open_with(&opts.dataset, &load, &config.dataset)?;
    anyhow::ensure!(
        ds.has_depth(),
        "{}: warp-check needs ground-truth depth",
        opts.dataset.display()
    );
    let window = opts.window.max(2);
    let step = opts.step.max(1);
    let span = (window - 1) * step + 1;
    anyhow::ensure!(
        ds.len() >= span,
        "{} frames selected, a window of {window} frames {step} apart needs {span}",
        ds.len()
    );
    let check = Check::new(opts, &config, ds.intrinsics(), window)?;
    let anchors = opts.anchors.max(1);
    let last_first = ds.len() - span;
    let mut rows = Vec::new();
    let mut total = WarpStats {
        first: usize::MAX,
        ..Default::default()
    };
    for a in 0..anchors {
        let first = if anchors == 1 {
            last_first / 2
        } else {
            last_first * a / (anchors - 1)
        };
        let ids: Vec<usize> = (0..window).map(|i| first + i * step).collect();
        let (poses, data, depths) = load_window(ds.as_ref(), &ids, opts.blur)?;
        let images = PackedImages {
            width: check.k.width,
            height: check.k.height,
            data: &data,
        };
        let mut rng = SplitMix::new(opts.seed ^ (first as u64).wrapping_mul(0x9e37_79b9));
        let picks = check.pick_pixels(&depths, opts.pixels, &mut rng);
        let rendered = match backend.as_mut() {
            Some(b) => Some(check.render_picks(b, &poses, &picks)?),
            None => None,
        };
        let mut st = WarpStats {
            first: ids[0],
            ..Default::default()
        };
        for (i, &pick) in picks.iter().enumerate() {
            let depth = rendered.as_ref().map(|r| r[i].depth);
            check.score(&mut st, &poses, &images, pick, depth);
        }
        total.add(&st);
        rows.push(st);
    }
    Ok((rows, total))
}

/// A sampled source pixel: window frame, column, row and its ground-truth depth.
type Pick = (usize, u32, u32, f32);

/// Poses, RGBA8-quantised colours (as the mapper's slot images hold them, after `blur`) and
/// ground-truth depths of the frames `ids`.
fn load_window(
    ds: &dyn dataset::Dataset,
    ids: &[usize],
    blur: u32,
) -> anyhow::Result<(Vec<Pose>, Vec<f32>, Vec<dataset::DepthImage>)> {
    let mut poses: Vec<Pose> = Vec::with_capacity(ids.len());
    let mut data: Vec<f32> = Vec::new();
    let mut depths = Vec::with_capacity(ids.len());
    for &i in ids {
        let f = ds.frame(i).with_context(|| format!("frame {i}"))?;
        poses.push(f.pose);
        let rgb = f.rgb.blurred(blur);
        for px in rgb.data.as_chunks::<3>().0 {
            let q =
                himap_core::train::pixel::unpack_rgba8(himap_core::train::pixel::pack_rgba8(*px));
            data.extend_from_slice(&q);
        }
        depths.push(f.depth.context("frame without depth")?);
    }
    Ok((poses, data, depths))
}

/// What every window of a check shares: the camera, the loss settings and the sweep.
struct Check {
    k: Intrinsics,
    window: usize,
    wcfg: WarpConfig,
    /// The centre term alone (its residual at the truth).
    centre_cfg: WarpConfig,
    border: u32,
    scales: Vec<f32>,
}

impl Check {
    fn new(
        opts: &WarpCheckOptions,
        config: &Config,
        k: Intrinsics,
        window: usize,
    ) -> anyhow::Result<Self> {
        let mapper = config.mapper_config()?;
        let wcfg: WarpConfig = mapper.warp;
        let border = mapper.border.max(wcfg.half + 1);
        anyhow::ensure!(
            opts.focal_scale.is_finite() && opts.focal_scale > 0.0,
            "focal scale {} must be positive",
            opts.focal_scale
        );
        let k = Intrinsics {
            fx: k.fx * opts.focal_scale,
            fy: k.fy * opts.focal_scale,
            ..k
        };
        let (w, h) = (k.width, k.height);
        anyhow::ensure!(
            w > 2 * border && h > 2 * border,
            "images of {w}x{h} are too small for a border of {border} px"
        );
        let centre_cfg = WarpConfig {
            w_patch: 0.0,
            w_center: 1.0,
            ..wcfg
        };
        Ok(Self {
            k,
            window,
            wcfg,
            centre_cfg,
            border,
            scales: sweep(),
        })
    }

    /// Up to `n` pixels away from the border that have a ground-truth depth.
    fn pick_pixels(
        &self,
        depths: &[dataset::DepthImage],
        n: usize,
        rng: &mut SplitMix,
    ) -> Vec<Pick> {
        let (w, h, border) = (self.k.width, self.k.height, self.border);
        let mut picks = Vec::with_capacity(n);
        let mut tries = 0;
        while picks.len() < n && tries < n * 20 {
            tries += 1;
            let src = rng.below(self.window as u32) as usize;
            let u = border + rng.below(w - 2 * border);
            let v = border + rng.below(h - 2 * border);
            let d = depths[src].get(u, v);
            if d > 0.0 && d.is_finite() {
                picks.push((src, u, v, d));
            }
        }
        picks
    }

    /// The map's rendering of the picked pixels' rays.
    fn render_picks(
        &self,
        b: &mut ParallelCpuBackend,
        poses: &[Pose],
        picks: &[Pick],
    ) -> anyhow::Result<Vec<RayResult>> {
        let rays: Vec<Ray> = picks
            .iter()
            .map(|&(src, u, v, _)| {
                let (origin, dir) = poses[src].ray(&self.k, u as f32, v as f32);
                Ray {
                    origin,
                    dir,
                    target: [0.0; 3],
                    target_depth: 0.0,
                }
            })
            .collect();
        let mut out = vec![RayResult::default(); rays.len()];
        b.render(&rays, &mut out)?;
        Ok(out)
    }

    /// Adds one pixel to the window's statistics: the sweep's minimum, the basin, the centre
    /// residual at the truth and, with a map's rendered depth, the comparison with it.
    fn score(
        &self,
        st: &mut WarpStats,
        poses: &[Pose],
        images: &PackedImages<'_>,
        (src, u, v, gt): Pick,
        rendered: Option<f32>,
    ) {
        let (wcfg, k, n) = (&self.wcfg, &self.k, self.window);
        let loss_at = |d: f32| warp_pixel(wcfg, k, poses, n, src, u, v, d, images);
        // The lowest loss (and its scale) over `d` times the sweep's scales below `start`;
        // a depth where too few views are valid scores 0: not a minimum to take.
        let sweep = |d: f32, start: f32| {
            let mut best = (start, 1.0f32);
            for &s in &self.scales {
                let r = loss_at(d * s);
                if r.valid_views >= wcfg.min_views && r.loss < best.0 {
                    best = (r.loss, s);
                }
            }
            best
        };
        st.sampled += 1;
        let at_gt = loss_at(gt);
        if at_gt.valid_views < wcfg.min_views {
            return;
        }
        st.valid += 1;
        let best = sweep(gt, f32::INFINITY);
        let rel = (best.1 - 1.0).abs();
        st.rel_err.push(rel);
        st.within5 += (rel <= 0.05) as usize;
        st.within10 += (rel <= 0.10) as usize;
        if grey_std(images, src, u, v) < PLAIN_STD {
            st.plain += 1;
            st.plain_within5 += (rel <= 0.05) as usize;
        }
        // The basin uses the gradients at 0.8 gt and 1.25 gt, two of the scales below.
        let (mut lo, mut hi) = (0.0f32, 0.0f32);
        for (j, &s) in BASIN_SCALES.iter().enumerate() {
            let r = loss_at(gt * s);
            if s == 0.8 {
                lo = r.d_depth;
            } else if s == 1.25 {
                hi = r.d_depth;
            }
            let towards = if s < 1.0 {
                r.d_depth < 0.0
            } else {
                r.d_depth > 0.0
            };
            st.towards[j] += (r.valid_views >= wcfg.min_views && towards) as usize;
        }
        st.basin += (lo < 0.0 && hi > 0.0) as usize;
        let c = warp_pixel(&self.centre_cfg, k, poses, n, src, u, v, gt, images);
        st.centre_residual += c.loss as f64 / c.valid_views.max(1) as f64;
        let Some(d) = rendered.filter(|d| d.is_finite() && *d > 0.0) else {
            return;
        };
        let at_r = loss_at(d);
        if at_r.valid_views >= wcfg.min_views {
            st.both += 1;
            st.gt_lower += (at_gt.loss < at_r.loss) as usize;
            st.loss_gt += at_gt.loss as f64 / at_gt.valid_views as f64;
            st.loss_rendered += at_r.loss as f64 / at_r.valid_views as f64;
            st.depth_err += (d - gt).abs() as f64;
            if (d - gt).abs() >= FAR_ERROR {
                st.far += 1;
                st.far_gt_lower += (at_gt.loss < at_r.loss) as usize;
            }
            let best = sweep(d, at_r.loss);
            let e = (d * best.1 - gt).abs() as f64;
            st.sweep_err += e;
            if best.0 < SWEEP_CONFIDENT * at_r.loss {
                st.confident += 1;
                st.confident_map_err += (d - gt).abs() as f64;
                st.confident_sweep_err += e;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::synth::{write_synthetic, SynthOptions};

    fn room() -> tempfile::TempDir {
        let dir = tempfile::tempdir().unwrap();
        let opts = SynthOptions {
            frames: 40,
            width: 96,
            height: 72,
            seed: 1,
        };
        write_synthetic(dir.path(), &opts).unwrap();
        dir
    }

    fn check(dir: &std::path::Path, focal_scale: f32) -> WarpStats {
        let mut o = WarpCheckOptions::new(dir.to_path_buf());
        o.window = 8;
        o.anchors = 2;
        o.pixels = 60;
        o.focal_scale = focal_scale;
        let (rows, total) = run(&o).unwrap();
        assert_eq!(rows.len(), 2);
        assert_eq!(rows[0].first, 0);
        assert_eq!(rows[1].first, 40 - 8);
        assert_eq!(total.sampled, 120);
        total
    }

    /// On exact synthetic data the loss's minimum sits at the true depth and its gradient
    /// points towards it; a wrong focal length (what real colour cameras with a depth
    /// camera's intrinsics give) breaks both and raises the photometric residual.
    #[test]
    fn finds_the_true_depth_on_exact_data_and_not_with_a_wrong_focal_length() {
        let dir = room();
        let good = check(dir.path(), 1.0);
        assert!(good.valid >= 80, "valid {}", good.valid);
        let share = |n: usize, s: &WarpStats| n as f64 / s.valid as f64;
        assert!(share(good.within10, &good) > 0.8, "{}", good.row("good"));
        assert!(good.median_rel() < 0.03, "{}", good.row("good"));
        assert!(share(good.basin, &good) > 0.6, "{}", good.row("good"));
        let bad = check(dir.path(), 0.85);
        assert!(
            share(bad.within5, &bad) < share(good.within5, &good) - 0.2,
            "{}\n{}",
            good.row("good"),
            bad.row("bad")
        );
        let residual = |s: &WarpStats| s.centre_residual / s.valid as f64;
        assert!(residual(&bad) > 1.3 * residual(&good));
    }

    #[test]
    fn too_short_a_sequence_is_an_error() {
        let dir = room();
        let mut o = WarpCheckOptions::new(dir.path().to_path_buf());
        o.window = 41;
        let e = run(&o).unwrap_err().to_string();
        assert!(e.contains("40 frames selected"), "{e}");
        o.window = 8;
        o.focal_scale = 0.0;
        assert!(run(&o).is_err());
    }

    #[test]
    fn sweep_is_symmetric_in_log_and_holds_one() {
        let s = sweep();
        assert_eq!(s.len(), 97);
        assert_eq!(s[48], 1.0);
        assert!((s[0] - 0.5).abs() < 1e-6 && (s[96] - 2.0).abs() < 1e-6);
        for i in 0..48 {
            assert!((s[i] * s[96 - i] - 1.0).abs() < 1e-5);
            assert!(s[i] < s[i + 1]);
        }
    }
}
