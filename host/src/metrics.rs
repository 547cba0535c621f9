//! Per-view image metrics as the paper reports them: PSNR, SSIM and depth L1.
//!
//! Images are flat `f32` slices in row-major, channel-interleaved (HWC) order, the layout of the
//! dataset loader's `RgbImage::data`. Colours are in [0, 1] (data range 1); depths are in metres.
//! All sums are accumulated in `f64`.
//!
//! SSIM follows the standard definition of Wang et al. (2004) exactly as `pytorch_msssim.ssim`
//! computes it (and `skimage.metrics.structural_similarity` with `gaussian_weights=True,
//! sigma=1.5, use_sample_covariance=False, data_range=1`): an 11x11 Gaussian window with
//! sigma 1.5 (normalised to sum 1), K1 = 0.01, K2 = 0.03, Gaussian-weighted means, variances and
//! covariance with the population (biased) estimator, a *valid* convolution (no padding: the
//! SSIM map is (H - 10) x (W - 10)), averaged over the valid map and over channels.

use rayon::prelude::*;

/// Side of the SSIM window.
pub const SSIM_WINDOW: usize = 11;
/// Standard deviation of the SSIM Gaussian window, in pixels.
pub const SSIM_SIGMA: f64 = 1.5;
/// SSIM stabiliser constant K1 (C1 = (K1 * data range)^2).
pub const SSIM_K1: f64 = 0.01;
/// SSIM stabiliser constant K2 (C2 = (K2 * data range)^2).
pub const SSIM_K2: f64 = 0.03;

/// Peak signal-to-noise ratio in dB of two images with values in [0, 1]:
/// `-10 log10(MSE)` with the MSE over all pixels and channels.
///
/// Returns `f64::INFINITY` for identical images (MSE 0) and `NaN` for empty slices; callers
/// averaging over a sequence decide how to treat an infinite value.
///
/// # Panics
/// If the slices have different lengths.
pub fn psnr(a: &[f32], b: &[f32]) -> f64 {
    assert_eq!(a.len(), b.len(), "psnr: images have different sizes");
    if a.is_empty() {
        return f64::NAN;
    }
    let mut sum = 0.0f64;
    for (x, y) in a.iter().zip(b) {
        let d = *x as f64 - *y as f64;
        sum += d * d;
    }
    let mse = sum / a.len() as f64;
    if mse == 0.0 {
        f64::INFINITY
    } else {
        -10.0 * mse.log10()
    }
}

/// The normalised 1-D Gaussian of the SSIM window (11 taps, sigma 1.5, sum 1).
pub fn ssim_kernel() -> [f64; SSIM_WINDOW] {
    let mut k = [0.0f64; SSIM_WINDOW];
    let c = (SSIM_WINDOW / 2) as f64;
    let mut sum = 0.0;
    for (i, w) in k.iter_mut().enumerate() {
        let x = i as f64 - c;
        *w = (-(x * x) / (2.0 * SSIM_SIGMA * SSIM_SIGMA)).exp();
        sum += *w;
    }
    for w in k.iter_mut() {
        *w /= sum;
    }
    k
}

/// SSIM of two RGB images (`width * height * 3` interleaved values in [0, 1]); see the module
/// documentation for the exact convention. Returns `NaN` when the image is smaller than the
/// 11x11 window (empty valid map).
///
/// # Panics
/// If a slice length is not `width * height * 3`.
pub fn ssim(a: &[f32], b: &[f32], width: usize, height: usize) -> f64 {
    ssim_channels(a, b, width, height, 3)
}

/// SSIM of two images with `channels` interleaved channels (see [`ssim`]): the mean of the
/// per-pixel SSIM over the valid `(height - 10) x (width - 10)` map and over the channels.
///
/// # Panics
/// If a slice length is not `width * height * channels`.
pub fn ssim_channels(a: &[f32], b: &[f32], width: usize, height: usize, channels: usize) -> f64 {
    let n = width * height * channels;
    assert_eq!(a.len(), n, "ssim: first image has the wrong size");
    assert_eq!(b.len(), n, "ssim: second image has the wrong size");
    if width < SSIM_WINDOW || height < SSIM_WINDOW || channels == 0 {
        return f64::NAN;
    }
    let k = ssim_kernel();
    let c1 = SSIM_K1 * SSIM_K1;
    let c2 = SSIM_K2 * SSIM_K2;
    let ow = width - (SSIM_WINDOW - 1);
    let oh = height - (SSIM_WINDOW - 1);
    // Horizontal pass: five moments per (row, output column), then the vertical pass. Rows
    // run in parallel; the per-row sums are added in a fixed order, so the result does not
    // depend on the thread count.
    let mut hor = vec![[0.0f64; 5]; height * ow];
    let mut row_sums = vec![0.0f64; oh];
    let mut total = 0.0f64;
    for c in 0..channels {
        hor.par_chunks_mut(ow).enumerate().for_each(|(y, row)| {
            for (x, out) in row.iter_mut().enumerate() {
                let mut m = [0.0f64; 5];
                for (i, w) in k.iter().enumerate() {
                    let idx = (y * width + x + i) * channels + c;
                    let p = a[idx] as f64;
                    let q = b[idx] as f64;
                    m[0] += w * p;
                    m[1] += w * q;
                    m[2] += w * p * p;
                    m[3] += w * q * q;
                    m[4] += w * p * q;
                }
                *out = m;
            }
        });
        row_sums.par_iter_mut().enumerate().for_each(|(y, sum)| {
            *sum = 0.0;
            for x in 0..ow {
                let mut m = [0.0f64; 5];
                for (j, w) in k.iter().enumerate() {
                    let h = &hor[(y + j) * ow + x];
                    for (mt, ht) in m.iter_mut().zip(h) {
                        *mt += w * ht;
                    }
                }
                *sum += ssim_from_moments(m, c1, c2);
            }
        });
        total += row_sums.iter().sum::<f64>();
    }
    total / (ow * oh * channels) as f64
}

/// SSIM of one window from its Gaussian-weighted moments
/// `[E x, E y, E x^2, E y^2, E xy]` (population variances).
#[inline]
fn ssim_from_moments(m: [f64; 5], c1: f64, c2: f64) -> f64 {
    let (mx, my) = (m[0], m[1]);
    let vx = m[2] - mx * mx;
    let vy = m[3] - my * my;
    let cxy = m[4] - mx * my;
    ((2.0 * mx * my + c1) * (2.0 * cxy + c2)) / ((mx * mx + my * my + c1) * (vx + vy + c2))
}

/// Depth L1 error in centimetres: the mean of `|rendered - gt|` over the pixels whose ground
/// truth is valid (`gt > 0` and finite), times 100 (depths in metres). Returns `None` when no
/// pixel has a valid ground truth. Rendered values are not filtered: a non-finite rendered
/// depth at a valid pixel makes the result non-finite.
///
/// # Panics
/// If the slices have different lengths.
pub fn depth_l1_cm(rendered: &[f32], gt: &[f32]) -> Option<f64> {
    assert_eq!(
        rendered.len(),
        gt.len(),
        "depth_l1_cm: depth maps have different sizes"
    );
    let mut sum = 0.0f64;
    let mut count = 0usize;
    for (r, g) in rendered.iter().zip(gt) {
        if *g > 0.0 && g.is_finite() {
            sum += (*r as f64 - *g as f64).abs();
            count += 1;
        }
    }
    (count > 0).then(|| sum / count as f64 * 100.0)
}

/// Grey-level standard deviation (the mean of the three channels, colour in `[0, 1]`) over
/// a pixel's `(2 PLAIN_HALF + 1)^2` neighbourhood below which [`depth_split_cm`] counts it as
/// plain: a patch the warping loss has nothing to compare on (at the evaluation scale).
pub const PLAIN_STD: f64 = 0.01;

/// Half size of the neighbourhood of [`PLAIN_STD`] (5 x 5, clamped at the image border).
pub const PLAIN_HALF: usize = 2;

/// What a view's Depth L1 is made of (centimetres, over the pixels with a valid ground
/// truth, as [`depth_l1_cm`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct DepthSplit {
    /// The Depth L1 itself.
    pub l1_cm: f64,
    /// The part of it from pixels rendered in front of the truth: the mean of
    /// `max(gt - rendered, 0)` (the rest, `l1_cm - near_cm`, lies behind it).
    pub near_cm: f64,
    /// The share of the pixels that are plain ([`PLAIN_STD`]).
    pub plain_share: f64,
    /// Depth L1 over the plain pixels alone (`None` without any).
    pub plain_l1_cm: Option<f64>,
}

/// [`depth_l1_cm`] split by the sign of the error and by the texture of the frame's colours
/// (`rgb`: `width * height` RGB triples, row-major, the same pixels as the depths). `None`
/// when no pixel has a valid ground truth.
///
/// # Panics
/// If the slices' sizes disagree with `width * height`.
pub fn depth_split_cm(
    rendered: &[f32],
    gt: &[f32],
    rgb: &[f32],
    width: usize,
    height: usize,
) -> Option<DepthSplit> {
    let n = width * height;
    assert!(
        rendered.len() == n && gt.len() == n && rgb.len() == 3 * n,
        "depth_split_cm: sizes differ"
    );
    // Summed-area tables of the grey level and its square.
    let w1 = width + 1;
    let mut s1 = vec![0.0f64; w1 * (height + 1)];
    let mut s2 = vec![0.0f64; w1 * (height + 1)];
    for y in 0..height {
        for x in 0..width {
            let i = 3 * (y * width + x);
            let g = (rgb[i] as f64 + rgb[i + 1] as f64 + rgb[i + 2] as f64) / 3.0;
            let (a, b, c) = ((y + 1) * w1 + x, y * w1 + x + 1, y * w1 + x);
            s1[a + 1] = g + s1[a] + s1[b] - s1[c];
            s2[a + 1] = g * g + s2[a] + s2[b] - s2[c];
        }
    }
    let (mut sum, mut near, mut count) = (0.0f64, 0.0f64, 0usize);
    let (mut plain_sum, mut plain_count) = (0.0f64, 0usize);
    for y in 0..height {
        for x in 0..width {
            let i = y * width + x;
            let g = gt[i];
            if !(g > 0.0 && g.is_finite()) {
                continue;
            }
            let e = rendered[i] as f64 - g as f64;
            sum += e.abs();
            near += (-e).max(0.0);
            count += 1;
            let (x0, x1) = (
                x.saturating_sub(PLAIN_HALF),
                (x + PLAIN_HALF + 1).min(width),
            );
            let (y0, y1) = (
                y.saturating_sub(PLAIN_HALF),
                (y + PLAIN_HALF + 1).min(height),
            );
            let box_sum =
                |s: &[f64]| s[y1 * w1 + x1] - s[y0 * w1 + x1] - s[y1 * w1 + x0] + s[y0 * w1 + x0];
            let k = ((x1 - x0) * (y1 - y0)) as f64;
            let mean = box_sum(&s1) / k;
            let var = box_sum(&s2) / k - mean * mean;
            if var < PLAIN_STD * PLAIN_STD {
                plain_sum += e.abs();
                plain_count += 1;
            }
        }
    }
    (count > 0).then(|| DepthSplit {
        l1_cm: sum / count as f64 * 100.0,
        near_cm: near / count as f64 * 100.0,
        plain_share: plain_count as f64 / count as f64,
        plain_l1_cm: (plain_count > 0).then(|| plain_sum / plain_count as f64 * 100.0),
    })
}

/// The spread of `|rendered - gt|` over many pixels (those with a valid ground truth, as in
/// [`depth_l1_cm`]), in millimetre bins up to 10 m: a mean Depth L1 can be carried by a few
/// pixels far off (a surface placed in front of the truth) while most are close, and the
/// median and the share of pixels off by more than a threshold tell the two apart.
#[derive(Clone, Debug)]
pub struct DepthErrorSpread {
    /// Pixels per millimetre bin; the last bin holds every error of 10 m and more (and
    /// non-finite ones).
    bins: Vec<u64>,
    count: u64,
}

impl Default for DepthErrorSpread {
    fn default() -> Self {
        Self {
            bins: vec![0; Self::BINS],
            count: 0,
        }
    }
}

impl DepthErrorSpread {
    const BINS: usize = 10_001;

    /// Adds the errors of one depth map.
    ///
    /// # Panics
    /// If the slices have different lengths.
    pub fn add(&mut self, rendered: &[f32], gt: &[f32]) {
        assert_eq!(rendered.len(), gt.len(), "depth maps have different sizes");
        for (r, g) in rendered.iter().zip(gt) {
            if *g > 0.0 && g.is_finite() {
                let e = (*r as f64 - *g as f64).abs() * 1000.0;
                let b = if e.is_finite() {
                    (e as usize).min(Self::BINS - 1)
                } else {
                    Self::BINS - 1
                };
                self.bins[b] += 1;
                self.count += 1;
            }
        }
    }

    /// Pixels counted.
    pub fn count(&self) -> u64 {
        self.count
    }

    /// Median error in centimetres (the middle of its millimetre bin); `None` without pixels.
    pub fn median_cm(&self) -> Option<f64> {
        if self.count == 0 {
            return None;
        }
        let half = self.count.div_ceil(2);
        let mut seen = 0;
        for (b, &n) in self.bins.iter().enumerate() {
            seen += n;
            if seen >= half {
                return Some((b as f64 + 0.5) / 10.0);
            }
        }
        None
    }

    /// Share (0..1) of the pixels whose error is at least `metres` (to the millimetre).
    pub fn share_at_least(&self, metres: f64) -> Option<f64> {
        if self.count == 0 {
            return None;
        }
        let from = ((metres * 1000.0).max(0.0) as usize).min(Self::BINS - 1);
        let n: u64 = self.bins[from..].iter().sum();
        Some(n as f64 / self.count as f64)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Deterministic values in [0, 1).
    fn noise(n: usize, seed: u64) -> Vec<f32> {
        let mut r = himap_core::rng::SplitMix::new(seed);
        (0..n).map(|_| r.unit()).collect()
    }

    #[test]
    fn psnr_identical_is_infinite_and_offset_is_closed_form() {
        let a = noise(8 * 6 * 3, 1);
        assert_eq!(psnr(&a, &a), f64::INFINITY);
        // A constant offset d on every value: MSE = d^2, PSNR = -10 log10(d^2) = -20 log10(d).
        // d = 0.125 is exact in f32; 0.25 + 0.125 etc. are exact too.
        let a: Vec<f32> = (0..300).map(|i| (i % 5) as f32 * 0.125).collect();
        let b: Vec<f32> = a.iter().map(|x| x + 0.125).collect();
        let expect = -20.0 * 0.125f64.log10(); // 18.0618 dB
        assert!((psnr(&a, &b) - expect).abs() < 1e-12, "{}", psnr(&a, &b));
        assert!((expect - 18.061_799_739_838_87).abs() < 1e-9);
        // Half the values off by 0.5: MSE = 0.125, PSNR = 10 log10(8) = 9.0309 dB.
        let c: Vec<f32> = (0..100)
            .map(|i| if i % 2 == 0 { 0.5 } else { 0.0 })
            .collect();
        let z = vec![0.0f32; 100];
        assert!((psnr(&c, &z) - 9.030_899_869_919_435).abs() < 1e-9);
    }

    #[test]
    fn ssim_identical_is_one() {
        let (w, h) = (23, 17);
        let a = noise(w * h * 3, 2);
        assert!((ssim(&a, &a, w, h) - 1.0).abs() < 1e-12);
        // Too small for one window: NaN.
        let s = noise(10 * 10 * 3, 3);
        assert!(ssim(&s, &s, 10, 10).is_nan());
    }

    #[test]
    fn ssim_constant_images_closed_form() {
        // 11x11 constants a and b: one window, means a and b, zero variances and covariance:
        // SSIM = (2ab + C1) / (a^2 + b^2 + C1) * (C2 / C2).
        // a = 0.25, b = 0.75: (0.375 + 1e-4) / (0.625 + 1e-4) = 0.375100 / 0.625100 = 0.600064.
        let a = vec![0.25f32; 11 * 11 * 3];
        let b = vec![0.75f32; 11 * 11 * 3];
        let s = ssim(&a, &b, 11, 11);
        assert!((s - 0.375_1 / 0.625_1).abs() < 1e-12, "{s}");
        assert!((s - 0.600_063_989_761_638).abs() < 1e-9);
    }

    #[test]
    fn ssim_checkerboard_against_constant_closed_form() {
        // x = c + d * (-1)^(i+j) on an 11x11 image, y = c constant. The window is separable,
        // so with A = sum_i w_i (-1)^(i - 5): E x = c + d A^2, E x^2 = c^2 + 2 c d A^2 + d^2,
        // var x = d^2 (1 - A^4), var y = cov = 0, so
        // SSIM = (2 c (c + d A^2) + C1) / (c^2 + (c + d A^2)^2 + C1) * C2 / (d^2 (1 - A^4) + C2).
        let (c, d) = (0.5f64, 0.25f64);
        let k = ssim_kernel();
        let a_sum: f64 = k
            .iter()
            .enumerate()
            .map(|(i, w)| if (i + 5) % 2 == 0 { *w } else { -*w })
            .sum();
        // A is the window's response at the Nyquist frequency: tiny (the untruncated Gaussian
        // gives exp(-pi^2 sigma^2 / 2) ~ 1.5e-5; truncation to 11 taps makes it ~ -1.39e-4).
        assert!(a_sum.abs() < 1e-3 && a_sum != 0.0, "{a_sum}");
        let (c1, c2) = (1e-4, 9e-4);
        let mx = c + d * a_sum * a_sum;
        let expect = (2.0 * c * mx + c1) / (c * c + mx * mx + c1) * c2
            / (d * d * (1.0 - a_sum.powi(4)) + c2);
        let mut x = vec![0.0f32; 11 * 11];
        for i in 0..11 {
            for j in 0..11 {
                x[i * 11 + j] = (c + d * if (i + j) % 2 == 0 { 1.0 } else { -1.0 }) as f32;
            }
        }
        let y = vec![c as f32; 11 * 11];
        let s = ssim_channels(&x, &y, 11, 11, 1);
        assert!((s - expect).abs() < 1e-12, "{s} vs {expect}");
        // Variance dominates: SSIM ~ C2 / (d^2 + C2) = 9e-4 / 0.0634 ~ 0.0142.
        assert!((s - 0.014_195).abs() < 1e-4, "{s}");
    }

    /// Direct (non-separable) f64 reference: 2-D window sums at every valid position.
    fn ssim_reference(a: &[f32], b: &[f32], w: usize, h: usize, ch: usize) -> f64 {
        let k = ssim_kernel();
        let mut total = 0.0;
        let mut count = 0usize;
        for c in 0..ch {
            for y0 in 0..=h - 11 {
                for x0 in 0..=w - 11 {
                    let (mut mx, mut my) = (0.0, 0.0);
                    for j in 0..11 {
                        for i in 0..11 {
                            let idx = ((y0 + j) * w + x0 + i) * ch + c;
                            mx += k[i] * k[j] * a[idx] as f64;
                            my += k[i] * k[j] * b[idx] as f64;
                        }
                    }
                    let (mut vx, mut vy, mut cxy) = (0.0, 0.0, 0.0);
                    for j in 0..11 {
                        for i in 0..11 {
                            let idx = ((y0 + j) * w + x0 + i) * ch + c;
                            let dx = a[idx] as f64 - mx;
                            let dy = b[idx] as f64 - my;
                            vx += k[i] * k[j] * dx * dx;
                            vy += k[i] * k[j] * dy * dy;
                            cxy += k[i] * k[j] * dx * dy;
                        }
                    }
                    let (c1, c2) = (1e-4, 9e-4);
                    total += (2.0 * mx * my + c1) * (2.0 * cxy + c2)
                        / ((mx * mx + my * my + c1) * (vx + vy + c2));
                    count += 1;
                }
            }
        }
        total / count as f64
    }

    #[test]
    fn ssim_matches_direct_reference_on_random_images() {
        let (w, h) = (32, 29);
        let a = noise(w * h * 3, 5);
        // b: a noisy, darkened copy of a, so SSIM is strictly between 0 and 1.
        let n = noise(w * h * 3, 6);
        let b: Vec<f32> = a
            .iter()
            .zip(&n)
            .map(|(x, e)| 0.8 * x + 0.3 * (e - 0.5))
            .collect();
        let s = ssim(&a, &b, w, h);
        let r = ssim_reference(&a, &b, w, h, 3);
        assert!((s - r).abs() < 1e-10, "{s} vs {r}");
        assert!(s > 0.3 && s < 0.99, "{s}");
        // Symmetric in its arguments.
        assert!((ssim(&b, &a, w, h) - s).abs() < 1e-12);
    }

    #[test]
    fn depth_error_spread_by_hand() {
        // Errors 0.0042, 0.0103, 0.7 and 2.0 m at valid pixels; the 0 and the NaN ground
        // truths are skipped. Sorted bins (mm): 4, 10, 700, 2000: the median is the 2nd of
        // 4 (div_ceil), bin 10 -> 1.05 cm; two of four are >= 0.5 m.
        let rd = [1.0042, 2.0, 3.0, 1.0, 5.0, 1.0];
        let gt = [1.0, 2.0103, 2.3, 3.0, 0.0, f32::NAN];
        let mut s = DepthErrorSpread::default();
        assert_eq!(s.median_cm(), None);
        s.add(&rd, &gt);
        assert_eq!(s.count(), 4);
        assert!((s.median_cm().unwrap() - 1.05).abs() < 1e-9);
        assert_eq!(s.share_at_least(0.5), Some(0.5));
        assert_eq!(s.share_at_least(0.0), Some(1.0));
        assert_eq!(s.share_at_least(20.0), Some(0.0));
        // A non-finite rendered depth counts as far off.
        s.add(&[f32::INFINITY], &[1.0]);
        assert_eq!(s.share_at_least(10.0), Some(0.2));
    }

    #[test]
    fn depth_split_separates_near_far_and_plain_pixels() {
        // 8 x 1 image: columns 0-3 one grey (plain), 4-7 alternating black and white
        // (textured; every 5 x 5 box reaching them from column 2 on has a large spread).
        let (w, h) = (8usize, 1usize);
        let mut rgb = vec![0.5f32; 3 * w];
        for x in 4..8 {
            let v = if x % 2 == 0 { 0.0 } else { 1.0 };
            rgb[3 * x..3 * x + 3].copy_from_slice(&[v, v, v]);
        }
        // gt 2 m except a hole at column 1; errors (m): col 0 -0.2 (in front), col 2 +0.1,
        // col 3 -0.3, cols 4-7 +0.05, -0.05, 0, +0.1
        let gt = [2.0f32, 0.0, 2.0, 2.0, 2.0, 2.0, 2.0, 2.0];
        let rd = [1.8f32, 9.0, 2.1, 1.7, 2.05, 1.95, 2.0, 2.1];
        let s = depth_split_cm(&rd, &gt, &rgb, w, h).unwrap();
        // 7 valid pixels: |e| sum 0.8 m -> 11.43 cm; in front: 0.2 + 0.3 + 0.05 = 0.55 m
        assert!((s.l1_cm - 80.0 / 7.0).abs() < 1e-4, "{s:?}");
        assert!((s.near_cm - 55.0 / 7.0).abs() < 1e-4, "{s:?}");
        // plain: column 0 (box 0..=2) and the hole's neighbours; column 2's box reaches
        // column 4 (black against 0.5 grey): textured. Valid plain pixels: column 0 only.
        assert!((s.plain_share - 1.0 / 7.0).abs() < 1e-12, "{s:?}");
        assert!((s.plain_l1_cm.unwrap() - 20.0).abs() < 1e-4, "{s:?}");
        assert!((depth_l1_cm(&rd, &gt).unwrap() - s.l1_cm).abs() < 1e-4);
        // no valid pixel, and a textured-only view
        assert_eq!(depth_split_cm(&rd, &[0.0; 8], &rgb, w, h), None);
        let stripes: Vec<f32> = (0..3 * w).map(|i| ((i / 3) % 2) as f32).collect();
        let t = depth_split_cm(&rd, &gt, &stripes, w, h).unwrap();
        assert_eq!((t.plain_share, t.plain_l1_cm), (0.0, None));
    }

    #[test]
    fn depth_l1_skips_holes() {
        // gt: valid 1.0, 2.0, 0.5; holes 0.0, NaN. Rendered errors 0.01, 0.03, 0.02 m on the
        // valid pixels (mean 0.02 m = 2 cm); the holes' large errors must not count.
        let gt = [1.0f32, 0.0, 2.0, f32::NAN, 0.5];
        let rd = [1.01f32, 5.0, 1.97, 7.0, 0.52];
        let l1 = depth_l1_cm(&rd, &gt).unwrap();
        assert!((l1 - 2.0).abs() < 1e-5, "{l1}");
        assert_eq!(depth_l1_cm(&[1.0, 2.0], &[0.0, -1.0]), None);
    }
}
