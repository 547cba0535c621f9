//! `himap-core`: the numerical heart of himap, a Rust implementation of Hi-Map (Hua et al.,
//! arXiv 2401.03203), monocular dense mapping with a hierarchical factorized radiance field.
//!
//! `#![no_std]`, no allocator. Every size is fixed at construction; capacity and shape problems
//! are [`Error`] values, never panics. Every function that runs per ray, per sample or per
//! parameter lives here once and is called both by the CPU backends and, through
//! `himap-shaders`, by the Vulkan backend. To keep the two bit-identical these kernels:
//! - call only the vendored [`math`] module for transcendental functions (never `libm`,
//!   never `glam` methods that go through it, never `mul_add`);
//! - read parameters through [`ParamRead`] and write gradients through [`GradSink`], which the
//!   backends implement as fixed-point `i64` accumulation ([`fixed`]);
//! - use plain arrays and slices with clamped indices, no recursion, no trait objects.
#![cfg_attr(not(test), no_std)]
#![deny(unsafe_code)]
#![deny(missing_docs)]

pub mod camera;
pub mod error;
pub mod field;
pub mod gpu_abi;
pub mod loss;
#[cfg(feature = "heapless")]
pub mod mapper;
pub mod math;
pub mod rng;
pub mod train;

pub use error::Error;
use field::mlp;
use train::fixed;

/// An axis-aligned box in world coordinates (metres).
///
/// # Examples
///
/// ```rust
/// use himap_core::Aabb;
///
/// let b = Aabb::new([-1.0, 0.0, 2.0], [1.0, 4.0, 3.0]);
/// assert!(b.is_valid());
/// assert_eq!(b.extent(), [2.0, 4.0, 1.0]);
/// // The centre maps to 0, the corners to -1 and +1; outside points are clamped.
/// assert_eq!(b.normalize([0.0, 2.0, 2.5]), [0.0, 0.0, 0.0]);
/// assert_eq!(b.normalize([-1.0, 4.0, 10.0]), [-1.0, 1.0, 1.0]);
/// // An empty box is not valid.
/// assert!(!Aabb::new([0.0; 3], [0.0; 3]).is_valid());
/// ```
#[derive(Clone, Copy, Debug, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Aabb {
    /// Minimum corner (metres).
    pub min: [f32; 3],
    /// Maximum corner (metres).
    pub max: [f32; 3],
}

impl Aabb {
    /// A box from its minimum and maximum corners (not checked: see [`Aabb::is_valid`]).
    pub const fn new(min: [f32; 3], max: [f32; 3]) -> Self {
        Self { min, max }
    }

    /// Extent along each axis.
    pub fn extent(&self) -> [f32; 3] {
        [
            self.max[0] - self.min[0],
            self.max[1] - self.min[1],
            self.max[2] - self.min[2],
        ]
    }

    /// Whether the box has a finite, strictly positive extent on every axis.
    pub fn is_valid(&self) -> bool {
        let e = self.extent();
        let mut ok = true;
        let mut a = 0;
        while a < 3 {
            ok &= self.min[a].is_finite() && self.max[a].is_finite() && e[a] > 0.0;
            a += 1;
        }
        ok
    }

    /// Maps a world position to grid coordinates in [-1, 1] (align-corners: -1 is the first
    /// vertex, +1 the last), clamped to the border.
    #[inline]
    pub fn normalize(&self, p: [f32; 3]) -> [f32; 3] {
        let mut out = [0.0f32; 3];
        let mut a = 0;
        while a < 3 {
            let x = math::div(p[a] - self.min[a], self.max[a] - self.min[a]) * 2.0 - 1.0;
            out[a] = math::clamp(x, -1.0, 1.0);
            a += 1;
        }
        out
    }
}

/// Read access to a flat parameter buffer. Implemented for `[f32]`; a GPU backend whose tensor
/// is split over several storage buffers implements it over the parts.
pub trait ParamRead {
    /// Parameter `i` of the flat buffer.
    fn at(&self, i: usize) -> f32;

    /// The whole buffer as one slice, when it is one (host-side kernels that read rows of
    /// channels use it; the GPU's split buffers are not, and never call it).
    #[inline(always)]
    fn as_slice(&self) -> Option<&[f32]> {
        None
    }

    /// `acc[i] += self.at(offset + i) * g` for every `i < n`, each `acc[i]` on its own (a
    /// decoder row's share of the input gradient). A slice does it over a sub-slice, which a
    /// CPU vectorises; the operations are the same.
    #[inline(always)]
    fn axpy(&self, offset: usize, g: f32, acc: &mut [f32; mlp::MAX_WIDTH], n: usize) {
        let mut i = 0;
        while i < n && i < mlp::MAX_WIDTH {
            acc[i] += self.at(offset + i) * g;
            i += 1;
        }
    }
}

impl ParamRead for [f32] {
    #[inline(always)]
    fn as_slice(&self) -> Option<&[f32]> {
        Some(self)
    }

    #[inline(always)]
    fn at(&self, i: usize) -> f32 {
        self[i]
    }

    #[inline(always)]
    fn axpy(&self, offset: usize, g: f32, acc: &mut [f32; mlp::MAX_WIDTH], n: usize) {
        let n = if n > mlp::MAX_WIDTH {
            mlp::MAX_WIDTH
        } else {
            n
        };
        match self.get(offset..offset + n) {
            Some(row) => {
                for (a, &w) in acc[..n].iter_mut().zip(row) {
                    *a += w * g;
                }
            }
            None => {
                // Out of range: the element-wise form (indexes, and panics, like `at`).
                let mut i = 0;
                while i < n {
                    acc[i] += self.at(offset + i) * g;
                    i += 1;
                }
            }
        }
    }
}

/// Where backward passes put their per-parameter gradient contributions. Every call is one
/// contribution; backends convert each one individually with [`fixed::to_fixed`] and add it
/// to an `i64` buffer, so the sum is independent of order.
pub trait GradSink {
    /// Whether [`Self::add_layer`] takes a decoder layer's parameter contributions in one
    /// call (a host sink that batches them over samples). False: the backward calls
    /// [`Self::add`] and [`Self::add_scaled`] row by row, as the shaders do.
    const LAYERS: bool = false;

    /// Adds one gradient contribution `g` to parameter `i`.
    fn add(&mut self, i: usize, g: f32);

    /// A decoder layer's parameter contributions for one sample: for every unit `j <
    /// fan_out` whose gradient `gs[j]` is not zero, `add(b_off + j, gs[j])` and
    /// `add_scaled(w_off + j * fan_in, gs[j], xs, fan_in)` (zero units contribute exactly 0).
    /// Called instead of those only when [`Self::LAYERS`] is true; a sink may defer the
    /// additions (to a flush of its own before the sums are read): the contributions, and
    /// hence the integer sums, are the same.
    #[inline(always)]
    #[allow(clippy::too_many_arguments)]
    fn add_layer(
        &mut self,
        w_off: usize,
        b_off: usize,
        gs: &[f32; mlp::MAX_WIDTH],
        fan_out: usize,
        xs: &[f32; mlp::MAX_WIDTH],
        fan_in: usize,
    ) {
        let mut j = 0;
        while j < fan_out && j < mlp::MAX_WIDTH {
            let g = gs[j];
            if g != 0.0 {
                self.add(b_off + j, g);
                self.add_scaled(w_off + j * fan_in, g, xs, fan_in);
            }
            j += 1;
        }
    }

    /// `add(offset + i, g * xs[i])` for every `i < n` (one contribution each; a decoder
    /// layer's weight row). Backends whose buffer is one slice override it with a tight loop
    /// over that slice; the contributions and hence the integer sums are the same.
    #[inline(always)]
    fn add_scaled(&mut self, offset: usize, g: f32, xs: &[f32; mlp::MAX_WIDTH], n: usize) {
        let mut i = 0;
        while i < n && i < mlp::MAX_WIDTH {
            self.add(offset + i, g * xs[i]);
            i += 1;
        }
    }

    /// `add_scaled(offsets[k], gs[k], xs, n)` for each `k` in order: the corners of one
    /// interpolated read, which share their row of values. A backend may override it to add
    /// the rows together (a narrow grid's neighbouring corners are one contiguous run); the
    /// contributions, and hence the integer sums, are the same.
    #[inline(always)]
    fn add_scaled_rows<const R: usize>(
        &mut self,
        offsets: [usize; R],
        gs: [f32; R],
        xs: &[f32; mlp::MAX_WIDTH],
        n: usize,
    ) {
        let mut k = 0;
        while k < R {
            self.add_scaled(offsets[k], gs[k], xs, n);
            k += 1;
        }
    }
}

/// A sink that drops everything (forward-only uses of a backward, and tests).
pub struct NullSink;

impl GradSink for NullSink {
    #[inline(always)]
    fn add(&mut self, _i: usize, _g: f32) {}
}

/// Accumulates contributions into a fixed-point `i64` slice. This is the reference
/// accumulation the CPU backends use and the GPU reproduces with atomics.
///
/// # Examples
///
/// ```rust
/// use himap_core::train::fixed::from_fixed;
/// use himap_core::{FixedSink, GradSink};
///
/// let mut acc = [0i64; 2];
/// let mut sink = FixedSink { acc: &mut acc };
/// sink.add(0, 0.25);
/// sink.add(0, -1.0);
/// sink.add(1, 2.0);
/// sink.add(7, 1.0); // past the end: dropped
/// assert_eq!(acc.map(from_fixed), [-0.75, 2.0]);
/// ```
pub struct FixedSink<'a> {
    /// Per-parameter gradient sums in fixed point ([`fixed::to_fixed`]); contributions to
    /// indices past its end are dropped.
    pub acc: &'a mut [i64],
}

impl GradSink for FixedSink<'_> {
    #[inline(always)]
    fn add(&mut self, i: usize, g: f32) {
        if i < self.acc.len() {
            self.acc[i] = self.acc[i].wrapping_add(fixed::to_fixed(g));
        }
    }
}

/// Accumulates contributions in plain `f32` (tests and finite-difference checks only: the
/// result depends on the order of the additions).
pub struct F32Sink<'a> {
    /// Per-parameter gradient sums; contributions to indices past its end are dropped.
    pub acc: &'a mut [f32],
}

impl GradSink for F32Sink<'_> {
    #[inline(always)]
    fn add(&mut self, i: usize, g: f32) {
        if i < self.acc.len() {
            self.acc[i] += g;
        }
    }
}
