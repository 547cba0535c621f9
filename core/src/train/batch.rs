//! The batch driver of the CPU backends: what one item (a ray or a pixel) of a training step,
//! a render or a mapping iteration runs, and the loop that drives a run of items in order.
//!
//! The core's reference backend ([`crate::train::reference::CpuBackend`]) drives a whole batch as one run
//! with the [`Recompute`](crate::field::model::Recompute) tape; the host's parallel backend cuts the
//! batch into chunks that run on a thread pool, each with its own tape and gradient sink. In
//! both, item `i` of the batch keeps `i` as its id (the stratified jitter and the warping
//! loss's pixel id), so the contributions do not depend on how the batch is cut: the
//! fixed-point sums are the same integers and the results the same bits.
//!
//! The GPU runs the same per-item functions ([`ray_train`], [`ray_forward_taped`],
//! [`pixel_train`]) as per-sample passes; its driver is the Vulkan backend's own.

use crate::camera::{Pose, PoseRead};
use crate::field::model::{
    ray_depth_forward_taped, ray_forward_taped, ray_train, sample_backward, LossConfig,
    ModelGradSink, ModelLayout, Params, Ray, RayCache, RayResult, SampleScratch, SampleTape,
};
use crate::loss::warp::FrameImages;
use crate::train::backend::{summarize, summarize_pixels, MapBatch, StepStats};
use crate::train::pixel::{
    is_line_triplet, pixel_train, triplet_depth, triplet_of, MappingLoss, PixelResult, PixelSample,
    PixelTriplet, SlotPixels, WindowImages, WindowView,
};
use crate::ParamRead;

/// What one thread needs to run items: the model, its parameters, the ray cache and scratch,
/// the tape that keeps the forward's activations and the sink that receives the gradient.
pub struct ItemRunner<'r, P: ParamRead + ?Sized, T: SampleTape, S: ModelGradSink> {
    /// The model's shapes.
    pub layout: &'r ModelLayout,
    /// The model's parameters.
    pub params: &'r Params<'r, P>,
    /// Samples and rendering of the current item's ray.
    pub cache: &'r mut RayCache,
    /// Per-sample evaluation scratch.
    pub scratch: &'r mut SampleScratch,
    /// Keeps the forward's decoder activations for the backward.
    pub tape: &'r mut T,
    /// Receives the gradient contributions.
    pub sink: &'r mut S,
    /// The rendered depths of the planarity triplet the runner is in (a run's items come in
    /// order, so a triplet's three items usually share one runner); start a run with
    /// [`TripletMemo::EMPTY`].
    pub memo: TripletMemo,
}

/// Rendered depths of one planarity triplet, kept between its items: the depth of batch item
/// `first + k` when `known[k]`. A depth is a function of the parameters, the item's pixel, id
/// and the step's seed only, none of which change within a run, so a kept depth has the bits
/// a new forward would give (a runner lives for one run of items).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TripletMemo {
    /// Batch index of the triplet's first item (`usize::MAX`: none).
    pub first: usize,
    /// Rendered depth of item `first + k` (camera z, metres), valid when `known[k]`.
    pub depth: [f32; 3],
    /// Which of the three depths are kept.
    pub known: [bool; 3],
}

impl TripletMemo {
    /// Nothing kept.
    pub const EMPTY: Self = Self {
        first: usize::MAX,
        depth: [0.0; 3],
        known: [false; 3],
    };
}

/// One batch of work: its items and what each runs.
pub trait BatchJob {
    /// What one item produces.
    type Output: Copy + Default;

    /// Items in the batch.
    fn len(&self) -> usize;

    /// Whether the batch has no items.
    fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Runs item `i` (its index in the whole batch, also its id).
    fn run<P: ParamRead + ?Sized, T: SampleTape, S: ModelGradSink>(
        &self,
        r: &mut ItemRunner<'_, P, T, S>,
        i: usize,
    ) -> Self::Output;

    /// The step statistics of the whole batch's outputs (in item order).
    fn summarize(results: &[Self::Output], t: u32) -> StepStats;
}

/// Runs items `first..first + out.len()` of `job` in order, item `first + k` into `out[k]`.
/// Items past the end of the batch leave their output untouched.
#[inline(always)]
pub fn run_items<J: BatchJob, P: ParamRead + ?Sized, T: SampleTape, S: ModelGradSink>(
    job: &J,
    r: &mut ItemRunner<'_, P, T, S>,
    first: usize,
    out: &mut [J::Output],
) {
    let n = job.len();
    for (k, o) in out.iter_mut().enumerate() {
        let i = first + k;
        if i >= n {
            break;
        }
        *o = job.run(r, i);
    }
}

/// A render's tape: every sample's forward goes to slot 0 of the runner's tape (the same
/// functions, so the same bits), since a render keeps nothing for a backward; one slot stays
/// in the L1 cache where a training ray's tape writes 2 x 2.5 KB per sample. Its backward (which
/// no render calls) recomputes the sample.
struct RenderTape<'t, T: SampleTape>(&'t mut T);

impl<T: SampleTape> SampleTape for RenderTape<'_, T> {
    #[cfg(not(target_arch = "spirv"))]
    #[inline(always)]
    fn has_lanes(&self) -> bool {
        self.0.has_lanes()
    }

    #[cfg(not(target_arch = "spirv"))]
    #[inline(always)]
    fn forward_lanes<P: ParamRead + ?Sized>(
        &mut self,
        layout: &ModelLayout,
        params: &Params<'_, P>,
        ray: &Ray,
        _i: usize,
        ts: &[f32],
        _keep: bool,
        s: &mut SampleScratch,
        sdf: &mut [f32; crate::field::mlp::LANES],
        rgb: &mut [[f32; 3]; crate::field::mlp::LANES],
    ) {
        // A render: nothing kept, slot 0 on as the one-sample forward.
        self.0
            .forward_lanes(layout, params, ray, 0, ts, false, s, sdf, rgb);
    }

    #[cfg(not(target_arch = "spirv"))]
    #[inline(always)]
    fn lazy_color(&self) -> bool {
        self.0.lazy_color()
    }

    #[cfg(not(target_arch = "spirv"))]
    #[inline(always)]
    fn render_lanes_part<P: ParamRead + ?Sized, const GEO: bool, const APP: bool>(
        &mut self,
        layout: &ModelLayout,
        params: &Params<'_, P>,
        ray: &Ray,
        ts: &[f32],
        s: &mut SampleScratch,
        sdf: &mut [f32; crate::field::mlp::LANES],
        rgb: &mut [[f32; 3]; crate::field::mlp::LANES],
    ) {
        self.0
            .render_lanes_part::<P, GEO, APP>(layout, params, ray, ts, s, sdf, rgb);
    }

    #[inline(always)]
    fn forward<P: ParamRead + ?Sized>(
        &mut self,
        layout: &ModelLayout,
        params: &Params<'_, P>,
        ray: &Ray,
        _i: usize,
        t: f32,
        s: &mut SampleScratch,
    ) -> (f32, [f32; 3]) {
        self.0.render_forward(layout, params, ray, 0, t, s)
    }

    #[inline(always)]
    fn sdf_forward<P: ParamRead + ?Sized>(
        &mut self,
        layout: &ModelLayout,
        params: &Params<'_, P>,
        ray: &Ray,
        _i: usize,
        t: f32,
        s: &mut SampleScratch,
    ) -> f32 {
        self.0.sdf_forward(layout, params, ray, 0, t, s)
    }

    #[inline(always)]
    fn backward<P: ParamRead + ?Sized, S: ModelGradSink>(
        &self,
        layout: &ModelLayout,
        params: &Params<'_, P>,
        ray: &Ray,
        _i: usize,
        t: f32,
        _rgb: [f32; 3],
        d_sdf: f32,
        d_rgb: [f32; 3],
        s: &mut SampleScratch,
        sink: &mut S,
    ) {
        sample_backward(layout, params, ray, t, d_sdf, d_rgb, s, sink);
    }

    #[inline(always)]
    fn prefetch<P: ParamRead + ?Sized>(
        &self,
        layout: &ModelLayout,
        params: &Params<'_, P>,
        ray: &Ray,
        t: f32,
    ) {
        self.0.prefetch(layout, params, ray, t);
    }
}

/// What a [`Rays`] job does with each ray.
#[derive(Clone, Copy)]
pub enum RayJob<'a> {
    /// A training step: [`ray_train`] with this loss.
    Train(&'a LossConfig),
    /// A render at the bins' centres (no jitter; the sink receives nothing).
    Render,
    /// A render of depth and opacity alone ([`ray_depth_forward_taped`]): the depth and
    /// opacity bits of [`RayJob::Render`], colour 0.
    RenderDepth,
}

/// Rays: a training step, a render or a depth-only render of every ray (see [`RayJob`]).
#[derive(Clone, Copy)]
pub struct Rays<'a> {
    /// The batch's rays (item `i` is ray `i`).
    pub rays: &'a [Ray],
    /// What is done with them.
    pub job: RayJob<'a>,
}

impl BatchJob for Rays<'_> {
    type Output = RayResult;

    fn len(&self) -> usize {
        self.rays.len()
    }

    #[inline(always)]
    fn run<P: ParamRead + ?Sized, T: SampleTape, S: ModelGradSink>(
        &self,
        r: &mut ItemRunner<'_, P, T, S>,
        i: usize,
    ) -> RayResult {
        let (ray, id) = (&self.rays[i], i as u32);
        let (l, p) = (r.layout, r.params);
        match self.job {
            RayJob::Train(loss) => {
                return ray_train(l, p, ray, id, loss, r.cache, r.scratch, r.tape, r.sink);
            }
            RayJob::Render => {
                let tape = &mut RenderTape(&mut *r.tape);
                ray_forward_taped(l, p, ray, id, 0, false, r.cache, r.scratch, tape);
            }
            RayJob::RenderDepth => {
                let tape = &mut RenderTape(&mut *r.tape);
                ray_depth_forward_taped(l, p, ray, id, 0, false, r.cache, r.scratch, tape);
            }
        }
        let out = &r.cache.out;
        RayResult {
            color: out.color,
            depth: out.depth,
            opacity: out.opacity,
            loss: 0.0,
        }
    }

    fn summarize(results: &[RayResult], t: u32) -> StepStats {
        summarize(results, t)
    }
}

/// A mapping iteration: [`pixel_train`] for every sampled pixel of a window.
pub struct MapPixels<'a, I: FrameImages + ?Sized, PS: PoseRead + ?Sized> {
    /// The sampled pixels (item `i` is pixel `i`).
    pub pixels: &'a [PixelSample],
    /// The window the pixels' `frame` indices refer to.
    pub window: WindowView<'a, I, PS>,
    /// Loss weights and switches.
    pub loss: &'a MappingLoss,
}

impl<'a, P: SlotPixels + ?Sized> MapPixels<'a, WindowImages<'a, P>, [Pose]> {
    /// The job of a mapping batch over `images`, the window's slot images (see
    /// [`MapBatch::window_images`]).
    pub fn of(batch: &'a MapBatch<'a>, images: &'a WindowImages<'a, P>) -> Self {
        MapPixels {
            pixels: batch.pixels,
            window: WindowView {
                k: batch.k,
                poses: batch.poses,
                images,
            },
            loss: &batch.loss,
        }
    }
}

impl<I: FrameImages + ?Sized, PS: PoseRead + ?Sized> MapPixels<'_, I, PS> {
    /// Item `i`'s planarity triplet, the partners' depths rendered here unless the runner's
    /// [`TripletMemo`] has them (from the triplet's earlier items in this run).
    fn triplet<P: ParamRead + ?Sized, T: SampleTape, S: ModelGradSink>(
        &self,
        r: &mut ItemRunner<'_, P, T, S>,
        i: usize,
    ) -> PixelTriplet {
        let mut t = PixelTriplet::NONE;
        if self.loss.planar.weight == 0.0 {
            return t;
        }
        let Some((first, m)) = triplet_of(i, self.pixels.len()) else {
            return t;
        };
        let mut k = 0;
        while k < 3 {
            t.pixels[k] = self.pixels[first + k];
            k += 1;
        }
        if !is_line_triplet(&t.pixels) {
            return t;
        }
        t.member = m as u32;
        if r.memo.first != first {
            r.memo = TripletMemo::EMPTY;
            r.memo.first = first;
        }
        let mut k = 0;
        while k < 3 {
            if k != m && r.memo.known[k] {
                t.depth[k] = r.memo.depth[k];
            } else if k != m {
                t.depth[k] = triplet_depth(
                    r.layout,
                    r.params,
                    &self.window,
                    t.pixels[k],
                    (first + k) as u32,
                    self.loss,
                    r.cache,
                    r.scratch,
                );
                r.memo.depth[k] = t.depth[k];
                r.memo.known[k] = true;
            }
            k += 1;
        }
        t
    }
}

impl<I: FrameImages + ?Sized, PS: PoseRead + ?Sized> BatchJob for MapPixels<'_, I, PS> {
    type Output = PixelResult;

    fn len(&self) -> usize {
        self.pixels.len()
    }

    #[inline(always)]
    fn run<P: ParamRead + ?Sized, T: SampleTape, S: ModelGradSink>(
        &self,
        r: &mut ItemRunner<'_, P, T, S>,
        i: usize,
    ) -> PixelResult {
        let triplet = self.triplet(r, i);
        let result = pixel_train(
            r.layout,
            r.params,
            &self.window,
            self.pixels[i],
            i as u32,
            self.loss,
            &triplet,
            r.cache,
            r.scratch,
            r.tape,
            r.sink,
        );
        let m = triplet.member as usize;
        if m < 3 && r.memo.first == i - m {
            r.memo.depth[m] = result.depth;
            r.memo.known[m] = true;
        }
        result
    }

    fn summarize(results: &[PixelResult], t: u32) -> StepStats {
        summarize_pixels(results, t)
    }
}
