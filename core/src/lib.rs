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

pub mod camera;
pub mod error;
pub mod field;
pub mod gpu_abi;
pub mod loss;
/// The mapper keeps its frames in `heapless` vectors: host-side only (the shaders build the
/// core without the feature).
#[cfg(feature = "heapless")]
pub mod mapper;
pub mod math;
pub mod rng;
pub mod train;

pub use error::Error;
use field::mlp;
use train::fixed;

/// An axis-aligned box in world coordinates (metres).
#[derive(Clone, Copy, Debug, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Aabb {
    pub min: [f32; 3],
    pub max: [f32; 3],
}

impl Aabb {
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
            let x = (p[a] - self.min[a]) / (self.max[a] - self.min[a]) * 2.0 - 1.0;
            out[a] = math::clamp(x, -1.0, 1.0);
            a += 1;
        }
        out
    }
}

/// Read access to a flat parameter buffer. Implemented for `[f32]`; a GPU backend whose tensor
/// is split over several storage buffers implements it over the parts.
pub trait ParamRead {
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
    fn add(&mut self, i: usize, g: f32);

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
}

/// A sink that drops everything (forward-only uses of a backward, and tests).
pub struct NullSink;

impl GradSink for NullSink {
    #[inline(always)]
    fn add(&mut self, _i: usize, _g: f32) {}
}

/// Accumulates contributions into a fixed-point `i64` slice. This is the reference
/// accumulation the CPU backends use and the GPU reproduces with atomics.
pub struct FixedSink<'a> {
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
