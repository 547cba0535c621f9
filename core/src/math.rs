//! Vendored `f32` math: the only transcendental functions kernels may call.
//!
//! Why this module exists: rust-gpu replaces every call into the crate named `libm` (and every
//! `glam`/`f32` method that goes through it) with a `GLSL.std.450` driver built-in (`Exp`, `Log`,
//! `Sqrt`, `Tanh`, ...), which Vulkan only requires to be accurate to a few ULP; on lavapipe 40% of
//! `exp` results differed from the CPU and subnormal results were flushed. Plain `f32`/integer
//! arithmetic, on the other hand, compiles op by op and gives identical bits on CPU and GPU (see
//! `shared/reference/gpu-toolchain-notes.md`). So every function here is written in plain
//! arithmetic and bit manipulation only:
//! - no call into `libm`, no `core::intrinsics`, no `f32` methods that lower to libm calls;
//! - no `mul_add` (the GPU lowers it to a separately rounded multiply and add);
//! - no panicking paths (no indexing that can fail, no `unwrap`, no division by zero of integers);
//! - special results (NaN, infinities) are returned as explicit values instead of being produced
//!   by arithmetic such as `0 / x` or `x * x + x` as libm does: lavapipe (Mesa 22.3) folds
//!   `0 / x` to 0 even for NaN `x`, with or without the `SignedZeroInfNanPreserve` mode.
//!
//! Checked on lavapipe (throwaway rust-gpu + ash harness, 1,048,576 inputs: specials, a strided
//! sweep over all bit patterns, dense ranges; 71,575 subnormal results): `exp`, `log`, `sqrt`,
//! `tanh`, `floor`, `sigmoid`, `softplus`, `pow_int`, `clamp`, and `mlp_forward`/`mlp_backward`
//! and `adam_update` built on them, gave bit-identical results to the CPU.
//!
//! [`exp`], [`log`], [`sqrt`], [`tanh`] and [`floor`] give exactly the same bits as the `libm`
//! crate's `expf`, `logf`, `sqrtf`, `tanhf` and `floorf` (tested bit for bit over ~2 million
//! inputs; NaN payloads may differ). [`sin`] and [`cos`] follow libm's `sinf`/`cosf`, which
//! evaluate their polynomial kernels and the argument reduction in `f64`: they are **host-only**
//! (parameter initialisation via [`crate::rng::normal`]) and must not be called from shader code,
//! where `f64` would need the `Float64` capability and is not known to be bit-exact.
//!
//! # Attribution and licence of the vendored code
//!
//! `exp`, `log`, `tanh` (with `expm1`), `floor`, `sin`, `cos` (with `k_sinf`, `k_cosf`,
//! `rem_pio2f`, `rem_pio2_large`) and the `scalbn` helpers are ports by hand of the pure-Rust
//! sources of the `libm` crate 0.2.16 (<https://github.com/rust-lang/libm>, now part of
//! rust-lang/compiler-builtins), which is available under the MIT licence:
//!
//! > Permission is hereby granted, free of charge, to any person obtaining a copy of this
//! > software and associated documentation files (the "Software"), to deal in the Software
//! > without restriction, including without limitation the rights to use, copy, modify, merge,
//! > publish, distribute, sublicense, and/or sell copies of the Software, and to permit persons
//! > to whom the Software is furnished to do so, subject to the following conditions:
//! > The above copyright notice and this permission notice shall be included in all copies or
//! > substantial portions of the Software.
//! > THE SOFTWARE IS PROVIDED "AS IS", WITHOUT WARRANTY OF ANY KIND, EXPRESS OR IMPLIED,
//! > INCLUDING BUT NOT LIMITED TO THE WARRANTIES OF MERCHANTABILITY, FITNESS FOR A PARTICULAR
//! > PURPOSE AND NONINFRINGEMENT. IN NO EVENT SHALL THE AUTHORS OR COPYRIGHT HOLDERS BE LIABLE
//! > FOR ANY CLAIM, DAMAGES OR OTHER LIABILITY, WHETHER IN AN ACTION OF CONTRACT, TORT OR
//! > OTHERWISE, ARISING FROM, OUT OF OR IN CONNECTION WITH THE SOFTWARE OR THE USE OR OTHER
//! > DEALINGS IN THE SOFTWARE.
//!
//! The libm crate is itself a port of musl libc's math library (Copyright © 2005-2020 Rich
//! Felker, et al., MIT licence), whose float routines come from FreeBSD's msun:
//! Copyright (C) 1993 by Sun Microsystems, Inc. All rights reserved. Developed at SunPro, a Sun
//! Microsystems, Inc. business. Permission to use, copy, modify, and distribute this software
//! is freely granted, provided that this notice is preserved. Conversion to float by Ian Lance
//! Taylor, Cygnus Support (ian@cygnus.com); debugged and optimized by Bruce D. Evans.
//!
//! `sqrt` is the bit-by-bit integer algorithm of FreeBSD's `e_sqrtf.c` (same Sun notice as
//! above), which is what older releases of the libm crate used for `sqrtf`; libm 0.2.16 uses
//! the SSE instruction or a Goldschmidt iteration on 64-bit integers instead. All three are
//! correctly rounded, so the bits agree; the bit-by-bit version needs only 32-bit integers.

// ------------------------------------------------------------------------------------------------
// Simple helpers
// ------------------------------------------------------------------------------------------------

/// Clamps `x` to `[lo, hi]` by plain comparisons (`x < lo` gives `lo`, `x > hi` gives `hi`,
/// otherwise `x`; a NaN `x` is returned unchanged).
#[inline(always)]
pub fn clamp(x: f32, lo: f32, hi: f32) -> f32 {
    if x < lo {
        lo
    } else if x > hi {
        hi
    } else {
        x
    }
}

/// Absolute value by clearing the sign bit (exact for every input, NaN included).
#[inline(always)]
pub fn abs(x: f32) -> f32 {
    f32::from_bits(x.to_bits() & 0x7fff_ffff)
}

/// The smaller of `a` and `b` by one comparison: `if a < b { a } else { b }` (so a NaN in either
/// argument returns `b`; `min(-0.0, 0.0)` is `0.0`).
#[inline(always)]
pub fn min(a: f32, b: f32) -> f32 {
    if a < b {
        a
    } else {
        b
    }
}

/// The larger of `a` and `b` by one comparison: `if a > b { a } else { b }` (so a NaN in either
/// argument returns `b`; `max(-0.0, 0.0)` is `0.0`).
#[inline(always)]
pub fn max(a: f32, b: f32) -> f32 {
    if a > b {
        a
    } else {
        b
    }
}

/// `a / b` in kernels: IEEE division rounded to nearest even, the same bits on every device.
/// On the CPU it is the processor's division (correctly rounded); in shader code
/// (`target_arch = "spirv"`) it is [`div_rn`], because Vulkan allows `OpFDiv` an error of
/// 2.5 ULP and NVIDIA's driver uses it (an H200 gave 1-ULP differences in every conformance
/// case that divides). Every float division of the core goes through here.
#[inline(always)]
pub fn div(a: f32, b: f32) -> f32 {
    #[cfg(target_arch = "spirv")]
    {
        div_rn(a, b)
    }
    #[cfg(not(target_arch = "spirv"))]
    {
        a / b
    }
}

/// Correctly rounded `a / b` (round to nearest even, subnormals exact) from an approximate
/// hardware quotient corrected with exact 32-bit integer arithmetic:
/// 1. the significands `ma`, `mb` (24 bits) are divided as floats in `[1, 2)`, where any
///    device's `OpFDiv` is within a few ULP (Vulkan allows 2.5) and nothing over- or
///    underflows;
/// 2. that estimate of `Q = floor(ma 2^s / mb)` (25 bits, one below the last significand bit)
///    is corrected with the exact remainder `R = ma 2^s - Q mb`, computed in wrapping `u32`
///    arithmetic: the true `R` is small (a few `mb`), so its low 32 bits are it;
/// 3. `Q` and `R != 0` (the sticky bit) are rounded once, to a normal or subnormal result.
///
/// Only 32-bit integer and float operations and no loops (an earlier form divided `u64`s
/// and stalled an NVIDIA H200). The correction accepts a hardware quotient up to about 30
/// ULP off (the remainder must fit an `i32`; tested with estimates pushed up to 16 ULP
/// away). Special values follow x86's SSE
/// division, which the CPU reference runs on: a NaN `a` comes back quieted, else a NaN `b`
/// quieted; `0 / 0` and `inf / inf` give the default NaN `0xffc0_0000`; `x / 0` gives a
/// signed infinity, `x / inf` a signed zero. Tested bit for bit against the processor's
/// division (specials, subnormals, overflow, random bit patterns).
///
/// Inlined at every call (the module grows from 1.5 to 3.6 MB): NVIDIA's driver (580.159,
/// H200) hangs at run time in any kernel that calls a function rust-gpu left as a SPIR-V
/// function (`#[inline(never)]`), even the one-line `divide_cs`; inlined, the conformance
/// suite matches the CPU bit for bit there.
#[inline(always)]
pub fn div_rn(a: f32, b: f32) -> f32 {
    div_corrected(a, b, 0)
}

/// [`div_rn`] with the hardware estimate pushed `nudge` ULP away (tests of the correction).
#[inline(always)]
fn div_corrected(a: f32, b: f32, nudge: i32) -> f32 {
    const INF: u32 = 0x7f80_0000;
    const QUIET: u32 = 0x0040_0000;
    const DEFAULT_NAN: u32 = 0xffc0_0000;
    let (ua, ub) = (a.to_bits(), b.to_bits());
    let sign = (ua ^ ub) & 0x8000_0000;
    let (xa, xb) = (ua & 0x7fff_ffff, ub & 0x7fff_ffff);
    if xa > INF {
        return f32::from_bits(ua | QUIET);
    }
    if xb > INF {
        return f32::from_bits(ub | QUIET);
    }
    if xa == INF {
        return f32::from_bits(if xb == INF { DEFAULT_NAN } else { sign | INF });
    }
    if xb == INF {
        return f32::from_bits(sign);
    }
    if xb == 0 {
        return f32::from_bits(if xa == 0 { DEFAULT_NAN } else { sign | INF });
    }
    if xa == 0 {
        return f32::from_bits(sign);
    }
    let ((ea, ma), (eb, mb)) = (unpack_finite(xa), unpack_finite(xb));
    // a / b = (ma / mb) 2^(ea - eb) with ma / mb in (1/2, 2). Q = floor(ma 2^s / mb) lies in
    // [2^24, 2^25) with s = 24 when ma >= mb, s = 25 when ma < mb.
    let s: i32 = if ma < mb { 25 } else { 24 };
    let fa = f32::from_bits(0x3f80_0000 | (ma & 0x007f_ffff));
    let fb = f32::from_bits(0x3f80_0000 | (mb & 0x007f_ffff));
    let est = ((fa / fb).to_bits() as i32).wrapping_add(nudge) as u32;
    // est = mq 2^(eq - 150), so est 2^s = mq 2^(s + eq - 150), about 2^24..2^25
    let mq = (est & 0x007f_ffff) | 0x0080_0000;
    let sh = s + ((est >> 23) & 0xff) as i32 - 150;
    let mut q = if sh >= 0 {
        mq << (sh & 7)
    } else {
        mq >> ((-sh) & 7)
    };
    let mbi = mb as i32;
    let mut r = (ma << s as u32).wrapping_sub(q.wrapping_mul(mb)) as i32;
    // Coarse step: k = trunc(r / mb) from floats (|r| < 2^31, so k is within 1 of the
    // exact quotient), then at most two unit steps each way leave 0 <= r < mb. No loops.
    let k = ((r as f32) / (mb as f32)) as i32;
    q = q.wrapping_add(k as u32);
    r = r.wrapping_sub(k.wrapping_mul(mbi));
    if r < 0 {
        q = q.wrapping_sub(1);
        r += mbi;
    }
    if r < 0 {
        q = q.wrapping_sub(1);
        r += mbi;
    }
    if r >= mbi {
        q = q.wrapping_add(1);
        r -= mbi;
    }
    if r >= mbi {
        q = q.wrapping_add(1);
        r -= mbi;
    }
    let sticky = r != 0;
    let mut e = ea - eb + 126 + (25 - s);
    let mut shift = 1u32;
    if e >= 255 {
        return f32::from_bits(sign | INF);
    }
    if e < 1 {
        // subnormal result: fewer significand bits (past 26 everything rounds to zero)
        let extra = (1 - e) as u32;
        shift = if extra > 25 { 26 } else { 1 + extra };
        e = 1;
    }
    let mant = q >> shift;
    let rest = q & ((1u32 << shift) - 1);
    let half = 1u32 << (shift - 1);
    let up = rest > half || (rest == half && (sticky || mant & 1 == 1));
    // the leading bit of `mant` (or the carry of rounding) adds 1 to the exponent field
    let bits = (((e - 1) as u32) << 23) + mant + up as u32;
    f32::from_bits(sign | if bits >= INF { INF } else { bits })
}

/// The biased exponent and 24-bit significand of a finite nonzero `|x|`'s bits, with the
/// leading bit at 23 (a subnormal is normalised: its exponent goes below 1).
#[inline(always)]
fn unpack_finite(bits: u32) -> (i32, u32) {
    let (mut e, mut m) = ((bits >> 23) as i32, bits & 0x007f_ffff);
    if e == 0 {
        // normalise a nonzero subnormal (m < 2^23) by a binary search for its leading bit
        e = 1;
        if m < 1 << 8 {
            m <<= 16;
            e -= 16;
        }
        if m < 1 << 16 {
            m <<= 8;
            e -= 8;
        }
        if m < 1 << 20 {
            m <<= 4;
            e -= 4;
        }
        if m < 1 << 22 {
            m <<= 2;
            e -= 2;
        }
        if m < 1 << 23 {
            m <<= 1;
            e -= 1;
        }
    } else {
        m |= 0x0080_0000;
    }
    (e, m)
}

/// `x^n` by repeated squaring (binary exponentiation, least significant bit first).
/// `pow_int(x, 0)` is `1.0` for every `x`. The multiplication order is fixed, so the result is
/// reproducible bit for bit; it is not always correctly rounded (each multiply rounds).
#[inline]
pub fn pow_int(x: f32, n: u32) -> f32 {
    let mut result = 1.0f32;
    let mut base = x;
    let mut n = n;
    while n > 0 {
        if n & 1 == 1 {
            result *= base;
        }
        n >>= 1;
        if n > 0 {
            base *= base;
        }
    }
    result
}

/// The logistic function `1 / (1 + exp(-x))`, evaluated without overflow for any `x`:
/// `1 / (1 + exp(-x))` for `x >= 0`, and `exp(x) / (1 + exp(x))` for `x < 0` (so very negative
/// inputs give the correct tiny, possibly subnormal, value instead of 0). NaN gives NaN.
#[inline]
pub fn sigmoid(x: f32) -> f32 {
    if x >= 0.0 {
        div(1.0, 1.0 + exp(-x))
    } else {
        let e = exp(x);
        div(e, 1.0 + e)
    }
}

/// `softplus(x) = log(1 + exp(x))`, stable for any `x`: evaluated as
/// `max(x, 0) + log1p(exp(-|x|))`, where `log1p(e)` uses Goldberg's trick
/// `log(1 + e) * e / ((1 + e) - 1)` (and `e` itself when `1 + e` rounds to 1). Large positive `x`
/// give `x`, very negative `x` give `exp(x)`. NaN gives NaN, `+inf` gives `+inf`, `-inf` gives 0.
#[inline]
pub fn softplus(x: f32) -> f32 {
    let e = exp(-abs(x));
    let u = 1.0 + e;
    let l = if u == 1.0 {
        e
    } else {
        log(u) * div(e, u - 1.0)
    };
    max(x, 0.0) + l
}

// ------------------------------------------------------------------------------------------------
// scalbn (port of libm's generic `scalbn`, specialised to f32 and f64)
// ------------------------------------------------------------------------------------------------

/// `x * 2^n` for f32, exact unless the result over/underflows (port of libm's `scalbnf`).
#[inline]
fn scalbnf(mut x: f32, mut n: i32) -> f32 {
    // 2^127, 2^-126 * 2^24 = 2^-102 (the prescale that cannot make a normal x subnormal).
    let x1p127 = f32::from_bits(0x7f00_0000);
    let x1p_102 = f32::from_bits(0x0c80_0000);
    if n > 127 {
        x *= x1p127;
        n -= 127;
        if n > 127 {
            x *= x1p127;
            n -= 127;
            if n > 127 {
                n = 127;
            }
        }
    } else if n < -126 {
        x *= x1p_102;
        n += 102;
        if n < -126 {
            x *= x1p_102;
            n += 102;
            if n < -126 {
                n = -126;
            }
        }
    }
    x * f32::from_bits(((0x7f + n) as u32) << 23)
}

/// `x * 2^n` for f64 (port of libm's `scalbn`; used only by the host-only `rem_pio2_large`).
#[inline]
fn scalbn64(mut x: f64, mut n: i32) -> f64 {
    let x1p1023 = f64::from_bits(0x7fe0_0000_0000_0000);
    // 2^-1022 * 2^53 = 2^-969
    let x1p_969 = f64::from_bits(0x0360_0000_0000_0000);
    if n > 1023 {
        x *= x1p1023;
        n -= 1023;
        if n > 1023 {
            x *= x1p1023;
            n -= 1023;
            if n > 1023 {
                n = 1023;
            }
        }
    } else if n < -1022 {
        x *= x1p_969;
        n += 969;
        if n < -1022 {
            x *= x1p_969;
            n += 969;
            if n < -1022 {
                n = -1022;
            }
        }
    }
    x * f64::from_bits(((0x3ff + n) as u64) << 52)
}

// ------------------------------------------------------------------------------------------------
// floor
// ------------------------------------------------------------------------------------------------

/// Largest integer value not greater than `x` (port of libm's generic `floorf`, musl's
/// algorithm: clear the fraction bits, rounding negative values down). Exact; `-0.0` stays
/// `-0.0`, `-0.5` gives `-1.0`, infinities and NaN are returned unchanged.
#[inline]
pub fn floor(x: f32) -> f32 {
    let mut ix = x.to_bits();
    let e = ((ix >> 23) & 0xff) as i32 - 127;
    if e >= 23 {
        // No fractional part (also inf and NaN).
        return x;
    }
    if e >= 0 {
        // |x| >= 1
        let m = 0x007f_ffffu32 >> e;
        if ix & m == 0 {
            return x;
        }
        if ix >> 31 != 0 {
            ix += m;
        }
        ix &= !m;
        f32::from_bits(ix)
    } else if ix >> 31 == 0 {
        // 0 <= x < 1
        0.0
    } else if ix << 1 != 0 {
        // -1 < x < 0
        -1.0
    } else {
        // -0.0
        x
    }
}

/// `f64` floor for the host-only argument reduction (port of libm's generic `floor`).
#[inline]
fn floor64(x: f64) -> f64 {
    let mut ix = x.to_bits();
    let e = ((ix >> 52) & 0x7ff) as i32 - 1023;
    if e >= 52 {
        return x;
    }
    if e >= 0 {
        let m = 0x000f_ffff_ffff_ffffu64 >> e;
        if ix & m == 0 {
            return x;
        }
        if ix >> 63 != 0 {
            ix += m;
        }
        ix &= !m;
        f64::from_bits(ix)
    } else if ix >> 63 == 0 {
        0.0
    } else if ix << 1 != 0 {
        -1.0
    } else {
        x
    }
}

// ------------------------------------------------------------------------------------------------
// sqrt (FreeBSD e_sqrtf.c, bit by bit)
// ------------------------------------------------------------------------------------------------

/// Correctly rounded square root (round to nearest even), computed bit by bit with 32-bit
/// integers (FreeBSD `e_sqrtf.c`). `sqrt(-0.0)` is `-0.0`, `sqrt(+inf)` is `+inf`, negative
/// inputs, `-inf` and NaN give NaN. Subnormal inputs are handled exactly.
#[inline]
pub fn sqrt(x: f32) -> f32 {
    let mut ix = x.to_bits() as i32;

    // Inf and NaN: sqrt(NaN) = NaN, sqrt(+inf) = +inf, sqrt(-inf) = NaN. (libm computes
    // `x * x + x`; explicit values keep GPU compilers that assume no NaN/inf out of it.)
    if (ix as u32) & 0x7f80_0000 == 0x7f80_0000 {
        return if ix as u32 == 0x7f80_0000 {
            x
        } else {
            f32::NAN
        };
    }
    // Zero and negative numbers.
    if ix <= 0 {
        if ix & 0x7fff_ffff == 0 {
            return x; // sqrt(+-0) = +-0
        }
        return f32::NAN; // sqrt(negative) = NaN (libm: (x - x) / (x - x))
    }
    // Normalise x.
    let mut m = ix >> 23;
    if m == 0 {
        // Subnormal: shift the significand up until the implicit bit is set.
        let mut i = 0i32;
        while ix & 0x0080_0000 == 0 {
            ix <<= 1;
            i += 1;
        }
        m -= i - 1;
    }
    m -= 127; // unbiased exponent
    ix = (ix & 0x007f_ffff) | 0x0080_0000;
    if m & 1 != 0 {
        // Odd exponent: double x to make it even.
        ix += ix;
    }
    m >>= 1; // m = floor(m / 2)

    // Generate sqrt(x) bit by bit.
    ix += ix;
    let mut q = 0i32; // q = sqrt(x)
    let mut s = 0i32;
    let mut r = 0x0100_0000i32; // moving bit from right to left
    while r != 0 {
        let t = s + r;
        if t <= ix {
            s = t + r;
            ix -= t;
            q += r;
        }
        ix += ix;
        r >>= 1;
    }
    // A non-zero remainder means the result is inexact: in round-to-nearest mode the original
    // code's floating-point probe (1 - tiny >= 1, 1 + tiny == 1) resolves to rounding half to
    // even on the extra bit q carries, which is what this does.
    if ix != 0 {
        q += q & 1;
    }
    let mut out = (q >> 1) + 0x3f00_0000;
    out += m << 23;
    f32::from_bits(out as u32)
}

// ------------------------------------------------------------------------------------------------
// exp, expm1, tanh
// ------------------------------------------------------------------------------------------------

const EXP_LN2_HI: f32 = f32::from_bits(0x3f31_7200); // 0x3f317200
const EXP_LN2_LO: f32 = f32::from_bits(0x35bf_be8e); // 0x35bfbe8e
const INV_LN2: f32 = f32::from_bits(0x3fb8_aa3b); // 0x3fb8aa3b
                                                  // Domain [-0.34568, 0.34568], |x*(exp(x)+1)/(exp(x)-1) - p(x)| < 2**-27.74
const EXP_P1: f32 = f32::from_bits(0x3e2a_aa8f); // 0xaaaa8f.0p-26
const EXP_P2: f32 = f32::from_bits(0xbb35_5215); // -0xb55215.0p-32

/// `e^x` (port of libm's `expf`, FreeBSD `e_expf.c`). Bit-identical to `libm::expf`: about
/// 1 ULP accurate, overflows to `+inf` for `x > 88.72284`, gives subnormal results down to
/// `x ~ -103.97` and `0` below; NaN gives NaN.
#[inline]
pub fn exp(x: f32) -> f32 {
    let mut x = x;
    let x1p127 = f32::from_bits(0x7f00_0000); // 2^127
    let mut hx = x.to_bits();
    let sign = (hx >> 31) as i32;
    let signb = sign != 0;
    hx &= 0x7fff_ffff; // |x|

    // Special cases.
    if hx >= 0x42ae_ac50 {
        // |x| >= 87.33655 or NaN
        if hx > 0x7f80_0000 {
            return x; // NaN
        }
        if hx >= 0x42b1_7218 && !signb {
            // x >= 88.722839: overflow
            x *= x1p127;
            return x;
        }
        if signb && hx >= 0x42cf_f1b5 {
            // x <= -103.972084: underflow to 0
            return 0.0;
        }
    }

    // Argument reduction: x = k ln2 + r, |r| <= 0.5 ln2.
    let k: i32;
    let hi: f32;
    let lo: f32;
    if hx > 0x3eb1_7218 {
        // |x| > 0.5 ln2
        if hx > 0x3f85_1592 {
            // |x| > 1.5 ln2
            let half = if signb { -0.5f32 } else { 0.5f32 };
            k = (INV_LN2 * x + half) as i32;
        } else {
            k = 1 - sign - sign;
        }
        let kf = k as f32;
        hi = x - kf * EXP_LN2_HI; // k * ln2_hi is exact here
        lo = kf * EXP_LN2_LO;
        x = hi - lo;
    } else if hx > 0x3900_0000 {
        // |x| > 2^-14
        k = 0;
        hi = x;
        lo = 0.0;
    } else {
        return 1.0 + x;
    }

    // x is now in the primary range.
    let xx = x * x;
    let c = x - xx * (EXP_P1 + xx * EXP_P2);
    let y = 1.0 + (div(x * c, 2.0 - c) - lo + hi);
    if k == 0 {
        y
    } else {
        scalbnf(y, k)
    }
}

const EXPM1_LN2_HI: f32 = f32::from_bits(0x3f31_7180); // 0x3f317180
const EXPM1_LN2_LO: f32 = f32::from_bits(0x3717_f7d1); // 0x3717f7d1
                                                       // Domain [-0.34568, 0.34568], scaled coefficients (see FreeBSD s_expm1.c).
const EXPM1_Q1: f32 = f32::from_bits(0xbd08_8868); // -0x888868.0p-28
const EXPM1_Q2: f32 = f32::from_bits(0x3acf_3010); // 0xcf3010.0p-33

/// `e^x - 1`, accurate near 0 (port of libm's `expm1f`, FreeBSD `s_expm1f.c`); used by [`tanh`].
#[inline]
fn expm1(x: f32) -> f32 {
    let mut x = x;
    let x1p127 = f32::from_bits(0x7f00_0000); // 2^127
    let mut hx = x.to_bits();
    let sign = (hx >> 31) != 0;
    hx &= 0x7fff_ffff;

    // Huge and non-finite arguments.
    if hx >= 0x4195_b844 {
        // |x| >= 27 ln2
        if hx > 0x7f80_0000 {
            return x; // NaN
        }
        if sign {
            return -1.0;
        }
        if hx > 0x42b1_7217 {
            // x > log(FLT_MAX)
            x *= x1p127;
            return x;
        }
    }

    let k: i32;
    let mut c = 0.0f32;
    // Argument reduction.
    if hx > 0x3eb1_7218 {
        // |x| > 0.5 ln2
        let hi: f32;
        let lo: f32;
        if hx < 0x3f85_1592 {
            // and |x| < 1.5 ln2
            if !sign {
                hi = x - EXPM1_LN2_HI;
                lo = EXPM1_LN2_LO;
                k = 1;
            } else {
                hi = x + EXPM1_LN2_HI;
                lo = -EXPM1_LN2_LO;
                k = -1;
            }
        } else {
            k = (INV_LN2 * x + if sign { -0.5 } else { 0.5 }) as i32;
            let t = k as f32;
            hi = x - t * EXPM1_LN2_HI; // t * ln2_hi is exact here
            lo = t * EXPM1_LN2_LO;
        }
        x = hi - lo;
        c = (hi - x) - lo;
    } else if hx < 0x3300_0000 {
        // |x| < 2^-25: expm1(x) = x
        return x;
    } else {
        k = 0;
    }

    // x is now in the primary range.
    let hfx = 0.5 * x;
    let hxs = x * hfx;
    let r1 = 1.0 + hxs * (EXPM1_Q1 + hxs * EXPM1_Q2);
    let t = 3.0 - r1 * hfx;
    let mut e = hxs * div(r1 - t, 6.0 - x * t);
    if k == 0 {
        // c is 0
        return x - (x * e - hxs);
    }
    e = x * (e - c) - c;
    e -= hxs;
    // exp(x) ~ 2^k (x_reduced - e + 1)
    if k == -1 {
        return 0.5 * (x - e) - 0.5;
    }
    if k == 1 {
        if x < -0.25 {
            return -2.0 * (e - (x + 0.5));
        }
        return 1.0 + 2.0 * (x - e);
    }
    // Plain comparisons rather than `RangeInclusive::contains` (shader-friendly).
    #[allow(clippy::manual_range_contains)]
    let outside = k < 0 || k > 56;
    if outside {
        // Suffices to return exp(x) - 1.
        let mut y = x - e + 1.0;
        if k == 128 {
            y = y * 2.0 * x1p127;
        } else {
            let twopk = f32::from_bits(((0x7f + k) as u32) << 23); // 2^k
            y *= twopk;
        }
        return y - 1.0;
    }
    let twopk = f32::from_bits(((0x7f + k) as u32) << 23); // 2^k
    let uf = f32::from_bits(((0x7f - k) as u32) << 23); // 2^-k
    if k < 23 {
        (x - e + (1.0 - uf)) * twopk
    } else {
        (x - (e + uf) + 1.0) * twopk
    }
}

/// Hyperbolic tangent (port of libm's `tanhf`). Bit-identical to `libm::tanhf`; exactly
/// `+-1` for `|x| > 10`, `x` itself for subnormal `x`, NaN gives NaN.
#[inline]
pub fn tanh(x: f32) -> f32 {
    let mut ix = x.to_bits();
    let sign = (ix >> 31) != 0;
    ix &= 0x7fff_ffff;
    let x = f32::from_bits(ix); // |x|
    let w = ix;

    if w > 0x7f80_0000 {
        // NaN. libm lets `1 + 0 / x` below propagate it, but GPU compilers may fold `0 / x`
        // to 0 (lavapipe returns 1.0 for NaN that way), so handle it explicitly.
        return x;
    }
    let tt = if w > 0x3f0c_9f54 {
        // |x| > log(3)/2 ~= 0.5493
        if w > 0x4120_0000 {
            // |x| > 10 (libm: `1 + 0 / x`, which only raises inexact; the value is 1)
            1.0
        } else {
            let t = expm1(2.0 * x);
            1.0 - div(2.0, t + 2.0)
        }
    } else if w > 0x3e82_c578 {
        // |x| > log(5/3)/2 ~= 0.2554
        let t = expm1(2.0 * x);
        div(t, t + 2.0)
    } else if w >= 0x0080_0000 {
        // |x| >= 2^-126
        let t = expm1(-2.0 * x);
        div(-t, t + 2.0)
    } else {
        // |x| is subnormal
        x
    };
    if sign {
        -tt
    } else {
        tt
    }
}

// ------------------------------------------------------------------------------------------------
// log
// ------------------------------------------------------------------------------------------------

const LOG_LN2_HI: f32 = f32::from_bits(0x3f31_7180); // 0x3f317180
const LOG_LN2_LO: f32 = f32::from_bits(0x3717_f7d1); // 0x3717f7d1
                                                     // |(log(1+s)-log(1-s))/s - Lg(s)| < 2**-34.24 (~[-4.95e-11, 4.97e-11]).
const LG1: f32 = f32::from_bits(0x3f2a_aaaa); // 0xaaaaaa.0p-24
const LG2: f32 = f32::from_bits(0x3ecc_ce13); // 0xccce13.0p-25
const LG3: f32 = f32::from_bits(0x3e91_e9ee); // 0x91e9ee.0p-25
const LG4: f32 = f32::from_bits(0x3e78_9e26); // 0xf89e26.0p-26

/// Natural logarithm (port of libm's `logf`, FreeBSD `e_logf.c`). Bit-identical to
/// `libm::logf`: `log(+-0) = -inf`, `log(1) = +0`, `log(+inf) = +inf`, negative inputs and NaN
/// give NaN; subnormal inputs are exact-scaled first.
#[inline]
pub fn log(x: f32) -> f32 {
    let mut x = x;
    let x1p25 = f32::from_bits(0x4c00_0000); // 2^25
    let mut ix = x.to_bits();
    let mut k = 0i32;

    if ix < 0x0080_0000 || (ix >> 31) != 0 {
        // x < 2^-126
        if ix << 1 == 0 {
            return f32::NEG_INFINITY; // log(+-0) = -inf (libm: -1 / (x * x))
        }
        if (ix >> 31) != 0 {
            return f32::NAN; // log(negative) = NaN (libm: (x - x) / 0)
        }
        // Subnormal: scale up x.
        k -= 25;
        x *= x1p25;
        ix = x.to_bits();
    } else if ix >= 0x7f80_0000 {
        return x;
    } else if ix == 0x3f80_0000 {
        return 0.0;
    }

    // Reduce x into [sqrt(2)/2, sqrt(2)].
    ix += 0x3f80_0000 - 0x3f35_04f3;
    k += ((ix >> 23) as i32) - 0x7f;
    ix = (ix & 0x007f_ffff) + 0x3f35_04f3;
    x = f32::from_bits(ix);

    let f = x - 1.0;
    let s = div(f, 2.0 + f);
    let z = s * s;
    let w = z * z;
    let t1 = w * (LG2 + w * LG4);
    let t2 = z * (LG1 + w * LG3);
    let r = t2 + t1;
    let hfsq = 0.5 * f * f;
    let dk = k as f32;
    s * (hfsq + r) + dk * LOG_LN2_LO - hfsq + f + dk * LOG_LN2_HI
}

// ------------------------------------------------------------------------------------------------
// sin, cos (HOST ONLY: f64 internally, like libm)
// ------------------------------------------------------------------------------------------------

// |cos(x) - c(x)| < 2**-34.1 (~[-5.37e-11, 5.295e-11]).
const KC0: f64 = f64::from_bits(0xbfdf_ffff_fd0c_5e81); // -0x1ffffffd0c5e81.0p-54
const KC1: f64 = f64::from_bits(0x3fa5_5553_e105_3a42); // 0x155553e1053a42.0p-57
const KC2: f64 = f64::from_bits(0xbf56_c087_e80f_1e27); // -0x16c087e80f1e27.0p-62
const KC3: f64 = f64::from_bits(0x3ef9_9342_e0ee_5069); // 0x199342e0ee5069.0p-68

/// cos on [-pi/4, pi/4] (libm's `k_cosf`).
#[inline]
fn k_cosf(x: f64) -> f32 {
    let z = x * x;
    let w = z * z;
    let r = KC2 + z * KC3;
    (((1.0 + z * KC0) + w * KC1) + (w * z) * r) as f32
}

// |sin(x)/x - s(x)| < 2**-37.5 (~[-4.89e-12, 4.824e-12]).
const KS1: f64 = f64::from_bits(0xbfc5_5555_54cb_ac77); // -0x15555554cbac77.0p-55
const KS2: f64 = f64::from_bits(0x3f81_1110_896e_fbb2); // 0x111110896efbb2.0p-59
const KS3: f64 = f64::from_bits(0xbf2a_00f9_e2ca_e774); // -0x1a00f9e2cae774.0p-65
const KS4: f64 = f64::from_bits(0x3ec6_cd87_8c3b_46a7); // 0x16cd878c3b46a7.0p-71

/// sin on [-pi/4, pi/4] (libm's `k_sinf`).
#[inline]
fn k_sinf(x: f64) -> f32 {
    let z = x * x;
    let w = z * z;
    let r = KS3 + z * KS4;
    let s = z * x;
    ((x + s * (KS1 + z * KS2)) + s * w * r) as f32
}

const FRAC_PI_2: f64 = core::f64::consts::FRAC_PI_2;
// Small multiples of pi/2 rounded to double precision.
const PIO2_X1: f64 = FRAC_PI_2;
const PIO2_X2: f64 = 2.0 * FRAC_PI_2;
const PIO2_X3: f64 = 3.0 * FRAC_PI_2;
const PIO2_X4: f64 = 4.0 * FRAC_PI_2;

/// Table of 2/pi: `IPIO2[i]` holds bits 24i .. 24i+23 after the binary point (the 66 entries
/// libm keeps for 32-bit targets; f32 arguments need at most the first 12 or so).
const IPIO2: [i32; 66] = [
    0xA2F983, 0x6E4E44, 0x1529FC, 0x2757D1, 0xF534DD, 0xC0DB62, 0x95993C, 0x439041, 0xFE5163,
    0xABDEBB, 0xC561B7, 0x246E3A, 0x424DD2, 0xE00649, 0x2EEA09, 0xD1921C, 0xFE1DEB, 0x1CB129,
    0xA73EE8, 0x8235F5, 0x2EBB44, 0x84E99C, 0x7026B4, 0x5F7E41, 0x3991D6, 0x398353, 0x39F49C,
    0x845F8B, 0xBDF928, 0x3B1FF8, 0x97FFDE, 0x05980F, 0xEF2F11, 0x8B5A0A, 0x6D1F6D, 0x367ECF,
    0x27CB09, 0xB74F46, 0x3F669E, 0x5FEA2D, 0x7527BA, 0xC7EBE5, 0xF17B3D, 0x0739F7, 0x8A5292,
    0xEA6BFB, 0x5FB11F, 0x8D5D08, 0x560330, 0x46FC7B, 0x6BABF0, 0xCFBC20, 0x9AF436, 0x1DA9E3,
    0x91615E, 0xE61B08, 0x659985, 0x5F14A0, 0x68408D, 0xFFD880, 0x4D7327, 0x310606, 0x1556CA,
    0x73A8C9, 0x60E27B, 0xC08C6B,
];

/// pi/2 cut into 24-bit chunks.
const PIO2_CHUNKS: [f64; 8] = [
    f64::from_bits(0x3ff9_21fb_4000_0000), // 0x3FF921FB, 0x40000000
    f64::from_bits(0x3e74_442d_0000_0000), // 0x3E74442D, 0x00000000
    f64::from_bits(0x3cf8_4698_8000_0000), // 0x3CF84698, 0x80000000
    f64::from_bits(0x3b78_cc51_6000_0000), // 0x3B78CC51, 0x60000000
    f64::from_bits(0x39f0_1b83_8000_0000), // 0x39F01B83, 0x80000000
    f64::from_bits(0x387a_2520_4000_0000), // 0x387A2520, 0x40000000
    f64::from_bits(0x36e3_8222_8000_0000), // 0x36E38222, 0x80000000
    f64::from_bits(0x3569_f31d_0000_0000), // 0x3569F31D, 0x00000000
];

/// Size of the work arrays of [`rem_pio2_large`] (libm uses 20; a power of two lets every index
/// be masked, so no bounds check can fail).
const RP_N: usize = 32;
const RP_MASK: usize = RP_N - 1;

#[inline(always)]
fn ipio2(i: usize) -> f64 {
    let i = if i < IPIO2.len() { i } else { IPIO2.len() - 1 };
    IPIO2[i] as f64
}

/// Payne-Hanek reduction for large arguments: returns `n & 7` and `y` with
/// `x0 * 2^e0 - n * pi/2 = y`, `|y| <= pi/4` (port of libm's `rem_pio2_large`, FreeBSD
/// `k_rem_pio2.c`, specialised to one 24-bit input chunk `x0` and single precision, `jk = 3`).
/// Host only.
fn rem_pio2_large(x0: f64, e0: i32) -> (i32, f64) {
    let x1p24 = f64::from_bits(0x4170_0000_0000_0000); // 2^24
    let x1p_24 = f64::from_bits(0x3e70_0000_0000_0000); // 2^-24
    const JK: usize = 3; // single precision
    const JP: usize = JK;

    let mut f = [0.0f64; RP_N];
    let mut fq = [0.0f64; RP_N];
    let mut q = [0.0f64; RP_N];
    let mut iq = [0i32; RP_N];

    // jx = 0 (one input chunk).
    let mut jv = (e0 - 3) / 24;
    if jv < 0 {
        jv = 0;
    }
    let mut q0 = e0 - 24 * (jv + 1);
    let jv = jv as usize;

    // f[0..=jk] = ipio2[jv..=jv+jk]
    let mut i = 0usize;
    while i <= JK {
        f[i & RP_MASK] = ipio2(jv + i);
        i += 1;
    }
    // q[i] = x0 * f[i]
    i = 0;
    while i <= JK {
        q[i & RP_MASK] = x0 * f[i & RP_MASK];
        i += 1;
    }

    let mut jz = JK;
    let mut z: f64;
    let mut n: i32;
    let mut ih: i32;
    let mut fw: f64;
    loop {
        // Distill q[] into iq[] in reverse.
        let mut ii = 0usize;
        z = q[jz & RP_MASK];
        let mut j = jz;
        while j >= 1 {
            fw = (x1p_24 * z) as i32 as f64;
            iq[ii & RP_MASK] = (z - x1p24 * fw) as i32;
            z = q[(j - 1) & RP_MASK] + fw;
            ii += 1;
            j -= 1;
        }

        // Compute n.
        z = scalbn64(z, q0); // actual value of z
        z -= 8.0 * floor64(z * 0.125); // trim off the integer >= 8
        n = z as i32;
        z -= n as f64;
        ih = 0;
        let top = (jz - 1) & RP_MASK;
        if q0 > 0 {
            // Need iq[jz-1] to determine n.
            let b = iq[top] >> (24 - q0);
            n += b;
            iq[top] -= b << (24 - q0);
            ih = iq[top] >> (23 - q0);
        } else if q0 == 0 {
            ih = iq[top] >> 23;
        } else if z >= 0.5 {
            ih = 2;
        }

        if ih > 0 {
            // q > 0.5
            n += 1;
            let mut carry = 0i32;
            let mut k = 0usize;
            while k < jz {
                // Compute 1 - q.
                let v = iq[k & RP_MASK];
                if carry == 0 {
                    if v != 0 {
                        carry = 1;
                        iq[k & RP_MASK] = 0x0100_0000 - v;
                    }
                } else {
                    iq[k & RP_MASK] = 0x00ff_ffff - v;
                }
                k += 1;
            }
            if q0 > 0 {
                // Rare case: chance is 1 in 12.
                if q0 == 1 {
                    iq[top] &= 0x007f_ffff;
                } else if q0 == 2 {
                    iq[top] &= 0x003f_ffff;
                }
            }
            if ih == 2 {
                z = 1.0 - z;
                if carry != 0 {
                    z -= scalbn64(1.0, q0);
                }
            }
        }

        // Check whether recomputation is needed.
        if z == 0.0 {
            let mut acc = 0i32;
            let mut k = jz - 1;
            while k >= JK {
                acc |= iq[k & RP_MASK];
                k -= 1;
            }
            if acc == 0 && jz + 8 < RP_N {
                // Need recomputation: k = number of extra terms needed.
                let mut k = 1usize;
                while k < JK && iq[(JK - k) & RP_MASK] == 0 {
                    k += 1;
                }
                let mut t = jz + 1;
                while t <= jz + k {
                    f[t & RP_MASK] = ipio2(jv + t);
                    q[t & RP_MASK] = x0 * f[t & RP_MASK];
                    t += 1;
                }
                jz += k;
                continue;
            }
        }
        break;
    }

    // Chop off zero terms.
    if z == 0.0 {
        jz -= 1;
        q0 -= 24;
        while jz > 0 && iq[jz & RP_MASK] == 0 {
            jz -= 1;
            q0 -= 24;
        }
    } else {
        // Break z into 24-bit chunks if necessary.
        z = scalbn64(z, -q0);
        if z >= x1p24 {
            fw = (x1p_24 * z) as i32 as f64;
            iq[jz & RP_MASK] = (z - x1p24 * fw) as i32;
            jz += 1;
            q0 += 24;
            iq[jz & RP_MASK] = fw as i32;
        } else {
            iq[jz & RP_MASK] = z as i32;
        }
    }

    // Convert the integer chunks to floating point.
    fw = scalbn64(1.0, q0);
    let mut k = jz as i32;
    while k >= 0 {
        q[k as usize & RP_MASK] = fw * (iq[k as usize & RP_MASK] as f64);
        fw *= x1p_24;
        k -= 1;
    }

    // fq[jz - i] = sum_k PIO2_CHUNKS[k] * q[i + k]
    let mut i = jz as i32;
    while i >= 0 {
        let iu = i as usize;
        fw = 0.0;
        let mut k = 0usize;
        while k <= JP && k <= jz - iu {
            fw += PIO2_CHUNKS[k & 7] * q[(iu + k) & RP_MASK];
            k += 1;
        }
        fq[(jz - iu) & RP_MASK] = fw;
        i -= 1;
    }

    // Compress fq[] into y (single precision: one term).
    fw = 0.0;
    let mut i = jz as i32;
    while i >= 0 {
        fw += fq[i as usize & RP_MASK];
        i -= 1;
    }
    let y = if ih == 0 { fw } else { -fw };
    (n & 7, y)
}

const TOINT: f64 = 1.5 / f64::EPSILON;
/// 53 bits of 2/pi
const INV_PIO2: f64 = f64::from_bits(0x3fe4_5f30_6dc9_c883); // 0x3FE45F30, 0x6DC9C883
/// First 25 bits of pi/2
const PIO2_1: f64 = f64::from_bits(0x3ff9_21fb_5000_0000); // 0x3FF921FB, 0x50000000
/// pi/2 - PIO2_1
const PIO2_1T: f64 = f64::from_bits(0x3e51_10b4_611a_6263); // 0x3E5110b4, 0x611A6263

/// `x = n * pi/2 + y` with `|y| <~ pi/4` (libm's `rem_pio2f`); `y` in f64. Host only.
fn rem_pio2f(x: f32) -> (i32, f64) {
    let x64 = x as f64;
    let ix = x.to_bits() & 0x7fff_ffff;
    // 25 + 53 bit pi is good enough for medium size.
    if ix < 0x4dc9_0fdb {
        // |x| ~< 2^28 * (pi/2): round x * 2/pi to an integer with the 1.5*2^52 trick.
        let tmp = x64 * INV_PIO2 + TOINT;
        let f_n = tmp - TOINT;
        return (f_n as i32, x64 - f_n * PIO2_1 - f_n * PIO2_1T);
    }
    if ix >= 0x7f80_0000 {
        // inf or NaN
        return (0, f64::NAN); // (libm: x - x)
    }
    // Scale x into [2^23, 2^24 - 1].
    let sign = (x.to_bits() >> 31) != 0;
    let e0 = ((ix >> 23) - (0x7f + 23)) as i32; // ilogb(|x|) - 23, positive
    let x0 = f32::from_bits(ix - ((e0 as u32) << 23)) as f64;
    let (n, y) = rem_pio2_large(x0, e0);
    if sign {
        (-n, -y)
    } else {
        (n, y)
    }
}

/// Sine (port of libm's `sinf`, FreeBSD `s_sinf.c`). **Host only**: the kernels and the
/// argument reduction run in `f64` (as in libm), so this must not be called from shader code.
/// Within 1 ULP of `libm::sinf` (tested; in practice identical); NaN and infinities give NaN.
pub fn sin(x: f32) -> f32 {
    let x64 = x as f64;
    let mut ix = x.to_bits();
    let sign = (ix >> 31) != 0;
    ix &= 0x7fff_ffff;

    if ix <= 0x3f49_0fda {
        // |x| ~<= pi/4
        if ix < 0x3980_0000 {
            // |x| < 2^-12
            return x;
        }
        return k_sinf(x64);
    }
    if ix <= 0x407b_53d1 {
        // |x| ~<= 5pi/4
        if ix <= 0x4016_cbe3 {
            // |x| ~<= 3pi/4
            if sign {
                return -k_cosf(x64 + PIO2_X1);
            } else {
                return k_cosf(x64 - PIO2_X1);
            }
        }
        return k_sinf(if sign {
            -(x64 + PIO2_X2)
        } else {
            -(x64 - PIO2_X2)
        });
    }
    if ix <= 0x40e2_31d5 {
        // |x| ~<= 9pi/4
        if ix <= 0x40af_eddf {
            // |x| ~<= 7pi/4
            if sign {
                return k_cosf(x64 + PIO2_X3);
            } else {
                return -k_cosf(x64 - PIO2_X3);
            }
        }
        return k_sinf(if sign { x64 + PIO2_X4 } else { x64 - PIO2_X4 });
    }

    // sin(inf or NaN) is NaN (libm: x - x)
    if ix >= 0x7f80_0000 {
        return f32::NAN;
    }

    // General argument reduction.
    let (n, y) = rem_pio2f(x);
    match n & 3 {
        0 => k_sinf(y),
        1 => k_cosf(y),
        2 => k_sinf(-y),
        _ => -k_cosf(y),
    }
}

/// Cosine (port of libm's `cosf`, FreeBSD `s_cosf.c`). **Host only**: the kernels and the
/// argument reduction run in `f64` (as in libm), so this must not be called from shader code.
/// Within 1 ULP of `libm::cosf` (tested; in practice identical); NaN and infinities give NaN.
pub fn cos(x: f32) -> f32 {
    let x64 = x as f64;
    let mut ix = x.to_bits();
    let sign = (ix >> 31) != 0;
    ix &= 0x7fff_ffff;

    if ix <= 0x3f49_0fda {
        // |x| ~<= pi/4
        if ix < 0x3980_0000 {
            // |x| < 2^-12
            return 1.0;
        }
        return k_cosf(x64);
    }
    if ix <= 0x407b_53d1 {
        // |x| ~<= 5pi/4
        if ix > 0x4016_cbe3 {
            // |x| ~> 3pi/4
            return -k_cosf(if sign { x64 + PIO2_X2 } else { x64 - PIO2_X2 });
        } else if sign {
            return k_sinf(x64 + PIO2_X1);
        } else {
            return k_sinf(PIO2_X1 - x64);
        }
    }
    if ix <= 0x40e2_31d5 {
        // |x| ~<= 9pi/4
        if ix > 0x40af_eddf {
            // |x| ~> 7pi/4
            return k_cosf(if sign { x64 + PIO2_X4 } else { x64 - PIO2_X4 });
        } else if sign {
            return k_sinf(-x64 - PIO2_X3);
        } else {
            return k_sinf(x64 - PIO2_X3);
        }
    }

    // cos(inf or NaN) is NaN (libm: x - x)
    if ix >= 0x7f80_0000 {
        return f32::NAN;
    }

    // General argument reduction.
    let (n, y) = rem_pio2f(x);
    match n & 3 {
        0 => k_cosf(y),
        1 => k_sinf(-y),
        2 => -k_cosf(y),
        _ => k_sinf(y),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `div_rn` against the processor's division, bit for bit, NaN payloads included.
    #[test]
    fn soft_division_equals_the_processors_division() {
        let hw = |a: f32, b: f32| core::hint::black_box(a) / core::hint::black_box(b);
        let check = |a: f32, b: f32| {
            let (s, h) = (div_rn(a, b), hw(a, b));
            assert_eq!(
                s.to_bits(),
                h.to_bits(),
                "{a:e} ({:#x}) / {b:e} ({:#x}): soft {s:e} ({:#x}), hardware {h:e} ({:#x})",
                a.to_bits(),
                b.to_bits(),
                s.to_bits(),
                h.to_bits()
            );
        };
        let specials = [
            0.0f32,
            -0.0,
            1.0,
            -1.0,
            3.0,
            0.1,
            f32::MIN_POSITIVE,
            -f32::MIN_POSITIVE,
            f32::from_bits(1),
            f32::from_bits(0x8000_0001),
            f32::from_bits(0x007f_ffff),
            f32::from_bits(0x0040_0000),
            f32::MAX,
            f32::MIN,
            f32::INFINITY,
            f32::NEG_INFINITY,
            f32::NAN,
            -f32::NAN,
            f32::from_bits(0x7f80_0001), // signalling
            f32::from_bits(0xffbf_ffff),
            1.0 + f32::EPSILON,
            1.0 - f32::EPSILON / 2.0,
        ];
        for &a in &specials {
            for &b in &specials {
                check(a, b);
            }
        }
        // random bit patterns (all exponents), and ranges where results are subnormal,
        // overflow, or ties could occur (small integers)
        let mut state = 0x9e37_79b9_7f4a_7c15u64;
        let mut next = || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            state
        };
        for _ in 0..2_000_000 {
            let r = next();
            check(f32::from_bits(r as u32), f32::from_bits((r >> 32) as u32));
        }
        for _ in 0..500_000 {
            let r = next();
            let a = f32::from_bits(((r as u32) & 0x80ff_ffff) | 0x0080_0000); // tiny exponents
            let b = f32::from_bits(((r >> 32) as u32 & 0x807f_ffff) | 0x4b00_0000); // ~2^23
            check(a, b);
            check(b, a);
            let (i, j) = ((r & 0xffff) as f32, ((r >> 16) & 0xff) as f32 + 1.0);
            check(i, j);
            check(-i, j * 3.0);
            let big = f32::from_bits(((r >> 40) as u32 & 0x00ff_ffff) | 0x7e80_0000);
            check(big, f32::from_bits((r as u32 & 0x007f_ffff) | 0x0010_0000));
        }
    }

    /// `unpack_finite`'s loop-free normalisation of subnormals equals shifting one bit at a
    /// time, for every subnormal significand (and a few normal numbers).
    #[test]
    fn subnormals_unpack_like_one_bit_at_a_time() {
        for m in (1u32..0x0080_0000).chain([0x0080_0000, 0x3f80_0001, 0x7f7f_ffff]) {
            let (mut e, mut x) = ((m >> 23) as i32, m & 0x007f_ffff);
            if e == 0 {
                e = 1;
                while x & 0x0080_0000 == 0 {
                    x <<= 1;
                    e -= 1;
                }
            } else {
                x |= 0x0080_0000;
            }
            assert_eq!(unpack_finite(m), (e, x), "{m:#x}");
        }
    }

    /// `div_rn`'s correction step recovers the exact quotient from a hardware quotient that is
    /// off by up to 16 ULP either way (Vulkan allows `OpFDiv` 2.5 ULP): on the CPU the
    /// estimate is exact, so it is pushed away on purpose here.
    #[test]
    fn division_corrects_an_inexact_hardware_quotient() {
        let mut state = 0x2545_f491_4f6c_dd1du64;
        let mut next = || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            state
        };
        let mut pairs = vec![
            (1.0f32, 3.0f32),
            (1.0, 1.0 + f32::EPSILON),
            (1.0 + f32::EPSILON, 1.0),
            (f32::from_bits(0x00ff_ffff), f32::from_bits(0x0080_0001)),
            (f32::MIN_POSITIVE, 3.0),
            (f32::from_bits(1), 0.75),
            (f32::MAX, 0.5),
            (2.0, 2.0),
        ];
        for _ in 0..20_000 {
            let r = next();
            pairs.push((f32::from_bits(r as u32), f32::from_bits((r >> 32) as u32)));
            // significands close to each other (quotients near 1, where the exponent of the
            // estimate can fall on either side)
            let m = (r as u32) & 0x007f_ffff;
            let d = ((r >> 32) as u32) & 0xf;
            pairs.push((
                f32::from_bits(0x3f80_0000 | m),
                f32::from_bits(0x3f80_0000 | m.wrapping_add(d) & 0x007f_ffff),
            ));
        }
        for &(a, b) in &pairs {
            let h = core::hint::black_box(a) / core::hint::black_box(b);
            for nudge in -16..=16 {
                let s = div_corrected(a, b, nudge);
                assert!(
                    s.to_bits() == h.to_bits() || (s.is_nan() && h.is_nan()),
                    "{a:e} / {b:e} with the estimate {nudge} ULP off: {s:e} ({:#x}), \
                     hardware {h:e} ({:#x})",
                    s.to_bits(),
                    h.to_bits()
                );
            }
        }
    }

    /// Bit equality with NaN == NaN (NaN payloads and signs are not part of the contract).
    fn same(a: f32, b: f32) -> bool {
        (a.is_nan() && b.is_nan()) || a.to_bits() == b.to_bits()
    }

    /// Special values every sweep includes.
    fn specials() -> Vec<f32> {
        let mut v = vec![
            0.0,
            -0.0,
            f32::INFINITY,
            f32::NEG_INFINITY,
            f32::NAN,
            -f32::NAN,
            f32::MIN_POSITIVE,
            -f32::MIN_POSITIVE,
            f32::from_bits(1),
            f32::from_bits(0x8000_0001),
            f32::from_bits(0x007f_ffff),
            f32::from_bits(0x807f_ffff),
            f32::from_bits(0x0040_0000),
            f32::MAX,
            f32::MIN,
            f32::EPSILON,
            1.0,
            -1.0,
            0.5,
            -0.5,
            2.0,
            88.72,
            -88.72,
            88.722_84,
            88.722_83,
            -87.336_55,
            -103.9,
            -103.972_08,
            -103.972_09,
            -104.0,
            10.0,
            -10.0,
            1e30,
            -1e30,
            1e-30,
            core::f32::consts::PI,
            core::f32::consts::LN_2,
        ];
        // The thresholds used inside the algorithms, and their neighbours.
        for &b in &[
            0x42ae_ac50u32,
            0x42b1_7218,
            0x42cf_f1b5,
            0x3eb1_7218,
            0x3f85_1592,
            0x3900_0000,
            0x4195_b844,
            0x3300_0000,
            0x3f0c_9f54,
            0x4120_0000,
            0x3e82_c578,
            0x3f35_04f3,
            0x3f80_0000,
            0x4b00_0000,
        ] {
            for d in [-1i32, 0, 1] {
                let bits = (b as i32 + d) as u32;
                v.push(f32::from_bits(bits));
                v.push(f32::from_bits(bits | 0x8000_0000));
            }
        }
        v
    }

    /// ~2.1 million inputs: a strided sweep over all 2^32 bit patterns (stride 2053, a prime, so
    /// every mantissa residue and every exponent is hit), plus the special values, plus a dense
    /// sweep of [-110, 110] where exp/tanh/floor have their interesting structure.
    fn sweep() -> Vec<f32> {
        let mut v = specials();
        let mut b: u64 = 0;
        while b < (1u64 << 32) {
            v.push(f32::from_bits(b as u32));
            b += 2053;
        }
        let n = 200_000;
        for i in 0..=n {
            v.push(-110.0 + 220.0 * (i as f32) / (n as f32));
        }
        v
    }

    fn check_bitwise(name: &str, ours: fn(f32) -> f32, reference: fn(f32) -> f32) {
        let inputs = sweep();
        assert!(inputs.len() > 2_000_000, "{}", inputs.len());
        let mut bad = 0usize;
        let mut first = None;
        for &x in &inputs {
            let (a, b) = (ours(x), reference(x));
            if !same(a, b) {
                bad += 1;
                if first.is_none() {
                    first = Some((x, a, b));
                }
            }
        }
        assert_eq!(
            bad,
            0,
            "{name}: {bad} mismatches of {}; first (x, ours, libm) = {first:?}",
            inputs.len()
        );
    }

    #[test]
    fn exp_is_bitwise_libm() {
        check_bitwise("exp", exp, libm::expf);
    }

    #[test]
    fn log_is_bitwise_libm() {
        check_bitwise("log", log, libm::logf);
    }

    #[test]
    fn sqrt_is_bitwise_libm() {
        check_bitwise("sqrt", sqrt, libm::sqrtf);
    }

    #[test]
    fn tanh_is_bitwise_libm() {
        check_bitwise("tanh", tanh, libm::tanhf);
    }

    #[test]
    fn floor_is_bitwise_libm() {
        check_bitwise("floor", floor, libm::floorf);
    }

    #[test]
    fn sqrt_is_exact_on_squares_and_all_subnormal_powers() {
        for i in 0..4096u32 {
            let f = i as f32;
            assert_eq!(sqrt(f * f), f);
        }
        // Every power of two 2^-149 .. 2^127 (subnormals included).
        for e in -149i32..=127 {
            let x = (e as f64).exp2() as f32;
            assert!(same(sqrt(x), libm::sqrtf(x)), "2^{e}");
        }
        assert_eq!(sqrt(-0.0).to_bits(), (-0.0f32).to_bits());
        assert!(sqrt(-1.0).is_nan());
        assert!(sqrt(f32::NEG_INFINITY).is_nan());
        assert_eq!(sqrt(f32::INFINITY), f32::INFINITY);
    }

    fn ulp_diff(a: f32, b: f32) -> u32 {
        if same(a, b) {
            return 0;
        }
        if a.is_nan() || b.is_nan() {
            return u32::MAX;
        }
        // Map to a monotone integer line.
        let key = |x: f32| {
            let b = x.to_bits() as i32;
            if b < 0 {
                i32::MIN - b
            } else {
                b
            }
        };
        (key(a) as i64 - key(b) as i64).unsigned_abs() as u32
    }

    /// sin/cos within 1 ULP of libm over a range sweep: 1M points in [-20, 20] (all the
    /// medium-size branches), a strided sweep over every finite bit pattern (covers the
    /// Payne-Hanek reduction for |x| >= 2^28 pi/2) and the special values.
    #[test]
    fn sin_cos_within_one_ulp_of_libm() {
        let mut inputs = specials();
        let n = 1_000_000;
        for i in 0..=n {
            inputs.push(-20.0 + 40.0 * (i as f32) / (n as f32));
        }
        let mut b: u64 = 0;
        while b < (1u64 << 32) {
            inputs.push(f32::from_bits(b as u32));
            b += 4099;
        }
        let mut large = 0;
        let (mut max_s, mut max_c) = (0u32, 0u32);
        for &x in &inputs {
            if x.is_finite() && x.abs() >= 4.2e8 {
                large += 1;
            }
            max_s = max_s.max(ulp_diff(sin(x), libm::sinf(x)));
            max_c = max_c.max(ulp_diff(cos(x), libm::cosf(x)));
        }
        eprintln!(
            "sin/cos over {} inputs: max {max_s} / {max_c} ULP from libm",
            inputs.len()
        );
        assert!(large > 100_000, "large-argument coverage {large}");
        assert!(max_s <= 1, "sin: max {max_s} ULP");
        assert!(max_c <= 1, "cos: max {max_c} ULP");
    }

    #[test]
    fn sin_cos_golden() {
        assert_eq!(sin(0.0), 0.0);
        assert_eq!(cos(0.0), 1.0);
        // sin(pi/6) = 1/2, cos(pi/3) = 1/2 (to within an ULP of the rounded arguments).
        assert!((sin(core::f32::consts::FRAC_PI_6) - 0.5).abs() <= 1e-7);
        assert!((cos(core::f32::consts::FRAC_PI_3) - 0.5).abs() <= 1e-7);
        assert!(sin(f32::INFINITY).is_nan() && cos(f32::NAN).is_nan());
    }

    #[test]
    fn floor_golden() {
        assert_eq!(floor(2.5), 2.0);
        assert_eq!(floor(-2.5), -3.0);
        assert_eq!(floor(-0.25), -1.0);
        assert_eq!(floor(0.75).to_bits(), 0.0f32.to_bits());
        assert_eq!(floor(-0.0).to_bits(), (-0.0f32).to_bits());
        assert_eq!(floor(-3.0), -3.0);
        assert_eq!(floor(8_388_607.5), 8_388_607.0);
    }

    #[test]
    fn abs_min_max_clamp() {
        assert_eq!(abs(-3.5), 3.5);
        assert_eq!(abs(-0.0).to_bits(), 0);
        assert_eq!(abs(f32::NEG_INFINITY), f32::INFINITY);
        assert!(abs(-f32::NAN).is_nan());
        assert_eq!(min(1.0, 2.0), 1.0);
        assert_eq!(min(2.0, -1.0), -1.0);
        assert_eq!(max(1.0, 2.0), 2.0);
        assert_eq!(max(-2.0, -3.0), -2.0);
        // Documented NaN behaviour: the second argument is returned.
        assert!(min(1.0, f32::NAN).is_nan());
        assert_eq!(min(f32::NAN, 1.0), 1.0);
        assert_eq!(max(f32::NAN, 1.0), 1.0);
        assert_eq!(clamp(5.0, -1.0, 1.0), 1.0);
        assert_eq!(clamp(-5.0, -1.0, 1.0), -1.0);
        assert_eq!(clamp(0.25, -1.0, 1.0), 0.25);
        assert!(clamp(f32::NAN, -1.0, 1.0).is_nan());
    }

    #[test]
    fn pow_int_golden_and_reference() {
        assert_eq!(pow_int(2.0, 10), 1024.0);
        assert_eq!(pow_int(-3.0, 3), -27.0);
        assert_eq!(pow_int(0.5, 0), 1.0);
        assert_eq!(pow_int(0.0, 0), 1.0);
        assert_eq!(pow_int(10.0, 1), 10.0);
        // 0.9^t and 0.999^t as Adam uses them: within a few ULP of the f64 value.
        for &b in &[0.9f32, 0.999, 1.5, -0.7] {
            for t in 1..=2000u32 {
                let ours = pow_int(b, t) as f64;
                let exact = (b as f64).powi(t as i32);
                if exact.abs() < 1e-30 || exact.abs() > 1e30 {
                    continue;
                }
                // Relative errors compound with the exponent: squaring doubles the error of
                // its operand, so x^t carries at most about (t - 1) roundings of 2^-24 each.
                let rel = ((ours - exact) / exact).abs();
                let bound = t as f64 * f64::from(f32::EPSILON) * 0.5;
                assert!(rel <= bound, "{b}^{t}: {ours} vs {exact} (rel {rel})");
                // ... and is far better than that for small t (Adam's early steps).
                if t <= 16 {
                    assert!(rel <= 8.0 * 6e-8, "{b}^{t}: rel {rel}");
                }
            }
        }
        // Square-and-multiply order: x^3 = x * x^2 exactly as written.
        let x = 1.1f32;
        assert_eq!(pow_int(x, 3).to_bits(), (x * (x * x)).to_bits());
    }

    #[test]
    fn sigmoid_values_and_stability() {
        assert_eq!(sigmoid(0.0), 0.5);
        // 1 / (1 + e^-2) = 0.880797077977882...
        assert!((sigmoid(2.0) - 0.880_797_1).abs() < 1e-7);
        assert!((sigmoid(-2.0) - 0.119_202_92).abs() < 1e-7);
        assert_eq!(sigmoid(100.0), 1.0);
        assert_eq!(sigmoid(f32::INFINITY), 1.0);
        assert_eq!(sigmoid(f32::NEG_INFINITY), 0.0);
        assert!(sigmoid(f32::NAN).is_nan());
        // Very negative inputs keep relative accuracy (e^-100 = 3.72e-44, subnormal).
        let s = sigmoid(-100.0) as f64;
        let exact = (-100.0f64).exp() / (1.0 + (-100.0f64).exp());
        assert!(
            s > 0.0 && (s - exact).abs() <= 2.0 * f32::from_bits(1) as f64,
            "{s}"
        );
        let s = sigmoid(-30.0) as f64;
        let exact = (-30.0f64).exp() / (1.0 + (-30.0f64).exp());
        assert!(((s - exact) / exact).abs() < 3e-7);
        // Monotone and symmetric: s(x) + s(-x) = 1 within rounding.
        let mut prev = 0.0;
        for i in -400..=400 {
            let x = i as f32 * 0.05;
            let s = sigmoid(x);
            assert!(s >= prev);
            prev = s;
            assert!((s + sigmoid(-x) - 1.0).abs() <= 1.2e-7);
        }
    }

    #[test]
    fn softplus_matches_f64_reference() {
        assert_eq!(softplus(f32::INFINITY), f32::INFINITY);
        assert_eq!(softplus(f32::NEG_INFINITY), 0.0);
        assert!(softplus(f32::NAN).is_nan());
        // log(2) = 0.693147180559945...
        assert!((softplus(0.0) - core::f32::consts::LN_2).abs() <= 6e-8);
        assert_eq!(softplus(100.0), 100.0);
        let mut x = -90.0f32;
        while x <= 90.0 {
            let s = softplus(x) as f64;
            let xd = x as f64;
            let exact = xd.max(0.0) + (-xd.abs()).exp().ln_1p();
            // 5e-7 relative, or 4 units of the smallest subnormal where the result is subnormal.
            let tol = (5e-7 * exact).max(4.0 * f64::from(f32::from_bits(1)));
            assert!(
                (s - exact).abs() <= tol,
                "softplus({x}) = {s}, exact {exact}"
            );
            x += 0.0137;
        }
    }
}
