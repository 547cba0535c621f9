//! Losses with hand-written gradients: L1 colour, smooth L1 (Huber), and the single-window
//! patch SSIM of DIM-SLAM's warping loss; [`warp`] is the warping loss itself (patches of one
//! pixel warped through its rendered depth into the other window frames).
//!
//! # SSIM
//!
//! For two patches `a`, `b` (one channel) over the used `size x size` region with the
//! normalised Gaussian window `w_k` ([`gaussian_window`], sigma [`SSIM_SIGMA`]):
//!
//! - means `mu_a = sum_k w_k a_k`, `mu_b = sum_k w_k b_k`;
//! - variances `var_a = E[a^2] - mu_a^2`, `var_b = E[b^2] - mu_b^2` and covariance
//!   `cov = E[ab] - mu_a mu_b`, where `E[f] = sum_k w_k f_k` (the biased, window-weighted
//!   moments, as a "valid" Gaussian convolution computes them). They are evaluated in the
//!   equal (for `sum_k w_k = 1`) central form `var_a = sum_k w_k (a_k - mu_a)^2`,
//!   `cov = sum_k w_k (a_k - mu_a)(b_k - mu_b)` after a first pass for the means: in f32 the
//!   `E[a^2] - mu^2` form loses about 1e-7 absolute, i.e. 1e-4 of `C2`, to cancellation;
//! - `SSIM = ((2 mu_a mu_b + C1)(2 cov + C2)) / ((mu_a^2 + mu_b^2 + C1)(var_a + var_b + C2))`
//!   with `C1 = (0.01 L)^2`, `C2 = (0.03 L)^2`, data range `L = 1`.
//!
//! With no padding, a window as large as the patch gives exactly one SSIM value per channel
//! (DIM-SLAM's loss). Patches are always stored as 11x11 (`PATCH`), row-major, RGB; `size` 7
//! uses the inner 7x7 pixels (offset 2) with a 7x7 window normalised over 7x7.
//!
//! Gradient: with `A1 = 2 mu_a mu_b + C1`, `A2 = 2 cov + C2`, `B1 = mu_a^2 + mu_b^2 + C1`,
//! `B2 = var_a + var_b + C2`, `S = A1 A2 / (B1 B2)`:
//! `dS/dA1 = A2 / (B1 B2)`, `dS/dA2 = A1 / (B1 B2)`, `dS/dB1 = -S / B1`, `dS/dB2 = -S / B2`;
//! with `dmu_a/da_k = w_k`, `dvar_a/da_k = 2 w_k (a_k - mu_a)`, `dcov/da_k = w_k (b_k - mu_b)`:
//! `dS/da_k = w_k (2 mu_b dA1 + 2 mu_a dB1 + 2 (a_k - mu_a) dB2 + 2 (b_k - mu_b) dA2)`
//! (symmetric for `b`). `B1 >= C1 > 0` and `B2 >= C2 > 0`, so nothing divides by zero.

pub mod planar;
pub mod warp;

use crate::math;

/// Side of the stored square patch (pixels).
pub const PATCH: usize = 11;
/// Pixels in a stored patch, `PATCH * PATCH`.
pub const PATCH_PIXELS: usize = 121;
/// SSIM stabiliser `(K1 L)^2` with `K1 = 0.01`, data range `L = 1`.
pub const SSIM_C1: f32 = 0.0001;
/// SSIM stabiliser `(K2 L)^2` with `K2 = 0.03`, data range `L = 1`.
pub const SSIM_C2: f32 = 0.0009;
/// Standard deviation (pixels) of the Gaussian SSIM window for every window size.
pub const SSIM_SIGMA: f32 = 1.5;

/// L1 colour: `sum_c |pred_c - target_c|`; returns `(loss, d loss / d pred)`. The subgradient
/// is 0 where `pred_c == target_c`.
#[inline]
pub fn l1_color(pred: [f32; 3], target: [f32; 3]) -> (f32, [f32; 3]) {
    let mut loss = 0.0f32;
    let mut grad = [0.0f32; 3];
    let mut c = 0;
    while c < 3 {
        let x = pred[c] - target[c];
        loss += math::abs(x);
        grad[c] = if x > 0.0 {
            1.0
        } else if x < 0.0 {
            -1.0
        } else {
            0.0
        };
        c += 1;
    }
    (loss, grad)
}

/// Smooth L1 (Huber) with threshold `beta`: `0.5 x^2 / beta` if `|x| < beta`, else
/// `|x| - 0.5 beta`. Returns `(value, d value / dx)`; the derivative is `x / beta` inside and
/// `sign(x)` outside (continuous at `|x| = beta`). `beta <= 0` gives plain `|x|` with
/// subgradient 0 at `x = 0`.
#[inline]
pub fn smooth_l1(x: f32, beta: f32) -> (f32, f32) {
    let ax = math::abs(x);
    if ax < beta {
        (math::div(0.5 * x * x, beta), math::div(x, beta))
    } else {
        let half = if beta > 0.0 { 0.5 * beta } else { 0.0 };
        let d = if x > 0.0 {
            1.0
        } else if x < 0.0 {
            -1.0
        } else {
            0.0
        };
        (ax - half, d)
    }
}

/// Clamps a window size to an odd value in `1..=PATCH` (even sizes round down).
#[inline(always)]
fn window_size(size: usize) -> usize {
    let s = if size > PATCH { PATCH } else { size };
    if s == 0 {
        1
    } else if s % 2 == 0 {
        s - 1
    } else {
        s
    }
}

/// Normalised 2-D Gaussian window of `size x size` (`size` odd, `<= 11`; other values are
/// clamped to an odd size in `1..=11`) with standard deviation `sigma`, written row-major into
/// `out[..size * size]`; the rest of `out` is zeroed. It is the outer product of the
/// normalised 1-D window `g_k = exp(-(k - c)^2 / (2 sigma^2)) / sum_j exp(-(j - c)^2 /
/// (2 sigma^2))`, `c = (size - 1) / 2`, so it sums to 1 up to rounding. A `sigma` that is not
/// positive and finite gives a delta at the centre.
pub fn gaussian_window(size: usize, sigma: f32, out: &mut [f32; PATCH_PIXELS]) {
    let size = window_size(size);
    let c = (size / 2) as f32;
    let mut g = [0.0f32; PATCH];
    if sigma > 0.0 && sigma < f32::INFINITY {
        let inv = math::div(1.0, 2.0 * sigma * sigma);
        let mut sum = 0.0f32;
        let mut k = 0;
        while k < size {
            let d = k as f32 - c;
            g[k] = math::exp(-(d * d) * inv);
            sum += g[k];
            k += 1;
        }
        k = 0;
        while k < size {
            g[k] = math::div(g[k], sum);
            k += 1;
        }
    } else {
        g[size / 2] = 1.0;
    }
    let mut i = 0;
    while i < PATCH_PIXELS {
        out[i] = 0.0;
        i += 1;
    }
    let mut r = 0;
    while r < size {
        let mut col = 0;
        while col < size {
            out[r * size + col] = g[r] * g[col];
            col += 1;
        }
        r += 1;
    }
}

/// Single-window SSIM between two RGB patches (no padding: one Gaussian-weighted SSIM per
/// channel, as DIM-SLAM's loss). Patches are stored row-major as 11x11; `size` (11 or 7; other
/// values are clamped to an odd size `<= 11`) selects the central `size x size` sub-patch, with
/// a `size x size` Gaussian window of sigma [`SSIM_SIGMA`] normalised over it. Returns the
/// per-channel SSIM and writes (does not accumulate) `d(sum over channels of SSIM)/d(patch)`
/// into `d_a` and `d_b`; pixels outside the used region get zero gradient. Formulas in the
/// module docs.
pub fn ssim_patch(
    size: usize,
    a: &[[f32; 3]; PATCH_PIXELS],
    b: &[[f32; 3]; PATCH_PIXELS],
    d_a: &mut [[f32; 3]; PATCH_PIXELS],
    d_b: &mut [[f32; 3]; PATCH_PIXELS],
) -> [f32; 3] {
    let src = SsimSource::new(size, a);
    let mut i = 0;
    while i < PATCH_PIXELS {
        d_a[i] = [0.0; 3];
        d_b[i] = [0.0; 3];
        i += 1;
    }
    let m = target_moments(&src, a, b);
    let (ssim, g) = ssim_and_moment_grads(&m);
    source_backward(&src, a, b, &m, &g, d_a);
    target_backward(&src, a, b, &m, &g, d_b);
    ssim
}

/// The source side of [`ssim_patch`], kept while one source patch is compared with many
/// targets (the warping loss compares a pixel's patch with every view): the window and the
/// source's window-weighted mean and variance, computed with [`ssim_patch`]'s operations in
/// its order.
pub struct SsimSource {
    size: usize,
    w: [f32; PATCH_PIXELS],
    mu: [f32; 3],
    var: [f32; 3],
}

impl SsimSource {
    /// The source side of patch `a` compared over its central `size x size` region.
    pub fn new(size: usize, a: &[[f32; 3]; PATCH_PIXELS]) -> Self {
        let size = window_size(size);
        let mut s = SsimSource {
            size,
            w: [0.0; PATCH_PIXELS],
            mu: [0.0; 3],
            var: [0.0; 3],
        };
        gaussian_window(size, SSIM_SIGMA, &mut s.w);
        let mut k = 0;
        while k < size * size {
            let (wk, p) = (s.w[k], patch_index(size, k));
            let mut c = 0;
            while c < 3 {
                s.mu[c] += wk * a[p][c];
                c += 1;
            }
            k += 1;
        }
        k = 0;
        while k < size * size {
            let (wk, p) = (s.w[k], patch_index(size, k));
            let mut c = 0;
            while c < 3 {
                let x = a[p][c] - s.mu[c];
                s.var[c] += wk * (x * x);
                c += 1;
            }
            k += 1;
        }
        s
    }
}

/// [`ssim_patch`] of the source `a` (prepared as `src`) against `b`, with only the target's
/// gradient: the same per-channel SSIM and the same `d_b` bits (each moment is accumulated
/// in [`ssim_patch`]'s order; the source's moments do not depend on `b`).
pub fn ssim_patch_target(
    src: &SsimSource,
    a: &[[f32; 3]; PATCH_PIXELS],
    b: &[[f32; 3]; PATCH_PIXELS],
    d_b: &mut [[f32; 3]; PATCH_PIXELS],
) -> [f32; 3] {
    if src.size < PATCH {
        let mut i = 0;
        while i < PATCH_PIXELS {
            d_b[i] = [0.0; 3];
            i += 1;
        }
    }
    let m = target_moments(src, a, b);
    let (ssim, g) = ssim_and_moment_grads(&m);
    target_backward(src, a, b, &m, &g, d_b);
    ssim
}

/// Index in the 11x11 patch of pixel `k` (row-major) of its central `size x size` region.
#[inline(always)]
pub(crate) fn patch_index(size: usize, k: usize) -> usize {
    let off = (PATCH - size) / 2;
    (k / size + off) * PATCH + k % size + off
}

/// The window-weighted moments of two patches, per channel.
struct SsimMoments {
    mu_a: [f32; 3],
    mu_b: [f32; 3],
    var_a: [f32; 3],
    var_b: [f32; 3],
    cov: [f32; 3],
}

/// The moments of `b` and its covariance with the source `a` ([`SsimSource`] holds `a`'s):
/// window-weighted means, then central second moments (two passes: `sum w (a - mu)^2`
/// instead of `E[a^2] - mu^2`, which cancels catastrophically in f32 when the variance is
/// small next to `C2`).
#[inline(always)]
fn target_moments(
    src: &SsimSource,
    a: &[[f32; 3]; PATCH_PIXELS],
    b: &[[f32; 3]; PATCH_PIXELS],
) -> SsimMoments {
    let (size, w) = (src.size, &src.w);
    let mut m = SsimMoments {
        mu_a: src.mu,
        mu_b: [0.0; 3],
        var_a: src.var,
        var_b: [0.0; 3],
        cov: [0.0; 3],
    };
    let mut k = 0;
    while k < size * size {
        let (wk, p) = (w[k], patch_index(size, k));
        let mut c = 0;
        while c < 3 {
            m.mu_b[c] += wk * b[p][c];
            c += 1;
        }
        k += 1;
    }
    k = 0;
    while k < size * size {
        let (wk, p) = (w[k], patch_index(size, k));
        let mut c = 0;
        while c < 3 {
            let x = a[p][c] - m.mu_a[c];
            let y = b[p][c] - m.mu_b[c];
            m.var_b[c] += wk * (y * y);
            m.cov[c] += wk * (x * y);
            c += 1;
        }
        k += 1;
    }
    m
}

/// d(SSIM)/d(moment) per channel.
struct SsimMomentGrads {
    mu_a: [f32; 3],
    mu_b: [f32; 3],
    var: [f32; 3],
    cov: [f32; 3],
}

/// Per-channel SSIM from the moments and its derivatives with respect to them.
#[inline(always)]
fn ssim_and_moment_grads(m: &SsimMoments) -> ([f32; 3], SsimMomentGrads) {
    let mut ssim = [0.0f32; 3];
    let mut g = SsimMomentGrads {
        mu_a: [0.0; 3],
        mu_b: [0.0; 3],
        var: [0.0; 3],
        cov: [0.0; 3],
    };
    let mut c = 0;
    while c < 3 {
        let (s, ga, gb) = ssim_channel(m.mu_a[c], m.mu_b[c], m.var_a[c], m.var_b[c], m.cov[c]);
        ssim[c] = s;
        g.mu_a[c] = ga;
        g.mu_b[c] = gb[0];
        g.var[c] = gb[1];
        g.cov[c] = gb[2];
        c += 1;
    }
    (ssim, g)
}

/// One channel's SSIM from the window-weighted means `ma`, `mb`, the variances and the
/// covariance, with its derivatives: `(SSIM, d/d mu_a, [d/d mu_b, d/d var_a = d/d var_b,
/// d/d cov])`.
#[inline(always)]
pub(crate) fn ssim_channel(
    ma: f32,
    mb: f32,
    var_a: f32,
    var_b: f32,
    cov: f32,
) -> (f32, f32, [f32; 3]) {
    let a1 = 2.0 * (ma * mb) + SSIM_C1;
    let a2 = 2.0 * cov + SSIM_C2;
    let b1 = ma * ma + mb * mb + SSIM_C1;
    let b2 = var_a + var_b + SSIM_C2;
    let den = b1 * b2;
    let s = math::div(a1 * a2, den);
    let d_a1 = math::div(a2, den);
    let d_a2 = math::div(a1, den);
    let d_b1 = math::div(-s, b1);
    let d_b2 = math::div(-s, b2);
    (
        s,
        2.0 * (mb * d_a1 + ma * d_b1),
        [2.0 * (ma * d_a1 + mb * d_b1), 2.0 * d_b2, 2.0 * d_a2],
    )
}

/// One pixel's SSIM gradient on one side of the comparison: the window weight `wk` times
/// the side's mean gradient `g_mu`, plus its own deviation from its mean times the variance
/// gradient, plus the other side's deviation times the covariance gradient.
#[inline(always)]
pub(crate) fn side_grad(wk: f32, g_mu: f32, own: f32, other: f32, g_var: f32, g_cov: f32) -> f32 {
    wk * (g_mu + own * g_var + other * g_cov)
}

/// The moments' gradients pushed back to one side's pixels of the used region (written,
/// not accumulated): `own` (the source `a` or the target `b`) with its mean and mean
/// gradient, `other` the other patch with its mean.
#[inline(always)]
fn side_backward(
    src: &SsimSource,
    (own, mu_own, g_own): (&[[f32; 3]; PATCH_PIXELS], &[f32; 3], &[f32; 3]),
    (other, mu_other): (&[[f32; 3]; PATCH_PIXELS], &[f32; 3]),
    g: &SsimMomentGrads,
    d: &mut [[f32; 3]; PATCH_PIXELS],
) {
    let (size, w) = (src.size, &src.w);
    let mut k = 0;
    while k < size * size {
        let (wk, p) = (w[k], patch_index(size, k));
        let mut c = 0;
        while c < 3 {
            let x = own[p][c] - mu_own[c];
            let y = other[p][c] - mu_other[c];
            d[p][c] = side_grad(wk, g_own[c], x, y, g.var[c], g.cov[c]);
            c += 1;
        }
        k += 1;
    }
}

/// [`side_backward`] for the source's pixels.
#[inline(always)]
fn source_backward(
    src: &SsimSource,
    a: &[[f32; 3]; PATCH_PIXELS],
    b: &[[f32; 3]; PATCH_PIXELS],
    m: &SsimMoments,
    g: &SsimMomentGrads,
    d_a: &mut [[f32; 3]; PATCH_PIXELS],
) {
    side_backward(src, (a, &m.mu_a, &g.mu_a), (b, &m.mu_b), g, d_a);
}

/// [`side_backward`] for the target's pixels.
#[inline(always)]
fn target_backward(
    src: &SsimSource,
    a: &[[f32; 3]; PATCH_PIXELS],
    b: &[[f32; 3]; PATCH_PIXELS],
    m: &SsimMoments,
    g: &SsimMomentGrads,
    d_b: &mut [[f32; 3]; PATCH_PIXELS],
) {
    side_backward(src, (b, &m.mu_b, &g.mu_b), (a, &m.mu_a), g, d_b);
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::uniform;

    type Patch = [[f32; 3]; PATCH_PIXELS];

    #[test]
    fn l1_golden_and_fd() {
        // |0.2-0.3| + |0.5-0.5| + |0.9-0.4| = 0.1 + 0 + 0.5 = 0.6; gradient (-1, 0, +1).
        let (l, g) = l1_color([0.2, 0.5, 0.9], [0.3, 0.5, 0.4]);
        assert!((l - 0.6).abs() < 1e-6);
        assert_eq!(g, [-1.0, 0.0, 1.0]);
        // FD away from the kinks (step 1e-3, exact for a piecewise-linear function up to
        // rounding; tolerance 1e-3).
        let p = [0.7f32, -0.2, 0.05];
        let q = [0.1f32, 0.3, 0.0];
        let (_, g) = l1_color(p, q);
        for c in 0..3 {
            let (mut a, mut b) = (p, p);
            a[c] += 1e-3;
            b[c] -= 1e-3;
            let fd = (l1_color(a, q).0 - l1_color(b, q).0) / 2e-3;
            assert!((fd - g[c]).abs() < 1e-3, "{c}: {fd} vs {}", g[c]);
        }
    }

    #[test]
    fn smooth_l1_golden_and_fd() {
        // beta 0.1: x = 0.05 -> 0.5 * 0.0025 / 0.1 = 0.0125, slope 0.5;
        // x = +-0.3 -> 0.3 - 0.05 = 0.25, slope +-1; x = 0.1 (boundary) -> 0.05 from both sides.
        let cases = [
            (0.05f32, 0.0125f32, 0.5f32),
            (-0.05, 0.0125, -0.5),
            (0.3, 0.25, 1.0),
            (-0.3, 0.25, -1.0),
            (0.1, 0.05, 1.0),
            (0.0, 0.0, 0.0),
        ];
        for (x, v, d) in cases {
            let (fv, fd) = smooth_l1(x, 0.1);
            assert!(
                (fv - v).abs() < 1e-6 && (fd - d).abs() < 1e-6,
                "{x}: {fv} {fd}"
            );
        }
        assert!((smooth_l1(0.0999999, 0.1).0 - 0.05).abs() < 1e-6);
        // beta <= 0 is plain |x|.
        assert_eq!(smooth_l1(-0.4, 0.0), (0.4, -1.0));
        assert_eq!(smooth_l1(0.0, 0.0), (0.0, 0.0));
        // FD, step 1e-4 (f32 rounding / h ~ 1e-3 relative), tolerance 2e-3 abs.
        let h = 1e-4f32;
        for i in 0..200 {
            let x = (uniform(3, 0, i) - 0.5) * 1.0;
            if (x.abs() - 0.1).abs() < 2.0 * h {
                continue;
            }
            let fd = (smooth_l1(x + h, 0.1).0 - smooth_l1(x - h, 0.1).0) / (2.0 * h);
            let d = smooth_l1(x, 0.1).1;
            assert!((fd - d).abs() < 2e-3, "{x}: {fd} vs {d}");
        }
    }

    /// The warping loss's prepared-source form gives `ssim_patch`'s SSIM and target gradient
    /// bit for bit, for every region size, on random and on flat patches (and zero outside the
    /// region).
    #[test]
    fn prepared_source_ssim_equals_ssim_patch() {
        let fill = |seed: u32, flat: bool| -> Patch {
            let mut p = [[0.0f32; 3]; PATCH_PIXELS];
            for (i, px) in p.iter_mut().enumerate() {
                for (c, v) in px.iter_mut().enumerate() {
                    *v = if flat {
                        0.25 + 0.1 * c as f32
                    } else {
                        uniform(seed, c as u32, i as u32)
                    };
                }
            }
            p
        };
        for (a, b) in [
            (fill(1, false), fill(2, false)),
            (fill(3, true), fill(4, false)),
            (fill(5, false), fill(5, false)),
        ] {
            for size in [1, 3, 5, 7, 9, 11, 12] {
                let (mut da, mut db) = ([[0.0f32; 3]; PATCH_PIXELS], [[0.0f32; 3]; PATCH_PIXELS]);
                let want = ssim_patch(size, &a, &b, &mut da, &mut db);
                let mut got_db = [[7.0f32; 3]; PATCH_PIXELS];
                let src = SsimSource::new(size, &a);
                let got = ssim_patch_target(&src, &a, &b, &mut got_db);
                assert_eq!(want.map(f32::to_bits), got.map(f32::to_bits), "size {size}");
                for p in 0..PATCH_PIXELS {
                    assert_eq!(
                        db[p].map(f32::to_bits),
                        got_db[p].map(f32::to_bits),
                        "size {size} pixel {p}"
                    );
                }
            }
        }
    }

    #[test]
    fn gaussian_window_values() {
        // 1-D, sigma 1.5, size 11: exp(-k^2 / 4.5) for k = 0..5 is 1, 0.800737, 0.411112,
        // 0.135335, 0.028566, 0.003866; sum = 1 + 2 * 1.379616 = 3.759233. Centre
        // 1 / 3.759233 = 0.266012, 2-D centre 0.266012^2 = 0.070762; corner
        // (0.003866 / 3.759233)^2 = 0.00102838^2 = 1.05757e-6.
        let mut w = [0.0f32; PATCH_PIXELS];
        gaussian_window(11, 1.5, &mut w);
        let sum: f64 = w.iter().map(|&x| x as f64).sum();
        assert!((sum - 1.0).abs() < 1e-6, "{sum}");
        assert!((w[60] - 0.070762).abs() < 1e-6, "{}", w[60]);
        assert!((w[0] - 1.05757e-6).abs() < 1e-9, "{}", w[0]);
        for r in 0..11 {
            for c in 0..11 {
                assert_eq!(w[r * 11 + c], w[c * 11 + r]);
                assert_eq!(w[r * 11 + c], w[(10 - r) * 11 + (10 - c)]);
            }
        }
        // size 7: sum = 1 + 2 * (0.800737 + 0.411112 + 0.135335) = 3.694368; centre
        // 0.270683, 2-D 0.073269.
        gaussian_window(7, 1.5, &mut w);
        let sum: f64 = w[..49].iter().map(|&x| x as f64).sum();
        assert!((sum - 1.0).abs() < 1e-6, "{sum}");
        assert!((w[24] - 0.073269).abs() < 1e-6, "{}", w[24]);
        assert!(w[49..].iter().all(|&x| x == 0.0));
        // Degenerate inputs do not panic: size clamps, sigma 0 is a delta.
        gaussian_window(40, 1.5, &mut w);
        assert!((w[60] - 0.070762).abs() < 1e-6);
        gaussian_window(5, 0.0, &mut w);
        assert_eq!(w[12], 1.0);
        assert_eq!(w.iter().sum::<f32>(), 1.0);
    }

    fn random_patch(seed: u32, stream: u32) -> Patch {
        let mut p = [[0.0f32; 3]; PATCH_PIXELS];
        for (i, px) in p.iter_mut().enumerate() {
            for (c, v) in px.iter_mut().enumerate() {
                *v = uniform(seed, stream * 3 + c as u32, i as u32);
            }
        }
        p
    }

    #[test]
    fn ssim_identical_is_one_with_zero_gradient() {
        for size in [11usize, 7] {
            let a = random_patch(1, 0);
            let (mut da, mut db) = ([[9.0f32; 3]; PATCH_PIXELS], [[9.0f32; 3]; PATCH_PIXELS]);
            let s = ssim_patch(size, &a, &a, &mut da, &mut db);
            for c in 0..3 {
                assert!((s[c] - 1.0).abs() < 1e-5, "{s:?}");
            }
            // Typical gradient entries are O(0.1) (see the FD test); at the maximum they vanish.
            for i in 0..PATCH_PIXELS {
                for c in 0..3 {
                    assert!(
                        da[i][c].abs() < 1e-4 && db[i][c].abs() < 1e-4,
                        "{}",
                        da[i][c]
                    );
                }
            }
        }
    }

    #[test]
    fn ssim_constant_patches() {
        // a = 0.5, b = 0.6 everywhere: mu = (0.5, 0.6), var = cov = 0, so
        // SSIM = (2 * 0.3 + C1) / (0.25 + 0.36 + C1) * (C2 / C2) = 0.6001 / 0.6101 = 0.983609.
        let a = [[0.5f32; 3]; PATCH_PIXELS];
        let b = [[0.6f32; 3]; PATCH_PIXELS];
        let (mut da, mut db) = ([[0.0f32; 3]; PATCH_PIXELS], [[0.0f32; 3]; PATCH_PIXELS]);
        for size in [11usize, 7] {
            let s = ssim_patch(size, &a, &b, &mut da, &mut db);
            for v in s {
                assert!((v - 0.983609).abs() < 2e-5, "{size}: {v}");
            }
        }
    }

    /// FD of the channel sum of SSIM, f32, step h = 1e-2 (rounding of the moments ~3e-8, / B2
    /// ~ 0.1 / h gives ~3e-5; the truncation ~ h^2 |S'''| is smaller since one pixel carries a
    /// window weight <= 0.073). Tolerance |analytic - fd| <= 2e-4 + 5e-3 |fd| (measured worst
    /// case 5e-5 absolute, 7e-4 relative for |fd| > 0.05).
    #[test]
    fn ssim_gradient_fd() {
        let h = 1e-2f32;
        for size in [11usize, 7] {
            for seed in 0..3u32 {
                let a = random_patch(seed + 10, 0);
                // b correlated with a, so SSIM is mid-range and the gradient non-trivial.
                let noise = random_patch(seed + 10, 1);
                let mut b = a;
                for i in 0..PATCH_PIXELS {
                    for c in 0..3 {
                        b[i][c] = 0.7 * a[i][c] + 0.3 * noise[i][c] + 0.05;
                    }
                }
                let (mut da, mut db) = ([[0.0f32; 3]; PATCH_PIXELS], [[0.0f32; 3]; PATCH_PIXELS]);
                let s = ssim_patch(size, &a, &b, &mut da, &mut db);
                assert!(s.iter().all(|&v| v > 0.2 && v < 0.99), "{s:?}");
                let total = |a: &Patch, b: &Patch| {
                    let (mut x, mut y) = ([[0.0f32; 3]; PATCH_PIXELS], [[0.0f32; 3]; PATCH_PIXELS]);
                    let s = ssim_patch(size, a, b, &mut x, &mut y);
                    s[0] + s[1] + s[2]
                };
                let off = (PATCH - size) / 2;
                let mut max_g = 0.0f32;
                for i in 0..PATCH_PIXELS {
                    let (r, col) = (i / PATCH, i % PATCH);
                    let inside = r >= off && r < off + size && col >= off && col < off + size;
                    for c in 0..3 {
                        if !inside {
                            assert_eq!((da[i][c], db[i][c]), (0.0, 0.0));
                            continue;
                        }
                        let (mut ap, mut am) = (a, a);
                        ap[i][c] += h;
                        am[i][c] -= h;
                        let fd = (total(&ap, &b) - total(&am, &b)) / (2.0 * h);
                        assert!(
                            (da[i][c] - fd).abs() <= 2e-4 + 5e-3 * fd.abs(),
                            "a {i} {c}: {} vs {fd}",
                            da[i][c]
                        );
                        let (mut bp, mut bm) = (b, b);
                        bp[i][c] += h;
                        bm[i][c] -= h;
                        let fd = (total(&a, &bp) - total(&a, &bm)) / (2.0 * h);
                        assert!(
                            (db[i][c] - fd).abs() <= 2e-4 + 5e-3 * fd.abs(),
                            "b {i} {c}: {} vs {fd}",
                            db[i][c]
                        );
                        max_g = max_g.max(da[i][c].abs());
                    }
                }
                // The check is not vacuous.
                assert!(max_g > 1e-2, "{max_g}");
            }
        }
    }
}
