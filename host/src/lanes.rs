//! The decoders' forward over [`LANES`] samples in the CPU's 8-lane vectors: the host's form of
//! [`himap_core::field::mlp::mlp_forward_lanes`] (which the compiler vectorises across the
//! units instead, transposing every lane in and out). Each lane performs the core's sequence
//! of operations, `bias + w_0 x_0 + w_1 x_1 + ...` in input order with a separate multiply
//! and add (no fused multiply-add), then the same ReLU, so every sample gets its one-sample
//! forward's bits (tested).

#[cfg(test)]
use himap_core::field::mlp::MAX_WIDTH;
use himap_core::field::mlp::{self, MlpLanes, MlpLayout, LANES, MAX_OUT};

/// Whether this CPU has the vector form ([`mlp_forward_lanes`] in AVX); elsewhere (other
/// architectures, x86 without AVX) a ray's samples go one at a time, which is faster than
/// the core's portable lanes.
#[inline(always)]
pub fn fast() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        std::arch::is_x86_feature_detected!("avx")
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        false
    }
}

/// [`mlp::mlp_forward_lanes`] with AVX where the CPU has it, the core's form otherwise.
#[inline(always)]
pub fn mlp_forward_lanes(
    layout: &MlpLayout,
    wt: &[f32],
    lanes: &mut MlpLanes,
    out: &mut [[f32; LANES]; MAX_OUT],
) {
    #[cfg(target_arch = "x86_64")]
    {
        if fast() && wt.len() >= layout.param_count as usize {
            // SAFETY: the CPU supports AVX (`fast`).
            return unsafe { forward_avx(layout, wt, lanes, out) };
        }
    }
    mlp::mlp_forward_lanes(layout, wt, lanes, out)
}

/// The AVX form; the caller checked that `wt` holds the layout's parameters.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx")]
fn forward_avx(
    layout: &MlpLayout,
    wt: &[f32],
    lanes: &mut MlpLanes,
    out: &mut [[f32; LANES]; MAX_OUT],
) {
    use std::arch::x86_64::*;
    let (n_in, hidden, layers, n_out) = layout.dims();
    // `relu` of the core: `x <= 0` (both zeros and negatives) gives +0, NaN passes.
    let relu = |x: __m256| _mm256_andnot_ps(_mm256_cmp_ps::<_CMP_LE_OQ>(x, _mm256_setzero_ps()), x);
    for k in 0..layers {
        let fan_in = if k == 0 { n_in } else { hidden };
        let w_off = layout.weight_offsets[k] as usize;
        let b_off = layout.bias_offsets[k] as usize;
        let (prev, next) = lanes.act.split_at_mut(k + 1);
        let x = &prev[k][..fan_in];
        let dst = &mut next[0][..hidden];
        let mut u = 0;
        while u + 8 <= hidden {
            let acc = units::<8>(wt, w_off, b_off, hidden, u, x);
            for (d, a) in dst[u..u + 8].iter_mut().zip(acc) {
                store(d, relu(a));
            }
            u += 8;
        }
        while u < hidden {
            let [a] = units::<1>(wt, w_off, b_off, hidden, u, x);
            store(&mut dst[u], relu(a));
            u += 1;
        }
    }
    let fan_in = if layers == 0 { n_in } else { hidden };
    let w_off = layout.weight_offsets[layers] as usize;
    let b_off = layout.bias_offsets[layers] as usize;
    let x = &lanes.act[layers][..fan_in];
    *out = [[0.0; LANES]; MAX_OUT];
    match n_out {
        1 => store(&mut out[0], units::<1>(wt, w_off, b_off, 1, 0, x)[0]),
        2 => {
            for (o, a) in out.iter_mut().zip(units::<2>(wt, w_off, b_off, 2, 0, x)) {
                store(o, a);
            }
        }
        3 => {
            for (o, a) in out.iter_mut().zip(units::<3>(wt, w_off, b_off, 3, 0, x)) {
                store(o, a);
            }
        }
        _ => {
            for (o, a) in out
                .iter_mut()
                .zip(units::<MAX_OUT>(wt, w_off, b_off, MAX_OUT, 0, x))
            {
                store(o, a);
            }
        }
    }
}

/// Units `u0..u0 + U` of a layer of `fan_out` units over transposed weights for all lanes:
/// `bias_j + w_0j x_0 + w_1j x_1 + ...` in input order (the caller checked that the weights
/// fit). `U` accumulators of 8 lanes stay in registers.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx")]
#[inline]
fn units<const U: usize>(
    wt: &[f32],
    w_off: usize,
    b_off: usize,
    fan_out: usize,
    u0: usize,
    x: &[[f32; LANES]],
) -> [std::arch::x86_64::__m256; U] {
    use std::arch::x86_64::*;
    let bias = &wt[b_off + u0..b_off + u0 + U];
    let mut acc: [__m256; U] = std::array::from_fn(|j| _mm256_set1_ps(bias[j]));
    let cols = &wt[w_off..w_off + x.len() * fan_out];
    for (col, xi) in cols.chunks_exact(fan_out).zip(x) {
        let w = &col[u0..u0 + U];
        let xv = load(xi);
        for (a, &wj) in acc.iter_mut().zip(w) {
            *a = _mm256_add_ps(*a, _mm256_mul_ps(_mm256_set1_ps(wj), xv));
        }
    }
    acc
}

/// The 8 lanes of `x` as a vector.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx")]
#[inline]
fn load(x: &[f32; LANES]) -> std::arch::x86_64::__m256 {
    // SAFETY: `x` holds 8 f32 (LANES is 8: checked at compile time below).
    unsafe { std::arch::x86_64::_mm256_loadu_ps(x.as_ptr()) }
}

/// Writes the vector `v` to the 8 lanes of `dst`.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx")]
#[inline]
fn store(dst: &mut [f32; LANES], v: std::arch::x86_64::__m256) {
    // SAFETY: `dst` holds 8 f32 (LANES is 8: checked at compile time below).
    unsafe { std::arch::x86_64::_mm256_storeu_ps(dst.as_mut_ptr(), v) }
}

const _: () = assert!(
    LANES == 8,
    "the AVX form holds one sample per f32 lane of a __m256"
);

#[cfg(test)]
mod tests {
    use super::*;
    use himap_core::field::mlp::{mlp_forward, transpose_weights, MlpScratch};
    use himap_core::rng::SplitMix;

    /// Every lane of the host form and of the core's portable form gets the one-sample
    /// forward's bits: outputs and every hidden activation, for the decoders' shapes and odd
    /// ones (no hidden layer, widths not a multiple of 8), with exact zeros, negative zeros,
    /// NaN and infinite inputs among them.
    #[test]
    fn lanes_equal_the_one_sample_forward() {
        type Form = fn(&MlpLayout, &[f32], &mut MlpLanes, &mut [[f32; LANES]; MAX_OUT]);
        for form in [mlp_forward_lanes as Form, mlp::mlp_forward_lanes as Form] {
            lanes_equal_the_one_sample_forward_in(form);
        }
    }

    fn lanes_equal_the_one_sample_forward_in(
        form: fn(&MlpLayout, &[f32], &mut MlpLanes, &mut [[f32; LANES]; MAX_OUT]),
    ) {
        let mut rng = SplitMix::new(21);
        for &(n_in, hidden, layers, n_out) in &[
            (12, 32, 2, 1),
            (67, 32, 2, 3),
            (35, 16, 2, 3),
            (5, 0, 0, 2),
            (9, 7, 3, 4),
            (20, 12, 1, 1),
        ] {
            let l = MlpLayout::new(n_in, hidden, layers, n_out).unwrap();
            let n = l.param_count as usize;
            for trial in 0..20 {
                let params: Vec<f32> = (0..n).map(|_| (rng.unit() - 0.5) * 0.7).collect();
                let mut wt = vec![0.0f32; n];
                transpose_weights(&l, &params, &mut wt).unwrap();
                let mut lanes = MlpLanes::new();
                let mut xs = [[0.0f32; MAX_WIDTH]; LANES];
                for (s, x) in xs.iter_mut().enumerate() {
                    for (i, v) in x.iter_mut().take(n_in as usize).enumerate() {
                        *v = match (s * 7 + i + trial) % 23 {
                            0 => 0.0,
                            1 => -0.0,
                            2 if trial == 3 => f32::NAN,
                            3 if trial == 5 => f32::INFINITY,
                            _ => (rng.unit() - 0.5) * 3.0,
                        };
                        lanes.act[0][i][s] = *v;
                    }
                }
                let mut out = [[7.0f32; LANES]; MAX_OUT];
                form(&l, &wt, &mut lanes, &mut out);
                for (s, x) in xs.iter().enumerate() {
                    let mut sc = MlpScratch::new();
                    let mut o = [0.0f32; MAX_OUT];
                    mlp_forward(&l, &params[..], x, &mut sc, &mut o);
                    for j in 0..MAX_OUT {
                        assert_eq!(
                            o[j].to_bits(),
                            out[j][s].to_bits(),
                            "trial {trial} lane {s}"
                        );
                    }
                    for k in 1..=layers as usize {
                        for j in 0..hidden as usize {
                            assert_eq!(sc.act[k][j].to_bits(), lanes.act[k][j][s].to_bits());
                        }
                    }
                }
            }
        }
    }

    /// Nanoseconds per sample of the decoders' forward, one sample at a time and in the host's
    /// lanes (`cargo test --release -p himap lanes_timing -- --ignored --nocapture`).
    #[test]
    #[ignore = "timing only"]
    fn lanes_timing() {
        let mut rng = SplitMix::new(3);
        for &(n_in, n_out) in &[(67u32, 3u32), (12, 1)] {
            let l = MlpLayout::new(n_in, 32, 2, n_out).unwrap();
            let n = l.param_count as usize;
            let params: Vec<f32> = (0..n).map(|_| (rng.unit() - 0.5) * 0.4).collect();
            let mut wt = vec![0.0f32; n];
            transpose_weights(&l, &params, &mut wt).unwrap();
            let reps = 400_000usize;
            let mut x = [0.0f32; MAX_WIDTH];
            for v in x.iter_mut().take(n_in as usize) {
                *v = rng.unit() - 0.5;
            }
            let mut sc = MlpScratch::new();
            let mut o = [0.0f32; MAX_OUT];
            let mut sum = 0.0f32;
            let t = std::time::Instant::now();
            for r in 0..reps {
                x[0] = r as f32 * 1e-6;
                mlp::mlp_forward_transposed(&l, &wt, &x, &mut sc, &mut o);
                sum += o[0];
            }
            let single = t.elapsed().as_nanos() as f64 / reps as f64;
            let mut lanes = MlpLanes::new();
            for (a, &v) in lanes.act[0].iter_mut().zip(&x[..n_in as usize]) {
                *a = [v; LANES];
            }
            let mut out = [[0.0f32; LANES]; MAX_OUT];
            let t = std::time::Instant::now();
            for r in 0..reps / LANES {
                lanes.act[0][0][0] = r as f32 * 1e-6;
                mlp_forward_lanes(&l, &wt, &mut lanes, &mut out);
                sum += out[0][0];
            }
            let lane = t.elapsed().as_nanos() as f64 / reps as f64;
            println!(
                "{n_in}-32-32-{n_out}: {single:.1} ns per sample alone, {lane:.1} in lanes ({sum})"
            );
        }
    }
}
