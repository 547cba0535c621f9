//! One training step on a batch of rays, and the [`Backend`] trait that the CPU and Vulkan
//! backends implement so the mapper and the CLI run on either.
//!
//! A step is: zero the fixed-point gradient buffers; for every ray, [`ray_train`] (forward,
//! loss, backward), each contribution converted on its own to fixed point and added into the
//! group's `i64` buffer; then Adam on every group with its own learning rate. Because the sums
//! are integer, any ray order or thread count gives the same bits. The step's loss is the sum
//! of the per-ray losses taken in ray order (f32), so it is also independent of scheduling.

use crate::adam::{self, AdamConfig, AdamStep};
use crate::batch::{run_items, BatchJob, ItemRunner, MapPixels, Rays};
use crate::camera::{Intrinsics, Pose};
use crate::error::check_len;
use crate::fixed;
use crate::mapping::{MappingLoss, PixelResult, PixelSample, SlotPixels, WindowImages};
use crate::model::{
    Group, LossConfig, ModelGradSink, ModelLayout, Params, PerGroup, Ray, RayCache, RayResult,
    Recompute, SampleScratch, NUM_GROUPS,
};
use crate::warp::MAX_WINDOW;
use crate::{Error, NullSink};

/// Parameters, Adam moments and the fixed-point gradient of one group, all caller-owned.
pub struct GroupState<'a> {
    pub params: &'a mut [f32],
    pub m: &'a mut [f32],
    pub v: &'a mut [f32],
    pub grad: &'a mut [i64],
}

/// Adds each contribution, converted to fixed point, into per-group `i64` buffers.
pub struct FixedModelSink<'s, 'a> {
    pub grads: [&'s mut [i64]; NUM_GROUPS],
    _marker: core::marker::PhantomData<&'a ()>,
}

impl<'s> FixedModelSink<'s, '_> {
    pub fn new(grads: [&'s mut [i64]; NUM_GROUPS]) -> Self {
        Self {
            grads,
            _marker: core::marker::PhantomData,
        }
    }
}

impl ModelGradSink for FixedModelSink<'_, '_> {
    #[inline(always)]
    fn add(&mut self, group: Group, i: usize, g: f32) {
        if let Some(slot) = self.grads[group as usize].get_mut(i) {
            *slot = slot.wrapping_add(fixed::to_fixed(g));
        }
    }
}

/// Summary of one step.
#[derive(Clone, Copy, Debug, PartialEq, Default)]
pub struct StepStats {
    /// Sum over rays of the per-ray scaled losses.
    pub loss: f32,
    /// Rays that intersected the scene box.
    pub rays_hit: u32,
    /// Adam step number after this step.
    pub t: u32,
    /// The step was not finite and was not applied: a ray's or pixel's loss, or a parameter
    /// or Adam moment the update would produce, was infinite or NaN. The parameters, the
    /// moments and `t` are as before the step (the fixed-point gradients are finite by
    /// construction: [`crate::fixed::to_fixed`] counts a NaN contribution as zero and
    /// saturates infinite ones, so the update is what can overflow).
    pub rejected: bool,
}

/// The operations the mapper and the CLI need from a compute backend.
pub trait Backend {
    type Error: core::fmt::Debug + core::fmt::Display;

    /// The model's shapes.
    fn layout(&self) -> &ModelLayout;
    /// Human-readable backend name ("cpu", "cpu-parallel(4)", "vulkan: <device>").
    fn name(&self) -> &str;
    /// One training step: gradients of the loss over `rays` (into zeroed fixed-point buffers)
    /// and an Adam update of every group, unless the step is not finite
    /// ([`StepStats::rejected`]: nothing but the gradient buffers changes then).
    /// `results[i]` receives ray i's outputs.
    fn train_step(
        &mut self,
        rays: &[Ray],
        loss: &LossConfig,
        results: &mut [RayResult],
    ) -> Result<StepStats, Self::Error>;
    /// Renders rays without jitter (bin centres); no gradients.
    fn render(&mut self, rays: &[Ray], results: &mut [RayResult]) -> Result<(), Self::Error>;
    /// Copies a group's parameters out.
    fn read_params(&mut self, group: Group, out: &mut [f32]) -> Result<(), Self::Error>;
    /// Copies a group's fixed-point gradient of the last step out.
    fn read_grads(&mut self, group: Group, out: &mut [i64]) -> Result<(), Self::Error>;
    /// Copies a group's Adam moments out.
    fn read_adam(&mut self, group: Group, m: &mut [f32], v: &mut [f32]) -> Result<(), Self::Error>;
    /// Overwrites a group's parameters (and resets its Adam moments when `reset_adam`).
    fn write_params(
        &mut self,
        group: Group,
        data: &[f32],
        reset_adam: bool,
    ) -> Result<(), Self::Error>;
    /// Image size and slot count fixed at construction (zero slots when the backend was built
    /// without image storage).
    fn image_store(&self) -> ImageStore;
    /// Stores a frame's packed RGBA8 image (`width * height` pixels, row-major, R in the low
    /// byte, see [`crate::mapping::pack_rgba8`]) in image slot `slot`.
    fn upload_frame(&mut self, slot: u32, rgba: &[u32]) -> Result<(), Self::Error>;
    /// One mapping iteration: zero the gradients, [`pixel_train`] for every pixel
    /// (`pixel_id` = its index in `batch.pixels`), Adam unless the step is not finite
    /// ([`StepStats::rejected`]). `results[i]` receives pixel i's
    /// outputs; the returned loss is the sum of the pixels' colour and warp losses in pixel
    /// order.
    fn map_step(
        &mut self,
        batch: &MapBatch<'_>,
        results: &mut [PixelResult],
    ) -> Result<StepStats, Self::Error>;
    /// Changes a group's Adam learning rate (moments are kept).
    fn set_adam_lr(&mut self, group: Group, lr: f32) -> Result<(), Self::Error>;
    /// A group's Adam learning rate.
    fn adam_lr(&self, group: Group) -> f32;
    /// Changes the model's early-termination threshold (`ModelConfig::min_transmittance`)
    /// for the steps and renders that follow.
    fn set_min_transmittance(&mut self, t: f32) -> Result<(), Self::Error>;
}

/// Size of the image slots a backend stores frames in (fixed at construction).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub struct ImageStore {
    pub width: u32,
    pub height: u32,
    pub slots: u32,
}

impl ImageStore {
    /// Pixels in one slot.
    pub const fn slot_len(&self) -> usize {
        self.width as usize * self.height as usize
    }

    /// `u32` words of the whole store (`slots * width * height`).
    pub const fn total_len(&self) -> usize {
        self.slot_len() * self.slots as usize
    }

    /// The words of image slot `slot` in the whole store, for a frame of `len` pixels
    /// ([`Backend::upload_frame`] of every backend): the frame must fill one slot exactly and
    /// the slot must exist.
    pub fn slot_range(&self, slot: u32, len: usize) -> Result<core::ops::Range<usize>, Error> {
        let n = self.slot_len();
        check_len("frame pixels", len, n)?;
        if slot >= self.slots {
            return Err(Error::Capacity {
                what: "image slot index",
                needed: slot as u64 + 1,
                capacity: self.slots as u64,
            });
        }
        let o = slot as usize * n;
        Ok(o..o + n)
    }
}

/// One mapping iteration's inputs: the window (intrinsics, camera-to-world poses, the image
/// slot of each window frame), the sampled pixels (their `frame` indexes the window) and the
/// loss settings.
#[derive(Clone, Copy, Debug)]
pub struct MapBatch<'a> {
    pub k: Intrinsics,
    pub poses: &'a [Pose],
    pub slots: &'a [u32],
    pub pixels: &'a [PixelSample],
    pub loss: MappingLoss,
}

/// Validates a batch against the image store and returns the window's slot table.
pub fn window_slots(batch: &MapBatch<'_>, store: &ImageStore) -> Result<[u32; MAX_WINDOW], Error> {
    let n = batch.poses.len();
    check_len("window slots", batch.slots.len(), n)?;
    if n == 0 {
        return Err(Error::InvalidConfig("mapping window is empty"));
    }
    if n > MAX_WINDOW {
        return Err(Error::Capacity {
            what: "mapping window frames",
            needed: n as u64,
            capacity: MAX_WINDOW as u64,
        });
    }
    if batch.k.width != store.width || batch.k.height != store.height {
        return Err(Error::InvalidConfig(
            "map_step: intrinsics size differs from the image store",
        ));
    }
    let mut out = [0u32; MAX_WINDOW];
    let mut i = 0;
    while i < n {
        if batch.slots[i] >= store.slots {
            return Err(Error::Capacity {
                what: "image slot index",
                needed: batch.slots[i] as u64 + 1,
                capacity: store.slots as u64,
            });
        }
        out[i] = batch.slots[i];
        i += 1;
    }
    batch.loss.warp.validate()?;
    Ok(out)
}

impl<'a> MapBatch<'a> {
    /// The window's slot images over a backend's store of `pixels`, after
    /// [`window_slots`]'s checks.
    pub fn window_images<P: SlotPixels + ?Sized>(
        &self,
        store: &ImageStore,
        pixels: &'a P,
    ) -> Result<WindowImages<'a, P>, Error> {
        Ok(WindowImages {
            width: store.width,
            height: store.height,
            slots: window_slots(self, store)?,
            pixels,
        })
    }
}

/// Step statistics of a mapping iteration (loss summed in pixel order).
pub fn summarize_pixels(results: &[PixelResult], t: u32) -> StepStats {
    let mut loss = 0.0f32;
    let mut hit = 0u32;
    let mut finite = true;
    for r in results {
        loss += r.color_loss + r.warp_loss;
        hit += (r.opacity > 0.0) as u32;
        finite &= adam::is_finite(r.color_loss) && adam::is_finite(r.warp_loss);
    }
    StepStats {
        loss,
        rays_hit: hit,
        t,
        rejected: !finite,
    }
}

/// The single-threaded reference backend: every other backend must match it bit for bit.
pub struct CpuBackend<'a> {
    layout: ModelLayout,
    groups: PerGroup<GroupState<'a>>,
    adam: PerGroup<AdamConfig>,
    t: u32,
    store: ImageStore,
    images: &'a mut [u32],
}

impl<'a> CpuBackend<'a> {
    /// Checks every buffer length against the layout.
    pub fn new(
        layout: ModelLayout,
        groups: PerGroup<GroupState<'a>>,
        adam: PerGroup<AdamConfig>,
    ) -> Result<Self, Error> {
        let lens = layout.group_lens();
        let mut g = 0;
        while g < NUM_GROUPS {
            let name = Group::ALL[g].name();
            check_len(name, groups[g].params.len(), lens[g])?;
            check_len(name, groups[g].m.len(), lens[g])?;
            check_len(name, groups[g].v.len(), lens[g])?;
            check_len(name, groups[g].grad.len(), lens[g])?;
            g += 1;
        }
        Ok(Self {
            layout,
            groups,
            adam,
            t: 0,
            store: ImageStore::default(),
            images: &mut [],
        })
    }

    /// Adds image slot storage: `images` must hold exactly `store.total_len()` words.
    pub fn with_images(mut self, store: ImageStore, images: &'a mut [u32]) -> Result<Self, Error> {
        check_len("image slots", images.len(), store.total_len())?;
        self.store = store;
        self.images = images;
        Ok(self)
    }

    /// Forward, losses and backward of a mapping batch, adding into the gradient buffers (not
    /// zeroed).
    pub fn accumulate_pixels(
        &mut self,
        batch: &MapBatch<'_>,
        results: &mut [PixelResult],
    ) -> Result<StepStats, Error> {
        let images = batch.window_images(&self.store, &*self.images)?;
        let job = MapPixels::of(batch, &images);
        let (params, mut sink) = params_and_sink(&mut self.groups);
        drive(&self.layout, &params, &mut sink, &job, results, self.t)
    }

    /// Adam steps taken so far.
    pub fn steps(&self) -> u32 {
        self.t
    }

    /// Read access to a group's parameters.
    pub fn params(&self, group: Group) -> &[f32] {
        self.groups[group].params
    }

    /// Read access to a group's fixed-point gradient.
    pub fn grads(&self, group: Group) -> &[i64] {
        self.groups[group].grad
    }

    /// Zeroes every gradient buffer.
    pub fn zero_grads(&mut self) {
        for g in self.groups.iter_mut() {
            for x in g.grad.iter_mut() {
                *x = 0;
            }
        }
    }

    /// Forward, loss and backward for `rays`, adding into the gradient buffers (not zeroed).
    pub fn accumulate(
        &mut self,
        rays: &[Ray],
        loss: &LossConfig,
        results: &mut [RayResult],
    ) -> Result<StepStats, Error> {
        let (params, mut sink) = params_and_sink(&mut self.groups);
        let job = Rays {
            rays,
            loss: Some(loss),
        };
        drive(&self.layout, &params, &mut sink, &job, results, self.t)
    }

    /// Adam on every group from the accumulated gradients.
    pub fn apply_adam(&mut self) -> Result<(), Error> {
        self.t += 1;
        for (g, state) in self.groups.iter_mut().enumerate() {
            let s = AdamStep::new(&self.adam[g], self.t);
            adam::adam_update_fixed(&s, state.params, state.m, state.v, state.grad)?;
        }
        Ok(())
    }

    /// Whether Adam from the accumulated gradients would leave every parameter and moment
    /// finite (nothing is written).
    pub fn adam_is_finite(&self) -> bool {
        self.groups.iter().enumerate().all(|(g, state)| {
            let s = AdamStep::new(&self.adam[g], self.t + 1);
            adam::adam_group_is_finite(&s, state.params, state.m, state.v, state.grad)
        })
    }

    /// Applies Adam unless `stats` already says the step is rejected or the update would not
    /// be finite (see [`StepStats::rejected`]); sets `stats.t` and `stats.rejected`.
    fn finish_step(&mut self, stats: &mut StepStats) -> Result<(), Error> {
        if !stats.rejected && self.adam_is_finite() {
            self.apply_adam()?;
        } else {
            stats.rejected = true;
        }
        stats.t = self.t;
        Ok(())
    }
}

/// The groups' parameters for reading and a sink into their fixed-point gradients.
fn params_and_sink<'s>(
    groups: &'s mut PerGroup<GroupState<'_>>,
) -> (Params<'s, [f32]>, FixedModelSink<'s, 's>) {
    let [g0, g1, g2, g3, g4] = &mut groups.0;
    let params = Params {
        geometry_grid: &*g0.params,
        appearance_grid: &*g1.params,
        geometry_mlp: &*g2.params,
        appearance_mlp: &*g3.params,
        beta: g4.params[0],
    };
    let sink = FixedModelSink::new([
        &mut *g0.grad,
        &mut *g1.grad,
        &mut *g2.grad,
        &mut *g3.grad,
        &mut *g4.grad,
    ]);
    (params, sink)
}

/// Runs a whole batch in order on this thread (the reference's driver: one run, the
/// recomputing tape) and summarizes it.
fn drive<J: BatchJob, S: ModelGradSink>(
    layout: &ModelLayout,
    params: &Params<'_, [f32]>,
    sink: &mut S,
    job: &J,
    results: &mut [J::Output],
    t: u32,
) -> Result<StepStats, Error> {
    check_len("results", results.len(), job.len())?;
    let mut cache = RayCache::new();
    let mut scratch = SampleScratch::new();
    let mut runner = ItemRunner {
        layout,
        params,
        cache: &mut cache,
        scratch: &mut scratch,
        tape: &mut Recompute,
        sink,
    };
    run_items(job, &mut runner, 0, results);
    Ok(J::summarize(results, t))
}

/// Step statistics from per-ray results (loss summed in ray order).
pub fn summarize(results: &[RayResult], t: u32) -> StepStats {
    let mut loss = 0.0f32;
    let mut hit = 0u32;
    let mut finite = true;
    for r in results {
        loss += r.loss;
        hit += (r.opacity > 0.0) as u32;
        finite &= adam::is_finite(r.loss);
    }
    StepStats {
        loss,
        rays_hit: hit,
        t,
        rejected: !finite,
    }
}

impl Backend for CpuBackend<'_> {
    type Error = Error;

    fn layout(&self) -> &ModelLayout {
        &self.layout
    }

    fn name(&self) -> &str {
        "cpu"
    }

    fn train_step(
        &mut self,
        rays: &[Ray],
        loss: &LossConfig,
        results: &mut [RayResult],
    ) -> Result<StepStats, Error> {
        self.zero_grads();
        let mut stats = self.accumulate(rays, loss, results)?;
        self.finish_step(&mut stats)?;
        Ok(stats)
    }

    fn render(&mut self, rays: &[Ray], results: &mut [RayResult]) -> Result<(), Error> {
        let (params, _) = params_and_sink(&mut self.groups);
        let job = Rays { rays, loss: None };
        drive(&self.layout, &params, &mut NullSink, &job, results, self.t)?;
        Ok(())
    }

    fn read_params(&mut self, group: Group, out: &mut [f32]) -> Result<(), Error> {
        copy_group(group, out, self.groups[group].params)
    }

    fn read_grads(&mut self, group: Group, out: &mut [i64]) -> Result<(), Error> {
        copy_group(group, out, self.groups[group].grad)
    }

    fn read_adam(&mut self, group: Group, m: &mut [f32], v: &mut [f32]) -> Result<(), Error> {
        let st = &self.groups[group];
        copy_group(group, m, st.m)?;
        copy_group(group, v, st.v)
    }

    fn write_params(&mut self, group: Group, data: &[f32], reset_adam: bool) -> Result<(), Error> {
        let st = &mut self.groups[group];
        write_group(group, data, st.params, st.m, st.v, reset_adam)
    }

    fn image_store(&self) -> ImageStore {
        self.store
    }

    fn upload_frame(&mut self, slot: u32, rgba: &[u32]) -> Result<(), Error> {
        let r = self.store.slot_range(slot, rgba.len())?;
        self.images[r].copy_from_slice(rgba);
        Ok(())
    }

    fn map_step(
        &mut self,
        batch: &MapBatch<'_>,
        results: &mut [PixelResult],
    ) -> Result<StepStats, Error> {
        self.zero_grads();
        let mut stats = self.accumulate_pixels(batch, results)?;
        self.finish_step(&mut stats)?;
        Ok(stats)
    }

    fn set_adam_lr(&mut self, group: Group, lr: f32) -> Result<(), Error> {
        self.adam[group].set_lr(lr)
    }

    fn adam_lr(&self, group: Group) -> f32 {
        self.adam[group].lr
    }

    fn set_min_transmittance(&mut self, t: f32) -> Result<(), Error> {
        self.layout.set_min_transmittance(t)
    }
}

/// Copies a group's buffer out ([`Backend::read_params`] / [`Backend::read_grads`] of a
/// backend in host memory): `out` must have the buffer's length.
pub fn copy_group<T: Copy>(group: Group, out: &mut [T], src: &[T]) -> Result<(), Error> {
    check_len(group.name(), out.len(), src.len())?;
    out.copy_from_slice(src);
    Ok(())
}

/// Overwrites a group's parameters and, when `reset_adam`, zeroes its Adam moments
/// ([`Backend::write_params`] of a backend in host memory).
pub fn write_group(
    group: Group,
    data: &[f32],
    params: &mut [f32],
    m: &mut [f32],
    v: &mut [f32],
    reset_adam: bool,
) -> Result<(), Error> {
    check_len(group.name(), data.len(), params.len())?;
    params.copy_from_slice(data);
    if reset_adam {
        m.fill(0.0);
        v.fill(0.0);
    }
    Ok(())
}

/// Default Adam settings per group (the paper's: grids 0.01, MLPs 1e-5; beta with the MLPs).
pub fn paper_adam() -> PerGroup<AdamConfig> {
    PerGroup([
        AdamConfig::new(0.01),
        AdamConfig::new(0.01),
        AdamConfig::new(1e-5),
        AdamConfig::new(1e-5),
        AdamConfig::new(1e-5),
    ])
}

/// Borrows per-group buffers (any owner: `Vec`, arrays) as the [`GroupState`]s of a
/// [`CpuBackend`], in [`Group::ALL`] order.
pub fn group_states<'a, F: AsMut<[f32]>, I: AsMut<[i64]>>(
    params: &'a mut [F; NUM_GROUPS],
    m: &'a mut [F; NUM_GROUPS],
    v: &'a mut [F; NUM_GROUPS],
    grads: &'a mut [I; NUM_GROUPS],
) -> PerGroup<GroupState<'a>> {
    let [p0, p1, p2, p3, p4] = params;
    let [m0, m1, m2, m3, m4] = m;
    let [v0, v1, v2, v3, v4] = v;
    let [g0, g1, g2, g3, g4] = grads;
    let s = |p: &'a mut F, m: &'a mut F, v: &'a mut F, g: &'a mut I| GroupState {
        params: p.as_mut(),
        m: m.as_mut(),
        v: v.as_mut(),
        grad: g.as_mut(),
    };
    PerGroup([
        s(p0, m0, v0, g0),
        s(p1, m1, v1, g1),
        s(p2, m2, v2, g2),
        s(p3, m3, v3, g3),
        s(p4, m4, v4, g4),
    ])
}
