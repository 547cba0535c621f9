//! rust-gpu compute entry points for himap.
//!
//! Every entry point only does index and bounds math and then calls a `himap-core` kernel, so
//! the GPU runs exactly the code the CPU backends run. `vulkan/build.rs` compiles this crate to
//! one SPIR-V module (`spirv-unknown-vulkan1.2`, capabilities `Int64` + `Int64Atomics`) and
//! decorates every float operation `NoContraction`.
//!
//! Conventions shared by all entry points:
//! - workgroups of [`WORKGROUP_SIZE`] invocations along x; one invocation per item
//!   (`global_invocation_id.x`), items at or past `n` return at once;
//! - descriptor set 0, bindings numbered from 0 in the order of the parameters;
//! - scalars that change per dispatch (`n`, seeds) come as push constants (the blocks of
//!   `himap_core::gpu_abi`, which also lists every entry point's bindings);
//! - layouts (offset tables) come as `u32` words in a storage buffer, f32 fields as their bits
//!   (see [`words`]);
//! - entry points live at the crate root: rust-gpu names an entry point in a module
//!   `module::name`.
//!
//! rust-gpu 0.11's linker merges identical parameter declarations (name, type, set, binding)
//! of different entry points into one global; `himap-vulkan`'s test
//! `entry_point_bindings_are_distinct_and_in_range` checks that no entry point ends up with a
//! binding twice or past its declared count (it caught a renumbering slip).
//!
//! rust-gpu 0.11 rejects, in code reachable from an entry point: `[false; N]` (bool array
//! repeat: "memset invalid on bool pattern"), `Result<_, himap_core::Error>` values (the
//! `&'static str` payload; layout constructors are host-side), unsizing a function-local array
//! to a slice (`&[T; N]` -> `&[T]`: only storage buffers can be slices), `u32::saturating_sub`
//! ("not implemented yet"), and `f64` without the `Float64` capability (`math::sin`/`cos`).
#![cfg_attr(target_arch = "spirv", no_std)]

use himap_core::camera::{Intrinsics, Pose};
use himap_core::field::grid::{self, MAX_GRID_FEATURES};
use himap_core::field::mlp::{self, MlpScratch, MAX_OUT, MAX_WIDTH};
use himap_core::field::model::{
    self, Group, LossConfig, ModelGradSink, ModelLayout, Params, Ray, RayCache, SampleScratch,
};
use himap_core::field::render::MAX_SAMPLES;
pub use himap_core::gpu_abi::WORKGROUP_SIZE;
use himap_core::gpu_abi::{
    pixel_result_record, ray_result_record, words, AdamPush, KernelPush, LossCheckPush, RangePush,
    SamplePush, TrainPush, PARAM_BINDINGS, PIXEL_AUX_FLOATS, RAY_FLOATS, SAMPLE_FLOATS,
    STATUS_REJECTED, STATUS_STEPS, STATUS_WORDS,
};
use himap_core::train::adam;
use himap_core::train::fixed;
use himap_core::train::pixel::{self, PixelResult, PixelSample, WindowImages, WindowView};
use himap_core::{rng, Aabb, GradSink, ParamRead};
use spirv_std::arch::{atomic_i_add, workgroup_memory_barrier_with_group_sync};
use spirv_std::glam::UVec3;
use spirv_std::memory::{Scope, Semantics};
use spirv_std::spirv;

/// `let ($n, $window) = ...`: the mapping window's frame count and its `WindowView` (the
/// word poses and slot images it borrows stay in the caller's scope) from the window words
/// and the image store, for the pixel passes. A macro rather than a function: a function
/// returning the borrowed parts changes the module's access chains, and the module is the
/// one verified bit for bit on an NVIDIA H200.
macro_rules! window_view {
    (let ($n:ident, $window:ident) = $window_words:expr, $images:expr) => {
        let ($n, width, height, slots) = words::window_frames($window_words);
        let poses = words::WordPoses {
            words: $window_words,
            n: $n,
        };
        let imgs = WindowImages {
            width,
            height,
            slots,
            pixels: $images,
            priors: words::word($window_words, words::WINDOW_PRIORS),
        };
        let $window = WindowView {
            k: words::intrinsics_from_words($window_words, 0),
            poses: &poses,
            images: &imgs,
        };
    };
}

/// A [`GradSink`] over a storage buffer: each contribution is converted with
/// [`fixed::to_fixed`] and added with a 64-bit integer atomic, so the sums equal
/// `himap_core::FixedSink`'s bit for bit in any order. Indices past the end are dropped.
///
/// `Scope::QueueFamily`: device scope needs an extra capability under rust-gpu's Vulkan memory
/// model.
pub struct AtomicSink<'a> {
    pub acc: &'a mut [i64],
}

impl GradSink for AtomicSink<'_> {
    #[inline(always)]
    fn add(&mut self, i: usize, g: f32) {
        if i < self.acc.len() {
            let q = fixed::to_fixed(g);
            unsafe {
                atomic_i_add::<i64, { Scope::QueueFamily as u32 }, { Semantics::NONE.bits() }>(
                    &mut self.acc[i],
                    q,
                );
            }
        }
    }
}

/// Toolchain probe: per pixel `i` of a `width` x `height` image (row-major), builds the camera
/// ray, takes the point at depth `t = 0.5 + 4 * uniform(seed, i, 0)`, normalizes it into the box
/// and round-trips the uniform draw through fixed point.
///
/// - binding 0 `scene`: words, [`words::AABB`] at 0, [`words::POSE`] at 6,
///   [`words::INTRINSICS`] at 18 (24 words);
/// - binding 1 `out`: 4 floats per pixel: normalized x, y, z, `from_fixed(to_fixed(u))`.
///
/// Push constants ([`KernelPush`]): `n` = pixel count, `arg` = seed.
#[spirv(compute(threads(64)))]
pub fn probe_cs(
    #[spirv(global_invocation_id)] id: UVec3,
    #[spirv(push_constant)] pc: &KernelPush,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] scene: &[u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] out: &mut [f32],
) {
    let i = id.x;
    if i >= pc.n || (i as usize + 1) * 4 > out.len() {
        return;
    }
    let aabb: Aabb = words::aabb_from_words(scene, 0);
    let pose: Pose = words::pose_from_words(scene, words::AABB);
    let k: Intrinsics = words::intrinsics_from_words(scene, words::AABB + words::POSE);
    let w = if k.width == 0 { 1 } else { k.width };
    let (u, v) = ((i % w) as f32, (i / w) as f32);
    let (o, d) = pose.ray(&k, u, v);
    let r = rng::uniform(pc.arg, i, 0);
    let t = 0.5 + 4.0 * r;
    let p = [o[0] + t * d[0], o[1] + t * d[1], o[2] + t * d[2]];
    let x = aabb.normalize(p);
    let base = i as usize * 4;
    out[base] = x[0];
    out[base + 1] = x[1];
    out[base + 2] = x[2];
    out[base + 3] = fixed::from_fixed(fixed::to_fixed(r));
}

/// Loop-budget canary: invocation 0 runs [`himap_core::gpu_abi::loop_canary`] for `n` steps
/// from seed `arg` and writes the final state and the step count to `out[0]`, `out[1]`. The
/// host compares them with the CPU's to find how many loop iterations an invocation may run.
///
/// - binding 0 `out`: 2 words.
///
/// Push constants ([`KernelPush`]): `n` = steps, `arg` = seed.
#[spirv(compute(threads(64)))]
pub fn loop_canary_cs(
    #[spirv(global_invocation_id)] id: UVec3,
    #[spirv(push_constant)] pc: &KernelPush,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] out: &mut [u32],
) {
    if id.x != 0 || out.len() < 2 {
        return;
    }
    let r = himap_core::gpu_abi::loop_canary(pc.n, pc.arg);
    out[0] = r[0];
    out[1] = r[1];
}

/// Division check (`himap devices --divide`): `out[i] = math::div(a[i], b[i])` (the kernels'
/// division, correctly rounded) and `out[n + i] = a[i] / b[i]` (the device's `OpFDiv`), so
/// the host sees both against the CPU's quotients.
///
/// - binding 0 `a`, binding 1 `b`: `n` floats each;
/// - binding 2 `out`: `2 n` floats.
///
/// Push constants ([`KernelPush`]): `n` = number of pairs.
#[spirv(compute(threads(64)))]
pub fn divide_cs(
    #[spirv(global_invocation_id)] id: UVec3,
    #[spirv(push_constant)] pc: &KernelPush,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] a: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] b: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 2)] out: &mut [f32],
) {
    let (i, n) = (id.x as usize, pc.n as usize);
    if i >= n || i >= a.len() || i >= b.len() || n + i >= out.len() {
        return;
    }
    out[i] = himap_core::math::div(a[i], b[i]);
    out[n + i] = a[i] / b[i];
}

/// Fixed-point atomics: `acc[i % buckets] += to_fixed(values[i])` through [`AtomicSink`]. The
/// sums are order-independent, so they match `himap_core::FixedSink` bit for bit.
///
/// - binding 0 `values`: `n` floats;
/// - binding 1 `acc`: the `i64` accumulators.
///
/// Push constants ([`KernelPush`]): `n` = number of values, `arg` = buckets (0 or more than `acc.len()` means
/// `acc.len()`).
#[spirv(compute(threads(64)))]
pub fn fixed_accumulate_cs(
    #[spirv(global_invocation_id)] id: UVec3,
    #[spirv(push_constant)] pc: &KernelPush,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] values: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] acc: &mut [i64],
) {
    let i = id.x as usize;
    let len = acc.len();
    if i >= pc.n as usize || i >= values.len() || len == 0 {
        return;
    }
    let mut buckets = pc.arg as usize;
    if buckets == 0 || buckets > len {
        buckets = len;
    }
    let mut sink = AtomicSink { acc };
    sink.add(i % buckets, values[i]);
}

/// MLP forward: `out[i * n_out + o] = mlp_forward(layout, params, inputs[i])[o]` for the
/// `n_in` inputs of item `i` at `inputs[i * n_in ..]`.
///
/// - binding 0 `layout`: the MLP layout as words ([`words::mlp_layout_from_words`]);
/// - binding 1 `params`: the MLP's flat parameters;
/// - binding 2 `inputs`: `n_in` floats per item;
/// - binding 3 `out`: `n_out` floats per item.
///
/// Push constants: `n` = number of items.
#[spirv(compute(threads(64)))]
pub fn mlp_forward_cs(
    #[spirv(global_invocation_id)] id: UVec3,
    #[spirv(push_constant)] pc: &KernelPush,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] layout: &[u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] params: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 2)] inputs: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 3)] out: &mut [f32],
) {
    let i = id.x as usize;
    if i >= pc.n as usize {
        return;
    }
    let layout = words::mlp_layout_from_words(layout, 0);
    let n_in = layout.n_in as usize;
    let n_out = layout.n_out as usize;
    let mut x = [0.0f32; MAX_WIDTH];
    let mut k = 0;
    while k < n_in && k < MAX_WIDTH && i * n_in + k < inputs.len() {
        x[k] = inputs[i * n_in + k];
        k += 1;
    }
    let mut scratch = MlpScratch::new();
    let mut y = [0.0f32; MAX_OUT];
    mlp::mlp_forward(&layout, params, &x, &mut scratch, &mut y);
    let mut o = 0;
    while o < n_out && o < MAX_OUT && i * n_out + o < out.len() {
        out[i * n_out + o] = y[o];
        o += 1;
    }
}

/// Grid forward: `out[i * D + k] = grid_forward(layout, params, positions[i])[k]` for the
/// `D = layout.feature_dim()` features of point `i`.
///
/// - binding 0 `layout`: the grid layout as words ([`words::grid_layout_from_words`]);
/// - binding 1 `params`: the grid's flat parameters;
/// - binding 2 `positions`: 3 floats per point (world, metres);
/// - binding 3 `out`: `D` floats per point.
///
/// Push constants: `n` = number of points.
#[spirv(compute(threads(64)))]
pub fn grid_forward_cs(
    #[spirv(global_invocation_id)] id: UVec3,
    #[spirv(push_constant)] pc: &KernelPush,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] layout: &[u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] params: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 2)] positions: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 3)] out: &mut [f32],
) {
    let i = id.x as usize;
    if i >= pc.n as usize || (i + 1) * 3 > positions.len() {
        return;
    }
    let layout = words::grid_layout_from_words(layout, 0);
    let p = [positions[3 * i], positions[3 * i + 1], positions[3 * i + 2]];
    let mut feat = [0.0f32; MAX_GRID_FEATURES];
    grid::grid_forward(&layout, params, p, &mut feat);
    let dim = layout.feature_dim();
    let base = i * dim;
    let mut k = 0;
    while k < dim && k < MAX_GRID_FEATURES && base + k < out.len() {
        out[base + k] = feat[k];
        k += 1;
    }
}

/// A [`ModelGradSink`] over the five fixed-point gradient buffers (one storage buffer per
/// [`Group`]), each contribution converted with [`fixed::to_fixed`] and added with a 64-bit
/// integer atomic: the sums equal the CPU's `FixedModelSink` bit for bit in any order.
/// Zero contributions are skipped (adding 0 changes nothing); indices past the end are dropped.
///
/// The two grid groups may be split in two bindings (see [`SplitParams`]): index `i` below
/// the split goes to the low part, the rest to the high part at `i - split`.
pub struct AtomicModelSink<'a> {
    pub geometry_grid: &'a mut [i64],
    pub geometry_grid_hi: &'a mut [i64],
    pub geometry_split: usize,
    pub appearance_grid: &'a mut [i64],
    pub appearance_grid_hi: &'a mut [i64],
    pub appearance_split: usize,
    pub geometry_mlp: &'a mut [i64],
    pub appearance_mlp: &'a mut [i64],
    pub beta: &'a mut [i64],
}

/// A parameter group read from one or two storage-buffer bindings: `lo` holds indices
/// `0..split`, `hi` the rest (a group larger than one binding may be). Reads past the end are
/// 0.
pub struct SplitParams<'a> {
    pub lo: &'a [f32],
    pub hi: &'a [f32],
    pub split: usize,
}

impl<'a> SplitParams<'a> {
    #[inline(always)]
    pub fn new(lo: &'a [f32], hi: &'a [f32], split: usize) -> Self {
        Self { lo, hi, split }
    }

    /// A group in one binding.
    #[inline(always)]
    pub fn whole(lo: &'a [f32]) -> Self {
        Self {
            lo,
            hi: lo,
            split: usize::MAX,
        }
    }
}

/// The field's parameters as the [`PARAM_BINDINGS`] bindings give them (grid split points
/// from the model words).
pub struct Field<'a> {
    pub geo: SplitParams<'a>,
    pub app: SplitParams<'a>,
    pub geometry_mlp: SplitParams<'a>,
    pub appearance_mlp: SplitParams<'a>,
    pub beta: f32,
}

impl<'a> Field<'a> {
    /// `p`: the seven parameter bindings in [`PARAM_BINDINGS`] order.
    #[inline(always)]
    pub fn new(model_words: &[u32], p: [&'a [f32]; PARAM_BINDINGS]) -> Self {
        Self {
            geo: SplitParams::new(p[0], p[1], words::split(model_words, 0)),
            app: SplitParams::new(p[2], p[3], words::split(model_words, 1)),
            geometry_mlp: SplitParams::whole(p[4]),
            appearance_mlp: SplitParams::whole(p[5]),
            beta: first_or_zero(p[6]),
        }
    }

    #[inline(always)]
    pub fn params(&self) -> Params<'_, SplitParams<'a>> {
        Params {
            geometry_grid: &self.geo,
            appearance_grid: &self.app,
            geometry_mlp: &self.geometry_mlp,
            appearance_mlp: &self.appearance_mlp,
            beta: self.beta,
        }
    }
}

impl ParamRead for SplitParams<'_> {
    #[inline(always)]
    fn at(&self, i: usize) -> f32 {
        if i < self.split {
            float_at(self.lo, i)
        } else {
            float_at(self.hi, i - self.split)
        }
    }
}

/// Counts one non-finite value into `status[0]` (the step's rejection flag).
#[inline(always)]
fn count_nonfinite(status: &mut [u32]) {
    if !status.is_empty() {
        unsafe {
            atomic_i_add::<u32, { Scope::QueueFamily as u32 }, { Semantics::NONE.bits() }>(
                &mut status[0],
                1,
            );
        }
    }
}

#[inline(always)]
fn atomic_add_i64(acc: &mut [i64], i: usize, q: i64) {
    if i < acc.len() {
        unsafe {
            atomic_i_add::<i64, { Scope::QueueFamily as u32 }, { Semantics::NONE.bits() }>(
                &mut acc[i],
                q,
            );
        }
    }
}

impl ModelGradSink for AtomicModelSink<'_> {
    #[inline(always)]
    fn add(&mut self, group: Group, i: usize, g: f32) {
        let q = fixed::to_fixed(g);
        if q == 0 {
            return;
        }
        match group {
            Group::GeometryGrid => {
                if i < self.geometry_split {
                    atomic_add_i64(self.geometry_grid, i, q)
                } else {
                    atomic_add_i64(self.geometry_grid_hi, i - self.geometry_split, q)
                }
            }
            Group::AppearanceGrid => {
                if i < self.appearance_split {
                    atomic_add_i64(self.appearance_grid, i, q)
                } else {
                    atomic_add_i64(self.appearance_grid_hi, i - self.appearance_split, q)
                }
            }
            Group::GeometryMlp => atomic_add_i64(self.geometry_mlp, i, q),
            Group::AppearanceMlp => atomic_add_i64(self.appearance_mlp, i, q),
            Group::Beta => atomic_add_i64(self.beta, i, q),
        }
    }
}

/// `v[k]`, or 0 past the end (no closures here: rust-gpu cannot load through a captured
/// pointer).
#[inline(always)]
fn float_at(v: &[f32], k: usize) -> f32 {
    if k < v.len() {
        v[k]
    } else {
        0.0
    }
}

#[inline(always)]
fn read_ray(rays: &[f32], i: usize) -> Ray {
    let b = i * RAY_FLOATS;
    Ray {
        origin: [
            float_at(rays, b),
            float_at(rays, b + 1),
            float_at(rays, b + 2),
        ],
        dir: [
            float_at(rays, b + 3),
            float_at(rays, b + 4),
            float_at(rays, b + 5),
        ],
        target: [
            float_at(rays, b + 6),
            float_at(rays, b + 7),
            float_at(rays, b + 8),
        ],
        target_depth: float_at(rays, b + 9),
    }
}

/// Writes record `i` of a results buffer (dropped past its end).
#[inline(always)]
fn write_record<const N: usize>(out: &mut [f32], i: usize, record: &[f32; N]) {
    let b = i * N;
    if b + N <= out.len() {
        let mut k = 0;
        while k < N {
            out[b + k] = record[k];
            k += 1;
        }
    }
}

#[inline(always)]
fn first_or_zero(v: &[f32]) -> f32 {
    float_at(v, 0)
}

/// Samples per ray of a layout (`config.max_ray_samples()`: `samples` plus `far_samples`
/// when they apply, at most `MAX_SAMPLES`, at least 1).
#[inline(always)]
fn samples_per_ray(layout: &ModelLayout) -> usize {
    layout.config.max_ray_samples()
}

/// Pass 1 of a step or a render: one sample per invocation. Record `i` is sample `k = i % S`
/// of ray `r = i / S`; it gets `t_k` from `model::ray_samples` (ray id `r`) and the field's
/// SDF and colour there (`model::sample_forward`). Samples past the ray's `n` are left as they
/// are.
///
/// - binding 0 `model`: the [`model::ModelLayout`] as words;
/// - bindings 1..=7: the parameters ([`PARAM_BINDINGS`]);
/// - binding 8 `rays`: [`RAY_FLOATS`] floats per ray;
/// - binding 9 `samples`: [`SAMPLE_FLOATS`] floats per sample record.
#[spirv(compute(threads(64)))]
#[allow(clippy::too_many_arguments)]
pub fn sample_forward_cs(
    #[spirv(global_invocation_id)] id: UVec3,
    #[spirv(push_constant)] pc: &SamplePush,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] model_words: &[u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] p_geometry_grid: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 2)] p_geometry_grid_hi: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 3)] p_appearance_grid: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 4)] p_appearance_grid_hi: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 5)] p_geometry_mlp: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 6)] p_appearance_mlp: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 7)] p_beta: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 8)] rays: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 9)] samples: &mut [f32],
) {
    if id.x >= pc.n {
        return;
    }
    let i = (pc.first + id.x) as usize;
    let layout = words::model_layout_from_words(model_words, 0);
    let per = samples_per_ray(&layout);
    let (r, k) = (i / per, i % per);
    let ray = read_ray(rays, r);
    let (t, n) = model::ray_sample(&layout, &ray, r as u32, pc.seed, pc.jitter != 0, k);
    if k >= n || (i + 1) * SAMPLE_FLOATS > samples.len() {
        return;
    }
    let field = Field::new(
        model_words,
        [
            p_geometry_grid,
            p_geometry_grid_hi,
            p_appearance_grid,
            p_appearance_grid_hi,
            p_geometry_mlp,
            p_appearance_mlp,
            p_beta,
        ],
    );
    let params = field.params();
    let mut scratch = SampleScratch::new();
    let (sdf, rgb) = model::sample_forward(&layout, &params, &ray, t, &mut scratch);
    let b = i * SAMPLE_FLOATS;
    samples[b] = t;
    samples[b + 1] = sdf;
    samples[b + 2] = rgb[0];
    samples[b + 3] = rgb[1];
    samples[b + 4] = rgb[2];
}

/// Rebuilds a ray's [`RayCache`] from the sample records [`sample_forward_cs`] wrote in the
/// same submission (`n` from `model::ray_span`) and composites it.
#[inline(always)]
fn load_ray(
    layout: &ModelLayout,
    beta: f32,
    ray: &Ray,
    r: usize,
    samples: &[f32],
    cache: &mut RayCache,
) {
    let per = samples_per_ray(layout);
    cache.n = model::ray_span(layout, ray).2;
    let mut k = 0;
    while k < cache.n {
        let b = (r * per + k) * SAMPLE_FLOATS;
        cache.t[k] = float_at(samples, b);
        cache.sdf[k] = float_at(samples, b + 1);
        cache.rgb[k] = [
            float_at(samples, b + 2),
            float_at(samples, b + 3),
            float_at(samples, b + 4),
        ];
        k += 1;
    }
    model::ray_composite(layout, beta, cache);
}

/// Writes the per-sample cotangents of ray `r` into its records (zeros past `n`, so that
/// [`sample_backward_cs`] skips them).
#[inline(always)]
fn store_cotangents(
    layout: &ModelLayout,
    r: usize,
    n: usize,
    d_sdf: &[f32; MAX_SAMPLES],
    d_rgb: &[[f32; 3]; MAX_SAMPLES],
    samples: &mut [f32],
) {
    let per = samples_per_ray(layout);
    let mut k = 0;
    while k < per {
        let b = (r * per + k) * SAMPLE_FLOATS;
        if b + SAMPLE_FLOATS <= samples.len() {
            let live = k < n;
            samples[b + 5] = if live { d_sdf[k] } else { 0.0 };
            samples[b + 6] = if live { d_rgb[k][0] } else { 0.0 };
            samples[b + 7] = if live { d_rgb[k][1] } else { 0.0 };
            samples[b + 8] = if live { d_rgb[k][2] } else { 0.0 };
        }
        k += 1;
    }
}

/// Pass 2 of a training step: one ray per invocation. Composites the ray from its sample
/// records, takes `ray_loss`, back-propagates through the compositing
/// (`model::ray_composite_backward`), stores the per-sample cotangents and adds the beta
/// gradient.
///
/// - binding 0 `model`; binding 1 `beta` (one float); binding 2 the beta gradient (`i64`);
/// - binding 3 `rays`; binding 4 `samples`; binding 5 `results` ([`himap_core::gpu_abi::RESULT_FLOATS`] per ray).
#[spirv(compute(threads(64)))]
#[allow(clippy::too_many_arguments)]
pub fn ray_train_cs(
    #[spirv(global_invocation_id)] id: UVec3,
    #[spirv(push_constant)] pc: &TrainPush,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] model_words: &[u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] p_beta: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 2)] g_beta: &mut [i64],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 3)] rays: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 4)] samples: &mut [f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 5)] results: &mut [f32],
) {
    if id.x >= pc.n {
        return;
    }
    let r = (pc.first + id.x) as usize;
    let layout = words::model_layout_from_words(model_words, 0);
    let beta = first_or_zero(p_beta);
    let ray = read_ray(rays, r);
    let mut cache = RayCache::new();
    load_ray(&layout, beta, &ray, r, samples, &mut cache);
    let loss = LossConfig {
        lambda_color: pc.lambda_color,
        lambda_depth: pc.lambda_depth,
        ray_scale: pc.ray_scale,
        color_to_geometry: pc.color_to_geometry != 0,
        seed: pc.seed,
    };
    let (res, d_color, d_depth) = model::ray_loss(&ray, &cache.out, &loss);
    let mut d_sdf = [0.0f32; MAX_SAMPLES];
    let mut d_rgb = [[0.0f32; 3]; MAX_SAMPLES];
    if cache.n > 0 {
        let mut d_beta = 0.0f32;
        model::ray_composite_backward(
            &layout,
            beta,
            &cache,
            d_color,
            d_depth,
            0.0,
            loss.color_to_geometry,
            &mut d_sdf,
            &mut d_rgb,
            &mut d_beta,
        );
        let q = fixed::to_fixed(d_beta);
        if q != 0 {
            atomic_add_i64(g_beta, 0, q);
        }
    }
    store_cotangents(&layout, r, cache.n, &d_sdf, &d_rgb, samples);
    write_record(results, r, &ray_result_record(&res));
}

/// Pass 3 of a training or mapping step: one sample per invocation,
/// `model::sample_backward` of record `i` (ray `i / S`) with its stored `t` and cotangents,
/// the gradients added by [`AtomicModelSink`].
///
/// - binding 0 `model`; bindings 1..=7 the parameters ([`PARAM_BINDINGS`]); bindings 8..=14
///   the gradients in the same order (`i64`);
/// - binding 15 `rays`; binding 16 `samples`.
#[spirv(compute(threads(64)))]
#[allow(clippy::too_many_arguments)]
pub fn sample_backward_cs(
    #[spirv(global_invocation_id)] id: UVec3,
    #[spirv(push_constant)] pc: &SamplePush,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] model_words: &[u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] p_geometry_grid: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 2)] p_geometry_grid_hi: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 3)] p_appearance_grid: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 4)] p_appearance_grid_hi: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 5)] p_geometry_mlp: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 6)] p_appearance_mlp: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 7)] p_beta: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 8)] g_geometry_grid: &mut [i64],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 9)] g_geometry_grid_hi: &mut [i64],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 10)] g_appearance_grid: &mut [i64],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 11)] g_appearance_grid_hi: &mut [i64],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 12)] g_geometry_mlp: &mut [i64],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 13)] g_appearance_mlp: &mut [i64],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 14)] g_beta: &mut [i64],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 15)] rays: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 16)] samples: &[f32],
) {
    if id.x >= pc.n {
        return;
    }
    let i = (pc.first + id.x) as usize;
    let b = i * SAMPLE_FLOATS;
    if b + SAMPLE_FLOATS > samples.len() {
        return;
    }
    let d_sdf = samples[b + 5];
    let d_rgb = [samples[b + 6], samples[b + 7], samples[b + 8]];
    if d_sdf == 0.0 && d_rgb[0] == 0.0 && d_rgb[1] == 0.0 && d_rgb[2] == 0.0 {
        return;
    }
    let layout = words::model_layout_from_words(model_words, 0);
    let per = samples_per_ray(&layout);
    let ray = read_ray(rays, i / per);
    let field = Field::new(
        model_words,
        [
            p_geometry_grid,
            p_geometry_grid_hi,
            p_appearance_grid,
            p_appearance_grid_hi,
            p_geometry_mlp,
            p_appearance_mlp,
            p_beta,
        ],
    );
    let params = field.params();
    let mut sink = AtomicModelSink {
        geometry_grid: g_geometry_grid,
        geometry_grid_hi: g_geometry_grid_hi,
        geometry_split: field.geo.split,
        appearance_grid: g_appearance_grid,
        appearance_grid_hi: g_appearance_grid_hi,
        appearance_split: field.app.split,
        geometry_mlp: g_geometry_mlp,
        appearance_mlp: g_appearance_mlp,
        beta: g_beta,
    };
    let mut scratch = SampleScratch::new();
    model::sample_backward(
        &layout,
        &params,
        &ray,
        samples[b],
        d_sdf,
        d_rgb,
        &mut scratch,
        &mut sink,
    );
}

/// Decoder-weight gradients a workgroup of [`sample_backward_wg_cs`] sums in workgroup memory:
/// 2048 `i64` (16 KiB, the smallest `maxComputeSharedMemorySize` Vulkan allows).
pub const WORKGROUP_MLP_SLOTS: usize = himap_core::gpu_abi::WORKGROUP_MLP_SLOTS;

/// [`AtomicModelSink`] whose decoder-weight contributions go to workgroup memory first: the
/// geometry decoder's at `0..geo`, then the appearance decoder's at `geo..geo + app` when the
/// two fit [`WORKGROUP_MLP_SLOTS`] (`app_shared`); others go straight to the global buffers.
pub struct WorkgroupModelSink<'a, 'b> {
    pub global: AtomicModelSink<'a>,
    pub shared: &'b mut [i64; WORKGROUP_MLP_SLOTS],
    pub geo_shared: bool,
    pub app_shared: bool,
    pub geo_len: usize,
}

#[inline(always)]
fn atomic_add_shared(acc: &mut [i64; WORKGROUP_MLP_SLOTS], i: usize, q: i64) {
    if i < WORKGROUP_MLP_SLOTS {
        unsafe {
            atomic_i_add::<i64, { Scope::Workgroup as u32 }, { Semantics::NONE.bits() }>(
                &mut acc[i],
                q,
            );
        }
    }
}

impl ModelGradSink for WorkgroupModelSink<'_, '_> {
    #[inline(always)]
    fn add(&mut self, group: Group, i: usize, g: f32) {
        match group {
            Group::GeometryMlp if self.geo_shared => {
                let q = fixed::to_fixed(g);
                if q != 0 {
                    atomic_add_shared(self.shared, i, q);
                }
            }
            Group::AppearanceMlp if self.app_shared => {
                let q = fixed::to_fixed(g);
                if q != 0 {
                    atomic_add_shared(self.shared, self.geo_len + i, q);
                }
            }
            _ => self.global.add(group, i, g),
        }
    }
}

/// [`sample_backward_cs`] with the decoders' weight gradients summed per workgroup in
/// workgroup memory (64-bit atomics there), then one global atomic per weight the workgroup
/// touched, instead of one per contribution: integer sums in any order, so the same bits.
/// Used on devices with `shaderSharedInt64Atomics`. Every invocation reaches both barriers
/// (no early return); which decoders use the workgroup memory depends only on the model
/// words, so the control flow around the barriers is uniform. Bindings as
/// [`sample_backward_cs`].
#[spirv(compute(threads(64)))]
#[allow(clippy::too_many_arguments)]
pub fn sample_backward_wg_cs(
    #[spirv(global_invocation_id)] id: UVec3,
    #[spirv(local_invocation_index)] lid: u32,
    #[spirv(push_constant)] pc: &SamplePush,
    #[spirv(workgroup)] shared: &mut [i64; WORKGROUP_MLP_SLOTS],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] model_words: &[u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] p_geometry_grid: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 2)] p_geometry_grid_hi: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 3)] p_appearance_grid: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 4)] p_appearance_grid_hi: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 5)] p_geometry_mlp: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 6)] p_appearance_mlp: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 7)] p_beta: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 8)] g_geometry_grid: &mut [i64],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 9)] g_geometry_grid_hi: &mut [i64],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 10)] g_appearance_grid: &mut [i64],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 11)] g_appearance_grid_hi: &mut [i64],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 12)] g_geometry_mlp: &mut [i64],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 13)] g_appearance_mlp: &mut [i64],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 14)] g_beta: &mut [i64],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 15)] rays: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 16)] samples: &[f32],
) {
    let layout = words::model_layout_from_words(model_words, 0);
    let geo_len = layout.geometry_mlp.param_count as usize;
    let app_len = layout.appearance_mlp.param_count as usize;
    let geo_shared = geo_len <= WORKGROUP_MLP_SLOTS;
    let app_shared = geo_shared && geo_len + app_len <= WORKGROUP_MLP_SLOTS;
    let used = if app_shared {
        geo_len + app_len
    } else if geo_shared {
        geo_len
    } else {
        0
    };
    let mut k = lid as usize;
    while k < used {
        shared[k] = 0;
        k += WORKGROUP_SIZE as usize;
    }
    workgroup_memory_barrier_with_group_sync();
    let i = (pc.first + id.x) as usize;
    let b = i * SAMPLE_FLOATS;
    let mut active = id.x < pc.n && b + SAMPLE_FLOATS <= samples.len();
    let (mut d_sdf, mut d_rgb) = (0.0f32, [0.0f32; 3]);
    if active {
        d_sdf = samples[b + 5];
        d_rgb = [samples[b + 6], samples[b + 7], samples[b + 8]];
        active = !(d_sdf == 0.0 && d_rgb[0] == 0.0 && d_rgb[1] == 0.0 && d_rgb[2] == 0.0);
    }
    let field = Field::new(
        model_words,
        [
            p_geometry_grid,
            p_geometry_grid_hi,
            p_appearance_grid,
            p_appearance_grid_hi,
            p_geometry_mlp,
            p_appearance_mlp,
            p_beta,
        ],
    );
    let mut sink = WorkgroupModelSink {
        global: AtomicModelSink {
            geometry_grid: g_geometry_grid,
            geometry_grid_hi: g_geometry_grid_hi,
            geometry_split: field.geo.split,
            appearance_grid: g_appearance_grid,
            appearance_grid_hi: g_appearance_grid_hi,
            appearance_split: field.app.split,
            geometry_mlp: g_geometry_mlp,
            appearance_mlp: g_appearance_mlp,
            beta: g_beta,
        },
        shared,
        geo_shared,
        app_shared,
        geo_len,
    };
    if active {
        let per = samples_per_ray(&layout);
        let ray = read_ray(rays, i / per);
        let params = field.params();
        let mut scratch = SampleScratch::new();
        model::sample_backward(
            &layout,
            &params,
            &ray,
            samples[b],
            d_sdf,
            d_rgb,
            &mut scratch,
            &mut sink,
        );
    }
    workgroup_memory_barrier_with_group_sync();
    let mut k = lid as usize;
    while k < used {
        let q = sink.shared[k];
        if q != 0 {
            if k < geo_len {
                atomic_add_i64(sink.global.geometry_mlp, k, q);
            } else {
                atomic_add_i64(sink.global.appearance_mlp, k - geo_len, q);
            }
        }
        k += WORKGROUP_SIZE as usize;
    }
}

/// Pass 2 of a render: one ray per invocation, composited from its sample records at the bin
/// centres (as the CPU backends' `render`, loss 0).
///
/// - binding 0 `model`; binding 1 `beta`; binding 2 `rays`; binding 3 `samples`;
/// - binding 4 `results` ([`himap_core::gpu_abi::RESULT_FLOATS`] per ray).
#[spirv(compute(threads(64)))]
pub fn ray_render_cs(
    #[spirv(global_invocation_id)] id: UVec3,
    #[spirv(push_constant)] pc: &RangePush,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] model_words: &[u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] p_beta: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 2)] rays: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 3)] samples: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 4)] results: &mut [f32],
) {
    if id.x >= pc.n {
        return;
    }
    let r = (pc.first + id.x) as usize;
    let layout = words::model_layout_from_words(model_words, 0);
    let ray = read_ray(rays, r);
    let mut cache = RayCache::new();
    load_ray(&layout, first_or_zero(p_beta), &ray, r, samples, &mut cache);
    let res = model::RayResult {
        color: cache.out.color,
        depth: cache.out.depth,
        opacity: cache.out.opacity,
        loss: 0.0,
    };
    write_record(results, r, &ray_result_record(&res));
}

/// Pass 0 of a mapping step: the camera ray of every sampled pixel (`pixel::pixel_ray`),
/// written as a ray record for the per-sample passes. A pixel whose frame is outside the
/// window gets a zero ray (pass 2 ignores it).
///
/// - binding 0 `window`: [`words::WINDOW`] words; binding 1 `pixels`: frame, u, v per pixel;
/// - binding 2 `images`: the RGBA8 image slots; binding 3 `rays` (written).
#[spirv(compute(threads(64)))]
pub fn pixel_rays_cs(
    #[spirv(global_invocation_id)] id: UVec3,
    #[spirv(push_constant)] pc: &RangePush,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] window_words: &[u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] pixels: &[u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 2)] images: &[u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 3)] rays: &mut [f32],
) {
    if id.x >= pc.n {
        return;
    }
    let i = (pc.first + id.x) as usize;
    window_view!(let (_n, window) = window_words, images);
    let px = read_pixel(pixels, i);
    let (ray, _) = pixel::pixel_ray(&window, px);
    let b = i * RAY_FLOATS;
    if b + RAY_FLOATS <= rays.len() {
        rays[b] = ray.origin[0];
        rays[b + 1] = ray.origin[1];
        rays[b + 2] = ray.origin[2];
        rays[b + 3] = ray.dir[0];
        rays[b + 4] = ray.dir[1];
        rays[b + 5] = ray.dir[2];
        rays[b + 6] = ray.target[0];
        rays[b + 7] = ray.target[1];
        rays[b + 8] = ray.target[2];
        rays[b + 9] = ray.target_depth;
    }
}

#[inline(always)]
fn u32_at(v: &[u32], k: usize) -> u32 {
    if k < v.len() {
        v[k]
    } else {
        0
    }
}

#[inline(always)]
fn read_pixel(pixels: &[u32], i: usize) -> PixelSample {
    PixelSample {
        frame: u32_at(pixels, 3 * i),
        u: u32_at(pixels, 3 * i + 1),
        v: u32_at(pixels, 3 * i + 2),
    }
}

/// Pass 2a of a mapping step (only with the planarity prior): one pixel per invocation.
/// Composites the pixel's ray from its sample records and stores the rendered depth in the
/// pixel's [`PIXEL_AUX_FLOATS`] record, where [`pixel_loss_cs`] reads its triplet partners'
/// depths (the same composite the partner's own invocation makes, so the same bits).
///
/// Bindings as [`pixel_loss_cs`] (0 model, 1 beta, 6 rays, 7 samples, 9 `aux` used).
#[spirv(compute(threads(64)))]
#[allow(clippy::too_many_arguments)]
pub fn pixel_depth_cs(
    #[spirv(global_invocation_id)] id: UVec3,
    #[spirv(push_constant)] pc: &RangePush,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] model_words: &[u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] p_beta: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 6)] pixel_rays: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 7)] pixel_samples: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 9)] aux: &mut [f32],
) {
    if id.x >= pc.n {
        return;
    }
    let i = (pc.first + id.x) as usize;
    let layout = words::model_layout_from_words(model_words, 0);
    let beta = first_or_zero(p_beta);
    let mut cache = RayCache::new();
    let ray = read_ray(pixel_rays, i);
    load_ray(&layout, beta, &ray, i, pixel_samples, &mut cache);
    let b = i * PIXEL_AUX_FLOATS;
    if b + PIXEL_AUX_FLOATS <= aux.len() {
        aux[b] = cache.out.depth;
    }
}

/// Pass 2b of a mapping step: one pixel per invocation. Composites the pixel's ray from its
/// sample records and takes `pixel::pixel_loss` (colour L1, DIM-SLAM warping loss through
/// the rendered depth, depth prior, planarity with the partners' depths from
/// [`pixel_depth_cs`]); writes the pixel's result and the cotangents of its rendered colour
/// and depth (aux floats 1..=4) for [`pixel_backward_cs`].
///
/// Three passes instead of one whole-pixel kernel: NVIDIA's driver (580, H200) failed to
/// build the fused kernel (`VK_ERROR_UNKNOWN` from `vkCreateComputePipelines`) while it
/// built the loss and the compositing backward as separate kernels.
///
/// - binding 0 `model`; binding 1 `beta`; binding 2 the beta gradient;
/// - binding 3 `window` words; binding 4 `pixels`; binding 5 `images`;
/// - binding 6 `rays` (from [`pixel_rays_cs`]); binding 7 `samples`;
/// - binding 8 `results` ([`himap_core::gpu_abi::PIXEL_RESULT_FLOATS`] per pixel);
/// - binding 9 `aux` ([`PIXEL_AUX_FLOATS`] per pixel).
#[spirv(compute(threads(64)))]
#[allow(clippy::too_many_arguments)]
pub fn pixel_loss_cs(
    #[spirv(global_invocation_id)] id: UVec3,
    #[spirv(push_constant)] pc: &RangePush,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] model_words: &[u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] p_beta: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 3)] window_words: &[u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 4)] pixels: &[u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 5)] images: &[u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 6)] pixel_rays: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 7)] pixel_samples: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 8)] pixel_results: &mut [f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 9)] aux: &mut [f32],
) {
    if id.x >= pc.n {
        return;
    }
    let i = (pc.first + id.x) as usize;
    let layout = words::model_layout_from_words(model_words, 0);
    let beta = first_or_zero(p_beta);
    window_view!(let (n, window) = window_words, images);
    let loss = words::mapping_loss_from_words(window_words, words::WINDOW_LOSS);
    let px = read_pixel(pixels, i);
    let mut res = PixelResult::default();
    let mut d = [0.0f32; 4];
    if (px.frame as usize) < n {
        // the planarity partners' depths, composited by their own `pixel_depth_cs`
        let mut triplet = pixel::PixelTriplet::NONE;
        if loss.planar.weight != 0.0 {
            if let Some((first, m)) = pixel::triplet_of(i, pc.total as usize) {
                triplet.pixels = [
                    read_pixel(pixels, first),
                    read_pixel(pixels, first + 1),
                    read_pixel(pixels, first + 2),
                ];
                if pixel::is_line_triplet(&triplet.pixels) {
                    triplet.member = m as u32;
                    let mut k = 0;
                    while k < 3 {
                        if k != m {
                            triplet.depth[k] = float_at(aux, (first + k) * PIXEL_AUX_FLOATS);
                        }
                        k += 1;
                    }
                }
            }
        }
        let mut cache = RayCache::new();
        let ray = read_ray(pixel_rays, i);
        load_ray(&layout, beta, &ray, i, pixel_samples, &mut cache);
        let (r, d_color, d_depth) =
            pixel::pixel_loss(&window, px, &ray, &cache.out, cache.n, &loss, &triplet);
        res = r;
        d = [d_color[0], d_color[1], d_color[2], d_depth];
    }
    let b = i * PIXEL_AUX_FLOATS;
    if b + PIXEL_AUX_FLOATS <= aux.len() {
        aux[b + 1] = d[0];
        aux[b + 2] = d[1];
        aux[b + 3] = d[2];
        aux[b + 4] = d[3];
    }
    write_record(pixel_results, i, &pixel_result_record(&res));
}

/// Pass 2c of a mapping step: one pixel per invocation. Composites the pixel's ray again,
/// back-propagates the cotangents [`pixel_loss_cs`] left in the pixel's aux record through
/// the compositing, stores the per-sample cotangents and adds the beta gradient. Bindings
/// as [`pixel_loss_cs`] (0, 1, 2, 3, 4, 6, 7 and 9 used).
#[spirv(compute(threads(64)))]
#[allow(clippy::too_many_arguments)]
pub fn pixel_backward_cs(
    #[spirv(global_invocation_id)] id: UVec3,
    #[spirv(push_constant)] pc: &RangePush,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] model_words: &[u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] p_beta: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 2)] g_beta: &mut [i64],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 3)] window_words: &[u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 4)] pixels: &[u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 6)] pixel_rays: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 7)] pixel_samples: &mut [f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 9)] aux: &[f32],
) {
    if id.x >= pc.n {
        return;
    }
    let i = (pc.first + id.x) as usize;
    let layout = words::model_layout_from_words(model_words, 0);
    let beta = first_or_zero(p_beta);
    let loss = words::mapping_loss_from_words(window_words, words::WINDOW_LOSS);
    let (n, _, _, _) = words::window_frames(window_words);
    let px = read_pixel(pixels, i);
    let mut d_sdf = [0.0f32; MAX_SAMPLES];
    let mut d_rgb = [[0.0f32; 3]; MAX_SAMPLES];
    let mut live = 0;
    if (px.frame as usize) < n {
        let mut cache = RayCache::new();
        let ray = read_ray(pixel_rays, i);
        load_ray(&layout, beta, &ray, i, pixel_samples, &mut cache);
        live = cache.n;
        if cache.n > 0 {
            let b = i * PIXEL_AUX_FLOATS;
            let d_color = [
                float_at(aux, b + 1),
                float_at(aux, b + 2),
                float_at(aux, b + 3),
            ];
            let mut d_beta = 0.0f32;
            model::ray_composite_backward(
                &layout,
                beta,
                &cache,
                d_color,
                float_at(aux, b + 4),
                0.0,
                loss.color_to_geometry,
                &mut d_sdf,
                &mut d_rgb,
                &mut d_beta,
            );
            let q = fixed::to_fixed(d_beta);
            if q != 0 {
                atomic_add_i64(g_beta, 0, q);
            }
        }
    }
    store_cotangents(&layout, i, live, &d_sdf, &d_rgb, pixel_samples);
}

/// Signed distance at points: `out[i] = sdf_at(points[i])`. Bindings 0..=7 as
/// [`sample_forward_cs`]; binding 8 `points` (3 floats each), binding 9 `out` (1 float each).
#[spirv(compute(threads(64)))]
#[allow(clippy::too_many_arguments)]
pub fn sdf_query_cs(
    #[spirv(global_invocation_id)] id: UVec3,
    #[spirv(push_constant)] pc: &RangePush,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] model_words: &[u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] p_geometry_grid: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 2)] p_geometry_grid_hi: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 3)] p_appearance_grid: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 4)] p_appearance_grid_hi: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 5)] p_geometry_mlp: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 6)] p_appearance_mlp: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 7)] p_beta: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 8)] points: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 9)] out: &mut [f32],
) {
    if id.x >= pc.n {
        return;
    }
    let i = (pc.first + id.x) as usize;
    if (i + 1) * 3 > points.len() || i >= out.len() {
        return;
    }
    let layout = words::model_layout_from_words(model_words, 0);
    let field = Field::new(
        model_words,
        [
            p_geometry_grid,
            p_geometry_grid_hi,
            p_appearance_grid,
            p_appearance_grid_hi,
            p_geometry_mlp,
            p_appearance_mlp,
            p_beta,
        ],
    );
    let params = field.params();
    let p = [points[3 * i], points[3 * i + 1], points[3 * i + 2]];
    let mut scratch = SampleScratch::new();
    out[i] = model::sdf_at(&layout, &params, p, &mut scratch);
}

/// Colour at points: `out[3i..3i+3] = color_at(points[i])`. Bindings as [`sdf_query_cs`]
/// (`out`: 3 floats each).
#[spirv(compute(threads(64)))]
#[allow(clippy::too_many_arguments)]
pub fn color_query_cs(
    #[spirv(global_invocation_id)] id: UVec3,
    #[spirv(push_constant)] pc: &RangePush,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] model_words: &[u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] p_geometry_grid: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 2)] p_geometry_grid_hi: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 3)] p_appearance_grid: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 4)] p_appearance_grid_hi: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 5)] p_geometry_mlp: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 6)] p_appearance_mlp: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 7)] p_beta: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 8)] points: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 9)] out: &mut [f32],
) {
    if id.x >= pc.n {
        return;
    }
    let i = (pc.first + id.x) as usize;
    if (i + 1) * 3 > points.len() || (i + 1) * 3 > out.len() {
        return;
    }
    let layout = words::model_layout_from_words(model_words, 0);
    let field = Field::new(
        model_words,
        [
            p_geometry_grid,
            p_geometry_grid_hi,
            p_appearance_grid,
            p_appearance_grid_hi,
            p_geometry_mlp,
            p_appearance_mlp,
            p_beta,
        ],
    );
    let params = field.params();
    let p = [points[3 * i], points[3 * i + 1], points[3 * i + 2]];
    let mut scratch = SampleScratch::new();
    let c = model::color_at(&layout, &params, p, &mut scratch);
    out[3 * i] = c[0];
    out[3 * i + 1] = c[1];
    out[3 * i + 2] = c[2];
}

/// A step's first finiteness check: counts the result records whose loss is not finite
/// into `status[0]` (the CPU's `StepStats::rejected` test on the same values).
///
/// - binding 0 `results`; binding 1 `status` (`u32`, zeroed before the step).
#[spirv(compute(threads(64)))]
pub fn loss_check_cs(
    #[spirv(global_invocation_id)] id: UVec3,
    #[spirv(push_constant)] pc: &LossCheckPush,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] results: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] status: &mut [u32],
) {
    if id.x >= pc.n {
        return;
    }
    let b = ((pc.first + id.x) * pc.stride) as usize;
    let (a, c) = (b + pc.loss_a as usize, b + pc.loss_b as usize);
    if a < results.len()
        && c < results.len()
        && !(adam::is_finite(results[a]) && adam::is_finite(results[c]))
    {
        count_nonfinite(status);
    }
}

/// A step's second finiteness check: counts the parameters whose Adam update would not be
/// finite (`adam::adam_update_is_finite`) into `status[0]`; writes nothing else.
///
/// - bindings 0..=3 as [`adam_cs`] (read only here); binding 4 `status`.
#[spirv(compute(threads(64)))]
pub fn adam_check_cs(
    #[spirv(global_invocation_id)] id: UVec3,
    #[spirv(push_constant)] pc: &AdamPush,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] params: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] m: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 2)] v: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 3)] grad: &[i64],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 4)] status: &mut [u32],
) {
    if id.x >= pc.n {
        return;
    }
    let i = (pc.first + id.x) as usize;
    if i >= params.len() || i >= m.len() || i >= v.len() || i >= grad.len() {
        return;
    }
    if status.len() < STATUS_WORDS {
        return;
    }
    let s = pc.step.at(status[STATUS_STEPS].wrapping_add(1));
    if !adam::adam_update_is_finite(&s, params[i], m[i], v[i], fixed::from_fixed(grad[i])) {
        count_nonfinite(status);
    }
}

/// The end of a step: counts it as taken (`status[STATUS_STEPS] += 1`) unless its checks
/// counted a non-finite value. One invocation.
///
/// - binding 0 `status` (`gpu_abi::STATUS_WORDS`).
#[spirv(compute(threads(64)))]
pub fn step_count_cs(
    #[spirv(global_invocation_id)] id: UVec3,
    #[spirv(push_constant)] pc: &RangePush,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] status: &mut [u32],
) {
    if id.x != 0 || pc.n == 0 || status.len() < STATUS_WORDS || status[STATUS_REJECTED] != 0 {
        return;
    }
    status[STATUS_STEPS] = status[STATUS_STEPS].wrapping_add(1);
}

/// Adam on one parameter per invocation (`adam::adam_update` with the gradient converted by
/// `fixed::from_fixed`), the scalars of the step as push constants with the bias corrections
/// of the device's step count (`AdamStep::at(status[STATUS_STEPS] + 1)`); nothing when the
/// step's checks counted a non-finite value (the step is rejected).
///
/// - binding 0 `params`, binding 1 `m`, binding 2 `v` (f32), binding 3 `grad` (i64);
/// - binding 4 `status` ([`loss_check_cs`], [`adam_check_cs`]).
#[spirv(compute(threads(64)))]
pub fn adam_cs(
    #[spirv(global_invocation_id)] id: UVec3,
    #[spirv(push_constant)] pc: &AdamPush,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] params: &mut [f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] m: &mut [f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 2)] v: &mut [f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 3)] grad: &[i64],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 4)] status: &[u32],
) {
    if id.x >= pc.n || status.len() < STATUS_WORDS || status[STATUS_REJECTED] != 0 {
        return;
    }
    let i = (pc.first + id.x) as usize;
    if i >= params.len() || i >= m.len() || i >= v.len() || i >= grad.len() {
        return;
    }
    let g = grad[i];
    // No gradient and both moments +0: the update would write the same bits back (the
    // checks passed, so the step size is finite and `param - step * 0 / eps` is `param`),
    // as the CPU's skip of blocks no step reached. Skipping saves a large box's untouched
    // parameters their reads and writes.
    if g == 0 && m[i].to_bits() == 0 && v[i].to_bits() == 0 {
        return;
    }
    let s = pc.step.at(status[STATUS_STEPS].wrapping_add(1));
    let mut p = params[i];
    let mut mi = m[i];
    let mut vi = v[i];
    adam::adam_update(&s, &mut p, &mut mi, &mut vi, fixed::from_fixed(g));
    params[i] = p;
    m[i] = mi;
    v[i] = vi;
}
