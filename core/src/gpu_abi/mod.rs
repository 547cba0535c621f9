//! The CPU/GPU interface, defined once: what `himap-vulkan` writes and `himap-shaders` reads.
//!
//! - [`words`]: layouts and scene constants as flat `u32` words (storage buffers);
//! - record sizes of the storage buffers ([`RAY_FLOATS`], [`RESULT_FLOATS`], ...);
//! - the push-constant blocks, `#[repr(C)]` with their sizes asserted at compile time;
//! - [`entry`]: every entry point's name, storage-buffer binding count and push-constant size,
//!   from which the host builds its pipelines (and which a test checks against the compiled
//!   module).
//!
//! Every entry point runs [`WORKGROUP_SIZE`] x 1 x 1 invocations per workgroup; invocation `i`
//! of a dispatch handles item `first + i` when `i < n` (dispatches larger than the
//! workgroup-count limit are split).

pub mod words;

use core::mem::size_of;

/// Invocations per workgroup of every entry point (x only).
pub const WORKGROUP_SIZE: u32 = 64;

/// Floats of one [`crate::field::model::Ray`] in a rays buffer: origin (3), dir (3), target (3),
/// target_depth.
pub const RAY_FLOATS: usize = 10;
/// Floats of one [`crate::field::model::RayResult`] in a results buffer: colour (3), depth, opacity,
/// loss.
pub const RESULT_FLOATS: usize = 6;
/// Floats of one sample record: `t`, `sdf`, `rgb` (3) written by the per-sample forward pass,
/// then `d_sdf`, `d_rgb` (3) written by the composite passes. Sample `k` of ray `r` is record
/// `r * S + k`, with `S = layout.config.samples`.
pub const SAMPLE_FLOATS: usize = 9;
/// Floats of one [`crate::train::pixel::PixelResult`] in a results buffer: colour (3), depth,
/// opacity, colour loss, warp loss, valid views (as f32, exact).
pub const PIXEL_RESULT_FLOATS: usize = 8;
/// The parameter bindings of the entry points that read the field (after binding 0, the model
/// words [`words::MODEL_WORDS`]): geometry grid (low, high part), appearance grid (low, high
/// part), geometry MLP, appearance MLP, beta (one float). A grid in one binding has its high
/// part bound to any buffer and split point `u32::MAX`.
pub const PARAM_BINDINGS: usize = 7;
/// Offsets of the loss fields in a [`RESULT_FLOATS`] record (the same twice: one loss).
pub const RESULT_LOSS: (usize, usize) = (5, 5);
/// Offsets of the colour and warp loss fields in a [`PIXEL_RESULT_FLOATS`] record.
pub const PIXEL_RESULT_LOSSES: (usize, usize) = (5, 6);

/// A [`crate::field::model::RayResult`] as its record in a results buffer ([`RESULT_FLOATS`]).
#[inline(always)]
pub fn ray_result_record(r: &crate::field::model::RayResult) -> [f32; RESULT_FLOATS] {
    [
        r.color[0], r.color[1], r.color[2], r.depth, r.opacity, r.loss,
    ]
}

/// The [`crate::field::model::RayResult`] of a record written by [`ray_result_record`].
pub fn ray_result_from_record(v: &[f32; RESULT_FLOATS]) -> crate::field::model::RayResult {
    crate::field::model::RayResult {
        color: [v[0], v[1], v[2]],
        depth: v[3],
        opacity: v[4],
        loss: v[5],
    }
}

/// A [`crate::train::pixel::PixelResult`] as its record in a results buffer
/// ([`PIXEL_RESULT_FLOATS`]; the valid-view count as an f32, exact).
#[inline(always)]
pub fn pixel_result_record(r: &crate::train::pixel::PixelResult) -> [f32; PIXEL_RESULT_FLOATS] {
    [
        r.color[0],
        r.color[1],
        r.color[2],
        r.depth,
        r.opacity,
        r.color_loss,
        r.warp_loss,
        r.warp_views as f32,
    ]
}

/// The [`crate::train::pixel::PixelResult`] of a record written by [`pixel_result_record`].
pub fn pixel_result_from_record(
    v: &[f32; PIXEL_RESULT_FLOATS],
) -> crate::train::pixel::PixelResult {
    crate::train::pixel::PixelResult {
        color: [v[0], v[1], v[2]],
        depth: v[3],
        opacity: v[4],
        color_loss: v[5],
        warp_loss: v[6],
        warp_views: v[7] as u32,
    }
}

/// Push constants of the single-kernel entry points (probe, fixed-point accumulation, MLP
/// and grid forward).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
#[repr(C)]
pub struct KernelPush {
    /// Number of items; invocations with `id.x >= n` do nothing.
    pub n: u32,
    /// The seed (`probe_cs`) or the bucket count (`fixed_accumulate_cs`); unused otherwise.
    pub arg: u32,
    /// Padding (unused, pushed as 0).
    pub _pad0: u32,
    /// Padding (unused, pushed as 0).
    pub _pad1: u32,
}

/// Push constants of the per-item entry points without extra scalars (render, queries,
/// backward, warping).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
#[repr(C)]
pub struct RangePush {
    /// Items in this dispatch; invocation `i` handles item `first + i`.
    pub n: u32,
    /// Batch index of the dispatch's first item.
    pub first: u32,
    /// Items in the whole batch (the mapping pass's planarity triplets need it; 0 elsewhere).
    pub total: u32,
    /// Padding (unused, pushed as 0).
    pub _pad1: u32,
}

/// Push constants of the per-sample forward pass.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
#[repr(C)]
pub struct SamplePush {
    /// Sample records in this dispatch; invocation `i` handles record `first + i`.
    pub n: u32,
    /// Index of the dispatch's first sample record.
    pub first: u32,
    /// Stratified jitter seed.
    pub seed: u32,
    /// 1: jittered samples (training), 0: bin centres (rendering).
    pub jitter: u32,
}

/// Push constants of the ray composite-and-loss pass: the
/// [`crate::field::model::LossConfig`] of the step plus the item range.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
#[repr(C)]
pub struct TrainPush {
    /// Rays in this dispatch; invocation `i` handles ray `first + i` (the ray's id for the
    /// stratified jitter).
    pub n: u32,
    /// Index of the dispatch's first ray.
    pub first: u32,
    /// `LossConfig::seed`: the step's stratified jitter seed.
    pub seed: u32,
    /// `LossConfig::color_to_geometry` as 0 / 1.
    pub color_to_geometry: u32,
    /// `LossConfig::lambda_color`.
    pub lambda_color: f32,
    /// `LossConfig::lambda_depth`.
    pub lambda_depth: f32,
    /// `LossConfig::ray_scale`.
    pub ray_scale: f32,
    /// Padding (unused, pushed as 0).
    pub _pad: u32,
}

/// The status words of a training step, in one `u32` buffer: the finiteness checks' count of
/// non-finite values ([`STATUS_REJECTED`], zeroed at the start of every step; non-zero: the
/// step is rejected and Adam does nothing) and the count of steps taken ([`STATUS_STEPS`],
/// kept on the device: Adam's bias corrections of a step are those of `count + 1`
/// ([`crate::train::adam::AdamStep::at`]), and `step_count_cs` adds 1 after an accepted
/// step). A step queued behind one whose checks are not yet known still gets the CPU's `t`.
pub const STATUS_WORDS: usize = 2;
/// See [`STATUS_WORDS`].
pub const STATUS_REJECTED: usize = 0;
/// See [`STATUS_WORDS`].
pub const STATUS_STEPS: usize = 1;

/// Push constants of the Adam passes: the item range and the group's
/// [`crate::train::adam::AdamStep`].
#[derive(Clone, Copy, Debug, Default, PartialEq)]
#[repr(C)]
pub struct AdamPush {
    /// Parameters in this dispatch; invocation `i` updates parameter `first + i`.
    pub n: u32,
    /// Index of the dispatch's first parameter in the group.
    pub first: u32,
    /// The step's Adam scalars (learning rate, betas, epsilon; the shaders replace the bias
    /// corrections by those of the device's step count, [`STATUS_WORDS`]).
    pub step: crate::train::adam::AdamStep,
}

/// Push constants of the loss check: the item range and where a record's loss fields are.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
#[repr(C)]
pub struct LossCheckPush {
    /// Records in this dispatch; invocation `i` checks record `first + i`.
    pub n: u32,
    /// Index of the dispatch's first record.
    pub first: u32,
    /// Floats per record ([`RESULT_FLOATS`] or [`PIXEL_RESULT_FLOATS`]).
    pub stride: u32,
    /// The two loss fields' offsets in a record (the same twice for a single loss).
    pub loss_a: u32,
    /// Offset of the second loss field (equal to `loss_a` for a single loss).
    pub loss_b: u32,
    /// Padding (unused, pushed as 0).
    pub _pad0: u32,
    /// Padding (unused, pushed as 0).
    pub _pad1: u32,
    /// Padding (unused, pushed as 0).
    pub _pad2: u32,
}

/// Largest push-constant block, in `u32` words (Vulkan guarantees 128 bytes).
pub const MAX_PUSH_WORDS: usize = 8;

/// A push-constant block as the words the host pushes (unused trailing words 0; the first
/// `size_of::<Self>()` bytes are pushed).
pub trait PushWords: Copy {
    /// The block's fields as `u32` words (floats by their bits), in declaration order.
    fn words(&self) -> [u32; MAX_PUSH_WORDS];
}

impl PushWords for KernelPush {
    fn words(&self) -> [u32; MAX_PUSH_WORDS] {
        [self.n, self.arg, 0, 0, 0, 0, 0, 0]
    }
}

impl PushWords for RangePush {
    fn words(&self) -> [u32; MAX_PUSH_WORDS] {
        [self.n, self.first, self.total, 0, 0, 0, 0, 0]
    }
}

impl PushWords for SamplePush {
    fn words(&self) -> [u32; MAX_PUSH_WORDS] {
        [self.n, self.first, self.seed, self.jitter, 0, 0, 0, 0]
    }
}

impl PushWords for TrainPush {
    fn words(&self) -> [u32; MAX_PUSH_WORDS] {
        [
            self.n,
            self.first,
            self.seed,
            self.color_to_geometry,
            self.lambda_color.to_bits(),
            self.lambda_depth.to_bits(),
            self.ray_scale.to_bits(),
            0,
        ]
    }
}

impl PushWords for AdamPush {
    fn words(&self) -> [u32; MAX_PUSH_WORDS] {
        let s = &self.step;
        [
            self.n,
            self.first,
            s.lr.to_bits(),
            s.beta1.to_bits(),
            s.beta2.to_bits(),
            s.eps.to_bits(),
            s.bias_correction1.to_bits(),
            s.bias_correction2.to_bits(),
        ]
    }
}

impl PushWords for LossCheckPush {
    fn words(&self) -> [u32; MAX_PUSH_WORDS] {
        [
            self.n,
            self.first,
            self.stride,
            self.loss_a,
            self.loss_b,
            0,
            0,
            0,
        ]
    }
}

const _: () = {
    assert!(size_of::<KernelPush>() == 16);
    assert!(size_of::<RangePush>() == 16);
    assert!(size_of::<SamplePush>() == 16);
    assert!(size_of::<TrainPush>() == 32);
    assert!(size_of::<AdamPush>() == 32);
    assert!(size_of::<LossCheckPush>() == 32);
    assert!(32 == 4 * MAX_PUSH_WORDS);
};

/// One compute entry point: its name in the module, the storage buffers of its descriptor set
/// 0 (bindings `0..bindings`) and the bytes of its push-constant block.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct EntryPoint {
    /// Entry point name in the SPIR-V module.
    pub name: &'static str,
    /// Storage buffers of descriptor set 0 (bindings `0..bindings`).
    pub bindings: u32,
    /// Size of the push-constant block (bytes).
    pub push_size: u32,
}

impl EntryPoint {
    const fn new(name: &'static str, bindings: u32, push_size: usize) -> Self {
        Self {
            name,
            bindings,
            push_size: push_size as u32,
        }
    }
}

/// The loop of the loop-budget canary (`loop_canary_cs`): `n` steps of a 32-bit LCG from
/// `seed`, returning the final state and the steps taken. A device that cuts loops short (the
/// software driver llvmpipe stops every loop of an invocation once 65535 iterations were
/// spent) returns fewer steps or another state; no compiler can fold the multiply into a
/// closed form, so the loop really runs.
///
/// # Examples
///
/// ```rust
/// use himap_core::gpu_abi::loop_canary;
///
/// assert_eq!(loop_canary(0, 7), [7, 0]);
/// assert_eq!(loop_canary(1, 0), [1_013_904_223, 1]);
/// ```
#[inline(always)]
pub fn loop_canary(n: u32, seed: u32) -> [u32; 2] {
    let mut x = seed;
    let mut i = 0u32;
    while i < n {
        x = x.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
        i += 1;
    }
    [x, i]
}

/// Decoder-weight gradients one workgroup of `sample_backward_wg_cs` sums in workgroup memory
/// before adding them to the global buffers: 2048 `i64` (16 KiB, the smallest
/// `maxComputeSharedMemorySize` a Vulkan device may have). The geometry decoder uses it when
/// it fits, the appearance decoder when both fit.
pub const WORKGROUP_MLP_SLOTS: usize = 2048;

/// Floats of a mapping step's per-pixel record between its pixel passes: the rendered depth
/// (`pixel_depth_cs`), then the cotangents of the rendered colour (3) and depth
/// (`pixel_loss_cs` for `pixel_backward_cs`).
pub const PIXEL_AUX_FLOATS: usize = 5;

/// Loop iterations one `pixel_loss_cs` invocation may run per other frame of the window
/// (an upper bound, counted over `loss/warp.rs` and `loss/mod.rs` for the full 11x11 patch:
/// the warp of the patch ~860, the 11x11 and 7x7 SSIM with their backward ~2,400, the
/// cotangent sums ~1,460; about 4,750, rounded up with a quarter's margin).
pub const PIXEL_TRAIN_LOOPS_PER_VIEW: u32 = 6_000;

/// Loop iterations of one `pixel_loss_cs` invocation independent of the window (compositing
/// over the samples, the colour, depth-prior and planarity terms): an upper bound.
pub const PIXEL_TRAIN_LOOPS_BASE: u32 = 4_000;

/// An upper bound on the loop iterations of one `pixel_loss_cs` invocation for a window of
/// `frames` frames, which a device's loop budget must exceed.
///
/// # Examples
///
/// ```rust
/// use himap_core::gpu_abi::pixel_train_loop_bound;
///
/// // llvmpipe's 65535: a 6-frame window fits, the 20-frame window of `small` does not.
/// assert!(pixel_train_loop_bound(6) < 65_535);
/// assert!(pixel_train_loop_bound(20) > 65_535);
/// ```
pub const fn pixel_train_loop_bound(frames: u32) -> u32 {
    let others = if frames == 0 { 0 } else { frames - 1 };
    PIXEL_TRAIN_LOOPS_BASE + others.saturating_mul(PIXEL_TRAIN_LOOPS_PER_VIEW)
}

/// Every entry point of the shader module (bindings are documented at each entry point in
/// `shaders/src/lib.rs`).
pub mod entry {
    use super::*;

    /// Toolchain probe: scene words, output.
    pub const PROBE: EntryPoint = EntryPoint::new("probe_cs", 2, size_of::<KernelPush>());
    /// Loop-budget canary ([`loop_canary`](super::loop_canary) of `n` = push `n`, seed = push
    /// `arg`): output (2 words: state, steps).
    pub const LOOP_CANARY: EntryPoint =
        EntryPoint::new("loop_canary_cs", 1, size_of::<KernelPush>());
    /// Division check (`himap devices --divide`): dividends, divisors, quotients (`2 n`
    /// floats: [`crate::math::div`], then the device's own `OpFDiv`).
    pub const DIVIDE: EntryPoint = EntryPoint::new("divide_cs", 3, size_of::<KernelPush>());
    /// Fixed-point atomic accumulation (`acc[i % buckets] += to_fixed(values[i])`): values,
    /// `i64` accumulators.
    pub const FIXED_ACCUMULATE: EntryPoint =
        EntryPoint::new("fixed_accumulate_cs", 2, size_of::<KernelPush>());
    /// MLP forward of many inputs: layout words, parameters, inputs, outputs.
    pub const MLP_FORWARD: EntryPoint =
        EntryPoint::new("mlp_forward_cs", 4, size_of::<KernelPush>());
    /// Grid forward at many points: layout words, parameters, positions, features.
    pub const GRID_FORWARD: EntryPoint =
        EntryPoint::new("grid_forward_cs", 4, size_of::<KernelPush>());
    /// Model words, [`PARAM_BINDINGS`], rays, sample records.
    pub const SAMPLE_FORWARD: EntryPoint = EntryPoint::new(
        "sample_forward_cs",
        1 + PARAM_BINDINGS as u32 + 2,
        size_of::<SamplePush>(),
    );
    /// Composite, loss and compositing backward of a training step's rays: model words,
    /// beta, beta gradient, rays, sample records, results.
    pub const RAY_TRAIN: EntryPoint = EntryPoint::new("ray_train_cs", 6, size_of::<TrainPush>());
    /// Per-sample backward with the decoders' weight gradients summed per workgroup first
    /// (devices with `shaderSharedInt64Atomics`): model words, [`PARAM_BINDINGS`], their
    /// gradients, rays, sample records.
    pub const SAMPLE_BACKWARD_WG: EntryPoint = EntryPoint::new(
        "sample_backward_wg_cs",
        1 + 2 * PARAM_BINDINGS as u32 + 2,
        size_of::<SamplePush>(),
    );
    /// Per-sample backward, every contribution with a global atomic: model words,
    /// [`PARAM_BINDINGS`], their gradients, rays, sample records.
    pub const SAMPLE_BACKWARD: EntryPoint = EntryPoint::new(
        "sample_backward_cs",
        1 + 2 * PARAM_BINDINGS as u32 + 2,
        size_of::<SamplePush>(),
    );
    /// Composite of a render's rays: model words, beta, rays, sample records, results.
    pub const RAY_RENDER: EntryPoint = EntryPoint::new("ray_render_cs", 5, size_of::<RangePush>());
    /// The camera ray of every sampled pixel of a mapping step: window words, pixels, image
    /// slots, rays.
    pub const PIXEL_RAYS: EntryPoint = EntryPoint::new("pixel_rays_cs", 4, size_of::<RangePush>());
    /// A mapping step's pixels, in three passes over the same bindings (model words, beta,
    /// beta gradient, window words, pixels, image slots, rays, sample records, results,
    /// [`PIXEL_AUX_FLOATS`] per pixel): each pixel's rendered depth (for the planarity
    /// partners), ...
    pub const PIXEL_DEPTH: EntryPoint =
        EntryPoint::new("pixel_depth_cs", 10, size_of::<RangePush>());
    /// ... the mapping losses and the cotangents of the rendered colour and depth, ...
    pub const PIXEL_LOSS: EntryPoint = EntryPoint::new("pixel_loss_cs", 10, size_of::<RangePush>());
    /// ... and the compositing backward (per-sample cotangents, beta gradient).
    pub const PIXEL_BACKWARD: EntryPoint =
        EntryPoint::new("pixel_backward_cs", 10, size_of::<RangePush>());
    /// Parameters, both moments, gradient, status words ([`STATUS_WORDS`]).
    pub const ADAM: EntryPoint = EntryPoint::new("adam_cs", 5, size_of::<AdamPush>());
    /// Counts non-finite losses: results, status word.
    pub const LOSS_CHECK: EntryPoint =
        EntryPoint::new("loss_check_cs", 2, size_of::<LossCheckPush>());
    /// Counts parameters whose Adam update would not be finite: as [`ADAM`].
    pub const ADAM_CHECK: EntryPoint = EntryPoint::new("adam_check_cs", 5, size_of::<AdamPush>());
    /// Counts the step as taken unless a check counted a non-finite value: status words.
    pub const STEP_COUNT: EntryPoint = EntryPoint::new("step_count_cs", 1, size_of::<RangePush>());
    /// Model words, [`PARAM_BINDINGS`], points, output.
    pub const SDF_QUERY: EntryPoint = EntryPoint::new(
        "sdf_query_cs",
        1 + PARAM_BINDINGS as u32 + 2,
        size_of::<RangePush>(),
    );
    /// Model words, [`PARAM_BINDINGS`], points, output (3 floats per point).
    pub const COLOR_QUERY: EntryPoint = EntryPoint::new(
        "color_query_cs",
        1 + PARAM_BINDINGS as u32 + 2,
        size_of::<RangePush>(),
    );

    /// All of them.
    pub const ALL: [EntryPoint; 21] = [
        SAMPLE_BACKWARD_WG,
        PROBE,
        LOOP_CANARY,
        DIVIDE,
        FIXED_ACCUMULATE,
        MLP_FORWARD,
        GRID_FORWARD,
        SAMPLE_FORWARD,
        RAY_TRAIN,
        SAMPLE_BACKWARD,
        RAY_RENDER,
        PIXEL_RAYS,
        PIXEL_DEPTH,
        PIXEL_LOSS,
        PIXEL_BACKWARD,
        ADAM,
        LOSS_CHECK,
        ADAM_CHECK,
        STEP_COUNT,
        SDF_QUERY,
        COLOR_QUERY,
    ];
}
