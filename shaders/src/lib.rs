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
//! - scalars that change per dispatch (`n`, seeds) come as push constants ([`Dispatch`]);
//! - layouts (offset tables) come as `u32` words in a storage buffer, f32 fields as their bits
//!   (see [`words`]);
//! - entry points live at the crate root: rust-gpu names an entry point in a module
//!   `module::name`.
//!
//! rust-gpu 0.11 rejects, in code reachable from an entry point: `[false; N]` (bool array
//! repeat: "memset invalid on bool pattern"), `Result<_, himap_core::Error>` values (the
//! `&'static str` payload; layout constructors are host-side), unsizing a function-local array
//! to a slice (`&[T; N]` -> `&[T]`: only storage buffers can be slices), `u32::saturating_sub`
//! ("not implemented yet"), and `f64` without the `Float64` capability (`math::sin`/`cos`).
#![cfg_attr(target_arch = "spirv", no_std)]

pub mod words;

use himap_core::camera::{Intrinsics, Pose};
use himap_core::grid::{self, MAX_GRID_FEATURES};
use himap_core::mlp::{self, MlpScratch, MAX_OUT, MAX_WIDTH};
use himap_core::{fixed, rng, Aabb, GradSink};
use spirv_std::arch::atomic_i_add;
use spirv_std::glam::UVec3;
use spirv_std::memory::{Scope, Semantics};
use spirv_std::spirv;

/// Invocations per workgroup of every entry point (x only).
pub const WORKGROUP_SIZE: u32 = 64;

/// Push constants of every entry point.
#[derive(Clone, Copy)]
#[repr(C)]
pub struct Dispatch {
    /// Number of items; invocations with `id.x >= n` do nothing.
    pub n: u32,
    /// Entry-point specific (seed, bucket count, ...).
    pub a: u32,
    pub b: u32,
    pub c: u32,
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
/// Push constants: `n` = pixel count, `a` = seed.
#[spirv(compute(threads(64)))]
pub fn probe_cs(
    #[spirv(global_invocation_id)] id: UVec3,
    #[spirv(push_constant)] pc: &Dispatch,
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
    let r = rng::uniform(pc.a, i, 0);
    let t = 0.5 + 4.0 * r;
    let p = [o[0] + t * d[0], o[1] + t * d[1], o[2] + t * d[2]];
    let x = aabb.normalize(p);
    let base = i as usize * 4;
    out[base] = x[0];
    out[base + 1] = x[1];
    out[base + 2] = x[2];
    out[base + 3] = fixed::from_fixed(fixed::to_fixed(r));
}

/// Fixed-point atomics: `acc[i % buckets] += to_fixed(values[i])` through [`AtomicSink`]. The
/// sums are order-independent, so they match `himap_core::FixedSink` bit for bit.
///
/// - binding 0 `values`: `n` floats;
/// - binding 1 `acc`: the `i64` accumulators.
///
/// Push constants: `n` = number of values, `a` = buckets (0 or more than `acc.len()` means
/// `acc.len()`).
#[spirv(compute(threads(64)))]
pub fn fixed_accumulate_cs(
    #[spirv(global_invocation_id)] id: UVec3,
    #[spirv(push_constant)] pc: &Dispatch,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] values: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] acc: &mut [i64],
) {
    let i = id.x as usize;
    let len = acc.len();
    if i >= pc.n as usize || i >= values.len() || len == 0 {
        return;
    }
    let mut buckets = pc.a as usize;
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
    #[spirv(push_constant)] pc: &Dispatch,
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
    #[spirv(push_constant)] pc: &Dispatch,
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
