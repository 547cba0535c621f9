//! The decoders' parameter gradients batched over samples: the CPU worker's form of
//! [`himap_core::GradSink::add_layer`]. A layer's per-sample contributions (`to_fixed(g_j x_i)`
//! for its weights, `to_fixed(g_j)` for its biases, each unit `j` whose gradient `g_j` is not
//! zero) are the same f32 products and the same conversions as row by row; only the order of
//! the integer additions changes, which gives the same sums. A layer holds up to [`CAP`]
//! samples; then each weight row takes all their contributions at once, in AVX2 lanes where
//! the CPU has them: the product `g x`, scaled by 2^40 and rounded by the float-to-`i32`
//! conversion (three operations per 8 contributions, none on the shuffle port the f64
//! widening of a row at a time needed), summed in `i32` lanes over runs of samples whose
//! bounds keep the sums below 2^31, then widened once into the row's `i64` sums. A sample
//! whose unit gradient is subnormal adds nothing to the weights (below half a quantum, decided
//! on the bits: multiplying by a subnormal costs a microcode assist on many x86 CPUs); one
//! whose products may not fit takes `to_fixed` one contribution at a time.

use himap_core::field::mlp::MAX_WIDTH;
use himap_core::field::negligible::max_abs;
use himap_core::train::fixed;

use crate::backend::{to_fixed_host, to_fixed_small};

/// Samples a layer holds before its contributions are added.
pub(crate) const CAP: usize = 32;

/// One decoder layer's waiting samples: unit gradients and inputs, `n` of each.
struct Layer {
    group: usize,
    w_off: usize,
    b_off: usize,
    fan_out: usize,
    fan_in: usize,
    n: usize,
    /// `gs[s * fan_out + j]`: sample `s`'s gradient of unit `j`.
    gs: Vec<f32>,
    /// `xs[s * stride + i]`: sample `s`'s input `i` (0 from `fan_in` to `stride`).
    xs: Vec<f32>,
    /// `fan_in` rounded up to a multiple of 8.
    stride: usize,
}

/// A worker's layers waiting to be added ([`Self::flush`] before its sums are read).
#[derive(Default)]
pub(crate) struct LayerBatches {
    layers: Vec<Layer>,
}

/// Where a flush adds: the gradient buffer of each group and its touched flags per block.
pub(crate) struct Dest<'a> {
    pub grads: &'a mut [Vec<i64>],
    pub touched: &'a mut [Vec<bool>],
    pub block_shift: u32,
}

impl LayerBatches {
    /// Holds one sample's contributions of a layer (see [`himap_core::GradSink::add_layer`]),
    /// adding the layer's batch when it is full.
    #[allow(clippy::too_many_arguments)]
    pub(crate) fn push(
        &mut self,
        dest: &mut Dest<'_>,
        group: usize,
        w_off: usize,
        b_off: usize,
        gs: &[f32; MAX_WIDTH],
        fan_out: usize,
        xs: &[f32; MAX_WIDTH],
        fan_in: usize,
    ) {
        let (fan_out, fan_in) = (fan_out.min(MAX_WIDTH), fan_in.min(MAX_WIDTH));
        let k = match self.layers.iter().position(|l| {
            l.group == group
                && l.w_off == w_off
                && l.b_off == b_off
                && l.fan_out == fan_out
                && l.fan_in == fan_in
        }) {
            Some(k) => k,
            None => {
                self.layers.push(Layer {
                    group,
                    w_off,
                    b_off,
                    fan_out,
                    fan_in,
                    n: 0,
                    gs: vec![0.0; CAP * fan_out],
                    xs: vec![0.0; CAP * fan_in.next_multiple_of(8)],
                    stride: fan_in.next_multiple_of(8),
                });
                self.layers.len() - 1
            }
        };
        let l = &mut self.layers[k];
        let s = l.n;
        l.gs[s * fan_out..(s + 1) * fan_out].copy_from_slice(&gs[..fan_out]);
        l.xs[s * l.stride..s * l.stride + fan_in].copy_from_slice(&xs[..fan_in]);
        l.n += 1;
        if l.n == CAP {
            l.add_into(dest);
        }
    }

    /// Adds every waiting sample.
    pub(crate) fn flush(&mut self, dest: &mut Dest<'_>) {
        for l in &mut self.layers {
            l.add_into(dest);
        }
    }
}

impl Layer {
    /// Adds the held samples' contributions and empties the batch.
    fn add_into(&mut self, dest: &mut Dest<'_>) {
        let n = std::mem::take(&mut self.n);
        if n == 0 {
            return;
        }
        let (fo, fi, stride) = (self.fan_out, self.fan_in, self.stride);
        let Some(dst) = dest.grads.get_mut(self.group) else {
            return;
        };
        let touched = &mut dest.touched[self.group];
        // Per sample, a bound on |x| (infinite when an input is not finite): every product
        // `g x` of the sample is at most `|g| xmax` after rounding (rounding is monotone).
        let mut xmax = [0.0f32; CAP];
        for (s, m) in xmax.iter_mut().enumerate().take(n) {
            // An f32 value (or 2^-126 for a subnormal maximum): exact as f32.
            *m = max_abs(&self.xs[s * stride..s * stride + fi]).map_or(f32::INFINITY, |b| b as f32);
        }
        for j in 0..fo {
            let mut fast = [(0u8, 0.0f32, 0.0f32); CAP];
            let mut n_fast = 0;
            let mut any = false;
            let row = self.w_off + j * fi;
            for (s, &xm) in xmax.iter().enumerate().take(n) {
                let g = self.gs[s * fo + j];
                // Zero, or too small for any contribution to reach half a quantum: a
                // subnormal `g` (below 2^-126) times inputs below 2^85 stays below 2^-41,
                // which rounds to 0 quanta. Decided on the bits: arithmetic on subnormal
                // numbers is slow on many CPUs.
                if g.to_bits() & 0x7fff_ffff < 0x0080_0000 && xm < TINY_X {
                    continue;
                }
                any = true;
                if let Some(b) = dst.get_mut(self.b_off + j) {
                    *b = b.wrapping_add(to_fixed_host(g));
                    touched[(self.b_off + j) >> dest.block_shift] = true;
                }
                // The scaled products' bound (NaN when `g` is: not fast).
                let bound = g.abs() * xm * QUANTA;
                if bound < I32_RUN as f32 {
                    fast[n_fast] = (s as u8, g, bound);
                    n_fast += 1;
                } else if let Some(row) = dst.get_mut(row..row + fi) {
                    // Large or non-finite products: one at a time, as `to_fixed` converts them.
                    for (d, &x) in row.iter_mut().zip(&self.xs[s * stride..s * stride + fi]) {
                        *d = d.wrapping_add(fixed::to_fixed(g * x));
                    }
                }
            }
            if !any || fi == 0 {
                continue;
            }
            let Some(dst_row) = dst.get_mut(row..row + fi) else {
                continue;
            };
            for t in &mut touched[row >> dest.block_shift..=(row + fi - 1) >> dest.block_shift] {
                *t = true;
            }
            add_row(dst_row, &self.xs, stride, &fast[..n_fast]);
        }
    }
}

/// `row[i] += to_fixed_small(g_s * xs[s * stride + i])` for every fast sample `(g_s, bound_s)`
/// (`bound_s = |g_s| 2^40 xmax_s`, below [`I32_RUN`]); the inputs of a sample are padded with
/// zeros to `stride`, a multiple of 8.
fn add_row(row: &mut [i64], xs: &[f32], stride: usize, fast: &[(u8, f32, f32)]) {
    if fast.is_empty() {
        return;
    }
    #[cfg(target_arch = "x86_64")]
    {
        if std::arch::is_x86_feature_detected!("avx2") {
            // SAFETY: the CPU supports AVX2 (checked above).
            return unsafe { add_row_avx2(row, xs, stride, fast) };
        }
    }
    for &(s, g, _) in fast {
        let x = &xs[s as usize * stride..][..row.len()];
        for (d, &x) in row.iter_mut().zip(x) {
            *d = d.wrapping_add(to_fixed_small(g * x));
        }
    }
}

/// 2^30: the samples a run of `i32` sums takes together bound the magnitudes of their scaled
/// products by this in all (so no sum, rounded values included, reaches 2^31).
const I32_RUN: f64 = (1u64 << 30) as f64;

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
fn add_row_avx2(row: &mut [i64], xs: &[f32], stride: usize, fast: &[(u8, f32, f32)]) {
    let groups = row.len().div_ceil(8);
    let mut q = 0;
    while q < groups {
        match groups - q {
            1 => chunk_avx2::<1>(row, xs, stride, fast, q),
            2 => chunk_avx2::<2>(row, xs, stride, fast, q),
            3 => chunk_avx2::<3>(row, xs, stride, fast, q),
            _ => chunk_avx2::<4>(row, xs, stride, fast, q),
        }
        q += 4;
    }
}

/// Groups `q..q + K` of 8 columns of a row. Each contribution is `g x` rounded to f32 (the
/// row-by-row product), scaled by 2^40 (exact: a power of two, and a product too small to be
/// a normal f32 rounds to 0 quanta either way) and rounded to a whole number of quanta by the
/// CPU's float-to-int32 conversion (round to nearest, ties to even: [`fixed::to_fixed`]'s
/// rounding), summed in `i32` lanes over a run of samples whose bounds stay below
/// [`I32_RUN`], then widened into the row's `i64` sums.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
fn chunk_avx2<const K: usize>(
    row: &mut [i64],
    xs: &[f32],
    stride: usize,
    fast: &[(u8, f32, f32)],
    q: usize,
) {
    use std::arch::x86_64::*;
    let c = 8 * q;
    let mut acc = [_mm256_setzero_si256(); 4];
    let mut budget = 0.0f64;
    for &(s, g, bound) in fast {
        if budget + bound as f64 >= I32_RUN {
            widen_add(row, c, &mut acc, K);
            budget = 0.0;
        }
        budget += bound as f64;
        let gv = _mm256_set1_ps(g);
        let scale = _mm256_set1_ps(QUANTA);
        let x = &xs[s as usize * stride + c..s as usize * stride + c + 8 * K];
        for (k, a) in acc.iter_mut().enumerate().take(K) {
            // SAFETY: `x` holds 8 K values (the slice above): the load stays within it.
            let p = _mm256_mul_ps(gv, unsafe { _mm256_loadu_ps(x.as_ptr().add(8 * k)) });
            let v = _mm256_cvtps_epi32(_mm256_mul_ps(p, scale));
            *a = _mm256_add_epi32(*a, v);
        }
    }
    widen_add(row, c, &mut acc, K);
}

/// 2^85: inputs below it times a subnormal unit gradient give no quantum.
const TINY_X: f32 = 3.8685626e25;

/// 2^40, the fixed-point scale.
const QUANTA: f32 = fixed::SCALE;

/// Adds the `i32` sums of groups `c / 8 ..` (`k` of them) into `row` as `i64` (columns past
/// the row's end are padding and hold 0) and clears them.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
fn widen_add(row: &mut [i64], c: usize, acc: &mut [std::arch::x86_64::__m256i; 4], k: usize) {
    use std::arch::x86_64::*;
    for (g, a) in acc.iter_mut().enumerate().take(k) {
        let lo = _mm256_cvtepi32_epi64(_mm256_castsi256_si128(*a));
        let hi = _mm256_cvtepi32_epi64(_mm256_extracti128_si256::<1>(*a));
        *a = _mm256_setzero_si256();
        let start = c + 8 * g;
        if start + 8 <= row.len() {
            // SAFETY: 8 sums from `start` lie within `row` (checked above).
            unsafe {
                let d = row.as_mut_ptr().add(start).cast::<__m256i>();
                _mm256_storeu_si256(d, _mm256_add_epi64(_mm256_loadu_si256(d), lo));
                let d = d.add(1);
                _mm256_storeu_si256(d, _mm256_add_epi64(_mm256_loadu_si256(d), hi));
            }
        } else {
            let mut sums = [0i64; 8];
            // SAFETY: `sums` holds 8 i64: the two stores of 4 stay within it.
            unsafe {
                _mm256_storeu_si256(sums.as_mut_ptr().cast(), lo);
                _mm256_storeu_si256(sums.as_mut_ptr().add(4).cast(), hi);
            }
            let len = row.len();
            for (d, v) in row[start.min(len)..].iter_mut().zip(sums) {
                *d = d.wrapping_add(v);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use himap_core::rng::SplitMix;

    /// The batched layers give the integer sums of the row-by-row contributions (each
    /// converted on its own with `to_fixed`), over shapes with tails, zero and inactive units,
    /// huge, subnormal, tie and non-finite values, and more samples than a batch holds.
    #[test]
    fn batched_layers_give_the_row_by_row_sums() {
        let mut rng = SplitMix::new(5);
        for &(fo, fi) in &[
            (32, 32),
            (32, 67),
            (1, 32),
            (3, 32),
            (32, 12),
            (5, 3),
            (7, 41),
        ] {
            for trial in 0..70 {
                let (w_off, b_off) = (3, 3 + fo * fi);
                let len = b_off + fo + 5;
                let mut want = vec![0i64; len];
                let mut grads = vec![vec![0i64; 4], vec![0i64; len]];
                let mut touched = vec![vec![false; 1], vec![false; len.div_ceil(8)]];
                let mut batches = LayerBatches::default();
                let samples = 1 + (rng.unit() * 100.0) as usize;
                for _ in 0..samples {
                    let mut gs = [0.0f32; MAX_WIDTH];
                    let mut xs = [0.0f32; MAX_WIDTH];
                    // Unit gradients at the scales of a step's (most products within the
                    // vector path, runs of samples that fill the `i32` sums) and larger.
                    let scale = [1.0e-4, 1.0e-3, 3.0e-6, 1.0, 2.0e-4][trial % 5];
                    for g in gs.iter_mut().take(fo) {
                        *g = match trial % 7 {
                            // Ties: odd multiples of half a quantum against inputs of 1.
                            6 => (2.0 * (rng.unit() * 50.0).floor() + 1.0) * (2.0f32).powi(-41),
                            _ => pick(&mut rng, trial) * scale,
                        };
                    }
                    for x in xs.iter_mut().take(fi) {
                        *x = match trial % 7 {
                            6 if rng.unit() < 0.5 => 1.0,
                            _ => pick(&mut rng, trial),
                        };
                    }
                    for jj in 0..fo {
                        let g = gs[jj];
                        if g == 0.0 {
                            continue;
                        }
                        want[b_off + jj] = want[b_off + jj].wrapping_add(fixed::to_fixed(g));
                        for i in 0..fi {
                            let w = &mut want[w_off + jj * fi + i];
                            *w = w.wrapping_add(fixed::to_fixed(g * xs[i]));
                        }
                    }
                    let mut dest = Dest {
                        grads: &mut grads,
                        touched: &mut touched,
                        block_shift: 3,
                    };
                    batches.push(&mut dest, 1, w_off, b_off, &gs, fo, &xs, fi);
                }
                let mut dest = Dest {
                    grads: &mut grads,
                    touched: &mut touched,
                    block_shift: 3,
                };
                batches.flush(&mut dest);
                assert_eq!(grads[1], want, "fo {fo} fi {fi} trial {trial}");
                assert!(grads[0].iter().all(|&v| v == 0));
                for (i, &v) in want.iter().enumerate() {
                    if v != 0 {
                        assert!(touched[1][i >> 3], "block of {i} not marked");
                    }
                }
            }
        }
    }

    /// A value of the kinds the conversions must agree on: mostly ordinary ones (some
    /// trials only those, so that the vector path runs), zeros (inactive units), and in
    /// the other trials huge, tiny, tie-making and non-finite ones.
    fn pick(rng: &mut SplitMix, trial: usize) -> f32 {
        let u = rng.unit();
        let v = (rng.unit() - 0.5) * 4.0;
        if u < 0.3 {
            return 0.0;
        }
        if trial.is_multiple_of(2) || u < 0.9 {
            return v;
        }
        match (u * 1000.0) as u32 % 8 {
            0 => f32::NAN,
            1 => f32::INFINITY,
            2 => -3.0e4,
            3 => 1.0e-42,
            4 => 1.5 * (2.0f32).powi(-40),
            5 => 2047.9,
            6 => -f32::MAX,
            _ => 5.0e3,
        }
    }
}
