//! Counter-based random numbers: a pure function of (seed, stream, index), so CPU threads and
//! GPU invocations draw identical values without sharing state.

/// `2^-24`, the step of the 24-bit uniform floats (a constant: no division in kernels).
const INV_2_24: f32 = 1.0 / 16_777_216.0;

/// PCG-style integer hash (the "PCG hash" of Jarzynski and Olano, 2020).
#[inline(always)]
pub fn hash_u32(x: u32) -> u32 {
    let state = x.wrapping_mul(747_796_405).wrapping_add(2_891_336_453);
    let word = ((state >> ((state >> 28).wrapping_add(4))) ^ state).wrapping_mul(277_803_737);
    (word >> 22) ^ word
}

/// Hash of three counters.
#[inline(always)]
pub fn hash3(seed: u32, a: u32, b: u32) -> u32 {
    hash_u32(hash_u32(hash_u32(seed) ^ a) ^ b.wrapping_mul(0x9E37_79B9))
}

/// Uniform in [0, 1), 24 random bits (every value exactly representable).
#[inline(always)]
pub fn uniform(seed: u32, a: u32, b: u32) -> f32 {
    (hash3(seed, a, b) >> 8) as f32 * INV_2_24
}

/// A standard normal draw by Box-Muller (host-side initialisation; uses vendored math).
pub fn normal(seed: u32, a: u32, b: u32) -> f32 {
    let u1 = uniform(seed, a, b.wrapping_mul(2));
    let u2 = uniform(seed, a, b.wrapping_mul(2).wrapping_add(1));
    // 1 - u1 is in (0, 1], so the log is finite.
    let r = crate::math::sqrt(-2.0 * crate::math::log(1.0 - u1));
    r * crate::math::cos(2.0 * core::f32::consts::PI * u2)
}

/// A small sequential generator for host-side sampling decisions (pixels, keyframes).
///
/// # Examples
///
/// ```rust
/// use himap_core::rng::SplitMix;
///
/// let mut a = SplitMix::new(42);
/// let i = a.below(10);
/// assert!(i < 10);
/// let x = a.unit();
/// assert!((0.0..1.0).contains(&x));
/// // The same seed gives the same sequence, and the state resumes it.
/// let mut b = SplitMix::new(42);
/// assert_eq!((b.below(10), b.unit()), (i, x));
/// let mut c = SplitMix::new(a.state());
/// assert_eq!(c.next_u64(), a.next_u64());
/// ```
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct SplitMix {
    state: u64,
}

impl SplitMix {
    /// A generator starting from `seed` (any value).
    pub const fn new(seed: u64) -> Self {
        Self { state: seed }
    }

    /// The generator's state: `SplitMix::new(g.state())` continues exactly where `g` is.
    pub const fn state(&self) -> u64 {
        self.state
    }

    /// The next 64 random bits (SplitMix64).
    pub fn next_u64(&mut self) -> u64 {
        self.state = self.state.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.state;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    /// Uniform integer in [0, n) (n > 0; returns 0 for n == 0).
    pub fn below(&mut self, n: u32) -> u32 {
        if n == 0 {
            return 0;
        }
        (((self.next_u64() >> 32) * n as u64) >> 32) as u32
    }

    /// Uniform in [0, 1).
    pub fn unit(&mut self) -> f32 {
        (self.next_u64() >> 40) as f32 * INV_2_24
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn uniform_is_in_range_and_deterministic() {
        let mut sum = 0.0f64;
        for i in 0..10_000u32 {
            let u = uniform(7, i, 3);
            assert!((0.0..1.0).contains(&u));
            assert_eq!(u.to_bits(), uniform(7, i, 3).to_bits());
            sum += u as f64;
        }
        let mean = sum / 10_000.0;
        assert!((mean - 0.5).abs() < 0.01, "mean {mean}");
        assert_ne!(uniform(7, 1, 3), uniform(8, 1, 3));
    }

    #[test]
    fn normal_has_unit_variance() {
        let n = 20_000u32;
        let (mut s, mut s2) = (0.0f64, 0.0f64);
        for i in 0..n {
            let x = normal(1, 0, i) as f64;
            s += x;
            s2 += x * x;
        }
        let mean = s / n as f64;
        let var = s2 / n as f64 - mean * mean;
        assert!(mean.abs() < 0.03, "mean {mean}");
        assert!((var - 1.0).abs() < 0.05, "var {var}");
    }

    #[test]
    fn splitmix_below_is_bounded() {
        let mut r = SplitMix::new(5);
        for _ in 0..1000 {
            assert!(r.below(17) < 17);
        }
        assert_eq!(r.below(0), 0);
    }
}
