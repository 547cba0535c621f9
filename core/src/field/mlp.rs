//! Tiny fully connected ReLU networks (the geometry and appearance decoders) with hand-written
//! forward and backward passes that run unchanged on the CPU and, through `himap-shaders`, on
//! the GPU.
//!
//! # Parameter layout
//!
//! A network with `hidden_layers = L` has `L + 1` linear layers: `L` hidden layers of `hidden`
//! units with ReLU, then a linear output layer of `n_out` units (no activation). Layer `k`
//! (`k = 0..=L`, the output layer is `k = L`) has `fan_in(k)` inputs (`n_in` for `k = 0`,
//! `hidden` otherwise) and `fan_out(k)` outputs (`hidden` for `k < L`, `n_out` for `k = L`).
//! In one flat `f32` buffer, layer after layer:
//!
//! ```text
//! weights of layer k: row-major [fan_out][fan_in] at weight_offsets[k]
//!                     (W[j][i] at weight_offsets[k] + j * fan_in + i)
//! biases  of layer k: [fan_out]                   at bias_offsets[k] = weight_offsets[k] + fan_out * fan_in
//! layer k + 1 starts right after the biases of layer k
//! ```
//!
//! so e.g. 12 -> 32 -> 32 -> 1 uses 12*32 + 32 + 32*32 + 32 + 32*1 + 1 = 1505 parameters.
//! Entries of `weight_offsets`/`bias_offsets` past the output layer are `param_count`.
//! `hidden_layers = 0` is a linear model `n_in -> n_out` (`hidden` is then unused).
//!
//! # Determinism
//!
//! Every dot product is a plain sequential loop in a fixed order (`acc = bias; acc += w * x`
//! for inputs `0, 1, ...`, each step a separately rounded multiply and add), so CPU and GPU round identically. The backward makes exactly
//! one [`GradSink::add`] call per parameter (zero contributions included), so the number and
//! order of contributions never depend on the data. The ReLU derivative at exactly 0 is 0.
//!
//! Kernels never panic for a layout built by [`MlpLayout::new`]: every width is clamped to the
//! fixed capacities ([`MAX_WIDTH`], [`MAX_OUT`], [`MAX_HIDDEN_LAYERS`]) before it is used as an
//! array bound. The parameter buffer must hold at least `param_count` values.

use crate::{math, Error, GradSink, ParamRead};

/// Largest number of inputs and of hidden units a network may have.
pub const MAX_WIDTH: usize = 128;
/// Largest number of outputs.
pub const MAX_OUT: usize = 4;
/// Largest number of hidden layers.
pub const MAX_HIDDEN_LAYERS: usize = 4;

/// Shape of a network and where each layer's weights and biases live in the flat parameter
/// buffer (see the module documentation for the layout).
#[derive(Clone, Copy, Debug, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct MlpLayout {
    /// Number of inputs (1..=[`MAX_WIDTH`]).
    pub n_in: u32,
    /// Units per hidden layer (1..=[`MAX_WIDTH`]; unused when `hidden_layers == 0`).
    pub hidden: u32,
    /// Number of hidden ReLU layers (0..=[`MAX_HIDDEN_LAYERS`]; 0 is a linear model).
    pub hidden_layers: u32,
    /// Number of outputs (1..=[`MAX_OUT`]).
    pub n_out: u32,
    /// Offset of each layer's row-major `[fan_out][fan_in]` weight matrix; index
    /// `hidden_layers` is the output layer, later entries are `param_count`.
    pub weight_offsets: [u32; MAX_HIDDEN_LAYERS + 1],
    /// Offset of each layer's `[fan_out]` bias vector; same indexing as `weight_offsets`.
    pub bias_offsets: [u32; MAX_HIDDEN_LAYERS + 1],
    /// Total number of parameters.
    pub param_count: u32,
}

impl MlpLayout {
    /// `(n_in, hidden, hidden_layers, n_out)` clamped to the fixed capacities, as every kernel
    /// reads them (an invalid hand-made layout never indexes out of range).
    #[inline(always)]
    pub fn dims(&self) -> (usize, usize, usize, usize) {
        clamped_dims(self)
    }

    /// Builds the layout of an `n_in -> hidden x hidden_layers -> n_out` network.
    ///
    /// Errors: [`Error::InvalidConfig`] for a zero `n_in`, `n_out`, or `hidden` (when
    /// `hidden_layers > 0`); [`Error::Capacity`] when `n_in` or `hidden` exceeds
    /// [`MAX_WIDTH`], `n_out` exceeds [`MAX_OUT`] or `hidden_layers` exceeds
    /// [`MAX_HIDDEN_LAYERS`].
    pub fn new(n_in: u32, hidden: u32, hidden_layers: u32, n_out: u32) -> Result<Self, Error> {
        if n_in == 0 {
            return Err(Error::InvalidConfig("mlp: n_in must be at least 1"));
        }
        if n_out == 0 {
            return Err(Error::InvalidConfig("mlp: n_out must be at least 1"));
        }
        if hidden_layers > 0 && hidden == 0 {
            return Err(Error::InvalidConfig(
                "mlp: hidden must be at least 1 when hidden_layers > 0",
            ));
        }
        if n_in as usize > MAX_WIDTH {
            return Err(Error::Capacity {
                what: "mlp inputs",
                needed: n_in as u64,
                capacity: MAX_WIDTH as u64,
            });
        }
        if hidden_layers > 0 && hidden as usize > MAX_WIDTH {
            return Err(Error::Capacity {
                what: "mlp hidden units",
                needed: hidden as u64,
                capacity: MAX_WIDTH as u64,
            });
        }
        if n_out as usize > MAX_OUT {
            return Err(Error::Capacity {
                what: "mlp outputs",
                needed: n_out as u64,
                capacity: MAX_OUT as u64,
            });
        }
        if hidden_layers as usize > MAX_HIDDEN_LAYERS {
            return Err(Error::Capacity {
                what: "mlp hidden layers",
                needed: hidden_layers as u64,
                capacity: MAX_HIDDEN_LAYERS as u64,
            });
        }
        // All sizes are <= 128, so the total (<= 128*129*5) fits u32 easily.
        let mut weight_offsets = [0u32; MAX_HIDDEN_LAYERS + 1];
        let mut bias_offsets = [0u32; MAX_HIDDEN_LAYERS + 1];
        let mut off = 0u32;
        let mut k = 0u32;
        while k <= hidden_layers {
            let fan_in = if k == 0 { n_in } else { hidden };
            let fan_out = if k == hidden_layers { n_out } else { hidden };
            weight_offsets[k as usize] = off;
            off += fan_in * fan_out;
            bias_offsets[k as usize] = off;
            off += fan_out;
            k += 1;
        }
        let mut k = hidden_layers as usize + 1;
        while k <= MAX_HIDDEN_LAYERS {
            weight_offsets[k] = off;
            bias_offsets[k] = off;
            k += 1;
        }
        Ok(Self {
            n_in,
            hidden,
            hidden_layers,
            n_out,
            weight_offsets,
            bias_offsets,
            param_count: off,
        })
    }

    /// Number of inputs of layer `k` (`k == hidden_layers` is the output layer).
    #[inline]
    pub fn fan_in(&self, k: u32) -> u32 {
        if k == 0 {
            self.n_in
        } else {
            self.hidden
        }
    }

    /// Number of outputs of layer `k` (`k == hidden_layers` is the output layer).
    #[inline]
    pub fn fan_out(&self, k: u32) -> u32 {
        if k >= self.hidden_layers {
            self.n_out
        } else {
            self.hidden
        }
    }
}

/// Widths clamped to the fixed capacities, so array indices can never go out of range even for
/// a hand-made (invalid) layout.
#[inline(always)]
fn clamped_dims(layout: &MlpLayout) -> (usize, usize, usize, usize) {
    let n_in = clamp_usize(layout.n_in as usize, MAX_WIDTH);
    let hidden = clamp_usize(layout.hidden as usize, MAX_WIDTH);
    let layers = clamp_usize(layout.hidden_layers as usize, MAX_HIDDEN_LAYERS);
    let n_out = clamp_usize(layout.n_out as usize, MAX_OUT);
    (n_in, hidden, layers, n_out)
}

#[inline(always)]
fn clamp_usize(x: usize, hi: usize) -> usize {
    if x > hi {
        hi
    } else {
        x
    }
}

/// Activations of one forward pass, kept for the backward pass: `act[0]` is a copy of the
/// input, `act[k]` (`k = 1..=hidden_layers`) the post-ReLU output of hidden layer `k`.
/// Entries past each layer's width are unspecified.
#[derive(Clone, Debug)]
pub struct MlpScratch {
    /// `act[0]`: input copy; `act[k]`: output of hidden layer `k` after the ReLU.
    pub act: [[f32; MAX_WIDTH]; MAX_HIDDEN_LAYERS + 1],
}

impl MlpScratch {
    /// All-zero scratch.
    pub const fn new() -> Self {
        Self {
            act: [[0.0; MAX_WIDTH]; MAX_HIDDEN_LAYERS + 1],
        }
    }
}

impl Default for MlpScratch {
    fn default() -> Self {
        Self::new()
    }
}

/// PyTorch's default `nn.Linear` initialisation: every weight and bias of layer `k` is drawn
/// from `U(-1/sqrt(fan_in(k)), 1/sqrt(fan_in(k)))`; parameter `i` uses
/// `crate::rng::uniform(seed, 1, i)` (so the values do not depend on the order of filling).
///
/// Errors: [`Error::Shape`] unless `params.len() == layout.param_count`.
pub fn mlp_init(layout: &MlpLayout, params: &mut [f32], seed: u32) -> Result<(), Error> {
    crate::error::check_len("mlp params", params.len(), layout.param_count as usize)?;
    let (_, _, layers, _) = clamped_dims(layout);
    let mut k = 0usize;
    while k <= layers {
        let start = layout.weight_offsets[k] as usize;
        // Layer k's weights and biases are contiguous and end where layer k + 1 starts.
        let end = if k < layers {
            layout.weight_offsets[k + 1] as usize
        } else {
            layout.param_count as usize
        };
        let bound = math::div(1.0, math::sqrt(layout.fan_in(k as u32) as f32));
        let mut i = start;
        while i < end && i < params.len() {
            let u = crate::rng::uniform(seed, 1, i as u32);
            params[i] = (2.0 * u - 1.0) * bound;
            i += 1;
        }
        k += 1;
    }
    Ok(())
}

/// Forward pass: `out[0..n_out]` receives the network output, `out[n_out..]` is set to 0.
/// Reads `input[0..n_in]` and records the activations in `scratch` for [`mlp_backward`].
pub fn mlp_forward<P: ParamRead + ?Sized>(
    layout: &MlpLayout,
    params: &P,
    input: &[f32; MAX_WIDTH],
    scratch: &mut MlpScratch,
    out: &mut [f32; MAX_OUT],
) {
    let (n_in, hidden, layers, n_out) = clamped_dims(layout);
    let mut i = 0;
    while i < n_in {
        scratch.act[0][i] = input[i];
        i += 1;
    }
    // Hidden layers: act[k + 1] = relu(W_k act[k] + b_k).
    let mut k = 0usize;
    while k < layers {
        let fan_in = if k == 0 { n_in } else { hidden };
        let w_off = layout.weight_offsets[k] as usize;
        let b_off = layout.bias_offsets[k] as usize;
        let mut j = 0;
        while j < hidden {
            let row = w_off + j * fan_in;
            let mut acc = params.at(b_off + j);
            let mut i = 0;
            while i < fan_in {
                acc += params.at(row + i) * scratch.act[k][i];
                i += 1;
            }
            scratch.act[k + 1][j] = relu(acc);
            j += 1;
        }
        k += 1;
    }
    // Output layer (linear).
    let fan_in = if layers == 0 { n_in } else { hidden };
    let w_off = layout.weight_offsets[layers] as usize;
    let b_off = layout.bias_offsets[layers] as usize;
    let mut o = 0;
    while o < MAX_OUT {
        if o < n_out {
            let row = w_off + o * fan_in;
            let mut acc = params.at(b_off + o);
            let mut i = 0;
            while i < fan_in {
                acc += params.at(row + i) * scratch.act[layers][i];
                i += 1;
            }
            out[o] = acc;
        } else {
            out[o] = 0.0;
        }
        o += 1;
    }
}

/// Writes the parameters of `params` with every layer's weight matrix transposed (`[in][out]`
/// instead of `[out][in]`; biases unchanged, at the same offsets) into `out`, for
/// [`mlp_forward_transposed`]. Errors: [`Error::Shape`] unless both hold `param_count` values.
pub fn transpose_weights(layout: &MlpLayout, params: &[f32], out: &mut [f32]) -> Result<(), Error> {
    let n = layout.param_count as usize;
    crate::error::check_len("mlp params", params.len(), n)?;
    crate::error::check_len("mlp transposed params", out.len(), n)?;
    out.copy_from_slice(params);
    let (n_in, hidden, layers, n_out) = clamped_dims(layout);
    let mut k = 0usize;
    while k <= layers {
        let fan_in = if k == 0 { n_in } else { hidden };
        let fan_out = if k == layers { n_out } else { hidden };
        let w = layout.weight_offsets[k] as usize;
        let mut j = 0;
        while j < fan_out {
            let mut i = 0;
            while i < fan_in {
                out[w + i * fan_out + j] = params[w + j * fan_in + i];
                i += 1;
            }
            j += 1;
        }
        k += 1;
    }
    Ok(())
}

/// [`mlp_forward`] from weights laid out by [`transpose_weights`], computing all units of a
/// layer together (input by input), which a CPU runs in SIMD lanes. Every unit still sums
/// `bias + w_0 x_0 + w_1 x_1 + ...` in input order, the operations of [`mlp_forward`], so the
/// outputs and activations are the same bits (tested). Host-side: the GPU runs
/// [`mlp_forward`].
#[inline]
pub fn mlp_forward_transposed(
    layout: &MlpLayout,
    wt: &[f32],
    input: &[f32; MAX_WIDTH],
    scratch: &mut MlpScratch,
    out: &mut [f32; MAX_OUT],
) {
    let (n_in, hidden, layers, n_out) = clamped_dims(layout);
    if wt.len() < layout.param_count as usize {
        // A wrong buffer: fall back to the plain order rather than index out of bounds.
        return mlp_forward(layout, wt, input, scratch, out);
    }
    scratch.act[0][..n_in].copy_from_slice(&input[..n_in]);
    // Hidden layers: each writes its ReLU'd units straight into the next activation row (no
    // accumulator array to clear and copy per layer: the stores it cost sat on the path).
    let mut k = 0usize;
    while k < layers {
        let fan_in = if k == 0 { n_in } else { hidden };
        let w_off = layout.weight_offsets[k] as usize;
        let b_off = layout.bias_offsets[k] as usize;
        let (prev, next) = scratch.act.split_at_mut(k + 1);
        // The first layer reads the caller's input (the same values as `act[0]`).
        let x = if k == 0 {
            &input[..fan_in]
        } else {
            &prev[k][..fan_in]
        };
        let dst = &mut next[0][..hidden];
        if hidden == 32 {
            // Fixed-size accumulators the compiler keeps in registers (the decoders' width).
            let a = layer_transposed::<32>(wt, w_off, b_off, x);
            for (d, v) in dst.iter_mut().zip(a) {
                *d = relu(v);
            }
        } else {
            dst.copy_from_slice(&wt[b_off..b_off + hidden]);
            for (i, &xi) in x.iter().enumerate() {
                let col = &wt[w_off + i * hidden..w_off + (i + 1) * hidden];
                for (a, &w) in dst.iter_mut().zip(col) {
                    *a += w * xi;
                }
            }
            for d in dst.iter_mut() {
                *d = relu(*d);
            }
        }
        k += 1;
    }
    // Output layer (linear), its few units in registers.
    let fan_in = if layers == 0 { n_in } else { hidden };
    let w_off = layout.weight_offsets[layers] as usize;
    let b_off = layout.bias_offsets[layers] as usize;
    let x = if layers == 0 {
        &input[..fan_in]
    } else {
        &scratch.act[layers][..fan_in]
    };
    let mut acc = [0.0f32; MAX_OUT];
    match n_out {
        1 => acc[0] = layer_transposed::<1>(wt, w_off, b_off, x)[0],
        3 => acc[..3].copy_from_slice(&layer_transposed::<3>(wt, w_off, b_off, x)),
        4 => acc = layer_transposed::<4>(wt, w_off, b_off, x),
        _ => {
            acc[..n_out].copy_from_slice(&wt[b_off..b_off + n_out]);
            for (i, &xi) in x.iter().enumerate() {
                let col = &wt[w_off + i * n_out..w_off + (i + 1) * n_out];
                for (a, &w) in acc[..n_out].iter_mut().zip(col) {
                    *a += w * xi;
                }
            }
        }
    }
    *out = acc;
}

/// Samples [`mlp_forward_lanes`] evaluates together, one per SIMD lane.
pub const LANES: usize = 8;

/// The activations of [`LANES`] samples side by side for [`mlp_forward_lanes`]: `act[k][j][l]`
/// is unit `j` of layer `k` (`act[0]`: the input) of sample `l`. Host-side (20 KB).
#[derive(Clone)]
pub struct MlpLanes {
    /// `act[0]`: the inputs; `act[k]`: the output of hidden layer `k` after the ReLU.
    pub act: [[[f32; LANES]; MAX_WIDTH]; MAX_HIDDEN_LAYERS + 1],
}

impl MlpLanes {
    /// All-zero lanes.
    pub const fn new() -> Self {
        Self {
            act: [[[0.0; LANES]; MAX_WIDTH]; MAX_HIDDEN_LAYERS + 1],
        }
    }
}

impl Default for MlpLanes {
    fn default() -> Self {
        Self::new()
    }
}

/// [`mlp_forward_transposed`] of [`LANES`] samples at once, sample `l` in lane `l`: the inputs
/// in `lanes.act[0][..n_in]`, the hidden activations written to `lanes.act[1..]`, output `o`
/// of sample `l` to `out[o][l]` (outputs past `n_out` 0). Every lane performs a unit's sum
/// `bias + w_0 x_0 + w_1 x_1 + ...` in input order, the operations of [`mlp_forward`], so each
/// sample gets its own forward's bits (tested by the host's `lanes` tests and the rays' test in
/// `model`); the lanes only make the units' chains of adds
/// independent (one sample's output unit is a chain of `hidden` dependent adds). Host-side.
#[inline]
pub fn mlp_forward_lanes(
    layout: &MlpLayout,
    wt: &[f32],
    lanes: &mut MlpLanes,
    out: &mut [[f32; LANES]; MAX_OUT],
) {
    let (n_in, hidden, layers, n_out) = clamped_dims(layout);
    if wt.len() < layout.param_count as usize {
        // A wrong buffer: sample by sample in the plain order rather than out of bounds.
        let mut scratch = MlpScratch::new();
        let mut x = [0.0f32; MAX_WIDTH];
        for l in 0..LANES {
            for (xi, a) in x[..n_in].iter_mut().zip(&lanes.act[0][..n_in]) {
                *xi = a[l];
            }
            let mut o = [0.0f32; MAX_OUT];
            mlp_forward(layout, wt, &x, &mut scratch, &mut o);
            for k in 1..=layers {
                for (a, &v) in lanes.act[k][..hidden].iter_mut().zip(&scratch.act[k]) {
                    a[l] = v;
                }
            }
            for (dst, v) in out.iter_mut().zip(o) {
                dst[l] = v;
            }
        }
        return;
    }
    let mut k = 0usize;
    while k < layers {
        let fan_in = if k == 0 { n_in } else { hidden };
        let w_off = layout.weight_offsets[k] as usize;
        let b_off = layout.bias_offsets[k] as usize;
        let (prev, next) = lanes.act.split_at_mut(k + 1);
        let x = &prev[k][..fan_in];
        let dst = &mut next[0][..hidden];
        let mut u = 0;
        // Blocks of 8 units: 8 accumulators of LANES lanes stay in registers.
        while u + 8 <= hidden {
            let a = units_lanes::<8>(wt, w_off, b_off, hidden, u, x);
            for (d, a) in dst[u..u + 8].iter_mut().zip(a) {
                *d = a.map(relu);
            }
            u += 8;
        }
        while u < hidden {
            let a = units_lanes::<1>(wt, w_off, b_off, hidden, u, x);
            dst[u] = a[0].map(relu);
            u += 1;
        }
        k += 1;
    }
    let fan_in = if layers == 0 { n_in } else { hidden };
    let w_off = layout.weight_offsets[layers] as usize;
    let b_off = layout.bias_offsets[layers] as usize;
    let x = &lanes.act[layers][..fan_in];
    *out = [[0.0; LANES]; MAX_OUT];
    match n_out {
        1 => out[0] = units_lanes::<1>(wt, w_off, b_off, 1, 0, x)[0],
        2 => out[..2].copy_from_slice(&units_lanes::<2>(wt, w_off, b_off, 2, 0, x)),
        3 => out[..3].copy_from_slice(&units_lanes::<3>(wt, w_off, b_off, 3, 0, x)),
        _ => *out = units_lanes::<MAX_OUT>(wt, w_off, b_off, MAX_OUT, 0, x),
    }
}

/// Units `u0..u0 + U` of a layer of `fan_out` units over transposed weights, for every lane:
/// `bias_j + w_0j x_0 + w_1j x_1 + ...` in input order (the caller checked that the weights
/// fit).
#[inline(always)]
fn units_lanes<const U: usize>(
    wt: &[f32],
    w_off: usize,
    b_off: usize,
    fan_out: usize,
    u0: usize,
    x: &[[f32; LANES]],
) -> [[f32; LANES]; U] {
    let mut acc = [[0.0f32; LANES]; U];
    for (a, &b) in acc.iter_mut().zip(&wt[b_off + u0..b_off + u0 + U]) {
        *a = [b; LANES];
    }
    let cols = &wt[w_off..w_off + x.len() * fan_out];
    for (col, xi) in cols.chunks_exact(fan_out).zip(x) {
        let w: &[f32; U] = match col[u0..].first_chunk() {
            Some(w) => w,
            None => return acc,
        };
        for (a, &wj) in acc.iter_mut().zip(w) {
            for (al, &xl) in a.iter_mut().zip(xi) {
                *al += wj * xl;
            }
        }
    }
    acc
}

/// One layer of `N` units over transposed weights: `bias_j + w_0j x_0 + w_1j x_1 + ...` in
/// input order for every unit `j` (the caller checked that the weights fit).
#[inline(always)]
fn layer_transposed<const N: usize>(wt: &[f32], w_off: usize, b_off: usize, x: &[f32]) -> [f32; N] {
    let mut acc = [0.0f32; N];
    acc.copy_from_slice(&wt[b_off..b_off + N]);
    let cols = &wt[w_off..w_off + x.len() * N];
    for (col, &xi) in cols.as_chunks::<N>().0.iter().zip(x) {
        for (a, &w) in acc.iter_mut().zip(col) {
            *a += w * xi;
        }
    }
    acc
}

/// ReLU that maps negative numbers and both zeros to `+0.0` and propagates NaN (like
/// `torch.relu`).
#[inline(always)]
fn relu(x: f32) -> f32 {
    if x <= 0.0 {
        0.0
    } else {
        x
    }
}

/// Backward pass. `scratch` must hold the activations of the [`mlp_forward`] call with the same
/// `layout`, `params` and input. Given `d_out[0..n_out]` (the loss gradient with respect to the
/// outputs), sends `dL/dparam` for every parameter to `sink` (one contribution per parameter,
/// with its index in the MLP's buffer, through `add` and `add_scaled`; the rows of units whose
/// gradient is exactly zero are skipped, their contributions being 0) and writes `dL/dinput` to `d_input[0..n_in]`
/// (`d_input[n_in..]` is set to 0).
pub fn mlp_backward<P: ParamRead + ?Sized, S: GradSink>(
    layout: &MlpLayout,
    params: &P,
    scratch: &MlpScratch,
    d_out: &[f32; MAX_OUT],
    d_input: &mut [f32; MAX_WIDTH],
    sink: &mut S,
) {
    let (n_in, hidden, layers, n_out) = clamped_dims(layout);
    // `delta` holds dL/d(output of the current layer); for the output layer it is d_out.
    let mut delta = [0.0f32; MAX_WIDTH];
    let mut o = 0;
    while o < n_out {
        delta[o] = d_out[o];
        o += 1;
    }
    let mut fan_out = n_out;
    // Walk the layers from the output layer (k = layers) down to the first (k = 0).
    let mut kk = 0usize;
    while kk <= layers {
        let k = layers - kk;
        let fan_in = if k == 0 { n_in } else { hidden };
        let w_off = layout.weight_offsets[k] as usize;
        let b_off = layout.bias_offsets[k] as usize;
        // Gradient with respect to this layer's pre-activation: the ReLU of hidden layers
        // passes it where the activation is strictly positive (derivative 0 at exactly 0).
        let mut j = 0;
        while j < fan_out {
            if k < layers {
                let active = scratch.act[k + 1][j] > 0.0;
                if !active {
                    delta[j] = 0.0;
                }
            }
            j += 1;
        }
        // Parameter gradients and the gradient with respect to this layer's input.
        // A zero `g` (an inactive ReLU) contributes exactly 0 to every parameter of its row
        // (`to_fixed` of +-0 and of NaN is 0), so its sink calls are skipped, and nothing to
        // `d_prev`: with finite weights its row would add products `w * (+-0) = +-0`, and
        // `x + (+-0)` is `x` for every `x` but `-0`, which `d_prev` never holds (it starts at
        // `+0`, and a round-to-nearest sum is `-0` only when both terms are). The other rows
        // add in row order.
        // A sink that takes whole layers gets this layer's contributions in one call (the
        // same ones: see `GradSink::add_layer`).
        if S::LAYERS {
            sink.add_layer(w_off, b_off, &delta, fan_out, &scratch.act[k], fan_in);
        }
        let mut d_prev = [0.0f32; MAX_WIDTH];
        let mut j = 0;
        while j < fan_out {
            let g = delta[j];
            let row = w_off + j * fan_in;
            if g != 0.0 {
                if !S::LAYERS {
                    sink.add(b_off + j, g);
                    sink.add_scaled(row, g, &scratch.act[k], fan_in);
                }
                params.axpy(row, g, &mut d_prev, fan_in);
            }
            j += 1;
        }
        delta = d_prev;
        fan_out = fan_in;
        kk += 1;
    }
    copy_prefix(d_input, &delta, n_in);
}

/// `dst[..n]` from `src[..n]` and the rest of `dst` 0 (`n` at most [`MAX_WIDTH`]): slice
/// copies on the CPU, the element loop in the shaders (the same values).
#[inline(always)]
pub(crate) fn copy_prefix(dst: &mut [f32; MAX_WIDTH], src: &[f32; MAX_WIDTH], n: usize) {
    #[cfg(not(target_arch = "spirv"))]
    {
        let n = n.min(MAX_WIDTH);
        dst[..n].copy_from_slice(&src[..n]);
        dst[n..].fill(0.0);
    }
    #[cfg(target_arch = "spirv")]
    {
        let mut i = 0;
        while i < MAX_WIDTH {
            dst[i] = if i < n { src[i] } else { 0.0 };
            i += 1;
        }
    }
}

#[cfg(test)]
#[allow(clippy::disallowed_methods)] // std's functions as test oracles
mod tests {
    use super::*;
    use crate::{F32Sink, NullSink};

    /// The transposed-weight forward gives the plain forward's bits: outputs and every
    /// activation, for several shapes (incl. no hidden layer) and random weights and inputs.
    #[test]
    fn transposed_forward_is_bit_identical() {
        let mut rng = crate::rng::SplitMix::new(11);
        for &(n_in, hidden, layers, n_out) in &[
            (12, 32, 2, 1),
            (67, 32, 2, 3),
            (35, 16, 2, 3),
            (5, 0, 0, 2),
            (9, 7, 3, 4),
        ] {
            let l = MlpLayout::new(n_in, hidden, layers, n_out).unwrap();
            let n = l.param_count as usize;
            for trial in 0..50 {
                let params: std::vec::Vec<f32> = (0..n).map(|_| (rng.unit() - 0.5) * 0.7).collect();
                let mut wt = std::vec![0.0f32; n];
                transpose_weights(&l, &params, &mut wt).unwrap();
                let mut x = [0.0f32; MAX_WIDTH];
                for v in x.iter_mut().take(n_in as usize) {
                    *v = (rng.unit() - 0.5) * 3.0;
                }
                let (mut s1, mut s2) = (MlpScratch::new(), MlpScratch::new());
                let (mut o1, mut o2) = ([0.0f32; MAX_OUT], [1.0f32; MAX_OUT]);
                mlp_forward(&l, &params[..], &x, &mut s1, &mut o1);
                mlp_forward_transposed(&l, &wt, &x, &mut s2, &mut o2);
                assert_eq!(o1.map(f32::to_bits), o2.map(f32::to_bits), "trial {trial}");
                for k in 0..=layers as usize {
                    let w = if k == 0 { n_in } else { hidden } as usize;
                    for i in 0..w {
                        assert_eq!(s1.act[k][i].to_bits(), s2.act[k][i].to_bits());
                    }
                }
            }
        }
    }

    #[test]
    fn offsets_are_exact() {
        // 12 -> 32 -> 32 -> 1: W0 12*32 = 384 at 0, b0 32 at 384; W1 32*32 = 1024 at 416,
        // b1 at 1440; W2 32 at 1472, b2 1 at 1504; total 1505.
        let l = MlpLayout::new(12, 32, 2, 1).unwrap();
        assert_eq!(l.weight_offsets, [0, 416, 1472, 1505, 1505]);
        assert_eq!(l.bias_offsets, [384, 1440, 1504, 1505, 1505]);
        assert_eq!(l.param_count, 12 * 32 + 32 + 32 * 32 + 32 + 32 + 1);
        assert_eq!(l.param_count, 1505);
        // 67 -> 32 -> 32 -> 3: W0 2144 at 0, b0 at 2144; W1 at 2176, b1 at 3200; W2 96 at 3232,
        // b2 at 3328; total 3331.
        let l = MlpLayout::new(67, 32, 2, 3).unwrap();
        assert_eq!(l.weight_offsets, [0, 2176, 3232, 3331, 3331]);
        assert_eq!(l.bias_offsets, [2144, 3200, 3328, 3331, 3331]);
        assert_eq!(l.param_count, 3331);
        // Linear model 5 -> 2: W 10 at 0, b 2 at 10.
        let l = MlpLayout::new(5, 0, 0, 2).unwrap();
        assert_eq!(l.weight_offsets, [0, 12, 12, 12, 12]);
        assert_eq!(l.bias_offsets, [10, 12, 12, 12, 12]);
        assert_eq!(l.param_count, 12);
        // Largest: 128 -> 128 x4 -> 4.
        let l = MlpLayout::new(128, 128, 4, 4).unwrap();
        assert_eq!(
            l.param_count,
            128 * 128 + 128 + 3 * (128 * 128 + 128) + 128 * 4 + 4
        );
        assert_eq!(l.fan_in(0), 128);
        assert_eq!(l.fan_out(4), 4);
    }

    #[test]
    fn layout_errors_are_values() {
        assert!(matches!(
            MlpLayout::new(0, 32, 2, 1),
            Err(Error::InvalidConfig(_))
        ));
        assert!(matches!(
            MlpLayout::new(3, 32, 2, 0),
            Err(Error::InvalidConfig(_))
        ));
        assert!(matches!(
            MlpLayout::new(3, 0, 1, 1),
            Err(Error::InvalidConfig(_))
        ));
        assert_eq!(
            MlpLayout::new(129, 32, 2, 1),
            Err(Error::Capacity {
                what: "mlp inputs",
                needed: 129,
                capacity: 128
            })
        );
        assert_eq!(
            MlpLayout::new(3, 129, 2, 1),
            Err(Error::Capacity {
                what: "mlp hidden units",
                needed: 129,
                capacity: 128
            })
        );
        assert_eq!(
            MlpLayout::new(3, 32, 2, 5),
            Err(Error::Capacity {
                what: "mlp outputs",
                needed: 5,
                capacity: 4
            })
        );
        assert_eq!(
            MlpLayout::new(3, 32, 5, 1),
            Err(Error::Capacity {
                what: "mlp hidden layers",
                needed: 5,
                capacity: 4
            })
        );
        let l = MlpLayout::new(3, 4, 1, 1).unwrap();
        let mut p = vec![0.0f32; l.param_count as usize + 1];
        assert_eq!(
            mlp_init(&l, &mut p, 1),
            Err(Error::Shape {
                what: "mlp params",
                expected: l.param_count as u64,
                got: l.param_count as u64 + 1
            })
        );
    }

    /// 2 -> 2 -> 1 by hand.
    /// W1 = [[1, -1], [0.5, 2]], b1 = [0.5, -1], W2 = [[2, -3]], b2 = [0.25], x = [1, 2]:
    /// pre1 = [1 - 2 + 0.5, 0.5 + 4 - 1] = [-0.5, 3.5] -> relu [0, 3.5];
    /// out = 0.25 + 2*0 - 3*3.5 = -10.25.
    /// Backward with dL/dout = 1: db2 = 1, dW2 = [0, 3.5]; dh = [2, -3] masked by relu' [0, 1]
    /// = [0, -3]; db1 = [0, -3], dW1 = [[0, 0], [-3, -6]]; dx = W1^T [0, -3] = [-1.5, -6].
    #[test]
    fn golden_2_2_1() {
        let l = MlpLayout::new(2, 2, 1, 1).unwrap();
        assert_eq!(l.weight_offsets[..2], [0, 6]);
        assert_eq!(l.bias_offsets[..2], [4, 8]);
        let p: [f32; 9] = [1.0, -1.0, 0.5, 2.0, 0.5, -1.0, 2.0, -3.0, 0.25];
        let mut x = [0.0f32; MAX_WIDTH];
        x[0] = 1.0;
        x[1] = 2.0;
        x[2] = 99.0; // past n_in: must be ignored
        let mut s = MlpScratch::new();
        let mut out = [7.0f32; MAX_OUT];
        mlp_forward(&l, &p[..], &x, &mut s, &mut out);
        assert_eq!(out, [-10.25, 0.0, 0.0, 0.0]);
        assert_eq!(s.act[1][..2], [0.0, 3.5]);

        let mut g = [0.0f32; 9];
        let mut dx = [5.0f32; MAX_WIDTH];
        let mut d_out = [0.0f32; MAX_OUT];
        d_out[0] = 1.0;
        d_out[1] = 100.0; // past n_out: must be ignored
        mlp_backward(
            &l,
            &p[..],
            &s,
            &d_out,
            &mut dx,
            &mut F32Sink { acc: &mut g },
        );
        assert_eq!(g, [0.0, 0.0, -3.0, -6.0, 0.0, -3.0, 0.0, 3.5, 1.0]);
        assert_eq!(dx[..3], [-1.5, -6.0, 0.0]);
        assert!(dx[3..].iter().all(|&v| v == 0.0));
    }

    /// Linear model 2 -> 2: out = b + W x with W = [[1, 2], [3, 4]], b = [0.5, -0.5],
    /// x = [1, -1]: out = [0.5 + 1 - 2, -0.5 + 3 - 4] = [-0.5, -1.5].
    #[test]
    fn golden_linear() {
        let l = MlpLayout::new(2, 0, 0, 2).unwrap();
        let p: [f32; 6] = [1.0, 2.0, 3.0, 4.0, 0.5, -0.5];
        let mut x = [0.0f32; MAX_WIDTH];
        x[0] = 1.0;
        x[1] = -1.0;
        let mut s = MlpScratch::new();
        let mut out = [0.0f32; MAX_OUT];
        mlp_forward(&l, &p[..], &x, &mut s, &mut out);
        assert_eq!(out[..2], [-0.5, -1.5]);
        // d_out = [1, 2]: dW = [[1, -1], [2, -2]], db = [1, 2], dx = W^T d = [7, 10].
        let mut g = [0.0f32; 6];
        let mut dx = [0.0f32; MAX_WIDTH];
        let d_out = [1.0, 2.0, 0.0, 0.0];
        mlp_backward(
            &l,
            &p[..],
            &s,
            &d_out,
            &mut dx,
            &mut F32Sink { acc: &mut g },
        );
        assert_eq!(g, [1.0, -1.0, 2.0, -2.0, 1.0, 2.0]);
        assert_eq!(dx[..2], [7.0, 10.0]);
    }

    /// Skipping the input-gradient rows of inactive units gives the bits of adding every row:
    /// the input gradient equals a plain all-rows computation on random decoders with many
    /// inactive units (and zero output gradients).
    #[test]
    fn input_gradient_equals_all_rows() {
        let layout = MlpLayout::new(12, 32, 2, 3).unwrap();
        let n = layout.param_count as usize;
        for seed in 0..40u32 {
            let mut params = std::vec![0.0f32; n];
            mlp_init(&layout, &mut params, seed).unwrap();
            let mut input = [0.0f32; MAX_WIDTH];
            for (i, x) in input[..12].iter_mut().enumerate() {
                *x = crate::rng::uniform(seed, 1, i as u32) * 4.0 - 2.0;
            }
            let mut scratch = MlpScratch::new();
            let mut out = [0.0f32; MAX_OUT];
            mlp_forward(&layout, &params[..], &input, &mut scratch, &mut out);
            let mut d_out = [0.0f32; MAX_OUT];
            for (o, d) in d_out[..3].iter_mut().enumerate() {
                // some outputs without gradient, some negative zeros
                *d = match (seed + o as u32) % 4 {
                    0 => 0.0,
                    1 => -0.0,
                    _ => crate::rng::uniform(seed, 2, o as u32) - 0.5,
                };
            }
            let mut d_in = [0.0f32; MAX_WIDTH];
            mlp_backward(
                &layout,
                &params[..],
                &scratch,
                &d_out,
                &mut d_in,
                &mut NullSink,
            );
            // Reference: every row of every layer, in row order.
            let mut delta = [0.0f32; MAX_WIDTH];
            delta[..3].copy_from_slice(&d_out[..3]);
            let mut fan_out = 3;
            for k in (0..=2usize).rev() {
                let fan_in = if k == 0 { 12 } else { 32 };
                if k < 2 {
                    for (j, d) in delta[..fan_out].iter_mut().enumerate() {
                        if scratch.act[k + 1][j] <= 0.0 {
                            *d = 0.0;
                        }
                    }
                }
                let w = layout.weight_offsets[k] as usize;
                let mut prev = [0.0f32; MAX_WIDTH];
                for (j, &g) in delta[..fan_out].iter().enumerate() {
                    for (i, p) in prev[..fan_in].iter_mut().enumerate() {
                        *p += params[w + j * fan_in + i] * g;
                    }
                }
                delta = prev;
                fan_out = fan_in;
            }
            let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<std::vec::Vec<_>>();
            assert_eq!(bits(&d_in[..12]), bits(&delta[..12]), "seed {seed}");
        }
    }

    #[test]
    fn relu_derivative_at_zero_is_zero() {
        // 1 -> 1 -> 1 with pre-activation exactly 0: w1 = 1, b1 = -2, x = 2; w2 = 3, b2 = 0.
        let l = MlpLayout::new(1, 1, 1, 1).unwrap();
        let p = [1.0f32, -2.0, 3.0, 0.0];
        let mut x = [0.0f32; MAX_WIDTH];
        x[0] = 2.0;
        let mut s = MlpScratch::new();
        let mut out = [0.0f32; MAX_OUT];
        mlp_forward(&l, &p[..], &x, &mut s, &mut out);
        assert_eq!(out[0], 0.0);
        let mut g = [9.0f32; 4];
        g.iter_mut().for_each(|v| *v = 0.0);
        let mut dx = [0.0f32; MAX_WIDTH];
        mlp_backward(
            &l,
            &p[..],
            &s,
            &[1.0, 0.0, 0.0, 0.0],
            &mut dx,
            &mut F32Sink { acc: &mut g },
        );
        assert_eq!(g, [0.0, 0.0, 0.0, 1.0]);
        assert_eq!(dx[0], 0.0);
    }

    struct CountSink {
        counts: Vec<u32>,
    }
    impl GradSink for CountSink {
        fn add(&mut self, i: usize, _g: f32) {
            self.counts[i] += 1;
        }
    }

    #[test]
    fn one_contribution_per_parameter_of_active_units() {
        for &(n_in, h, layers, n_out) in &[(12, 32, 2, 1), (67, 32, 2, 3), (5, 7, 0, 4)] {
            let l = MlpLayout::new(n_in, h, layers, n_out).unwrap();
            let mut p = vec![0.0f32; l.param_count as usize];
            mlp_init(&l, &mut p, 3).unwrap();
            let x = [0.3f32; MAX_WIDTH];
            let mut s = MlpScratch::new();
            let mut out = [0.0f32; MAX_OUT];
            mlp_forward(&l, &p[..], &x, &mut s, &mut out);
            let mut sink = CountSink {
                counts: vec![0; l.param_count as usize],
            };
            let mut dx = [0.0f32; MAX_WIDTH];
            mlp_backward(&l, &p[..], &s, &[1.0; MAX_OUT], &mut dx, &mut sink);
            // At most one contribution per parameter; a unit's row (weights and bias) gets one
            // exactly when its gradient can be non-zero: output units always, hidden units
            // when active (an inactive ReLU's row is skipped: all its contributions are 0).
            assert!(sink.counts.iter().all(|&c| c <= 1));
            for k in 0..=layers as usize {
                let fan_in = l.fan_in(k as u32) as usize;
                let fan_out = l.fan_out(k as u32) as usize;
                for j in 0..fan_out {
                    let want = (k == layers as usize || s.act[k + 1][j] > 0.0) as u32;
                    let b = l.bias_offsets[k] as usize + j;
                    assert_eq!(sink.counts[b], want, "layer {k} unit {j}");
                    let w = l.weight_offsets[k] as usize + j * fan_in;
                    assert!(sink.counts[w..w + fan_in].iter().all(|&c| c == want));
                }
            }
            if layers > 0 {
                assert!(sink.counts.contains(&1));
            }
        }
    }

    #[test]
    fn init_follows_pytorch_bounds_and_is_deterministic() {
        let l = MlpLayout::new(12, 32, 2, 1).unwrap();
        let mut p = vec![0.0f32; l.param_count as usize];
        mlp_init(&l, &mut p, 42).unwrap();
        let mut q = vec![0.0f32; l.param_count as usize];
        mlp_init(&l, &mut q, 42).unwrap();
        assert_eq!(p, q);
        mlp_init(&l, &mut q, 43).unwrap();
        assert_ne!(p, q);
        // Layer 0 (weights and biases, indices 0..416) uses 1/sqrt(12) = 0.2887, the others
        // 1/sqrt(32) = 0.1768.
        let check = |range: core::ops::Range<usize>, bound: f32| {
            let vals = &p[range];
            let maxabs = vals.iter().fold(0.0f32, |m, v| m.max(v.abs()));
            assert!(maxabs <= bound, "{maxabs} > {bound}");
            if vals.len() > 20 {
                assert!(maxabs > 0.8 * bound, "{maxabs} vs {bound}");
            }
            let mean = vals.iter().map(|&v| v as f64).sum::<f64>() / vals.len() as f64;
            assert!(mean.abs() < 0.25 * bound as f64, "mean {mean}");
        };
        check(0..416, 1.0 / 12f32.sqrt());
        check(416..1472, 1.0 / 32f32.sqrt());
        check(1472..1505, 1.0 / 32f32.sqrt());
        // The exact value of one parameter: index 5 of layer 0.
        let u = crate::rng::uniform(42, 1, 5);
        assert_eq!(p[5], (2.0 * u - 1.0) * (1.0 / math::sqrt(12.0)));
    }

    /// Loss L = sum_o c_o out_o and the sign pattern of every hidden unit.
    fn eval(
        l: &MlpLayout,
        p: &[f32],
        x: &[f32; MAX_WIDTH],
        c: &[f32; MAX_OUT],
    ) -> (f32, Vec<bool>) {
        let mut s = MlpScratch::new();
        let mut out = [0.0f32; MAX_OUT];
        mlp_forward(l, p, x, &mut s, &mut out);
        let mut loss = 0.0f32;
        for o in 0..l.n_out as usize {
            loss += c[o] * out[o];
        }
        let mut pattern = Vec::new();
        for k in 1..=l.hidden_layers as usize {
            for j in 0..l.hidden as usize {
                pattern.push(s.act[k][j] > 0.0);
            }
        }
        (loss, pattern)
    }

    /// Central finite differences in f32 against the analytic backward.
    ///
    /// Step h = 1e-2 on every parameter and input; the denominator is the actual difference of
    /// the two perturbed f32 values. With the ReLU pattern fixed, the network is exactly
    /// linear in any single parameter or input, so the only FD error is f32 rounding of the
    /// two losses (|L| ~ 1, ~1e-7 absolute each, divided by 2h; observed max 1.7e-5):
    /// tolerance |fd - analytic| <= 1e-4 + 1e-3 |analytic|. Perturbations that flip a ReLU (the function
    /// has a kink inside [-h, h]) are skipped and counted; they must be rare (< 2%).
    fn fd_check(n_in: u32, hidden: u32, layers: u32, n_out: u32, seed: u32) {
        let l = MlpLayout::new(n_in, hidden, layers, n_out).unwrap();
        let n = l.param_count as usize;
        let mut p = vec![0.0f32; n];
        mlp_init(&l, &mut p, seed).unwrap();
        // Scale up so the output (and gradients) are O(1) rather than tiny.
        for v in p.iter_mut() {
            *v *= 2.0;
        }
        let mut x = [0.0f32; MAX_WIDTH];
        for (i, xi) in x.iter_mut().enumerate().take(n_in as usize) {
            *xi = 2.0 * crate::rng::uniform(seed, 7, i as u32) - 1.0;
        }
        let mut c = [0.0f32; MAX_OUT];
        for (o, co) in c.iter_mut().enumerate().take(n_out as usize) {
            *co = 2.0 * crate::rng::uniform(seed, 8, o as u32) - 1.0;
        }
        // Analytic.
        let mut s = MlpScratch::new();
        let mut out = [0.0f32; MAX_OUT];
        mlp_forward(&l, &p[..], &x, &mut s, &mut out);
        let mut g = vec![0.0f32; n];
        let mut dx = [0.0f32; MAX_WIDTH];
        mlp_backward(&l, &p[..], &s, &c, &mut dx, &mut F32Sink { acc: &mut g });
        let (_, base_pattern) = eval(&l, &p, &x, &c);
        // Both ReLU branches must be exercised (a hidden layer that is all on or all off would
        // not test the mask).
        if layers > 0 {
            assert!(base_pattern.iter().any(|&b| b) && base_pattern.iter().any(|&b| !b));
        }

        let h = 1e-2f32;
        let tol = |a: f32| 1e-4 + 1e-3 * a.abs();
        let (mut skipped, mut checked, mut max_err) = (0usize, 0usize, 0.0f32);
        let mut nonzero = 0usize;
        // Parameters.
        for i in 0..n {
            let mut pp = p.clone();
            let orig = p[i];
            pp[i] = orig + h;
            let hi = pp[i];
            let (lp, pat_p) = eval(&l, &pp, &x, &c);
            pp[i] = orig - h;
            let lo = pp[i];
            let (lm, pat_m) = eval(&l, &pp, &x, &c);
            if pat_p != base_pattern || pat_m != base_pattern {
                skipped += 1;
                continue;
            }
            let fd = (lp - lm) / (hi - lo);
            let err = (fd - g[i]).abs();
            max_err = max_err.max(err);
            assert!(err <= tol(g[i]), "param {i}: fd {fd} vs analytic {}", g[i]);
            checked += 1;
            if g[i] != 0.0 {
                nonzero += 1;
            }
        }
        // Inputs.
        for i in 0..n_in as usize {
            let mut xx = x;
            xx[i] = x[i] + h;
            let hi = xx[i];
            let (lp, pat_p) = eval(&l, &p, &xx, &c);
            xx[i] = x[i] - h;
            let lo = xx[i];
            let (lm, pat_m) = eval(&l, &p, &xx, &c);
            if pat_p != base_pattern || pat_m != base_pattern {
                skipped += 1;
                continue;
            }
            let fd = (lp - lm) / (hi - lo);
            let err = (fd - dx[i]).abs();
            max_err = max_err.max(err);
            assert!(
                err <= tol(dx[i]),
                "input {i}: fd {fd} vs analytic {}",
                dx[i]
            );
            checked += 1;
        }
        let total = n + n_in as usize;
        assert!(skipped * 50 < total, "skipped {skipped} of {total}");
        assert!(
            nonzero * 4 > checked,
            "too few non-zero gradients: {nonzero}/{checked}"
        );
        eprintln!("fd {n_in}-{hidden}x{layers}-{n_out}: checked {checked}, skipped {skipped}, max err {max_err:e}");
    }

    #[test]
    fn fd_gradients_12_32_32_1() {
        fd_check(12, 32, 2, 1, 11);
    }

    #[test]
    fn fd_gradients_67_32_32_3() {
        fd_check(67, 32, 2, 3, 12);
    }

    #[test]
    fn fd_gradients_linear_and_deep() {
        fd_check(9, 16, 0, 2, 13);
        fd_check(6, 20, 4, 4, 14);
    }

    #[test]
    fn null_sink_backward_still_gives_input_gradient() {
        let l = MlpLayout::new(2, 2, 1, 1).unwrap();
        let p: [f32; 9] = [1.0, -1.0, 0.5, 2.0, 0.5, -1.0, 2.0, -3.0, 0.25];
        let mut x = [0.0f32; MAX_WIDTH];
        x[0] = 1.0;
        x[1] = 2.0;
        let mut s = MlpScratch::default();
        let mut out = [0.0f32; MAX_OUT];
        mlp_forward(&l, &p[..], &x, &mut s, &mut out);
        let mut dx = [0.0f32; MAX_WIDTH];
        mlp_backward(
            &l,
            &p[..],
            &s,
            &[2.0, 0.0, 0.0, 0.0],
            &mut dx,
            &mut NullSink,
        );
        assert_eq!(dx[..2], [-3.0, -12.0]);
    }
}
