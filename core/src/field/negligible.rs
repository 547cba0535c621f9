//! Work that provably changes no result (host-side): samples whose backward adds nothing,
//! and the colours a render need not evaluate.
//!
//! Every contribution of a sample's backward is converted to fixed point on its own
//! (`to_fixed`: `g * 2^40` rounded to the nearest integer), so a contribution below half a
//! quantum (2^-41) in magnitude adds exactly 0. A sample far from every surface has a
//! cotangent many orders of magnitude below that (`d_sdf` of 1e-30 and less, often
//! subnormal), and its backward through a decoder and a grid then adds only zeros while its
//! arithmetic runs on subnormal numbers, which costs a microcode assist per operation on many
//! CPUs. [`branch_negligible`] bounds, from the sample's own activations and grid factors and
//! the decoder's largest weights, every value that branch's backward computes, and says
//! whether all of them stay below [`LIMIT`] (2^-44, an eighth of a quantum's half): the
//! branch can then be skipped with the same integer sums, hence the same bits.
//!
//! The bounds use round-to-nearest f32 arithmetic: a product or sum of `n <= 128` terms is
//! at most `(1 + 2^-24)^(2n) < 1.00002` times the exact sum of magnitudes plus `2n` times the
//! largest subnormal rounding error (2^-150); each step below takes a factor 2 and adds 2^-140
//! instead. Non-finite values anywhere make the check fail (the branch then runs).

use crate::field::mlp::{MlpLayout, MlpScratch, MAX_HIDDEN_LAYERS};
use crate::ParamRead;

/// Contributions provably below this (2^-44) round to 0 quanta.
pub const LIMIT: f64 = 1.0 / (1u64 << 44) as f64;

/// Absolute slack added at each bound (2^-140): covers the subnormal rounding errors.
const SLACK: f64 = 1.0 / (1u128 << 100) as f64 / (1u64 << 40) as f64;

/// Bits of 2^-40: a cotangent at least this large never takes the check (it costs a pass over
/// the sample's activations and factors; a sample that large is unlikely to pass).
const GATE_BITS: u32 = (127 - 40) << 23;

/// The largest |weight| of every layer of a decoder, as f64 (+inf where a weight is not
/// finite; entries past the output layer 0).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LayerBounds(pub [f64; MAX_HIDDEN_LAYERS + 1]);

impl LayerBounds {
    /// The bounds of `params` laid out as `layout` (a weight past the buffer counts as +inf).
    pub fn of<P: ParamRead + ?Sized>(layout: &MlpLayout, params: &P) -> Self {
        let (n_in, hidden, layers, n_out) = layout.dims();
        let mut w = [0.0f64; MAX_HIDDEN_LAYERS + 1];
        for (k, wk) in w.iter_mut().enumerate().take(layers + 1) {
            let fan_in = if k == 0 { n_in } else { hidden };
            let fan_out = if k == layers { n_out } else { hidden };
            let off = layout.weight_offsets[k] as usize;
            *wk = group_max(params, off, fan_in * fan_out).unwrap_or(f64::INFINITY);
        }
        Self(w)
    }
}

/// [`LayerBounds`] of both decoders.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct DecoderBounds {
    /// The geometry decoder's.
    pub geometry: LayerBounds,
    /// The appearance decoder's.
    pub appearance: LayerBounds,
}

/// An upper bound on `|x|` for the magnitude bits `m` of an f32 (`m` = bits with the sign
/// cleared), without arithmetic on a subnormal: 2^-126 for a subnormal, `None` when not
/// finite.
#[inline(always)]
fn bits_bound(m: u32) -> Option<f64> {
    if m >= 0x7f80_0000 {
        None
    } else if m == 0 {
        Some(0.0)
    } else if m < 0x0080_0000 {
        Some(f64::from(f32::MIN_POSITIVE))
    } else {
        Some(f64::from(f32::from_bits(m)))
    }
}

/// An upper bound on `max |x|` over `xs` (`None` when one is not finite). Compares the
/// magnitudes' bits (their order is the numbers' for finite floats): no float arithmetic.
#[inline(always)]
pub fn max_abs(xs: &[f32]) -> Option<f64> {
    let mut m = 0u32;
    for &x in xs {
        m = m.max(x.to_bits() & 0x7fff_ffff);
    }
    bits_bound(m)
}

/// Whether `x` is small enough in magnitude (below 2^-40) to try [`branch_negligible`] (NaN is
/// not).
#[inline(always)]
pub fn below_gate(x: f32) -> bool {
    (x.to_bits() & 0x7fff_ffff) < GATE_BITS
}

/// A bound on `|d_sdf|`, the geometry decoder's output cotangent.
#[inline(always)]
pub fn sdf_top(d_sdf: f32) -> f64 {
    bits_bound(d_sdf.to_bits() & 0x7fff_ffff).unwrap_or(f64::INFINITY)
}

/// A bound on the appearance decoder's output cotangents `d_rgb[c] * rgb[c] * (1 - rgb[c])`
/// (`color_decoder_backward`'s, rounded twice): `2 |d| |r| (1 + |r|)` plus the slack.
#[inline(always)]
pub fn color_top(d_rgb: [f32; 3], rgb: [f32; 3]) -> f64 {
    let mut top = 0.0f64;
    for c in 0..3 {
        let d = bits_bound(d_rgb[c].to_bits() & 0x7fff_ffff);
        let r = bits_bound(rgb[c].to_bits() & 0x7fff_ffff);
        let (Some(d), Some(r)) = (d, r) else {
            return f64::INFINITY;
        };
        top = top.max(2.0 * d * r * (1.0 + r) + SLACK);
    }
    top
}

/// Whether the backward of one decoder branch of a sample adds only zeros: the decoder's
/// backward from output cotangents at most `top` in magnitude (its bias and weight
/// contributions, layer by layer, with the sample's activations `act` and the decoder's
/// weight bounds `w`), then the grid's contributions, each a feature cotangent times one of
/// the sample's kept term factors `kept` times an interpolation weight in [0, 1]
/// ([`crate::field::grid::grid_backward_rows_kept`]). True only when every one of those
/// contributions is provably below [`LIMIT`].
pub fn branch_negligible(
    layout: &MlpLayout,
    act: &MlpScratch,
    w: &LayerBounds,
    top: f64,
    kept: &[f32],
) -> bool {
    let (n_in, hidden, layers, n_out) = layout.dims();
    // `b`: a bound on the cotangents of the current layer's outputs (its units' gradients).
    let mut b = top;
    let mut fan_out = n_out;
    for kk in 0..=layers {
        let k = layers - kk;
        let fan_in = if k == 0 { n_in } else { hidden };
        let Some(a) = max_abs(&act.act[k][..fan_in]) else {
            return false;
        };
        // Bias contributions (the unit gradients) and weight contributions (times inputs).
        let within = b < LIMIT && 2.0 * b * a + SLACK < LIMIT;
        if !within {
            return false;
        }
        let wk = w.0[k];
        if !wk.is_finite() {
            return false;
        }
        // The cotangents of this layer's inputs: sums of `fan_out` products with the weights.
        b = 2.0 * fan_out as f64 * b * wk + SLACK;
        fan_out = fan_in;
    }
    let Some(f) = max_abs(kept) else {
        return false;
    };
    2.0 * b * f + SLACK < LIMIT
}

/// Whether the appearance decoder's outputs are finite for every sample (so that no colour
/// is NaN: the sigmoid of a finite number is in [0, 1]), given `grid_max`, the largest
/// magnitude of the appearance grid's parameters. A feature is at most `3 (2 v) (2 v)` (a
/// factorized level's three line-plane products of interpolated values, each within twice
/// the largest corner: weights in [0, 1] that sum to 1, plus rounding) or `2 v` (a dense
/// level), doubled for rounding; the normalised position is within [-1, 1]. Each layer's
/// outputs are then at most `2 (fan_in max|W| h + max|b|) + 1`; all below 1e36 leaves a
/// factor of 300 to `f32::MAX`, so no sum overflows and no NaN arises.
pub fn appearance_output_finite<P: ParamRead + ?Sized>(
    layout: &MlpLayout,
    decoder: &P,
    grid_max: f64,
) -> bool {
    if !grid_max.is_finite() {
        return false;
    }
    let v = 2.0 * grid_max;
    let mut h = (2.0 * (3.0 * v * v + v)).max(2.0);
    let (n_in, hidden, layers, n_out) = layout.dims();
    for k in 0..=layers {
        let fan_in = if k == 0 { n_in } else { hidden };
        let fan_out = if k == layers { n_out } else { hidden };
        let w = group_max(decoder, layout.weight_offsets[k] as usize, fan_in * fan_out);
        let b = group_max(decoder, layout.bias_offsets[k] as usize, fan_out);
        let (Some(w), Some(b)) = (w, b) else {
            return false;
        };
        h = 2.0 * (fan_in as f64 * w * h + b) + 1.0;
        let bounded = h < 1.0e36;
        if !bounded {
            return false;
        }
    }
    true
}

/// [`max_abs`] of `n` parameters from `off` (`None` past the buffer or when one is not
/// finite).
fn group_max<P: ParamRead + ?Sized>(params: &P, off: usize, n: usize) -> Option<f64> {
    match params.as_slice() {
        Some(s) => max_abs(s.get(off..off + n)?),
        None => {
            let mut m = 0u32;
            for i in 0..n {
                m = m.max(params.at(off + i).to_bits() & 0x7fff_ffff);
            }
            bits_bound(m)
        }
    }
}

#[cfg(test)]
#[allow(clippy::disallowed_methods)] // std's functions as test oracles
mod tests {
    use super::*;
    use crate::field::mlp::{self, MAX_OUT, MAX_WIDTH};
    use crate::rng::SplitMix;
    use crate::train::fixed::to_fixed;
    use crate::GradSink;

    /// Records the largest |contribution| and whether any converts to a non-zero quantum.
    struct Probe {
        largest: f64,
        nonzero: bool,
    }

    impl GradSink for Probe {
        fn add(&mut self, _i: usize, g: f32) {
            self.largest = self.largest.max(f64::from(g.abs()));
            self.nonzero |= to_fixed(g) != 0;
        }
    }

    #[test]
    fn constants_are_the_powers_of_two() {
        assert_eq!(LIMIT, 2.0f64.powi(-44));
        assert_eq!(SLACK, 2.0f64.powi(-140));
        assert_eq!(f32::from_bits(GATE_BITS), 2.0f32.powi(-40));
        assert!(below_gate(1.0e-13) && !below_gate(1.0e-12) && !below_gate(f32::NAN));
        assert!(below_gate(-1.0e-40) && below_gate(0.0));
    }

    #[test]
    fn bounds_of_special_values() {
        assert_eq!(max_abs(&[0.5, -2.0, 1.0]), Some(2.0));
        assert_eq!(max_abs(&[0.0, -0.0]), Some(0.0));
        assert_eq!(
            max_abs(&[1.0e-45, -3.0e-39]),
            Some(f64::from(f32::MIN_POSITIVE))
        );
        assert_eq!(max_abs(&[1.0, f32::NAN]), None);
        assert_eq!(max_abs(&[f32::NEG_INFINITY]), None);
        assert_eq!(sdf_top(f32::NAN), f64::INFINITY);
        assert_eq!(
            color_top([1.0e-20, 0.0, 0.0], [f32::NAN, 0.5, 0.5]),
            f64::INFINITY
        );
        let l = MlpLayout::new(3, 4, 1, 2).unwrap();
        let mut p = std::vec![0.25f32; l.param_count as usize];
        p[l.weight_offsets[1] as usize + 5] = -3.0;
        let b = LayerBounds::of(&l, &p[..]);
        assert_eq!(&b.0[..2], &[0.25, 3.0]);
        p[1] = f32::INFINITY;
        assert_eq!(LayerBounds::of(&l, &p[..]).0[0], f64::INFINITY);
    }

    /// The appearance guard: true for ordinary decoders and grids, false for non-finite or
    /// huge ones; and where it says finite, the decoder's outputs at inputs of the bound's
    /// magnitude (features of `3 (2 v)^2` either sign, positions of +-1) are finite.
    #[test]
    fn appearance_guard_means_finite_outputs() {
        let l = MlpLayout::new(35, 32, 2, 3).unwrap();
        let mut rng = SplitMix::new(8);
        let mut said_finite = 0;
        for trial in 0..300 {
            let wscale = [0.5f32, 30.0, 1.0e3, 1.0e5][trial % 4];
            let p: std::vec::Vec<f32> = (0..l.param_count)
                .map(|_| (rng.unit() - 0.5) * 2.0 * wscale)
                .collect();
            let v = [0.01f64, 1.0, 1.0e4, 1.0e8][(trial / 4) % 4];
            if !appearance_output_finite(&l, &p[..], v) {
                continue;
            }
            said_finite += 1;
            for _ in 0..20 {
                let mut x = [0.0f32; MAX_WIDTH];
                for (i, xi) in x.iter_mut().take(35).enumerate() {
                    let sign = if rng.unit() < 0.5 { -1.0 } else { 1.0 };
                    *xi = if i < 3 {
                        sign
                    } else {
                        sign * (12.0 * v * v) as f32
                    };
                }
                let mut s = mlp::MlpScratch::new();
                let mut out = [0.0f32; MAX_OUT];
                mlp::mlp_forward(&l, &p[..], &x, &mut s, &mut out);
                assert!(out[..3].iter().all(|o| o.is_finite()), "trial {trial}");
            }
        }
        assert!(
            said_finite > 30,
            "the guard passed only {said_finite} decoders"
        );
        let p = std::vec![0.1f32; l.param_count as usize];
        assert!(appearance_output_finite(&l, &p[..], 0.05));
        assert!(!appearance_output_finite(&l, &p[..], f64::INFINITY));
        assert!(!appearance_output_finite(&l, &p[..], 1.0e20));
        let mut q = p.clone();
        q[7] = f32::NAN;
        assert!(!appearance_output_finite(&l, &q[..], 0.05));
    }

    /// Over random decoders, activations and cotangents spanning the scale where the check
    /// turns (including subnormal cotangents): whenever the check says negligible, the actual
    /// backward adds no non-zero quantum and stays below the limit, its input cotangents times
    /// any factor of the kept bound too; and the check does pass for cotangents far below the
    /// limit.
    #[test]
    fn negligible_branches_add_nothing() {
        let mut rng = SplitMix::new(3);
        let mut passed = 0;
        let mut failed = 0;
        for trial in 0..4000 {
            let (n_in, hidden, layers, n_out) =
                [(12, 32, 2, 1), (67, 32, 2, 3), (5, 7, 1, 2)][trial % 3];
            let l = MlpLayout::new(n_in, hidden, layers, n_out).unwrap();
            let wscale = [0.1f32, 1.0, 8.0][(trial / 3) % 3];
            let p: std::vec::Vec<f32> = (0..l.param_count)
                .map(|_| (rng.unit() - 0.5) * 2.0 * wscale)
                .collect();
            let mut x = [0.0f32; MAX_WIDTH];
            for v in x.iter_mut().take(n_in as usize) {
                *v = (rng.unit() - 0.5) * 4.0;
            }
            let mut s = mlp::MlpScratch::new();
            let mut out = [0.0f32; MAX_OUT];
            mlp::mlp_forward(&l, &p[..], &x, &mut s, &mut out);
            // Cotangents from 2^-150 to 2^-20.
            let e = -20.0 - f64::from(rng.unit()) * 130.0;
            let mut d_out = [0.0f32; MAX_OUT];
            for d in d_out.iter_mut().take(n_out as usize) {
                *d = (2.0f64.powf(e) * (rng.unit() as f64 + 0.5)) as f32;
            }
            let top = d_out.iter().map(|&d| sdf_top(d)).fold(0.0, f64::max);
            let kept: std::vec::Vec<f32> = (0..24).map(|_| (rng.unit() - 0.5) * 8.0).collect();
            let w = LayerBounds::of(&l, &p[..]);
            let ok = branch_negligible(&l, &s, &w, top, &kept);
            let mut probe = Probe {
                largest: 0.0,
                nonzero: false,
            };
            let mut d_in = [0.0f32; MAX_WIDTH];
            mlp::mlp_backward(&l, &p[..], &s, &d_out, &mut d_in, &mut probe);
            let kmax = max_abs(&kept).unwrap();
            if ok {
                passed += 1;
                assert!(!probe.nonzero && probe.largest < LIMIT, "trial {trial}");
                for &d in &d_in[..n_in as usize] {
                    let g = (d * kmax as f32).abs();
                    assert!(f64::from(g) < LIMIT && to_fixed(g) == 0, "trial {trial}");
                }
            } else {
                failed += 1;
            }
            if e < -120.0 && wscale <= 1.0 {
                assert!(ok, "trial {trial}: a cotangent of 2^{e} must pass");
            }
        }
        assert!(
            passed > 1000 && failed > 500,
            "passed {passed}, failed {failed}"
        );
    }
}
