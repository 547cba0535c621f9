//! The single-threaded reference backend ([`CpuBackend`]): a whole batch runs in order on one
//! thread with the recomputing tape, each gradient contribution goes through
//! [`FixedModelSink`] into the groups' `i64` buffers, then Adam runs on every group. Every
//! other backend (the host's parallel one, Vulkan) must match it bit for bit.

use crate::error::check_len;
use crate::field::model::{
    Group, LossConfig, ModelGradSink, ModelLayout, Params, PerGroup, Ray, RayCache, RayResult,
    Recompute, SampleScratch, NUM_GROUPS,
};
use crate::train::adam::{self, AdamConfig, AdamStep};
use crate::train::backend::{copy_group, write_group, Backend, ImageStore, MapBatch, StepStats};
use crate::train::batch::{run_items, BatchJob, ItemRunner, MapPixels, RayJob, Rays, TripletMemo};
use crate::train::fixed;
use crate::train::pixel::PixelResult;
use crate::{Error, NullSink};

/// Parameters, Adam moments and the fixed-point gradient of one group, all caller-owned.
pub struct GroupState<'a> {
    /// The group's parameters.
    pub params: &'a mut [f32],
    /// Adam's first moments (same length as `params`).
    pub m: &'a mut [f32],
    /// Adam's second moments (same length as `params`).
    pub v: &'a mut [f32],
    /// The fixed-point gradient of the last step ([`fixed`]; same length as `params`).
    pub grad: &'a mut [i64],
}

/// Adds each contribution, converted to fixed point, into per-group `i64` buffers.
pub struct FixedModelSink<'s, 'a> {
    /// One fixed-point buffer per group, in [`Group::ALL`] order; contributions past a
    /// buffer's end are dropped.
    pub grads: [&'s mut [i64]; NUM_GROUPS],
    _marker: core::marker::PhantomData<&'a ()>,
}

impl<'s> FixedModelSink<'s, '_> {
    /// A sink adding into `grads` (one buffer per group, in [`Group::ALL`] order).
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

    /// Adds image slot storage: `images` must hold exactly `store.total_len()` words, or
    /// twice as many for per-pixel depth priors ([`Backend::set_depth_prior`]; a target's
    /// bits per pixel after the slots, as the Vulkan backend's buffer holds them).
    pub fn with_images(mut self, store: ImageStore, images: &'a mut [u32]) -> Result<Self, Error> {
        if images.len() != 2 * store.total_len() {
            check_len("image slots", images.len(), store.total_len())?;
        }
        self.store = store;
        self.images = images;
        Ok(self)
    }

    /// Where the depth priors start in the image words (0 = the store has none).
    fn priors_at(&self) -> u32 {
        let total = self.store.total_len();
        if total > 0 && self.images.len() == 2 * total {
            total as u32
        } else {
            0
        }
    }

    /// Forward, losses and backward of a mapping batch, adding into the gradient buffers (not
    /// zeroed).
    pub fn accumulate_pixels(
        &mut self,
        batch: &MapBatch<'_>,
        results: &mut [PixelResult],
    ) -> Result<StepStats, Error> {
        let mut images = batch.window_images(&self.store, &*self.images)?;
        images.priors = self.priors_at();
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
            job: RayJob::Train(loss),
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
        memo: TripletMemo::EMPTY,
    };
    run_items(job, &mut runner, 0, results);
    Ok(J::summarize(results, t))
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
        let job = Rays {
            rays,
            job: RayJob::Render,
        };
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
        let at = self.priors_at() as usize;
        if at != 0 {
            self.images[at + r.start..at + r.end].fill(0);
        }
        self.images[r].copy_from_slice(rgba);
        Ok(())
    }

    fn set_depth_prior(&mut self, slot: u32, prior: &[f32]) -> Result<bool, Error> {
        let r = self.store.slot_range(slot, prior.len())?;
        let at = self.priors_at() as usize;
        if at == 0 {
            return Ok(false);
        }
        for (w, p) in self.images[at + r.start..at + r.end].iter_mut().zip(prior) {
            *w = p.to_bits();
        }
        Ok(true)
    }

    fn slot_texel(&self, slot: u32, u: u32, v: u32) -> u32 {
        match self.store.texel_index(slot, u, v) {
            Some(i) if i < self.images.len() => self.images[i],
            _ => 0,
        }
    }

    fn map_step(
        &mut self,
        batch: &MapBatch<'_>,
        results: &mut [PixelResult],
        _next: Option<&MapBatch<'_>>,
    ) -> Result<StepStats, Error> {
        let adam = batch.adam(&self.adam)?;
        let saved = core::mem::replace(&mut self.adam, adam);
        self.zero_grads();
        let stepped = self
            .accumulate_pixels(batch, results)
            .and_then(|mut stats| {
                self.finish_step(&mut stats)?;
                Ok(stats)
            });
        self.adam = saved;
        stepped
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
