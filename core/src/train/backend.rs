//! The [`Backend`] trait that the CPU and Vulkan backends implement so the mapper and the CLI
//! run on either, and what every backend shares: the batches it is given ([`MapBatch`]), the
//! image store ([`ImageStore`]), step statistics ([`StepStats`], [`summarize`]) and the checks
//! of host-memory group buffers ([`copy_group`], [`write_group`]).
//!
//! A step is: zero the fixed-point gradient buffers; for every ray,
//! [`ray_train`](crate::field::model::ray_train) (forward, loss, backward), each contribution
//! converted on its own to fixed point and added into the group's `i64` buffer; then Adam on
//! every group with its own learning rate. Because the sums are integer, any ray order or
//! thread count gives the same bits. The step's loss is the sum of the per-ray losses taken in
//! ray order (f32), so it is also independent of scheduling. The single-threaded form of that
//! step, the reference every backend matches, is [`crate::train::reference`].

use crate::camera::{Intrinsics, Pose};
use crate::error::check_len;
use crate::field::model::{Group, LossConfig, ModelLayout, PerGroup, Ray, RayResult};
use crate::loss::warp::MAX_WINDOW;
use crate::train::adam::{self, AdamConfig};
use crate::train::pixel::{MappingLoss, PixelResult, PixelSample, SlotPixels, WindowImages};
use crate::Error;

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
    /// construction: [`crate::train::fixed::to_fixed`] counts a NaN contribution as zero and
    /// saturates infinite ones, so the update is what can overflow).
    pub rejected: bool,
}

/// The operations the mapper and the CLI need from a compute backend.
pub trait Backend {
    /// What the backend's operations fail with.
    type Error: core::fmt::Debug + core::fmt::Display;

    /// The model's shapes.
    fn layout(&self) -> &ModelLayout;
    /// Human-readable backend name (`"cpu"`, `"cpu-parallel(4)"`, `"vulkan: <device>"`).
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
    /// [`Backend::render`]'s depth and opacity (the same bits) where the colour is not needed;
    /// a backend may leave the colour 0 and skip the appearance. By default the full render.
    fn render_depth(&mut self, rays: &[Ray], results: &mut [RayResult]) -> Result<(), Self::Error> {
        self.render(rays, results)
    }
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
    /// byte, see [`crate::train::pixel::pack_rgba8`]) in image slot `slot`.
    fn upload_frame(&mut self, slot: u32, rgba: &[u32]) -> Result<(), Self::Error>;
    /// Packed RGBA8 texel `(u, v)` of image slot `slot` as last uploaded (0 outside the store).
    /// The mapper reads frames through it to place region planarity triplets
    /// (`MapperConfig::planar_region_step`); a device backend answers from a host copy.
    fn slot_texel(&self, slot: u32, u: u32, v: u32) -> u32;
    /// Sets the per-pixel depth prior of image slot `slot` (a target depth per pixel,
    /// row-major; 0 = none), which the mapping loss reads with weight
    /// [`crate::train::pixel::MappingLoss::lambda_plane`]
    /// ([`crate::loss::warp::FrameImages::depth_prior`]) until the slot's next
    /// [`Self::upload_frame`], which clears it. `Ok(false)`: the backend has no such priors
    /// (the default; nothing changes).
    fn set_depth_prior(&mut self, _slot: u32, _prior: &[f32]) -> Result<bool, Self::Error> {
        Ok(false)
    }
    /// One mapping iteration: zero the gradients,
    /// [`pixel_train`](crate::train::pixel::pixel_train) for every pixel
    /// (`pixel_id` = its index in `batch.pixels`), Adam unless the step is not finite
    /// ([`StepStats::rejected`]). `results[i]` receives pixel i's
    /// outputs; the returned loss is the sum of the pixels' colour and warp losses in pixel
    /// order.
    ///
    /// `next`, when given, is the batch of the caller's next call, which must be `map_step`
    /// with that same batch: a backend may start it before returning (the Vulkan backend
    /// queues it behind this step, so the device does not wait for the host between
    /// iterations); others ignore it. A queued step changes the parameters even if the
    /// caller then stops, so callers pass `next` only when the next call is certain.
    fn map_step(
        &mut self,
        batch: &MapBatch<'_>,
        results: &mut [PixelResult],
        next: Option<&MapBatch<'_>>,
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
    /// Width of every slot image (pixels).
    pub width: u32,
    /// Height of every slot image (pixels).
    pub height: u32,
    /// Number of image slots.
    pub slots: u32,
}

impl ImageStore {
    /// Index of texel `(u, v)` of slot `slot` in the whole store (`None` outside it).
    pub const fn texel_index(&self, slot: u32, u: u32, v: u32) -> Option<usize> {
        if slot < self.slots && u < self.width && v < self.height {
            Some(
                (slot as usize * self.height as usize + v as usize) * self.width as usize
                    + u as usize,
            )
        } else {
            None
        }
    }

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
    /// Intrinsics of every window frame (their size must match the image store).
    pub k: Intrinsics,
    /// Camera-to-world pose of each window frame.
    pub poses: &'a [Pose],
    /// Image slot of each window frame (same length as `poses`).
    pub slots: &'a [u32],
    /// The pixels to train on.
    pub pixels: &'a [PixelSample],
    /// Loss weights and switches.
    pub loss: MappingLoss,
    /// The Adam learning rate of each group ([`crate::field::model::Group::ALL`] order) for
    /// this step; `None` uses the backend's ([`Backend::set_adam_lr`]). The mapper decides
    /// them when it prepares the batch, so a backend that starts a queued step early
    /// ([`Backend::map_step`]'s `next`) trains it with the same rates as one that runs it
    /// later.
    pub lr: Option<[f32; crate::field::model::NUM_GROUPS]>,
}

impl MapBatch<'_> {
    /// `adam` with this batch's learning rates ([`Self::lr`]; `adam` itself when `None`).
    /// Errors: a rate that is not finite and `>= 0`.
    pub fn adam(&self, adam: &PerGroup<AdamConfig>) -> Result<PerGroup<AdamConfig>, Error> {
        let mut out = *adam;
        if let Some(lr) = self.lr {
            for (cfg, lr) in out.0.iter_mut().zip(lr) {
                cfg.set_lr(lr)?;
            }
        }
        Ok(out)
    }
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
            priors: 0,
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
