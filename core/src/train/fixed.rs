//! Fixed-point gradient accumulation.
//!
//! Every per-sample gradient contribution is converted on its own to a signed 64-bit integer
//! with [`FRAC_BITS`] fractional bits and added into an `i64` buffer. Integer addition is
//! associative, so any order (threads, GPU atomics) gives the same bits.
//!
//! Scale: 2^40. Resolution 2^-40 ~ 9.1e-13, so a contribution of magnitude 1e-6 keeps ~1e-6
//! relative precision. Each contribution is clamped to +-[`MAX_CONTRIBUTION`] (2^22 ~ 4.2e6)
//! before conversion (Rust's `as` saturates but SPIR-V's conversion is undefined on overflow),
//! and a sum overflows only past 2^23 ~ 8.4e6, far above any realistic gradient of the
//! normalised losses. Multiplying by a power of two is exact in f32, and the conversion
//! rounds to nearest, ties to even, on both CPU and GPU (the error of a sum then behaves like a
//! random walk of at most half a quantum per contribution; truncation toward zero biased every
//! contribution by half a quantum toward zero, an error growing linearly with their number).
//!
//! The rounding is computed from the truncating conversion and the exact remainder
//! `x - trunc(x)` (see [`to_fixed`]), so it needs no rounding built-in on the GPU.
//!
//! # Examples
//!
//! ```rust
//! use himap_core::train::fixed::{from_fixed, to_fixed, INV_SCALE, MAX_CONTRIBUTION};
//!
//! // One is 2^40 quanta; the round trip of a representable value is exact.
//! assert_eq!(to_fixed(1.0), 1i64 << 40);
//! assert_eq!(from_fixed(to_fixed(-0.375)), -0.375);
//! // Sums of contributions do not depend on their order.
//! let g = [0.1f32, -0.3, 1e-5, 7.0];
//! let a: i64 = g.iter().map(|&x| to_fixed(x)).sum();
//! let b: i64 = g.iter().rev().map(|&x| to_fixed(x)).sum();
//! assert_eq!(a, b);
//! assert!((from_fixed(a) - 6.80001).abs() < 1e-5);
//! // Rounding to the nearest quantum, NaN counts as zero, huge values are clamped.
//! assert_eq!(to_fixed(INV_SCALE * 0.75), 1);
//! assert_eq!(to_fixed(f32::NAN), 0);
//! assert_eq!(from_fixed(to_fixed(1e30)), MAX_CONTRIBUTION);
//! ```

/// Fractional bits of the fixed-point format (Q23.40).
pub const FRAC_BITS: u32 = 40;
/// 2^FRAC_BITS as f32 (exact).
pub const SCALE: f32 = (1u64 << FRAC_BITS) as f32;
/// 2^-FRAC_BITS as f32 (exact).
pub const INV_SCALE: f32 = 1.0 / SCALE;
/// Largest magnitude one contribution may have; larger ones are clamped.
pub const MAX_CONTRIBUTION: f32 = (1u32 << 22) as f32;

/// Converts one gradient contribution to fixed point. NaN becomes 0 (so one bad sample cannot
/// poison a whole buffer on the GPU, where the conversion of NaN is undefined).
#[inline(always)]
#[allow(clippy::manual_clamp)] // f32::clamp differs on NaN and is not a kernel-safe primitive
pub fn to_fixed(g: f32) -> i64 {
    // `g != g` is the NaN test that compiles to plain comparisons on every target.
    #[allow(clippy::eq_op)]
    let g = if g != g { 0.0 } else { g };
    let g = if g > MAX_CONTRIBUTION {
        MAX_CONTRIBUTION
    } else if g < -MAX_CONTRIBUTION {
        -MAX_CONTRIBUTION
    } else {
        g
    };
    let x = g * SCALE; // exact: a power-of-two scale, |x| <= 2^62
    let q = x as i64; // toward zero
                      // Exact: |x| < 2^23 leaves q below 2^23 (representable), larger |x| are integers (r = 0).
    let r = x - q as f32;
    let odd = (q & 1) != 0;
    if r > 0.5 || (r == 0.5 && odd) {
        q + 1
    } else if r < -0.5 || (r == -0.5 && odd) {
        q - 1
    } else {
        q
    }
}

/// Converts an accumulated fixed-point sum back to f32 (rounded to nearest by the int-to-float
/// conversion, then scaled exactly by a power of two).
#[inline(always)]
pub fn from_fixed(s: i64) -> f32 {
    (s as f32) * INV_SCALE
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trip_is_within_resolution() {
        for &g in &[0.0f32, 1.0, -1.0, 1e-6, -3.25e-3, 12345.678, -0.5] {
            let back = from_fixed(to_fixed(g));
            assert!(
                (back - g).abs() <= INV_SCALE * 2.0 + g.abs() * 1e-7,
                "{g} -> {back}"
            );
        }
    }

    #[test]
    fn exact_values() {
        assert_eq!(to_fixed(1.0), 1i64 << 40);
        assert_eq!(to_fixed(-0.5), -(1i64 << 39));
        assert_eq!(to_fixed(f32::NAN), 0);
        assert_eq!(to_fixed(f32::INFINITY), (MAX_CONTRIBUTION as i64) << 40);
        assert_eq!(to_fixed(-1e30), -((MAX_CONTRIBUTION as i64) << 40));
        // round to nearest below the resolution, ties to even
        assert_eq!(to_fixed(INV_SCALE * 0.75), 1);
        assert_eq!(to_fixed(INV_SCALE * 0.25), 0);
        assert_eq!(to_fixed(-INV_SCALE * 0.75), -1);
        assert_eq!(to_fixed(INV_SCALE * 0.5), 0);
        assert_eq!(to_fixed(INV_SCALE * 1.5), 2);
        assert_eq!(to_fixed(INV_SCALE * 2.5), 2);
        assert_eq!(to_fixed(-INV_SCALE * 1.5), -2);
        assert_eq!(to_fixed(-INV_SCALE * 2.5), -2);
        assert_eq!(to_fixed(-INV_SCALE * 3.5), -4);
        assert_eq!(to_fixed(INV_SCALE * 1.25), 1);
    }

    /// Every f32 in [-2^23, 2^23] quanta (all exponents below the clamp, both signs, every
    /// 97th significand) against an f64 reference: round half to even of `g * 2^40`.
    #[test]
    fn rounds_to_nearest_even_like_f64() {
        let mut bits = 0u32;
        let mut n = 0u64;
        while bits < 0x4a80_0000 {
            // up to 2^22 = MAX_CONTRIBUTION
            for g in [f32::from_bits(bits), -f32::from_bits(bits)] {
                let y = g as f64 * (1u64 << FRAC_BITS) as f64;
                let want = y.round_ties_even() as i64;
                assert_eq!(to_fixed(g), want, "g = {g:e} ({:#x})", g.to_bits());
                n += 1;
            }
            bits += 97;
        }
        assert!(n > 20_000_000);
    }

    /// The mean error of many sub-quantum contributions stays near zero (truncation lost half
    /// a quantum each).
    #[test]
    fn sum_error_is_unbiased() {
        let mut rng = crate::rng::SplitMix::new(5);
        let (mut exact, mut q) = (0.0f64, 0i64);
        for _ in 0..100_000 {
            let g = rng.unit() * INV_SCALE * 7.0;
            exact += g as f64 * (1u64 << FRAC_BITS) as f64;
            q += to_fixed(g);
        }
        // A random walk of 1e5 steps of at most 1/2: a few hundred quanta; truncation ~5e4.
        assert!((q as f64 - exact).abs() < 2_000.0, "{q} vs {exact}");
    }

    #[test]
    fn sums_are_order_independent() {
        let vals: [f32; 6] = [0.1, -0.3, 1e-5, 7.0, -2.5e-4, 0.333];
        let a: i64 = vals.iter().map(|&g| to_fixed(g)).sum();
        let b: i64 = vals.iter().rev().map(|&g| to_fixed(g)).sum();
        assert_eq!(a, b);
    }
}
