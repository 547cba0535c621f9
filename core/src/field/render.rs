//! Per-ray volume rendering with hand-written forward and backward passes.
//!
//! A ray `o + t d` is cut to the scene box ([`ray_aabb`]), sampled at `n <= MAX_SAMPLES`
//! stratified depths `t_i` ([`stratified_samples`]), the model gives an SDF value `s_i` and a
//! colour `c_i` per sample, and [`render_forward`] turns them into per-sample weights `w_i`:
//!
//! - colour  `C = sum_i w_i c_i`,
//! - depth   `D = sum_i w_i t_i`,
//! - opacity `O = sum_i w_i`.
//!
//! `x = beta * s_i` below, and `sig` is the logistic sigmoid. The three [`RenderMode`]s:
//!
//! **`SdfDensity`** (Hi-Map's SDF-as-density, no `delta t` factor as in its peers):
//! `sigma_i = beta sig(-beta s_i)`, `alpha_i = 1 - exp(-sigma_i)`,
//! `T_i = exp(-sum_{k<i} sigma_k)` (computed as the running product of `exp(-sigma_k)`),
//! `w_i = T_i alpha_i`.
//!
//! **`SdfDirect`** (the "SDF directly to weights" ablation; Co-SLAM's bell):
//! `b_i = sig(beta s_i) sig(-beta s_i)`, `Z = sum_k b_k + DIRECT_EPS`, `w_i = b_i / Z`.
//! The output fields are `alpha_i = b_i` (the unnormalised bell) and `trans_i = 1 / Z` (the
//! same for every sample), so `w_i = trans_i alpha_i` holds in every mode. `O = sum_i w_i =
//! B / (B + DIRECT_EPS)` with `B = sum_k b_k`: 1 up to `DIRECT_EPS / B` whenever the ray has any
//! bell mass (with `beta = 10` and `|s| <= 1`, `B >= 4.5e-5 n`), and 0 for a ray whose bells
//! all underflow, instead of the 0/0 that an unguarded normalisation would give.
//!
//! **`Occupancy`** (DIM-SLAM-like ablation; `-s` read as an occupancy logit scaled by beta):
//! `alpha_i = sig(-beta s_i)`, `T_i = prod_{k<i} (1 - alpha_k)` where `1 - alpha_k` is computed
//! directly as `sig(beta s_k)`, `w_i = T_i alpha_i`.
//!
//! # Backward
//!
//! The loss reaches the renderer as cotangents `dL/dC` (`d_color`), `dL/dD`, `dL/dO`. Per sample
//! `dL/dc_i = d_color w_i`, and the weight cotangent is
//! `g_i = dL/dw_i = d_color . c_i + dL/dD t_i + dL/dO`. When `color_to_geometry` is false the
//! colour term is dropped from `g_i` (the colour path sees detached weights), so `d_color` only
//! produces `d_rgb`.
//!
//! For the two compositing modes (`SdfDensity`, `Occupancy`) with `w_i = alpha_i T_i`,
//! `T_{i+1} = T_i (1 - alpha_i)`, the suffix sum
//! `Q_k = sum_{j>k} g_j alpha_j prod_{k<m<j} (1 - alpha_m)`, obtained backwards by
//! `Q_{n-1} = 0`, `Q_{k-1} = g_k alpha_k + (1 - alpha_k) Q_k`, gives without any division
//! `dL/dalpha_k = T_k (g_k - Q_k)`. In `SdfDensity` this becomes
//! `dL/dsigma_k = T_{k+1} (g_k - Q_k)` with
//! `dsigma/ds = -beta^2 sig(-x) sig(x)` and `dsigma/dbeta = sig(-x) - x sig(-x) sig(x)`.
//! In `Occupancy`, `dalpha/ds = -beta sig(-x) sig(x)` and `dalpha/dbeta = -s sig(-x) sig(x)`.
//!
//! For `SdfDirect`, `dL/db_k = (g_k - sum_j g_j w_j) / Z` with
//! `db/ds = beta b (sig(-x) - sig(x))` and `db/dbeta = s b (sig(-x) - sig(x))`.
//!
//! Everything is O(n). `sig(x)` and `sig(-x)` are both evaluated (never `1 - sig`), so for
//! `|s| = 1e4`, `beta = 100` the products that multiply large factors are exact zeros and no
//! `inf * 0` or `0 / 0` can occur: no NaN for finite inputs.
//!
//! # Early ray termination
//!
//! With `t_min > 0` the two compositing modes stop after the first sample `k` whose
//! transmittance past it, `T_{k+1}`, is below `t_min`: samples `k+1..n` get weight 0 and take no
//! part in the backward either (the suffix sum starts at `k`), so the renderer and its gradient
//! are those of the ray cut after `k`. [`render_forward`] returns the count it used,
//! `k + 1` (`n` when it did not stop). The cut-off mass is below `t_min` (at most `t_min` of
//! colour, depth / `t_far` and opacity); `SdfDirect` never stops (its weights are normalised
//! over the whole ray). [`transmittance_factor`] gives the factor `T_{i+1} / T_i` with the same
//! bits, so a caller that evaluates samples one at a time can stop evaluating where the
//! renderer will stop.
//!
//! All kernels here follow the crate's bit-exactness rules: only [`crate::math`], plain
//! fixed-size arrays, no panics (`n` is clamped to [`MAX_SAMPLES`]).

use crate::math;

/// Capacity of the per-ray sample arrays; larger `n` are clamped to it.
pub const MAX_SAMPLES: usize = 128;

/// Guard added to the bell sum of [`RenderMode::SdfDirect`] before normalising.
pub const DIRECT_EPS: f32 = 1e-8;

/// How per-sample SDF values become rendering weights (formulas in the module docs).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[repr(u32)]
pub enum RenderMode {
    /// Hi-Map: `sigma = beta sig(-beta s)`, alpha compositing.
    SdfDensity = 0,
    /// Ablation: normalised bell `sig(beta s) sig(-beta s)` weights.
    SdfDirect = 1,
    /// Ablation: `alpha = sig(-beta s)` as an occupancy probability, alpha compositing.
    Occupancy = 2,
}

/// Ray/box intersection for `o + t d`, `t >= 0` (slab method; `d` need not be normalised and
/// may have zero components). Returns `(near, far, hit)` with `near = max(entry, 0)`, so an
/// origin inside the box gives `near = 0`. A ray that only touches the box (grazing a face,
/// edge or corner, `entry == exit`) counts as a hit. On a miss (or a box entirely behind the
/// origin) returns `(0, 0, false)`.
pub fn ray_aabb(o: [f32; 3], d: [f32; 3], aabb: &crate::Aabb) -> (f32, f32, bool) {
    let mut t0 = 0.0f32;
    let mut t1 = f32::INFINITY;
    let mut hit = true;
    let mut a = 0;
    while a < 3 {
        if d[a] == 0.0 {
            // Parallel to this slab: inside it for every t, or never.
            if o[a] < aabb.min[a] || o[a] > aabb.max[a] {
                hit = false;
            }
        } else {
            let inv = math::div(1.0, d[a]);
            let ta = (aabb.min[a] - o[a]) * inv;
            let tb = (aabb.max[a] - o[a]) * inv;
            let (lo, hi) = if ta < tb { (ta, tb) } else { (tb, ta) };
            if lo > t0 {
                t0 = lo;
            }
            if hi < t1 {
                t1 = hi;
            }
        }
        a += 1;
    }
    // `t0 <= t1` is false for NaN too (degenerate boxes or inputs): a miss.
    let overlap = t0 <= t1;
    if !hit || !overlap {
        return (0.0, 0.0, false);
    }
    (t0, t1, true)
}

/// `n` stratified samples on `[near, far]`: `n` evenly spaced bins of width
/// `step = (far - near) / n`, sample `i` at `near + (i + u_i) step` with
/// `u_i = crate::rng::uniform(seed, ray_id, i)` (`u_i = 0.5`, the bin centre, when `jitter` is
/// false). Samples are non-decreasing and clamped to `[near, far]`; entries `n..MAX_SAMPLES`
/// are set to `far`. `n` is clamped to [`MAX_SAMPLES`]; `far < near` is treated as `far = near`.
pub fn stratified_samples(
    near: f32,
    far: f32,
    n: usize,
    seed: u32,
    ray_id: u32,
    jitter: bool,
    t: &mut [f32; MAX_SAMPLES],
) {
    let n = if n > MAX_SAMPLES { MAX_SAMPLES } else { n };
    let far = if far > near { far } else { near };
    let mut i = 0;
    while i < MAX_SAMPLES {
        t[i] = if i < n {
            stratified_sample(near, far, n, seed, ray_id, jitter, i)
        } else {
            far
        };
        i += 1;
    }
}

/// Sample `i < n` of [`stratified_samples`] alone (the same bits), for a kernel that handles
/// one sample.
#[inline(always)]
pub fn stratified_sample(
    near: f32,
    far: f32,
    n: usize,
    seed: u32,
    ray_id: u32,
    jitter: bool,
    i: usize,
) -> f32 {
    let far = if far > near { far } else { near };
    let step = if n > 0 {
        math::div(far - near, n as f32)
    } else {
        0.0
    };
    let u = if jitter {
        crate::rng::uniform(seed, ray_id, i as u32)
    } else {
        0.5
    };
    math::clamp(near + (i as f32 + u) * step, near, far)
}

/// Sample `j < m` of `m` samples stratified uniformly in inverse depth on `[a, b]` (`0 < a <
/// b`): bin `j` spans `1/t` from `1/a + j (1/b - 1/a) / m` to the next, the sample at
/// fraction `u = crate::rng::uniform(seed, ray_id, k)` of it (`k`: the sample's index on its
/// ray, so that its jitter differs from the near samples'; 0.5 without `jitter`), clamped to
/// `[a, b]`. Bins grow with depth, as a pixel's footprint does.
#[allow(clippy::too_many_arguments)]
#[inline(always)]
pub fn disparity_sample(
    a: f32,
    b: f32,
    m: usize,
    seed: u32,
    ray_id: u32,
    jitter: bool,
    k: usize,
    j: usize,
) -> f32 {
    let b = if b > a { b } else { a };
    let (ia, ib) = (math::div(1.0, a), math::div(1.0, b));
    let step = if m > 0 {
        math::div(ib - ia, m as f32)
    } else {
        0.0
    };
    let u = if jitter {
        crate::rng::uniform(seed, ray_id, k as u32)
    } else {
        0.5
    };
    math::clamp(math::div(1.0, ia + (j as f32 + u) * step), a, b)
}

/// Forward results for one ray. Entries at and past `n` are zero.
#[derive(Clone, Copy)]
pub struct RayOutput {
    /// `w_i`, the rendering weight of each sample.
    pub weights: [f32; MAX_SAMPLES],
    /// `alpha_i` (in `SdfDirect`: the unnormalised bell `b_i`).
    pub alpha: [f32; MAX_SAMPLES],
    /// `T_i`, the transmittance before sample `i` (in `SdfDirect`: `1 / Z` everywhere).
    pub trans: [f32; MAX_SAMPLES],
    /// `C = sum w_i c_i`.
    pub color: [f32; 3],
    /// `D = sum w_i t_i`.
    pub depth: f32,
    /// `O = sum w_i`.
    pub opacity: f32,
}

impl RayOutput {
    /// All zeros.
    pub const fn zeroed() -> Self {
        Self {
            weights: [0.0; MAX_SAMPLES],
            alpha: [0.0; MAX_SAMPLES],
            trans: [0.0; MAX_SAMPLES],
            color: [0.0; 3],
            depth: 0.0,
            opacity: 0.0,
        }
    }
}

/// `T_{i+1} / T_i` of a sample with SDF value `sdf`: `exp(-sigma)` in `SdfDensity`,
/// `sig(beta s)` in `Occupancy` (the bits [`render_forward`] multiplies its transmittance by),
/// 1 in `SdfDirect`.
#[inline(always)]
pub fn transmittance_factor(mode: RenderMode, beta: f32, sdf: f32) -> f32 {
    match mode {
        RenderMode::SdfDensity => math::exp(-(beta * math::sigmoid(-beta * sdf))),
        RenderMode::Occupancy => math::sigmoid(beta * sdf),
        RenderMode::SdfDirect => 1.0,
    }
}

/// Renders one ray: fills `out` from the first `n` samples (`n` clamped to [`MAX_SAMPLES`])
/// of `sdf`, `rgb` and `t`, stopping early once the transmittance falls below `t_min` (0 =
/// never). Returns the number of samples used (formulas and the stopping rule in the module
/// docs); only `sdf[0..used]`, `rgb[0..used]`, `t[0..used]` are read.
#[allow(clippy::too_many_arguments)]
pub fn render_forward(
    mode: RenderMode,
    n: usize,
    sdf: &[f32; MAX_SAMPLES],
    rgb: &[[f32; 3]; MAX_SAMPLES],
    t: &[f32; MAX_SAMPLES],
    beta: f32,
    t_min: f32,
    out: &mut RayOutput,
) -> usize {
    let mut n = if n > MAX_SAMPLES { MAX_SAMPLES } else { n };
    match mode {
        RenderMode::SdfDensity => {
            let mut trans = 1.0f32;
            let mut i = 0;
            while i < n {
                let e = transmittance_factor(mode, beta, sdf[i]);
                out.alpha[i] = 1.0 - e;
                out.trans[i] = trans;
                out.weights[i] = trans * (1.0 - e);
                trans *= e;
                i += 1;
                if trans < t_min {
                    n = i;
                }
            }
        }
        RenderMode::SdfDirect => {
            let mut sum = 0.0f32;
            let mut i = 0;
            while i < n {
                let x = beta * sdf[i];
                let b = math::sigmoid(x) * math::sigmoid(-x);
                out.alpha[i] = b;
                sum += b;
                i += 1;
            }
            let inv_z = math::div(1.0, sum + DIRECT_EPS);
            i = 0;
            while i < n {
                out.trans[i] = inv_z;
                out.weights[i] = out.alpha[i] * inv_z;
                i += 1;
            }
        }
        RenderMode::Occupancy => {
            let mut trans = 1.0f32;
            let mut i = 0;
            while i < n {
                let x = beta * sdf[i];
                let alpha = math::sigmoid(-x);
                out.alpha[i] = alpha;
                out.trans[i] = trans;
                out.weights[i] = trans * alpha;
                trans *= transmittance_factor(mode, beta, sdf[i]);
                i += 1;
                if trans < t_min {
                    n = i;
                }
            }
        }
    }
    let mut color = [0.0f32; 3];
    let mut depth = 0.0f32;
    let mut opacity = 0.0f32;
    let mut i = 0;
    while i < n {
        let w = out.weights[i];
        color[0] += w * rgb[i][0];
        color[1] += w * rgb[i][1];
        color[2] += w * rgb[i][2];
        depth += w * t[i];
        opacity += w;
        i += 1;
    }
    while i < MAX_SAMPLES {
        out.weights[i] = 0.0;
        out.alpha[i] = 0.0;
        out.trans[i] = 0.0;
        i += 1;
    }
    out.color = color;
    out.depth = depth;
    out.opacity = opacity;
    n
}

/// Backward of [`render_forward`] given its output `fwd` (same `mode`, `n`, inputs and `beta`)
/// and the cotangents of colour, depth and opacity. Writes (does not accumulate) `d_sdf`,
/// `d_rgb` (zero past `n`) and `d_beta`. With `color_to_geometry == false` the colour path uses
/// detached weights: `d_color` reaches `d_rgb` only, not `d_sdf` or `d_beta`. O(n); formulas
/// in the module docs.
#[allow(clippy::too_many_arguments)]
pub fn render_backward(
    mode: RenderMode,
    n: usize,
    sdf: &[f32; MAX_SAMPLES],
    rgb: &[[f32; 3]; MAX_SAMPLES],
    t: &[f32; MAX_SAMPLES],
    beta: f32,
    fwd: &RayOutput,
    d_color: [f32; 3],
    d_depth: f32,
    d_opacity: f32,
    color_to_geometry: bool,
    d_sdf: &mut [f32; MAX_SAMPLES],
    d_rgb: &mut [[f32; 3]; MAX_SAMPLES],
    d_beta: &mut f32,
) {
    let n = if n > MAX_SAMPLES { MAX_SAMPLES } else { n };
    let dc = if color_to_geometry {
        d_color
    } else {
        [0.0f32; 3]
    };
    let mut db = 0.0f32;
    let mut i = 0;
    while i < n {
        let w = fwd.weights[i];
        d_rgb[i] = [d_color[0] * w, d_color[1] * w, d_color[2] * w];
        i += 1;
    }
    while i < MAX_SAMPLES {
        d_rgb[i] = [0.0; 3];
        d_sdf[i] = 0.0;
        i += 1;
    }
    match mode {
        RenderMode::SdfDensity => {
            // dL/dsigma_k = T_{k+1} (g_k - Q_k), with T_{k+1} = T_k exp(-sigma_k) as in the
            // forward; Q_k = sum_{j>k} g_j w_j / T_{k+1}, built back to front.
            let mut q = 0.0f32;
            let mut k = n;
            while k > 0 {
                k -= 1;
                let g = weight_cotangent(dc, rgb[k], d_depth, t[k], d_opacity);
                let x = beta * sdf[k];
                let sp = math::sigmoid(x);
                let sm = math::sigmoid(-x);
                let e = math::exp(-(beta * sm));
                let d_sigma = fwd.trans[k] * e * (g - q);
                let ss = sm * sp;
                d_sdf[k] = d_sigma * (-(beta * beta) * ss);
                db += d_sigma * (sm - x * ss);
                q = g * (1.0 - e) + e * q;
            }
        }
        RenderMode::Occupancy => {
            // dL/dalpha_k = T_k (g_k - Q_k), alpha_k = sig(-x_k), 1 - alpha_k = sig(x_k).
            let mut q = 0.0f32;
            let mut k = n;
            while k > 0 {
                k -= 1;
                let g = weight_cotangent(dc, rgb[k], d_depth, t[k], d_opacity);
                let x = beta * sdf[k];
                let sp = math::sigmoid(x);
                let sm = math::sigmoid(-x);
                let d_alpha = fwd.trans[k] * (g - q);
                let ss = sm * sp;
                d_sdf[k] = d_alpha * (-beta * ss);
                db += d_alpha * (-sdf[k] * ss);
                q = g * sm + sp * q;
            }
        }
        RenderMode::SdfDirect => {
            // sum_j g_j w_j, then dL/db_k = (g_k - gw) / Z with 1 / Z = trans_k.
            let mut gw = 0.0f32;
            let mut k = 0;
            while k < n {
                gw += weight_cotangent(dc, rgb[k], d_depth, t[k], d_opacity) * fwd.weights[k];
                k += 1;
            }
            k = 0;
            while k < n {
                let g = weight_cotangent(dc, rgb[k], d_depth, t[k], d_opacity);
                let x = beta * sdf[k];
                let sp = math::sigmoid(x);
                let sm = math::sigmoid(-x);
                let d_b = (g - gw) * fwd.trans[k];
                let slope = sp * sm * (sm - sp);
                d_sdf[k] = d_b * (beta * slope);
                db += d_b * (sdf[k] * slope);
                k += 1;
            }
        }
    }
    *d_beta = db;
}

/// `g = dL/dw = dc . c + d_depth t + d_opacity` for one sample.
#[inline(always)]
fn weight_cotangent(dc: [f32; 3], c: [f32; 3], d_depth: f32, t: f32, d_opacity: f32) -> f32 {
    dc[0] * c[0] + dc[1] * c[1] + dc[2] * c[2] + d_depth * t + d_opacity
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::uniform;
    use crate::Aabb;

    const MODES: [RenderMode; 3] = [
        RenderMode::SdfDensity,
        RenderMode::SdfDirect,
        RenderMode::Occupancy,
    ];

    fn close(a: f32, b: f64, tol: f64) -> bool {
        ((a as f64) - b).abs() <= tol
    }

    /// `render_forward` of both samples of [`golden_ray`] (no early termination).
    fn golden_forward(mode: RenderMode) -> RayOutput {
        let (sdf, rgb, t, beta) = golden_ray();
        let mut out = RayOutput::zeroed();
        render_forward(mode, 2, &sdf, &rgb, &t, beta, 0.0, &mut out);
        out
    }

    /// `render_backward` over the first `n` samples of [`golden_ray`] (colour attached, no
    /// opacity cotangent), into buffers filled with 1 beforehand (so a missed write shows).
    fn golden_backward(
        mode: RenderMode,
        n: usize,
        out: &RayOutput,
        d_color: [f32; 3],
        d_depth: f32,
    ) -> ([f32; MAX_SAMPLES], [[f32; 3]; MAX_SAMPLES], f32) {
        let (sdf, rgb, t, beta) = golden_ray();
        let (mut ds, mut dr, mut db) = ([1.0; MAX_SAMPLES], [[1.0; 3]; MAX_SAMPLES], 1.0);
        render_backward(
            mode, n, &sdf, &rgb, &t, beta, out, d_color, d_depth, 0.0, true, &mut ds, &mut dr,
            &mut db,
        );
        (ds, dr, db)
    }

    /// The 2-sample golden ray: beta = 2, s = (0, -ln(3)/2), so beta s = (0, -ln 3) and
    /// sig(-beta s) = (1/2, 3/4), sig(beta s) = (1/2, 1/4). t = (1, 2),
    /// c_0 = (1, 0, 0), c_1 = (0, 1, 0.5).
    fn golden_ray() -> (
        [f32; MAX_SAMPLES],
        [[f32; 3]; MAX_SAMPLES],
        [f32; MAX_SAMPLES],
        f32,
    ) {
        let mut sdf = [0.0f32; MAX_SAMPLES];
        let mut rgb = [[0.0f32; 3]; MAX_SAMPLES];
        let mut t = [0.0f32; MAX_SAMPLES];
        sdf[1] = -(3.0f64.ln() / 2.0) as f32;
        rgb[0] = [1.0, 0.0, 0.0];
        rgb[1] = [0.0, 1.0, 0.5];
        t[0] = 1.0;
        t[1] = 2.0;
        (sdf, rgb, t, 2.0)
    }

    /// Early termination on the golden ray: T after sample 0 is exp(-1) = 0.368, so a
    /// threshold of 0.5 stops after it (the 1-sample ray's bits, sample 1 weightless and
    /// without gradient) and 0.3 does not (the uncut ray's bits).
    #[test]
    fn early_termination_golden() {
        let (sdf, rgb, t, beta) = golden_ray();
        let bits = |o: &RayOutput| {
            let mut v: Vec<u32> = o
                .weights
                .iter()
                .chain(&o.alpha)
                .chain(&o.trans)
                .map(|x| x.to_bits())
                .collect();
            v.extend([o.depth, o.opacity, o.color[0], o.color[1], o.color[2]].map(f32::to_bits));
            v
        };
        let render = |n: usize, t_min: f32| {
            let mut out = RayOutput::zeroed();
            let used = render_forward(
                RenderMode::SdfDensity,
                n,
                &sdf,
                &rgb,
                &t,
                beta,
                t_min,
                &mut out,
            );
            (used, out)
        };
        let (used, cut) = render(2, 0.5);
        let (one, first) = render(1, 0.0);
        assert_eq!((used, one), (1, 1));
        assert_eq!(bits(&cut), bits(&first));
        assert_eq!(cut.weights[1], 0.0);
        assert!(close(cut.opacity, 1.0 - (-1.0f64).exp(), 1e-6));
        let (used, kept) = render(2, 0.3);
        let (two, whole) = render(2, 0.0);
        assert_eq!((used, two), (2, 2));
        assert_eq!(bits(&kept), bits(&whole));
        // The backward over the used samples leaves the cut one without gradient.
        let (d_sdf, d_rgb, _) =
            golden_backward(RenderMode::SdfDensity, 1, &cut, [1.0, 0.5, 0.25], 0.5);
        assert_eq!((d_sdf[1], d_rgb[1]), (0.0, [0.0; 3]));
        assert!(d_sdf[0] != 0.0);
        // Occupancy: alpha_0 = sig(0) = 1/2, T_1 = 1/2: 0.6 stops, 0.4 does not.
        let used = |mode: RenderMode, t_min: f32| {
            let mut out = RayOutput::zeroed();
            render_forward(mode, 2, &sdf, &rgb, &t, beta, t_min, &mut out)
        };
        assert_eq!(used(RenderMode::Occupancy, 0.6), 1);
        assert_eq!(used(RenderMode::Occupancy, 0.4), 2);
        // SdfDirect never stops.
        assert_eq!(used(RenderMode::SdfDirect, 0.99), 2);
    }

    #[test]
    fn golden_two_samples_density() {
        let out = golden_forward(RenderMode::SdfDensity);
        // sigma = 2 * (1/2, 3/4) = (1, 1.5); alpha = 1 - exp(-sigma) = (0.632121, 0.776870);
        // T = (1, e^-1 = 0.367879); w = (0.632121, 0.367879 * 0.776870 = 0.285794).
        // C = (0.632121, 0.285794, 0.142897); D = 0.632121 + 2 * 0.285794 = 1.203709;
        // O = 1 - e^-2.5 = 0.917915.
        let tol = 2e-6;
        assert!(close(out.alpha[0], 0.632121, tol) && close(out.alpha[1], 0.776870, tol));
        assert!(close(out.trans[0], 1.0, tol) && close(out.trans[1], 0.367879, tol));
        assert!(close(out.weights[0], 0.632121, tol) && close(out.weights[1], 0.285794, tol));
        assert!(close(out.color[0], 0.632121, tol));
        assert!(close(out.color[1], 0.285794, tol));
        assert!(close(out.color[2], 0.142897, tol));
        assert!(close(out.depth, 1.203709, tol));
        assert!(close(out.opacity, 0.917915, tol));
        assert_eq!(out.weights[2], 0.0);

        // Backward of L = D: g = t = (1, 2). Q_1 = 0, Q_0 = g_1 alpha_1 = 1.553740.
        // dL/dsigma_0 = T_1 (g_0 - Q_0) = 0.367879 * (1 - 1.553740) = -0.203709;
        // dL/dsigma_1 = T_2 g_1 = e^-2.5 * 2 = 0.164170.
        // dsigma/ds = -beta^2 sig(-x) sig(x) = (-1, -0.75): d_s = (0.203709, -0.123127).
        // dsigma/dbeta = sig(-x) - x sig(-x) sig(x) = (0.5, 0.75 + ln3 * 0.1875 = 0.955990):
        // d_beta = -0.203709 * 0.5 + 0.164170 * 0.955990 = 0.055090.
        let (ds, dr, db) = golden_backward(RenderMode::SdfDensity, 2, &out, [0.0; 3], 1.0);
        assert!(close(ds[0], 0.203709, 2e-6), "{}", ds[0]);
        assert!(close(ds[1], -0.123127, 2e-6), "{}", ds[1]);
        assert!(close(db, 0.055090, 2e-6), "{db}");
        assert_eq!(dr[0], [0.0; 3]);
    }

    #[test]
    fn golden_two_samples_occupancy_and_direct() {
        // Occupancy: alpha = sig(-x) = (0.5, 0.75); T = (1, 0.5); w = (0.5, 0.375);
        // D = 0.5 + 0.75 = 1.25; O = 0.875.
        let out = golden_forward(RenderMode::Occupancy);
        assert!(close(out.weights[0], 0.5, 1e-6) && close(out.weights[1], 0.375, 1e-6));
        assert!(close(out.depth, 1.25, 1e-6) && close(out.opacity, 0.875, 1e-6));
        // L = D = a0 + 2 (1 - a0) a1: dL/da0 = 1 - 2 a1 = -0.5, dL/da1 = 2 (1 - a0) = 1.
        // dalpha/ds = -beta sig(-x) sig(x) = (-0.5, -0.375): d_s = (0.25, -0.375).
        // dalpha/dbeta = -s sig(-x) sig(x) = (0, 0.549306 * 0.1875 = 0.102995): d_beta = 0.102995.
        let (ds, _, db) = golden_backward(RenderMode::Occupancy, 2, &out, [0.0; 3], 1.0);
        assert!(
            close(ds[0], 0.25, 1e-6) && close(ds[1], -0.375, 1e-6),
            "{ds:?}"
        );
        assert!(close(db, 0.102995, 1e-6), "{db}");

        // SdfDirect: b = sig(x) sig(-x) = (0.25, 0.1875); Z = 0.4375 (+1e-8);
        // w = (4/7, 3/7) = (0.571429, 0.428571); D = 4/7 + 6/7 = 10/7 = 1.428571.
        let out = golden_forward(RenderMode::SdfDirect);
        assert!(close(out.weights[0], 4.0 / 7.0, 1e-6));
        assert!(close(out.weights[1], 3.0 / 7.0, 1e-6));
        assert!(close(out.depth, 10.0 / 7.0, 1e-6) && close(out.opacity, 1.0, 1e-6));
        assert!(close(out.alpha[1], 0.1875, 1e-7) && close(out.trans[0], 1.0 / 0.4375, 1e-5));
        // L = D: g = (1, 2), sum g w = 10/7; dL/db = (g - 10/7) / Z = (-48/49, 64/49).
        // db/ds = beta b (sig(-x) - sig(x)) = (0, 2 * 0.1875 * 0.5 = 0.1875):
        // d_s = (0, 64/49 * 0.1875 = 0.244898).
        // db/dbeta = s b (sig(-x) - sig(x)) = (0, -0.549306 * 0.09375 = -0.051497):
        // d_beta = 64/49 * -0.051497 = -0.067261.
        let (ds, _, db) = golden_backward(RenderMode::SdfDirect, 2, &out, [0.0; 3], 1.0);
        assert!(
            close(ds[0], 0.0, 1e-6) && close(ds[1], 0.244898, 1e-6),
            "{ds:?}"
        );
        assert!(close(db, -0.067261, 1e-6), "{db}");
    }

    struct Case {
        n: usize,
        sdf: [f32; MAX_SAMPLES],
        rgb: [[f32; 3]; MAX_SAMPLES],
        t: [f32; MAX_SAMPLES],
        d_color: [f32; 3],
        d_depth: f32,
        d_opacity: f32,
    }

    fn random_case(n: usize, seed: u32) -> Case {
        let mut c = Case {
            n,
            sdf: [0.0; MAX_SAMPLES],
            rgb: [[0.0; 3]; MAX_SAMPLES],
            t: [0.0; MAX_SAMPLES],
            d_color: [0.0; 3],
            d_depth: 0.0,
            d_opacity: 0.0,
        };
        for i in 0..n {
            c.sdf[i] = (uniform(seed, 1, i as u32) - 0.5) * 0.6;
            for k in 0..3 {
                c.rgb[i][k] = uniform(seed, 2 + k as u32, i as u32);
            }
        }
        stratified_samples(0.5, 3.0, n, seed, 9, true, &mut c.t);
        for k in 0..3 {
            c.d_color[k] = uniform(seed, 10 + k as u32, 0) * 2.0 - 1.0;
        }
        c.d_depth = uniform(seed, 20, 0) * 2.0 - 1.0;
        c.d_opacity = uniform(seed, 21, 0) * 2.0 - 1.0;
        c
    }

    /// The scalar loss the cotangents define: `d_color . C` (if `with_color`) plus
    /// `d_depth D + d_opacity O`.
    fn loss(
        mode: RenderMode,
        c: &Case,
        sdf: &[f32; MAX_SAMPLES],
        rgb: &[[f32; 3]; MAX_SAMPLES],
        beta: f32,
        with_color: bool,
    ) -> f32 {
        let mut out = RayOutput::zeroed();
        render_forward(mode, c.n, sdf, rgb, &c.t, beta, 0.0, &mut out);
        let mut l = c.d_depth * out.depth + c.d_opacity * out.opacity;
        if with_color {
            for k in 0..3 {
                l += c.d_color[k] * out.color[k];
            }
        }
        l
    }

    /// Central finite differences in f32. Steps: h = 2e-3 for s and beta (L = O(1), rounding
    /// ~ 1e-7 / h ~ 5e-5; the truncation ~ h^2 beta^3 |L'''| / 6 is of the same order), 1e-2
    /// for rgb (L is linear in rgb, so only rounding, ~5e-6). Tolerances |analytic - fd| <=
    /// 5e-4 + 5e-3 |fd| for s and beta (measured worst case 1.7e-4 absolute, 9e-4 relative for
    /// |fd| > 0.05) and 5e-5 + 1e-3 |fd| for rgb.
    #[test]
    fn finite_difference_all_modes() {
        let beta = 10.0f32;
        let (h, h_rgb) = (2e-3f32, 1e-2f32);
        let ok = |a: f32, fd: f32| (a - fd).abs() <= 5e-4 + 5e-3 * fd.abs();
        let ok_rgb = |a: f32, fd: f32| (a - fd).abs() <= 5e-5 + 1e-3 * fd.abs();
        let mut checked = 0;
        for mode in MODES {
            for &n in &[16usize, 48] {
                for &ctg in &[true, false] {
                    for seed in 0..3u32 {
                        let c = random_case(n, seed * 7 + n as u32);
                        let mut out = RayOutput::zeroed();
                        render_forward(mode, n, &c.sdf, &c.rgb, &c.t, beta, 0.0, &mut out);
                        let mut ds = [f32::NAN; MAX_SAMPLES];
                        let mut dr = [[f32::NAN; 3]; MAX_SAMPLES];
                        let mut db = f32::NAN;
                        render_backward(
                            mode,
                            n,
                            &c.sdf,
                            &c.rgb,
                            &c.t,
                            beta,
                            &out,
                            c.d_color,
                            c.d_depth,
                            c.d_opacity,
                            ctg,
                            &mut ds,
                            &mut dr,
                            &mut db,
                        );
                        // With detached colour weights, geometry sees only depth + opacity.
                        let geo_color = ctg;
                        for i in 0..n {
                            let (mut sp, mut sm) = (c.sdf, c.sdf);
                            sp[i] += h;
                            sm[i] -= h;
                            let fd = (loss(mode, &c, &sp, &c.rgb, beta, geo_color)
                                - loss(mode, &c, &sm, &c.rgb, beta, geo_color))
                                / (2.0 * h);
                            assert!(
                                ok(ds[i], fd),
                                "{mode:?} n{n} ctg{ctg} d_sdf[{i}] {} vs {fd}",
                                ds[i]
                            );
                            for k in 0..3 {
                                let (mut rp, mut rm) = (c.rgb, c.rgb);
                                rp[i][k] += h_rgb;
                                rm[i][k] -= h_rgb;
                                let fd = (loss(mode, &c, &c.sdf, &rp, beta, true)
                                    - loss(mode, &c, &c.sdf, &rm, beta, true))
                                    / (2.0 * h_rgb);
                                assert!(
                                    ok_rgb(dr[i][k], fd),
                                    "{mode:?} d_rgb[{i}][{k}] {} vs {fd}",
                                    dr[i][k]
                                );
                            }
                            checked += 1;
                        }
                        let fd = (loss(mode, &c, &c.sdf, &c.rgb, beta + h, geo_color)
                            - loss(mode, &c, &c.sdf, &c.rgb, beta - h, geo_color))
                            / (2.0 * h);
                        assert!(ok(db, fd), "{mode:?} n{n} ctg{ctg} d_beta {db} vs {fd}");
                        // Past n: zeroed.
                        assert_eq!(ds[n], 0.0);
                        assert_eq!(dr[n], [0.0; 3]);
                    }
                }
            }
        }
        assert_eq!(checked, 3 * 2 * 3 * (16 + 48));
    }

    /// The detached colour path must actually differ from the attached one (so the test above
    /// checks something), and agree with it when d_color = 0.
    #[test]
    fn color_detach_changes_only_color_part() {
        let c = random_case(16, 5);
        for mode in MODES {
            let mut out = RayOutput::zeroed();
            render_forward(mode, 16, &c.sdf, &c.rgb, &c.t, 10.0, 0.0, &mut out);
            let run = |dcol: [f32; 3], ctg: bool| {
                let (mut ds, mut dr, mut db) = ([0.0; MAX_SAMPLES], [[0.0; 3]; MAX_SAMPLES], 0.0);
                render_backward(
                    mode,
                    16,
                    &c.sdf,
                    &c.rgb,
                    &c.t,
                    10.0,
                    &out,
                    dcol,
                    c.d_depth,
                    c.d_opacity,
                    ctg,
                    &mut ds,
                    &mut dr,
                    &mut db,
                );
                (ds, dr, db)
            };
            let (a, ar, ab) = run(c.d_color, true);
            let (b, br, bb) = run(c.d_color, false);
            let (z, _, zb) = run([0.0; 3], true);
            assert_eq!(ar, br, "d_rgb must not depend on the detach flag");
            assert_eq!(b, z);
            assert_eq!(bb, zb);
            assert!(a.iter().zip(b.iter()).any(|(x, y)| (x - y).abs() > 1e-4));
            assert!((ab - bb).abs() > 1e-6);
        }
    }

    #[test]
    fn no_nan_for_extreme_inputs() {
        let mut t = [0.0f32; MAX_SAMPLES];
        stratified_samples(0.1, 10.0, MAX_SAMPLES, 3, 4, true, &mut t);
        let mut rgb = [[0.5f32; 3]; MAX_SAMPLES];
        rgb[3] = [1.0, 0.0, 0.25];
        let patterns: [fn(usize) -> f32; 5] = [
            |_| 1e4,
            |_| -1e4,
            |i| if i % 2 == 0 { 1e4 } else { -1e4 },
            |i| if i < 60 { 1e4 } else { -1e4 },
            |i| (i as f32 - 64.0) * 0.01,
        ];
        for mode in MODES {
            for p in patterns {
                for &beta in &[0.0f32, 1.0, 10.0, 100.0] {
                    let mut sdf = [0.0f32; MAX_SAMPLES];
                    for (i, s) in sdf.iter_mut().enumerate() {
                        *s = p(i);
                    }
                    let mut out = RayOutput::zeroed();
                    render_forward(mode, MAX_SAMPLES, &sdf, &rgb, &t, beta, 0.0, &mut out);
                    let (mut ds, mut dr, mut db) =
                        ([0.0; MAX_SAMPLES], [[0.0; 3]; MAX_SAMPLES], 0.0);
                    render_backward(
                        mode,
                        MAX_SAMPLES,
                        &sdf,
                        &rgb,
                        &t,
                        beta,
                        &out,
                        [1.0, -2.0, 0.5],
                        3.0,
                        -1.0,
                        true,
                        &mut ds,
                        &mut dr,
                        &mut db,
                    );
                    let scalars = [out.depth, out.opacity, db];
                    let all = out
                        .weights
                        .iter()
                        .chain(out.alpha.iter())
                        .chain(out.trans.iter())
                        .chain(out.color.iter())
                        .chain(scalars.iter())
                        .chain(ds.iter())
                        .chain(dr.iter().flatten());
                    for v in all {
                        assert!(v.is_finite(), "{mode:?} beta {beta}: {v}");
                    }
                    assert!(
                        out.opacity >= 0.0 && out.opacity <= 1.0 + 1e-5,
                        "{}",
                        out.opacity
                    );
                }
            }
        }
    }

    #[test]
    fn opaque_surface_gives_its_depth() {
        // A step from free space (s > 0) to solid (s < 0) between samples 9 and 10: with
        // beta = 100 the density and occupancy modes stop at sample 10.
        let mut t = [0.0f32; MAX_SAMPLES];
        stratified_samples(0.0, 2.0, 20, 0, 0, false, &mut t);
        let mut sdf = [0.0f32; MAX_SAMPLES];
        for (i, s) in sdf.iter_mut().enumerate().take(20) {
            *s = if i < 10 { 0.5 } else { -0.5 };
        }
        let rgb = [[0.2f32; 3]; MAX_SAMPLES];
        for mode in [RenderMode::SdfDensity, RenderMode::Occupancy] {
            let mut out = RayOutput::zeroed();
            render_forward(mode, 20, &sdf, &rgb, &t, 100.0, 0.0, &mut out);
            assert!((out.depth - t[10]).abs() < 1e-3, "{mode:?} {}", out.depth);
            assert!((out.opacity - 1.0).abs() < 1e-5);
            assert!((out.color[0] - 0.2).abs() < 1e-5);
        }
    }

    #[test]
    fn n_is_clamped() {
        let c = random_case(MAX_SAMPLES, 1);
        let mut a = RayOutput::zeroed();
        let mut b = RayOutput::zeroed();
        render_forward(
            RenderMode::SdfDensity,
            10_000,
            &c.sdf,
            &c.rgb,
            &c.t,
            10.0,
            0.0,
            &mut a,
        );
        render_forward(
            RenderMode::SdfDensity,
            MAX_SAMPLES,
            &c.sdf,
            &c.rgb,
            &c.t,
            10.0,
            0.0,
            &mut b,
        );
        assert_eq!(a.depth.to_bits(), b.depth.to_bits());
        let mut z = RayOutput::zeroed();
        render_forward(
            RenderMode::SdfDensity,
            0,
            &c.sdf,
            &c.rgb,
            &c.t,
            10.0,
            0.0,
            &mut z,
        );
        assert_eq!((z.depth, z.opacity, z.weights[0]), (0.0, 0.0, 0.0));
    }

    fn unit_box() -> Aabb {
        Aabb::new([-1.0; 3], [1.0; 3])
    }

    #[test]
    fn ray_aabb_cases() {
        let b = unit_box();
        // Straight through from outside: enters at z = -1 (t = 4), leaves at z = 1 (t = 6).
        assert_eq!(
            ray_aabb([0.0, 0.0, -5.0], [0.0, 0.0, 1.0], &b),
            (4.0, 6.0, true)
        );
        // Unnormalised direction halves the t values.
        assert_eq!(
            ray_aabb([0.0, 0.0, -5.0], [0.0, 0.0, 2.0], &b),
            (2.0, 3.0, true)
        );
        // Origin inside: near = 0, far at x = 1.
        assert_eq!(
            ray_aabb([0.0, 0.0, 0.0], [1.0, 0.0, 0.0], &b),
            (0.0, 1.0, true)
        );
        assert_eq!(
            ray_aabb([0.5, 0.0, 0.0], [-0.5, 0.0, 0.0], &b),
            (0.0, 3.0, true)
        );
        // Parallel to a slab, outside it.
        assert!(!ray_aabb([0.0, 5.0, -5.0], [0.0, 0.0, 1.0], &b).2);
        // Oblique miss: x-slab t in [2, 4], y-slab t in [-0.5, 0.5].
        assert_eq!(
            ray_aabb([-3.0, 0.0, 0.0], [1.0, 2.0, 0.0], &b),
            (0.0, 0.0, false)
        );
        // Box entirely behind the origin.
        assert!(!ray_aabb([0.0, 0.0, 5.0], [0.0, 0.0, 1.0], &b).2);
        // Grazing along a face (y = 1) and along an edge (y = z = 1).
        assert_eq!(
            ray_aabb([-3.0, 1.0, 0.0], [1.0, 0.0, 0.0], &b),
            (2.0, 4.0, true)
        );
        assert_eq!(
            ray_aabb([-3.0, 1.0, 1.0], [1.0, 0.0, 0.0], &b),
            (2.0, 4.0, true)
        );
        // Touching an edge at one point: x-slab t in [-1, 1], y-slab t in [1, 3] -> t = 1.
        assert_eq!(
            ray_aabb([0.0, 2.0, 0.0], [1.0, -1.0, 0.0], &b),
            (1.0, 1.0, true)
        );
        // Just outside that edge: a miss.
        assert!(!ray_aabb([0.0, 2.001, 0.0], [1.0, -1.0, 0.0], &b).2);
        // Zero direction: hit (near = far = 0) from inside, miss from outside.
        assert!(ray_aabb([0.0; 3], [0.0; 3], &b).2);
        assert!(!ray_aabb([2.0, 0.0, 0.0], [0.0; 3], &b).2);
    }

    #[test]
    fn stratified_samples_properties() {
        // No jitter: bin centres. near 1, far 3, n 4: step 0.5, t = 1.25, 1.75, 2.25, 2.75.
        let mut t = [0.0f32; MAX_SAMPLES];
        stratified_samples(1.0, 3.0, 4, 0, 0, false, &mut t);
        assert_eq!(&t[..5], &[1.25, 1.75, 2.25, 2.75, 3.0]);
        assert!(t[4..].iter().all(|&x| x == 3.0));

        for ray in 0..200u32 {
            let (near, far) = (0.1 + ray as f32 * 0.01, 2.0 + ray as f32 * 0.05);
            for &n in &[1usize, 7, 60, 128, 500] {
                let mut a = [0.0f32; MAX_SAMPLES];
                let mut b = [0.0f32; MAX_SAMPLES];
                stratified_samples(near, far, n, 42, ray, true, &mut a);
                stratified_samples(near, far, n, 42, ray, true, &mut b);
                assert_eq!(a.map(f32::to_bits), b.map(f32::to_bits), "deterministic");
                let m = n.min(MAX_SAMPLES);
                let step = (far - near) / m as f32;
                for i in 0..MAX_SAMPLES {
                    assert!(a[i] >= near && a[i] <= far, "bounds");
                    if i + 1 < MAX_SAMPLES {
                        assert!(a[i] <= a[i + 1], "sorted");
                    }
                    if i < m {
                        // In its own bin (with a little rounding slack).
                        let lo = near + i as f32 * step;
                        assert!(a[i] >= lo - 1e-5 && a[i] <= lo + step + 1e-5);
                    }
                }
                let mut c = [0.0f32; MAX_SAMPLES];
                stratified_samples(near, far, n, 43, ray, true, &mut c);
                assert!(n < 2 || a != c, "seed changes the jitter");
            }
        }
        // far < near collapses to near.
        stratified_samples(2.0, 1.0, 8, 0, 0, true, &mut t);
        assert!(t.iter().all(|&x| x == 2.0));
    }
}
