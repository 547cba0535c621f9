//! An edge-aware planarity prior on the rendered depth of pixel triplets.
//!
//! The warping loss shapes a surface only where the surface has texture: on a plain wall
//! every depth explains the frames equally well and the rendered depth drifts into blobs of
//! near and far values. The prior asks three rendered depths `d_a`, `d_b`, `d_c` of pixels
//! `b - s`, `b`, `b + s` along one image row or column of a frame to lie on a plane:
//!
//! - the inverse depth of a plane is affine in the pixel coordinates, so its second
//!   difference along a line of pixels is zero for every plane, whatever its slant (a first
//!   difference of depth would pull slanted floors and walls towards the camera's plane);
//! - relative to the centre's inverse depth the residual is scale-free:
//!   `r = (1/d_a + 1/d_c - 2/d_b) d_b = d_b/d_a + d_b/d_c - 2`;
//! - `loss = w smoothL1_beta(r)`, with an edge weight `w = 1 / (1 + edge g)` from the frame's
//!   own colours, `g = max(mean_c |I_a - I_b|, mean_c |I_b - I_c|)`: depth edges usually are
//!   colour edges, so a triplet across one is weighted down (a rational weight rather than
//!   Monodepth's `exp(-g)`: plain IEEE operations, the same bits on every device).
//!
//! Gradients: `dr/dd_a = -(d_b/d_a)/d_a`, `dr/dd_c = -(d_b/d_c)/d_c`, `dr/dd_b = 1/d_a +
//! 1/d_c`, times `w smoothL1'(r)`. A triplet with a depth below [`MIN_DEPTH`] (a pixel that
//! rendered nothing) gives no loss.
//!
//! **Unequal spacings** (`b - s_a`, `b`, `b + s_c`: the region triplets of
//! `mapper.planar_region_step`, whose outer pixels are the ends of the plain run around `b`):
//! the plane's inverse depth at `b` is the interpolation `(s_c/d_a + s_a/d_c) / (s_a + s_c)`,
//! so with `k_a = 2 s_c / (s_a + s_c)` and `k_c = 2 s_a / (s_a + s_c)` the residual is
//! `r = (k_a d_b/d_a - 1) + (k_c d_b/d_c - 1)` and the gradients carry the same factors. For
//! `s_a = s_c` both factors are exactly 1 and every operation is the equal-spacing one (the
//! same bits).

use super::smooth_l1;
use crate::math;

/// `1 / 3`, rounded once by the compiler (a constant, so no division in kernels).
pub const THIRD: f32 = 1.0 / 3.0;

/// Depths below this (m) make a triplet invalid: the pixel rendered (almost) nothing, or its
/// view collapsed onto the camera (as `mapper.depth_prior_near`: nothing is that close to a
/// camera in free space). The gradient grows as `d_b / d_a^2`, so near-zero depths would
/// dominate every other term.
pub const MIN_DEPTH: f32 = 0.5;

/// The prior's settings (see the module documentation).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PlanarConfig {
    /// Weight of the prior (scaled by the mapping loss's per-pixel scale); 0 = off.
    pub weight: f32,
    /// Edge sensitivity `edge` of `w = 1 / (1 + edge g)` (0 = no edge weighting).
    pub edge: f32,
    /// Smooth-L1 threshold of the residual `r`.
    pub beta: f32,
    /// A triplet pays the prior only where its centre has the warping term's `min_views`
    /// valid views (see [`crate::train::pixel::pixel_loss`]).
    pub gated: bool,
}

impl PlanarConfig {
    /// The prior switched off.
    pub const OFF: Self = Self {
        weight: 0.0,
        edge: 0.0,
        beta: 0.0,
        gated: false,
    };
}

/// Mean over the channels of `|x - y|` (the colour step of the edge weight, and the one the
/// mapper's region triplets stop at).
#[inline(always)]
pub fn mean_abs_diff(x: [f32; 3], y: [f32; 3]) -> f32 {
    (math::abs(x[0] - y[0]) + math::abs(x[1] - y[1]) + math::abs(x[2] - y[2])) * THIRD
}

/// The edge weight `1 / (1 + edge g)` of a triplet's colours.
#[inline(always)]
pub fn edge_weight(rgb: &[[f32; 3]; 3], edge: f32) -> f32 {
    let g = math::max(mean_abs_diff(rgb[0], rgb[1]), mean_abs_diff(rgb[1], rgb[2]));
    math::div(1.0, 1.0 + edge * g)
}

/// The prior of one triplet with equal spacings (depths and colours of pixels `b - s`, `b`,
/// `b + s`): returns `(loss, d loss / d depth)` (zeros for an invalid triplet). Unweighted by
/// `cfg.weight`.
#[inline]
pub fn planarity(depth: [f32; 3], rgb: &[[f32; 3]; 3], cfg: &PlanarConfig) -> (f32, [f32; 3]) {
    planarity_spaced(depth, rgb, cfg, [1, 1])
}

/// [`planarity`] for pixels `b - s_a`, `b`, `b + s_c` (`spacing = [s_a, s_c]`, both >= 1;
/// the module documentation gives the interpolation). Equal spacings give [`planarity`]'s bits.
#[inline]
pub fn planarity_spaced(
    depth: [f32; 3],
    rgb: &[[f32; 3]; 3],
    cfg: &PlanarConfig,
    spacing: [u32; 2],
) -> (f32, [f32; 3]) {
    let [da, db, dc] = depth;
    // `!(x >= MIN)` also rejects NaN
    if !(da >= MIN_DEPTH && db >= MIN_DEPTH && dc >= MIN_DEPTH) {
        return (0.0, [0.0; 3]);
    }
    let (sa, sc) = (spacing[0] as f32, spacing[1] as f32);
    let sum = sa + sc;
    let ka = math::div(sc + sc, sum);
    let kc = math::div(sa + sa, sum);
    let inv_a = math::div(1.0, da);
    let inv_c = math::div(1.0, dc);
    let ra = ka * (db * inv_a);
    let rc = kc * (db * inv_c);
    let r = (ra - 1.0) + (rc - 1.0);
    let (v, dv) = smooth_l1(r, cfg.beta);
    let w = edge_weight(rgb, cfg.edge);
    let k = w * dv;
    (
        w * v,
        [
            -(k * (ra * inv_a)),
            k * (ka * inv_a + kc * inv_c),
            -(k * (rc * inv_c)),
        ],
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    const CFG: PlanarConfig = PlanarConfig {
        weight: 1.0,
        edge: 10.0,
        beta: 0.05,
        gated: false,
    };
    const GREY: [[f32; 3]; 3] = [[0.5; 3]; 3];

    /// Every plane gives zero: inverse depth affine along the line of pixels.
    #[test]
    fn planes_of_any_slant_give_no_loss() {
        for (z0, dz) in [
            (1.0f32, 0.0f32),
            (1.0, 0.25),
            (0.5, 0.125),
            (1.5, -0.25),
            (0.25, 0.0625),
        ] {
            // inverse depths z0 - dz, z0, z0 + dz (exact binary fractions)
            let depth = [1.0 / (z0 - dz), 1.0 / z0, 1.0 / (z0 + dz)];
            let (l, g) = planarity(depth, &GREY, &CFG);
            assert!(l.abs() < 1e-9, "z0 {z0} dz {dz}: loss {l}");
            assert!(g.iter().all(|x| x.abs() < 1e-5), "{g:?}");
        }
    }

    /// Hand-computed: depths 1, 2, 1 give r = 2 + 2 - 2 = 2 (L1 side): loss 2 - beta / 2,
    /// dr/dd = (-2, 2, -2), grey colours weight 1.
    #[test]
    fn golden_bump() {
        let (l, g) = planarity([1.0, 2.0, 1.0], &GREY, &CFG);
        assert_eq!(l, 2.0 - 0.025);
        assert_eq!(g, [-2.0, 2.0, -2.0]);
        // an edge of 0.3 in every channel: w = 1 / (1 + 10 * 0.3) = 0.25
        let rgb = [[0.2; 3], [0.5; 3], [0.5; 3]];
        let (l, g) = planarity([1.0, 2.0, 1.0], &rgb, &CFG);
        assert!((l - 0.25 * 1.975).abs() < 1e-6);
        assert!((g[1] - 0.5).abs() < 1e-6);
    }

    #[test]
    fn pixels_without_depth_give_nothing() {
        for d in [[0.0, 1.0, 1.0], [1.0, 0.01, 1.0], [1.0, 1.0, f32::NAN]] {
            assert_eq!(planarity(d, &GREY, &CFG), (0.0, [0.0; 3]));
        }
    }

    /// Unequal spacings: a plane's inverse depth sampled at `b - 1`, `b`, `b + 3` gives no
    /// loss; the spacing [s, s] gives the equal-spacing bits; a bump is hand-computed.
    #[test]
    fn unequal_spacings_interpolate_the_plane() {
        // inverse depth 1 + u / 8 at u = -1, 0, 3 (exact binary fractions)
        let depth = [1.0 / 0.875, 1.0, 1.0 / 1.375];
        let (l, g) = planarity_spaced(depth, &GREY, &CFG, [1, 3]);
        assert!(l.abs() < 1e-9, "loss {l}");
        assert!(g.iter().all(|x| x.abs() < 1e-5), "{g:?}");
        for d in [[1.3f32, 1.5, 1.62], [2.0, 1.2, 2.9]] {
            for s in [1, 5, 48] {
                assert_eq!(
                    planarity_spaced(d, &GREY, &CFG, [s, s]),
                    planarity(d, &GREY, &CFG)
                );
            }
        }
        // depths 1, 2, 1 at spacings 1 and 3: k_a = 1.5, k_c = 0.5, r = (3 - 1) + (1 - 1) = 2
        let (l, g) = planarity_spaced([1.0, 2.0, 1.0], &GREY, &CFG, [1, 3]);
        assert_eq!(l, 2.0 - 0.025);
        assert_eq!(g, [-3.0, 2.0, -1.0]);
    }

    /// Central finite differences in f64 of the f32 loss, both sides of beta.
    #[test]
    fn gradient_matches_finite_differences() {
        let rgb = [[0.1, 0.2, 0.3], [0.15, 0.2, 0.35], [0.4, 0.2, 0.3]];
        for depth in [[1.3f32, 1.5, 1.62], [2.0, 1.2, 2.9], [0.8, 0.81, 0.79]] {
            for sp in [[1, 1], [2, 7], [30, 4]] {
                let f = |d| planarity_spaced(d, &rgb, &CFG, sp);
                let (_, g) = f(depth);
                for k in 0..3 {
                    let h = 1e-3f32;
                    let mut p = depth;
                    let mut m = depth;
                    p[k] += h;
                    m[k] -= h;
                    let fd = (f(p).0 as f64 - f(m).0 as f64) / (2.0 * h as f64);
                    let tol = 2e-3 * (1.0 + fd.abs());
                    assert!(
                        (fd - g[k] as f64).abs() < tol,
                        "depth {depth:?} spacing {sp:?} k {k}: fd {fd} analytic {}",
                        g[k]
                    );
                }
            }
        }
    }
}
