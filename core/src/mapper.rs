//! Hi-Map's online mapper: the sliding window, the keyframe cache, pixel sampling and the
//! iteration schedule, generic over a [`Backend`]. No allocation: every capacity is a constant
//! of this module, the per-iteration pixel buffers are caller-provided slices, and every
//! problem is an error value.
//!
//! # Schedule (paper values in brackets, all from [`MapperConfig`])
//!
//! - Frames are pushed one at a time ([`Mapper::push_frame`]); each gets the next frame id
//!   (0, 1, ...) and an image slot in the backend.
//! - **Initialisation**: when `init_frames` \[15\] frames have been pushed, `init_iters` \[1500\]
//!   iterations run on a window of exactly those frames, with `lambda_color_init` \[0.1\]; the
//!   colour loss reaches the geometry only during the first `init_color_iters` \[250\]
//!   iterations (detached rendering weights afterwards).
//! - **Online updates**: after every `update_every` \[5\] further frames, the local set is cut
//!   back to the `local_frames` \[15\] most recent frames: of the frames leaving it, the oldest
//!   joins the keyframe cache and the others are dropped (their slots are freed). Then up to
//!   `window_keyframes` \[5\] keyframes are chosen from the cache by view overlap with the newest
//!   frame (below) and `iters` \[20\] iterations run on the window (the chosen keyframes,
//!   then the local frames, each oldest first), colour weight `lambda_color` \[0.001\],
//!   detached colour (unless `online_color_to_geometry`; the final refinement has its own
//!   `refine_color_to_geometry` and `refine_lambda_color`).
//! - **Keyframe cache full** (`max_keyframes`): [`KeyframeOverflow::Thin`] drops every other
//!   keyframe (keeps cache indices 0, 2, 4, ...: the cache keeps covering the whole
//!   trajectory at half the density), [`KeyframeOverflow::DropOldest`] drops the oldest.
//! - [`Mapper::flush`] runs a pending update at the end of a sequence (the initialisation on
//!   the frames so far if there were fewer than `init_frames`).
//!
//! # Keyframe overlap (NICE-SLAM's selection, with rendered instead of sensor depth)
//!
//! `overlap_pixels` \[100\] random pixels of the newest frame are rendered (bin centres, no
//! jitter); for each with positive opacity and depth `D`, `overlap_points` \[16\] points evenly
//! spaced on camera depth `[0.8 D, D + 0.5 m]` are back-projected. A keyframe's overlap is the
//! fraction of these points in front of it and projecting more than `overlap_margin` \[20\] px
//! inside its image. Keyframes with overlap > 0 and at least `overlap_min` \[0\] of the tested
//! points are candidates; `window_keyframes` of them are
//! drawn uniformly at random without replacement (all when fewer). Then `global_keyframes`
//! \[0\] more are drawn uniformly from the rest of the cache, whatever their overlap: the
//! regions the camera has left keep receiving gradients (their colour term at least; their
//! warp pairs with the window are mostly invalid and masked).
//!
//! # Pixel sampling and loss reduction
//!
//! Every iteration draws `pixels` integer pixels, spread evenly over the window frames
//! (`pixels / n` each, the first `pixels % n` frames one more), uniform in
//! `[border, W - 1 - border]^2`. The colour term is averaged over the sampled pixels
//! (`color_scale = 1 / pixels`), and so is the warping term (`warp_scale = 1 / pixels`; each
//! pixel's warp term is DIM-SLAM's sum over its valid pairs; pixels with too few valid views
//! count as zero).
//!
//! Online, `new_frame_share` (0 = off, the paper's even spread) gives the frames that arrived
//! since the last update (the last `min(pending, window)` window frames) that fraction of the
//! pixels (rounded, at least one per frame on each side), spread evenly over them as above;
//! the other window frames share the rest evenly, unless `keyframe_share` \[0\] gives the
//! window's keyframes that fraction of the pixels (rounded, at least one per keyframe, the
//! older local frames the rest). The initialisation always spreads evenly.
//!
//! The mapper keeps its frames in `heapless` vectors: host-side only (the shaders build the
//! core without the feature).

use crate::camera::{Intrinsics, Pose};
use crate::field::model::{Group, Ray, RayResult, NUM_GROUPS};
use crate::loss::planar::{mean_abs_diff, PlanarConfig};
use crate::loss::warp::{WarpConfig, MAX_WINDOW};
use crate::rng::{hash_u32, SplitMix};
use crate::train::backend::{Backend, ImageStore, MapBatch};
use crate::train::pixel::{MappingLoss, PixelResult, PixelSample};
use crate::Error;
use heapless::Vec;

/// Largest local set plus frames pending for the next update.
pub const MAX_LOCAL: usize = 32;
/// Largest keyframe cache.
pub const MAX_KEYFRAMES: usize = 1024;
/// Most pixels rendered for the keyframe overlap test.
pub const MAX_OVERLAP_PIXELS: usize = 256;

/// What happens when a frame joins a full keyframe cache.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum KeyframeOverflow {
    /// Drop every other keyframe (keep cache indices 0, 2, 4, ...).
    Thin,
    /// Drop the oldest keyframe.
    DropOldest,
}

/// Every setting of the mapper. [`MapperConfig::paper`] gives the paper's values.
///
/// # Examples
///
/// ```rust
/// use himap_core::mapper::MapperConfig;
/// use himap_core::train::backend::ImageStore;
/// use himap_core::Error;
///
/// let cfg = MapperConfig::paper(1024);
/// assert_eq!((cfg.local_frames, cfg.window_keyframes, cfg.iters), (15, 5, 20));
/// // Local set (15) + pending frames (5) + keyframe cache (512).
/// assert_eq!(cfg.slots_needed(), 532);
///
/// // The backend's image store must be large enough for the schedule.
/// let store = ImageStore { width: 640, height: 480, slots: cfg.slots_needed() };
/// assert_eq!(cfg.validate(&store), Ok(()));
/// let small = ImageStore { slots: 16, ..store };
/// assert!(matches!(cfg.validate(&small), Err(Error::Capacity { .. })));
///
/// // Out-of-range settings are errors.
/// let bad = MapperConfig { pixels: 0, ..cfg };
/// assert!(matches!(bad.validate(&store), Err(Error::InvalidConfig(_))));
/// ```
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct MapperConfig {
    /// Most recent frames in the window (15).
    pub local_frames: u32,
    /// Keyframes drawn into the window by view overlap with the newest frame (5).
    pub window_keyframes: u32,
    /// Further keyframes drawn uniformly from the rest of the cache, overlapping or not
    /// (0, the paper's), so that regions the camera has left keep receiving gradients.
    pub global_keyframes: u32,
    /// New frames between online updates (5).
    pub update_every: u32,
    /// Frames of the initialisation window (15).
    pub init_frames: u32,
    /// Initialisation iterations (1500).
    pub init_iters: u32,
    /// Initialisation iterations whose colour loss reaches the geometry (250).
    pub init_color_iters: u32,
    /// Whether the colour loss reaches the geometry in the online updates too (false:
    /// detached rendering weights after the initialisation's `init_color_iters`, DIM-SLAM's
    /// and the paper's). With it the colour term carves what hides other views' colours and
    /// pulls surfaces to where the views agree, as in a NeRF; its share against the warping
    /// term is `lambda_color`. The final refinement has its own `refine_color_to_geometry`.
    pub online_color_to_geometry: bool,
    /// Iterations per online update (20).
    pub iters: u32,
    /// Pixels sampled per iteration (over the whole window).
    pub pixels: u32,
    /// Sampled pixels keep this distance (px) from the image border (>= warp half + 1).
    pub border: u32,
    /// Online updates: fraction of the pixels given to the frames new since the last update
    /// (0 = spread evenly over the window, the paper's; in [0, 1]).
    pub new_frame_share: f32,
    /// Online updates with `new_frame_share`: fraction of the pixels given to the window's
    /// keyframes (0 = they share the rest evenly with the older local frames; in [0, 1]).
    pub keyframe_share: f32,
    /// Colour weight during initialisation (0.1).
    pub lambda_color_init: f32,
    /// Colour weight online (0.001).
    pub lambda_color: f32,
    /// Warping-loss weight (1.0).
    pub lambda_warp: f32,
    /// Settings of DIM-SLAM's warping loss (patch half-size, margin, minimum valid views,
    /// weights).
    pub warp: WarpConfig,
    /// Keyframe cache capacity (<= [`MAX_KEYFRAMES`]).
    pub max_keyframes: u32,
    /// What happens when a frame joins a full keyframe cache ([`KeyframeOverflow::Thin`]).
    pub keyframe_overflow: KeyframeOverflow,
    /// Rendered pixels of the overlap test (100, <= [`MAX_OVERLAP_PIXELS`]).
    pub overlap_pixels: u32,
    /// Points per pixel of the overlap test (16).
    pub overlap_points: u32,
    /// Projections must fall this far (px) inside a keyframe (20).
    pub overlap_margin: f32,
    /// Smallest share of the overlap test's points a keyframe must see to be a candidate
    /// (0 = any point, NICE-SLAM's rule; in [0, 1)).
    pub overlap_min: f32,
    /// Seed of pixel sampling, keyframe choice and stratified jitter.
    pub seed: u64,
    /// DIM-SLAM's depth prior during the first `depth_prior_iters` initialisation iterations:
    /// weight (per pixel, averaged like the colour term; 0 = off) and target depth (metres).
    pub lambda_depth_prior: f32,
    /// Target depth of the depth prior (camera z, metres; 1.5).
    pub depth_prior: f32,
    /// Initialisation iterations that use `lambda_depth_prior` on every pixel (150).
    pub depth_prior_iters: u32,
    /// After those iterations (online updates included): the same prior with this weight on
    /// the pixels whose rendered depth is below `depth_prior_near` (m), so that a view
    /// collapsed onto the camera in newly explored space gets a plausible start (0 = off).
    pub lambda_depth_prior_online: f32,
    /// Rendered depth (camera z, metres) below which `lambda_depth_prior_online` acts (0.5).
    pub depth_prior_near: f32,
    /// The edge-aware planarity prior on the rendered depth (see [`crate::loss::planar`]):
    /// weight per pixel, averaged like the colour term (0 = off), edge sensitivity and
    /// smooth-L1 threshold. When on, the sampled pixels come in triplets `b - s`, `b`,
    /// `b + s` along a row or a column of one frame, `s` drawn in `1..=planar_spacing` px.
    /// A triplet pays it only where its centre has the warping term's `min_views` valid views
    /// (plain surfaces the window sees, not space only the newest frames look into).
    pub lambda_planar: f32,
    /// Edge sensitivity of the planarity prior ([`PlanarConfig::edge`]).
    pub planar_edge: f32,
    /// Smooth-L1 threshold of the planarity prior ([`PlanarConfig::beta`]).
    pub planar_beta: f32,
    /// Largest pixel spacing `s` of a planarity triplet (px, >= 1 when the prior is on).
    pub planar_spacing: u32,
    /// Share of the batch's triples made triplets (spread evenly over the batch; the other
    /// pixels stay independent draws), in (0, 1].
    pub planar_share: f32,
    /// Region triplets (0 = off: spacings drawn in `1..=planar_spacing`). When > 0, a
    /// triplet's outer pixels are the ends of the plain run around its centre along the drawn
    /// row or column: the walk from the centre stops before the first step between
    /// neighbouring pixels whose mean channel difference exceeds this (colour in [0, 1]), at
    /// `planar_spacing` px or at the sampling border. So the prior asks the centre of a plain
    /// region to lie on the plane through the region's ends, whose depth the warping term can
    /// see (textured borders), instead of on a plane with its immediate neighbours (which a
    /// smooth lump satisfies). A centre with either end closer than
    /// [`PLANAR_REGION_MIN`] px (textured: the warping term shapes it) stays an independent
    /// draw, as do its two partners.
    pub planar_region_step: f32,
    /// Whether a triplet pays the prior only where its centre has the warping term's
    /// `min_views` valid views (true). The gate keeps fixed-spacing triplets from carrying a
    /// near edge's depth into space only the newest frames see; region triplets stop at
    /// colour edges on their own, and measured better without it (ARCHITECTURE.md).
    pub planar_gate: bool,
    /// Non-finite steps: every rejected step (see [`crate::train::backend::StepStats::rejected`]) is
    /// skipped and counted; after `rejected_lr_after` rejected steps in a row (0 = never)
    /// every group's learning rate is multiplied by `rejected_lr_factor` (in (0, 1]).
    pub rejected_lr_after: u32,
    /// Factor applied to every group's learning rate after `rejected_lr_after` rejected steps
    /// in a row (in (0, 1]).
    pub rejected_lr_factor: f32,
    /// Early-termination threshold during the initialisation (0 = none); online updates use
    /// the model's own `min_transmittance`. Without termination the samples behind the
    /// initial surface (the sphere) still receive gradients, so the true surfaces behind it
    /// can emerge while the geometry is first found.
    pub init_min_transmittance: f32,
    /// Iterations of the final refinement [`Mapper::refine`] runs after the last frame
    /// (0 = none, the paper's): windows of `refine_window` held frames (keyframe cache and
    /// local frames) neighbouring in time around a random one, `refine_block` iterations
    /// each, so that every region the camera saw gets steps again after the camera left it.
    pub refine_iters: u32,
    /// Frames per window of the final refinement (>= 2 when `refine_iters` > 0).
    pub refine_window: u32,
    /// Iterations per window of the final refinement (>= 1 when `refine_iters` > 0).
    pub refine_block: u32,
    /// Learning-rate factor at the end of the final refinement, reached linearly from 1 over
    /// its blocks (1 = constant; in (0, 1]); the rates are restored afterwards.
    pub refine_lr_end: f32,
    /// Whether the final refinement moves the geometry (grid, decoder, beta) too (true);
    /// false refines the appearance only (the geometry groups' rates are 0 during it).
    pub refine_geometry: bool,
    /// Whether the final refinement's colour loss reaches the geometry (false: detached
    /// rendering weights, as online). Every view is held by then, so the colour term can
    /// make the surfaces consistent across all of them (no effect with `refine_geometry`
    /// false).
    pub refine_color_to_geometry: bool,
    /// Colour weight of the final refinement (0: `lambda_color`, the online weight).
    pub refine_lambda_color: f32,
    /// Planarity weight of the final refinement (0: `lambda_planar`, the online weight):
    /// the prior (with its triplets and their settings) can shape the final surfaces
    /// without acting on the online updates.
    pub refine_lambda_planar: f32,
    /// Weight of the per-pixel depth priors during online updates
    /// ([`MappingLoss::lambda_plane`]; the host's plane priors of plain regions, set through
    /// [`Backend::set_depth_prior`]). 0 = off.
    pub lambda_plane: f32,
    /// Weight of the per-pixel depth priors in the final refinement. 0 = off.
    pub refine_lambda_plane: f32,
}

impl MapperConfig {
    /// The paper's schedule with `pixels` pixels per iteration.
    pub const fn paper(pixels: u32) -> Self {
        Self {
            local_frames: 15,
            window_keyframes: 5,
            global_keyframes: 0,
            update_every: 5,
            init_frames: 15,
            init_iters: 1500,
            init_color_iters: 250,
            online_color_to_geometry: false,
            iters: 20,
            pixels,
            border: 10,
            new_frame_share: 0.0,
            keyframe_share: 0.0,
            lambda_color_init: 0.1,
            lambda_color: 0.001,
            lambda_warp: 1.0,
            warp: WarpConfig::dim_slam(),
            max_keyframes: 512,
            keyframe_overflow: KeyframeOverflow::Thin,
            overlap_pixels: 100,
            overlap_points: 16,
            overlap_margin: 20.0,
            overlap_min: 0.0,
            seed: 0,
            lambda_depth_prior: 1.0,
            depth_prior: 1.5,
            depth_prior_iters: 150,
            lambda_depth_prior_online: 0.0,
            depth_prior_near: 0.5,
            lambda_planar: 0.0,
            planar_edge: 10.0,
            planar_beta: 0.05,
            planar_spacing: 8,
            planar_share: 1.0,
            planar_region_step: 0.0,
            planar_gate: true,
            rejected_lr_after: 3,
            rejected_lr_factor: 0.5,
            init_min_transmittance: 0.0,
            refine_iters: 0,
            refine_window: 8,
            refine_block: 10,
            refine_lr_end: 1.0,
            refine_geometry: true,
            refine_color_to_geometry: false,
            refine_lambda_color: 0.0,
            refine_lambda_planar: 0.0,
            lambda_plane: 0.0,
            refine_lambda_plane: 0.0,
        }
    }

    /// Image slots the backend needs: local set, pending frames and the keyframe cache.
    pub const fn slots_needed(&self) -> u32 {
        let local = if self.init_frames > self.local_frames {
            self.init_frames
        } else {
            self.local_frames
        };
        local + self.update_every + self.max_keyframes
    }

    /// Checks every range against the module's capacities and the backend's image store.
    pub fn validate(&self, store: &ImageStore) -> Result<(), Error> {
        let cap = |what, needed: u64, capacity: usize| -> Result<(), Error> {
            if needed > capacity as u64 {
                Err(Error::Capacity {
                    what,
                    needed,
                    capacity: capacity as u64,
                })
            } else {
                Ok(())
            }
        };
        if self.local_frames == 0 || self.update_every == 0 || self.init_frames == 0 {
            return Err(Error::InvalidConfig(
                "mapper: local_frames, update_every and init_frames must be >= 1",
            ));
        }
        if self.pixels == 0 {
            return Err(Error::InvalidConfig("mapper: pixels must be >= 1"));
        }
        if !(0.0..1.0).contains(&self.init_min_transmittance) {
            return Err(Error::InvalidConfig(
                "mapper: init_min_transmittance must be in [0, 1)",
            ));
        }
        if !(self.rejected_lr_factor > 0.0 && self.rejected_lr_factor <= 1.0) {
            return Err(Error::InvalidConfig(
                "mapper: rejected_lr_factor must be in (0, 1]",
            ));
        }
        if !(self.keyframe_share >= 0.0 && self.new_frame_share + self.keyframe_share <= 1.0) {
            return Err(Error::InvalidConfig(
                "mapper: keyframe_share must be >= 0 and new_frame_share + keyframe_share <= 1",
            ));
        }
        if !(self.new_frame_share >= 0.0 && self.new_frame_share <= 1.0) {
            return Err(Error::InvalidConfig(
                "mapper: new_frame_share must be in [0, 1]",
            ));
        }
        let local = self.local_frames.max(self.init_frames);
        cap(
            "mapper local frames + update_every",
            (local + self.update_every) as u64,
            MAX_LOCAL,
        )?;
        cap(
            "mapper window (local_frames + window_keyframes + global_keyframes)",
            (self.local_frames + self.window_keyframes + self.global_keyframes) as u64,
            MAX_WINDOW,
        )?;
        cap("mapper init_frames", self.init_frames as u64, MAX_WINDOW)?;
        if self.refine_iters > 0 {
            if self.refine_window < 2 || self.refine_block == 0 {
                return Err(Error::InvalidConfig(
                    "mapper: refine_window must be >= 2 and refine_block >= 1 when refine_iters > 0",
                ));
            }
            if !(self.refine_lr_end > 0.0 && self.refine_lr_end <= 1.0) {
                return Err(Error::InvalidConfig(
                    "mapper: refine_lr_end must be in (0, 1]",
                ));
            }
            cap(
                "mapper refine_window",
                self.refine_window as u64,
                MAX_WINDOW,
            )?;
        }
        cap(
            "mapper max_keyframes",
            self.max_keyframes as u64,
            MAX_KEYFRAMES,
        )?;
        cap(
            "mapper overlap_pixels",
            self.overlap_pixels as u64,
            MAX_OVERLAP_PIXELS,
        )?;
        if self.max_keyframes < 2 && self.keyframe_overflow == KeyframeOverflow::Thin {
            return Err(Error::InvalidConfig(
                "mapper: thinning the keyframe cache needs max_keyframes >= 2",
            ));
        }
        if self.overlap_points < 2 {
            return Err(Error::InvalidConfig("mapper: overlap_points must be >= 2"));
        }
        if !(self.overlap_margin.is_finite() && self.overlap_margin >= 0.0) {
            return Err(Error::InvalidConfig(
                "mapper: overlap_margin must be finite and >= 0",
            ));
        }
        if !(self.overlap_min >= 0.0 && self.overlap_min < 1.0) {
            return Err(Error::InvalidConfig(
                "mapper: overlap_min must be in [0, 1)",
            ));
        }
        let ok = |x: f32| x.is_finite() && x >= 0.0;
        if !(ok(self.lambda_color_init)
            && ok(self.lambda_color)
            && ok(self.lambda_warp)
            && ok(self.refine_lambda_color))
        {
            return Err(Error::InvalidConfig(
                "mapper: loss weights must be finite and >= 0",
            ));
        }
        if !(ok(self.lambda_plane) && ok(self.refine_lambda_plane)) {
            return Err(Error::InvalidConfig(
                "mapper: lambda_plane and refine_lambda_plane must be finite and >= 0",
            ));
        }
        if !(ok(self.lambda_planar)
            && ok(self.refine_lambda_planar)
            && ok(self.planar_edge)
            && ok(self.planar_beta))
        {
            return Err(Error::InvalidConfig(
                "mapper: lambda_planar, planar_edge and planar_beta must be finite and >= 0",
            ));
        }
        if !ok(self.planar_region_step) {
            return Err(Error::InvalidConfig(
                "mapper: planar_region_step must be finite and >= 0",
            ));
        }
        if !(self.planar_share > 0.0 && self.planar_share <= 1.0) {
            return Err(Error::InvalidConfig(
                "mapper: planar_share must be in (0, 1]",
            ));
        }
        // region triplets: `planar_spacing` is the longest run, cut at the border anyway
        // the shortest spacing accepted, and the room a triplet needs inside the border
        let (min, room) = if self.planar_region_step > 0.0 {
            (PLANAR_REGION_MIN, PLANAR_REGION_MIN)
        } else {
            (1, self.planar_spacing)
        };
        if (self.lambda_planar > 0.0 || (self.refine_iters > 0 && self.refine_lambda_planar > 0.0))
            && (self.planar_spacing < min
                || store.width <= 2 * (self.border + room)
                || store.height <= 2 * (self.border + room))
        {
            return Err(Error::InvalidConfig(
                "mapper: planar_spacing must be >= 1 (>= 4 with planar_region_step) and leave \
                 room inside the sampling border",
            ));
        }
        self.warp.validate()?;
        if self.border < self.warp.half + 1 {
            return Err(Error::InvalidConfig(
                "mapper: border must be at least warp half + 1",
            ));
        }
        if store.width <= 2 * self.border || store.height <= 2 * self.border {
            return Err(Error::InvalidConfig(
                "mapper: image smaller than twice the sampling border",
            ));
        }
        if store.slots < self.slots_needed() {
            return Err(Error::Capacity {
                what: "backend image slots",
                needed: self.slots_needed() as u64,
                capacity: store.slots as u64,
            });
        }
        Ok(())
    }
}

/// Mapper errors: its own (capacities, configuration, bad input) or the backend's.
#[derive(Debug)]
pub enum MapperError<E> {
    /// The mapper's own error (capacity, configuration or bad input).
    Core(Error),
    /// The backend's error.
    Backend(E),
}

impl<E> From<Error> for MapperError<E> {
    fn from(e: Error) -> Self {
        MapperError::Core(e)
    }
}

impl<E: core::fmt::Display> core::fmt::Display for MapperError<E> {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        match self {
            MapperError::Core(e) => write!(f, "mapper: {e}"),
            MapperError::Backend(e) => write!(f, "backend: {e}"),
        }
    }
}

impl<E: core::fmt::Debug + core::fmt::Display> core::error::Error for MapperError<E> {}

/// Which kind of optimisation an update was.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum UpdateKind {
    /// The initialisation on the first `init_frames` frames.
    Init,
    /// An online update of the sliding window.
    Online,
    /// The final refinement over every held frame ([`Mapper::refine`]).
    Refine,
}

/// Progress of one iteration (passed to the observer of [`Mapper::push_frame_observed`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct IterInfo {
    /// The update this iteration belongs to.
    pub kind: UpdateKind,
    /// Iteration within this update (0-based) and the update's total.
    pub iter: u32,
    /// Iterations of this update.
    pub iters: u32,
    /// Total loss, and its colour and warp parts (each averaged over the pixels, weighted).
    pub loss: f32,
    /// Colour part of the loss (averaged over the pixels, weighted; includes the priors).
    pub color_loss: f32,
    /// Warp part of the loss (averaged over the pixels, weighted).
    pub warp_loss: f32,
    /// Fraction of sampled pixels with a valid warp term.
    pub warp_valid: f32,
    /// Fraction of sampled pixels whose ray leaves the scene box mostly unabsorbed (rendered
    /// opacity < 0.5): it met no surface inside the box (a box too small there, or space not
    /// mapped yet).
    pub open_rays: f32,
    /// The step was not finite and was not applied ([`crate::train::backend::StepStats::rejected`]).
    pub rejected: bool,
    /// What the update's frames new since the last update looked like before its first step
    /// (online updates, iteration 0 only; 0 otherwise): the mean per-pixel loss (colour +
    /// warp) of their sampled pixels over that of the window's other frames, and the share of
    /// their pixels with a valid warp term. A low valid share means the newest geometry is
    /// not yet constrained by enough views (the update cannot place it, whatever the loss).
    pub new_loss_ratio: f32,
    /// Share of the new frames' sampled pixels with a valid warp term (see
    /// `new_loss_ratio`).
    pub new_warp_valid: f32,
}

/// What one mapping update did.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct UpdateReport {
    /// Initialisation or online update.
    pub kind: UpdateKind,
    /// Id of the newest frame (the "current" frame of the update).
    pub frame: u32,
    /// Iterations run.
    pub iters: u32,
    /// Loss of the first and the last iteration.
    pub first: IterInfo,
    /// The last iteration.
    pub last: IterInfo,
    /// Frames in the window, of which keyframes.
    pub window_frames: u32,
    /// Keyframes in the window.
    pub window_keyframes: u32,
    /// Keyframes with overlap > 0 (candidates), and the cache size.
    pub candidates: u32,
    /// Keyframes in the cache after the update.
    pub keyframes: u32,
}

/// A frame the mapper holds: its id (push order), its image slot in the backend and its pose.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct HeldFrame {
    /// Frame id (0, 1, ... in push order).
    pub id: u32,
    /// Image slot of the frame in the backend.
    pub slot: u32,
    /// Camera-to-world pose.
    pub pose: Pose,
}

/// Shortest distance (px) from a region triplet's centre to either end of its plain run
/// ([`MapperConfig::planar_region_step`]).
pub const PLANAR_REGION_MIN: u32 = 4;

/// Most image slots a mapper hands out.
pub const MAX_SLOTS: usize = MAX_LOCAL + MAX_KEYFRAMES;

/// Everything of a [`Mapper`] that lasts from one pushed frame to the next (the window and the
/// overlap test are rebuilt at every update): [`Mapper::state`] takes it, [`Mapper::restore`]
/// continues from it bit for bit, given the backend's model state and the images of the
/// held frames ([`MapperState::held`]) in their slots.
#[derive(Clone, Debug, PartialEq)]
pub struct MapperState {
    /// Local frames (oldest first) and the keyframe cache (oldest first).
    pub local: Vec<HeldFrame, MAX_LOCAL>,
    /// The keyframe cache (oldest first).
    pub keyframes: Vec<HeldFrame, MAX_KEYFRAMES>,
    /// Frames pushed since the last update.
    pub pending: usize,
    /// Free image slots (a stack: the last is handed out next).
    pub free: Vec<u32, MAX_SLOTS>,
    /// Whether the initialisation has run.
    pub initialized: bool,
    /// Frames pushed so far (the next frame's id).
    pub pushed: u32,
    /// Mapping iterations run so far.
    pub total_iters: u32,
    /// Steps rejected as non-finite so far.
    pub rejected_steps: u32,
    /// Rejected steps in a row (reset by an accepted step and by a learning-rate reduction).
    pub rejected_run: u32,
    /// Times the learning rates were lowered after rejected steps.
    pub lr_reductions: u32,
    /// [`SplitMix::state`] of the sampling generator.
    pub rng: u64,
}

impl MapperState {
    /// The frames whose images the backend holds: local frames, then keyframes.
    pub fn held(&self) -> impl Iterator<Item = &HeldFrame> + '_ {
        self.local.iter().chain(self.keyframes.iter())
    }
}

/// The online mapper. See the module documentation for the schedule.
pub struct Mapper<'a, B: Backend> {
    backend: B,
    cfg: MapperConfig,
    k: Intrinsics,
    store: ImageStore,
    /// What lasts between pushed frames; its `rng` is not kept current (the live generator
    /// is `rng`, [`Self::state`] reads it).
    st: MapperState,
    rng: SplitMix,
    /// One batch of `cfg.pixels` samples, or two (the next iteration's drawn while the
    /// backend runs the current one).
    pixels: &'a mut [PixelSample],
    /// Where [`Self::sample_pixels`] and [`Self::make_triplets`] write in `pixels`.
    pix_off: usize,
    results: &'a mut [PixelResult],
    win_ids: Vec<u32, MAX_WINDOW>,
    win_poses: Vec<Pose, MAX_WINDOW>,
    win_slots: Vec<u32, MAX_WINDOW>,
    win_kf: usize,
    overlap_rays: [Ray; MAX_OVERLAP_PIXELS],
    overlap_out: [RayResult; MAX_OVERLAP_PIXELS],
    candidates: [u16; MAX_KEYFRAMES],
}

impl<'a, B: Backend> Mapper<'a, B> {
    /// A mapper over `backend` (whose image store must match `k` and hold
    /// [`MapperConfig::slots_needed`] slots). `results` must hold exactly `cfg.pixels`
    /// entries and `pixels` either as many or twice as many: with two batches the mapper
    /// draws the next iteration's pixels before the current one's results are in and hands
    /// both to [`Backend::map_step`], so a GPU backend can queue the next step behind the
    /// current one (no host round trip between iterations). The map is the same bits
    /// either way.
    pub fn new(
        backend: B,
        cfg: MapperConfig,
        k: Intrinsics,
        pixels: &'a mut [PixelSample],
        results: &'a mut [PixelResult],
    ) -> Result<Self, Error> {
        let store = backend.image_store();
        cfg.validate(&store)?;
        if k.width != store.width || k.height != store.height {
            return Err(Error::InvalidConfig(
                "mapper: intrinsics size differs from the backend's image store",
            ));
        }
        if pixels.len() != 2 * cfg.pixels as usize {
            crate::error::check_len("mapper pixel buffer", pixels.len(), cfg.pixels as usize)?;
        }
        crate::error::check_len("mapper result buffer", results.len(), cfg.pixels as usize)?;
        let n_slots = cfg.slots_needed() as usize;
        // Popped from the end: slot 0 is used first.
        let free: Vec<u32, MAX_SLOTS> = (0..n_slots as u32).rev().collect();
        Ok(Self {
            backend,
            cfg,
            k,
            store,
            st: MapperState {
                local: Vec::new(),
                keyframes: Vec::new(),
                pending: 0,
                free,
                initialized: false,
                pushed: 0,
                total_iters: 0,
                rejected_steps: 0,
                rejected_run: 0,
                lr_reductions: 0,
                rng: cfg.seed,
            },
            rng: SplitMix::new(cfg.seed),
            pixels,
            pix_off: 0,
            results,
            win_ids: Vec::new(),
            win_poses: Vec::new(),
            win_slots: Vec::new(),
            win_kf: 0,
            overlap_rays: [Ray {
                origin: [0.0; 3],
                dir: [0.0; 3],
                target: [0.0; 3],
                target_depth: 0.0,
            }; MAX_OVERLAP_PIXELS],
            overlap_out: [RayResult::default(); MAX_OVERLAP_PIXELS],
            candidates: [0; MAX_KEYFRAMES],
        })
    }

    /// What the mapper holds between pushed frames (see [`MapperState`]).
    pub fn state(&self) -> MapperState {
        MapperState {
            rng: self.rng.state(),
            ..self.st.clone()
        }
    }

    /// A mapper that continues from `state` (taken by [`Self::state`] with the same `cfg`
    /// and intrinsics) over a backend that holds the model as it was then and the images of
    /// `state.held()` in their slots. Errors: the checks of [`Self::new`], and a state that
    /// does not fit `cfg` (lengths, slots).
    pub fn restore(
        backend: B,
        cfg: MapperConfig,
        k: Intrinsics,
        pixels: &'a mut [PixelSample],
        results: &'a mut [PixelResult],
        state: &MapperState,
    ) -> Result<Self, Error> {
        let mut m = Self::new(backend, cfg, k, pixels, results)?;
        let slots = cfg.slots_needed();
        let (local, kf, free) = (state.local.len(), state.keyframes.len(), state.free.len());
        let ok = kf <= cfg.max_keyframes as usize
            && local + kf + free == slots as usize
            && state.held().all(|e| e.slot < slots)
            && state.free.iter().all(|&s| s < slots);
        if !ok {
            return Err(Error::InvalidConfig(
                "mapper: the saved state does not fit this configuration",
            ));
        }
        m.st = state.clone();
        m.rng = SplitMix::new(state.rng);
        Ok(m)
    }

    /// The backend.
    pub fn backend(&self) -> &B {
        &self.backend
    }

    /// The backend, mutably.
    pub fn backend_mut(&mut self) -> &mut B {
        &mut self.backend
    }

    /// Consumes the mapper and returns its backend.
    pub fn into_backend(self) -> B {
        self.backend
    }

    /// The mapper's settings.
    pub fn config(&self) -> &MapperConfig {
        &self.cfg
    }

    /// The intrinsics of every frame.
    pub fn intrinsics(&self) -> Intrinsics {
        self.k
    }

    /// Whether the initialisation has run.
    pub fn is_initialized(&self) -> bool {
        self.st.initialized
    }

    /// Frames pushed so far.
    pub fn frames_pushed(&self) -> u32 {
        self.st.pushed
    }

    /// Steps rejected as non-finite so far (skipped; see [`MapperConfig::rejected_lr_after`]).
    pub fn rejected_steps(&self) -> u32 {
        self.st.rejected_steps
    }

    /// Times the learning rates were lowered after rejected steps.
    pub fn lr_reductions(&self) -> u32 {
        self.st.lr_reductions
    }

    /// Mapping iterations run so far.
    pub fn iterations(&self) -> u32 {
        self.st.total_iters
    }

    /// Ids of the local frames, oldest first (including frames pending for the next update).
    pub fn local_ids(&self) -> impl Iterator<Item = u32> + '_ {
        self.st.local.iter().map(|e| e.id)
    }

    /// Ids of the keyframe cache, oldest first.
    pub fn keyframe_ids(&self) -> impl Iterator<Item = u32> + '_ {
        self.st.keyframes.iter().map(|e| e.id)
    }

    /// Ids of the frames of the last update's window (keyframes first).
    pub fn window_ids(&self) -> &[u32] {
        &self.win_ids
    }

    /// Pushes a posed frame (packed RGBA8, see [`crate::train::pixel::pack_rgba8`]; camera-to-world
    /// pose) and runs an update when the schedule says so.
    pub fn push_frame(
        &mut self,
        rgba: &[u32],
        pose: Pose,
    ) -> Result<Option<UpdateReport>, MapperError<B::Error>> {
        self.push_frame_observed(rgba, pose, &mut |_| {})
    }

    /// [`Self::push_frame`] with an observer called after every iteration.
    pub fn push_frame_observed<F: FnMut(&IterInfo)>(
        &mut self,
        rgba: &[u32],
        pose: Pose,
        observe: &mut F,
    ) -> Result<Option<UpdateReport>, MapperError<B::Error>> {
        crate::error::check_len("frame pixels", rgba.len(), self.store.slot_len())?;
        if !pose.is_rigid(1e-3) {
            return Err(
                Error::InvalidConfig("mapper: pose is not a finite rigid transform").into(),
            );
        }
        let capacity = Error::Capacity {
            what: "mapper frame slots",
            needed: self.st.local.len() as u64 + 1,
            capacity: MAX_LOCAL as u64,
        };
        let (true, Some(&slot)) = (!self.st.local.is_full(), self.st.free.last()) else {
            return Err(capacity.into());
        };
        self.backend
            .upload_frame(slot, rgba)
            .map_err(MapperError::Backend)?;
        self.st.free.pop();
        let held = HeldFrame {
            id: self.st.pushed,
            slot,
            pose,
        };
        self.st.local.push(held).map_err(|_| capacity)?;
        self.st.pushed += 1;
        self.st.pending += 1;
        if !self.st.initialized {
            if self.st.local.len() >= self.cfg.init_frames as usize {
                return self.initialise(observe).map(Some);
            }
            return Ok(None);
        }
        if self.st.pending >= self.cfg.update_every as usize {
            return self.online_update(observe).map(Some);
        }
        Ok(None)
    }

    /// Runs the pending update, if any (end of a sequence): the initialisation when it has not
    /// run yet, else an online update when frames arrived since the last one.
    pub fn flush<F: FnMut(&IterInfo)>(
        &mut self,
        observe: &mut F,
    ) -> Result<Option<UpdateReport>, MapperError<B::Error>> {
        if self.st.local.is_empty() {
            return Ok(None);
        }
        if !self.st.initialized {
            return self.initialise(observe).map(Some);
        }
        if self.st.pending > 0 {
            return self.online_update(observe).map(Some);
        }
        Ok(None)
    }

    /// The final refinement (after the last frame and [`Self::flush`]; `None` when
    /// `refine_iters` is 0 or the map is not initialised): `refine_iters` iterations over the
    /// frames the mapper holds (the keyframe cache and the local frames, in push order), in
    /// blocks of `refine_block` iterations whose window is a random held frame and its
    /// neighbours in push order (`refine_window` frames). Pixels are spread evenly over the
    /// window and the online losses apply. An online map forgets: later views rewrite the
    /// appearance of regions the camera has left; this gives every region steps with its own
    /// views again once nothing new arrives. It reads nothing but frames already pushed.
    pub fn refine<F: FnMut(&IterInfo)>(
        &mut self,
        observe: &mut F,
    ) -> Result<Option<UpdateReport>, MapperError<B::Error>> {
        self.refine_part(self.cfg.refine_iters, observe)
    }

    /// [`Self::refine`] with `iters` iterations instead of `refine_iters`: a refinement run
    /// in parts (the host refreshes per-pixel priors between them). With `refine_lr_end` 1
    /// and parts that are multiples of `refine_block`, the parts in a row are the same
    /// iterations as one refinement of their sum.
    pub fn refine_part<F: FnMut(&IterInfo)>(
        &mut self,
        iters: u32,
        observe: &mut F,
    ) -> Result<Option<UpdateReport>, MapperError<B::Error>> {
        if iters == 0 || !self.st.initialized {
            return Ok(None);
        }
        let n = self.st.keyframes.len() + self.st.local.len();
        let (mut first, mut last) = (None, None);
        let base = Group::ALL.map(|g| self.backend.adam_lr(g));
        let result = self.refine_blocks(iters, n, base, observe, &mut first, &mut last);
        if self.cfg.refine_lr_end != 1.0 || !self.cfg.refine_geometry {
            for g in Group::ALL {
                self.backend
                    .set_adam_lr(g, base[g as usize])
                    .map_err(MapperError::Backend)?;
            }
        }
        result?;
        let (Some(first), Some(last)) = (first, last) else {
            return Ok(None);
        };
        Ok(Some(self.report(UpdateKind::Refine, iters, first, last, 0)))
    }

    /// The blocks of [`Self::refine`] over `n` held frames, the learning rates `base` scaled.
    fn refine_blocks<F: FnMut(&IterInfo)>(
        &mut self,
        iters: u32,
        n: usize,
        base: [f32; crate::field::model::NUM_GROUPS],
        observe: &mut F,
        first: &mut Option<IterInfo>,
        last: &mut Option<IterInfo>,
    ) -> Result<(), MapperError<B::Error>> {
        let w = (self.cfg.refine_window as usize).min(n);
        let end = self.cfg.refine_lr_end;
        let appearance_only = !self.cfg.refine_geometry;
        let mut done = 0;
        while done < iters {
            if end != 1.0 || appearance_only {
                let f = 1.0 + (end - 1.0) * (done as f32 / iters as f32);
                for g in Group::ALL {
                    let appearance = matches!(g, Group::AppearanceGrid | Group::AppearanceMlp);
                    let f = if appearance_only && !appearance {
                        0.0
                    } else {
                        f
                    };
                    self.backend
                        .set_adam_lr(g, base[g as usize] * f)
                        .map_err(MapperError::Backend)?;
                }
            }
            let anchor = self.rng.below(n as u32) as usize;
            let start = anchor.saturating_sub(w / 2).min(n - w);
            self.clear_window();
            for i in start..start + w {
                // keyframes (oldest first) come before the local frames in push order
                let e = match self.st.keyframes.get(i) {
                    Some(e) => *e,
                    None => self.st.local[i - self.st.keyframes.len()],
                };
                self.add_to_window(e);
            }
            let block = self.cfg.refine_block.min(iters - done);
            // The observer counts the refinement's iterations, not the block's.
            let mut whole = |info: &IterInfo| {
                observe(&IterInfo {
                    iter: done + info.iter,
                    iters,
                    ..*info
                })
            };
            let (f, l) = self.run_iters(UpdateKind::Refine, block, &mut whole)?;
            first.get_or_insert(f);
            *last = Some(l);
            done += block;
        }
        Ok(())
    }

    fn initialise<F: FnMut(&IterInfo)>(
        &mut self,
        observe: &mut F,
    ) -> Result<UpdateReport, MapperError<B::Error>> {
        self.clear_window();
        for i in 0..self.st.local.len() {
            self.add_to_window(self.st.local[i]);
        }
        let online_t = self.backend.layout().config.min_transmittance;
        let init_t = self.cfg.init_min_transmittance;
        if init_t != online_t {
            self.backend
                .set_min_transmittance(init_t)
                .map_err(MapperError::Backend)?;
        }
        let iters = self.run_iters(UpdateKind::Init, self.cfg.init_iters, observe);
        if init_t != online_t {
            self.backend
                .set_min_transmittance(online_t)
                .map_err(MapperError::Backend)?;
        }
        let (first, last) = iters?;
        self.st.initialized = true;
        self.st.pending = 0;
        // A longer initialisation window than the local set: trim it now.
        self.evict_to(self.cfg.local_frames as usize)?;
        Ok(self.report(UpdateKind::Init, self.cfg.init_iters, first, last, 0))
    }

    fn online_update<F: FnMut(&IterInfo)>(
        &mut self,
        observe: &mut F,
    ) -> Result<UpdateReport, MapperError<B::Error>> {
        self.evict_to(self.cfg.local_frames as usize)?;
        let candidates = self.select_keyframes()?;
        // window: the chosen keyframes (already in win_*), then the local frames
        for i in 0..self.st.local.len() {
            self.add_to_window(self.st.local[i]);
        }
        let (first, last) = self.run_iters(UpdateKind::Online, self.cfg.iters, observe)?;
        self.st.pending = 0;
        Ok(self.report(UpdateKind::Online, self.cfg.iters, first, last, candidates))
    }

    fn report(
        &self,
        kind: UpdateKind,
        iters: u32,
        first: IterInfo,
        last: IterInfo,
        candidates: u32,
    ) -> UpdateReport {
        UpdateReport {
            kind,
            frame: self.st.pushed.saturating_sub(1),
            iters,
            first,
            last,
            window_frames: self.win_ids.len() as u32,
            window_keyframes: self.win_kf as u32,
            candidates,
            keyframes: self.st.keyframes.len() as u32,
        }
    }

    /// Empties the window (its frames and keyframe count).
    fn clear_window(&mut self) {
        self.win_ids.clear();
        self.win_poses.clear();
        self.win_slots.clear();
        self.win_kf = 0;
    }

    fn add_to_window(&mut self, e: HeldFrame) {
        // A full window takes no more frames (the three lists grow together).
        if self.win_ids.push(e.id).is_ok() {
            let _ = self.win_poses.push(e.pose);
            let _ = self.win_slots.push(e.slot);
        }
    }

    fn free_slot(&mut self, slot: u32) {
        // Every slot comes from the stack, so it always has room for it again.
        let _ = self.st.free.push(slot);
    }

    /// Cuts the local set to its `keep` most recent frames: the oldest leaving frame joins the
    /// keyframe cache, the other leaving frames are dropped.
    fn evict_to(&mut self, keep: usize) -> Result<(), Error> {
        let n = self.st.local.len();
        if n <= keep {
            return Ok(());
        }
        let leave = n - keep;
        let oldest = self.st.local[0];
        for i in 1..leave {
            let slot = self.st.local[i].slot;
            self.free_slot(slot);
        }
        self.st.local.copy_within(leave.., 0);
        self.st.local.truncate(keep);
        self.add_keyframe(oldest);
        Ok(())
    }

    fn add_keyframe(&mut self, e: HeldFrame) {
        let cap = self.cfg.max_keyframes as usize;
        if cap == 0 {
            self.free_slot(e.slot);
            return;
        }
        if self.st.keyframes.len() >= cap {
            match self.cfg.keyframe_overflow {
                KeyframeOverflow::Thin => {
                    // keep cache indices 0, 2, 4, ...
                    let n = self.st.keyframes.len();
                    for r in (1..n).step_by(2) {
                        let slot = self.st.keyframes[r].slot;
                        self.free_slot(slot);
                    }
                    for w in 1..n.div_ceil(2) {
                        self.st.keyframes[w] = self.st.keyframes[2 * w];
                    }
                    self.st.keyframes.truncate(n.div_ceil(2));
                }
                KeyframeOverflow::DropOldest => {
                    let oldest = self.st.keyframes.remove(0);
                    self.free_slot(oldest.slot);
                }
            }
        }
        // `max_keyframes <= MAX_KEYFRAMES` (validated), so there is room now.
        if let Err(e) = self.st.keyframes.push(e) {
            self.free_slot(e.slot);
        }
    }

    /// Chooses the window's keyframes (into `win_*`, resetting the window) and returns the
    /// number of candidates.
    fn select_keyframes(&mut self) -> Result<u32, MapperError<B::Error>> {
        self.clear_window();
        let want = self.cfg.window_keyframes as usize;
        if want + self.cfg.global_keyframes as usize == 0
            || self.st.keyframes.is_empty()
            || self.st.local.is_empty()
        {
            return Ok(0);
        }
        let n = self.render_overlap_rays()?;
        let n_cand = self.overlap_candidates(n);
        // Partial Fisher-Yates: the first `take` candidates are a uniform random subset.
        let take = want.min(n_cand);
        self.shuffle_prefix(0, take, n_cand);
        let take = self.draw_global_keyframes(take);
        // Keep the chosen keyframes in cache order (oldest first).
        self.candidates[..take].sort_unstable();
        let mut i = 0;
        while i < take {
            let e = self.st.keyframes[self.candidates[i] as usize];
            self.add_to_window(e);
            i += 1;
        }
        self.win_kf = take;
        Ok(n_cand as u32)
    }

    /// Renders `overlap_pixels` random pixels of the newest frame into `overlap_out` and
    /// returns their number.
    fn render_overlap_rays(&mut self) -> Result<usize, MapperError<B::Error>> {
        let cur = self.st.local[self.st.local.len() - 1].pose;
        let k = self.k;
        let n = self.cfg.overlap_pixels as usize;
        let mut i = 0;
        while i < n {
            let u = self.rng.below(k.width) as f32;
            let v = self.rng.below(k.height) as f32;
            let (origin, dir) = cur.ray(&k, u, v);
            self.overlap_rays[i] = Ray {
                origin,
                dir,
                target: [0.0; 3],
                target_depth: 0.0,
            };
            i += 1;
        }
        self.backend
            .render(&self.overlap_rays[..n], &mut self.overlap_out[..n])
            .map_err(MapperError::Backend)?;
        Ok(n)
    }

    /// Writes the cache indices of the keyframes that see any back-projected point of the
    /// first `n` overlap rays, and at least `overlap_min` of those tested, into `candidates`
    /// (cache order) and returns their number.
    fn overlap_candidates(&mut self, n: usize) -> usize {
        let mut n_cand = 0usize;
        let mut tested = 0u32;
        // 0 (every preset) needs no count: any point inside makes a candidate.
        if self.cfg.overlap_min > 0.0 {
            let mut r = 0;
            while r < n {
                let out = self.overlap_out[r];
                if out.opacity > 0.0 && out.depth > 0.0 {
                    tested += self.cfg.overlap_points;
                }
                r += 1;
            }
        }
        let need = self.cfg.overlap_min * tested as f32;
        let mut f = 0;
        while f < self.st.keyframes.len() {
            let inside = self.overlap_points_inside(self.st.keyframes[f].pose, n);
            if inside > 0 && inside as f32 >= need {
                self.candidates[n_cand] = f as u16;
                n_cand += 1;
            }
            f += 1;
        }
        n_cand
    }

    /// How many of the overlap test's points (`overlap_points` per rendered ray with positive
    /// opacity and depth `D`, evenly on `[0.8 D, D + 0.5 m]`) project inside keyframe `kf`
    /// (in front of it, more than `overlap_margin` px from its border).
    fn overlap_points_inside(&self, kf: Pose, n: usize) -> u32 {
        let k = self.k;
        let np = self.cfg.overlap_points as usize;
        let margin = self.cfg.overlap_margin;
        let (w, h) = (k.width as f32, k.height as f32);
        let mut inside = 0u32;
        let mut r = 0;
        while r < n {
            let out = self.overlap_out[r];
            if out.opacity > 0.0 && out.depth > 0.0 {
                let d = out.depth;
                let ray = &self.overlap_rays[r];
                let (t0, t1) = (0.8 * d, d + 0.5);
                let mut s = 0;
                while s < np {
                    let t = t0 + (t1 - t0) * s as f32 / (np - 1) as f32;
                    let p = [
                        ray.origin[0] + t * ray.dir[0],
                        ray.origin[1] + t * ray.dir[1],
                        ray.origin[2] + t * ray.dir[2],
                    ];
                    let (pu, pv, z) = k.project(kf.inverse_transform(p));
                    if z > 0.0
                        && pu > margin
                        && pu < w - 1.0 - margin
                        && pv > margin
                        && pv < h - 1.0 - margin
                    {
                        inside += 1;
                    }
                    s += 1;
                }
            }
            r += 1;
        }
        inside
    }

    /// Partial Fisher-Yates over `candidates[from..len]`: afterwards `candidates[from..to]`
    /// is a uniform random subset of it.
    fn shuffle_prefix(&mut self, from: usize, to: usize, len: usize) {
        let mut i = from;
        while i < to {
            let j = i + self.rng.below((len - i) as u32) as usize;
            self.candidates.swap(i, j);
            i += 1;
        }
    }

    /// Appends up to `global_keyframes` keyframes drawn uniformly from the cache entries not
    /// among `candidates[..take]` and returns the new count.
    fn draw_global_keyframes(&mut self, take: usize) -> usize {
        let global = self.cfg.global_keyframes as usize;
        if global == 0 || take >= self.st.keyframes.len() {
            return take;
        }
        // the cache indices not chosen yet, after the chosen ones
        let mut m = take;
        let mut f = 0;
        while f < self.st.keyframes.len() {
            if !self.candidates[..take].contains(&(f as u16)) {
                self.candidates[m] = f as u16;
                m += 1;
            }
            f += 1;
        }
        let extra = global.min(m - take);
        self.shuffle_prefix(take, take + extra, m);
        take + extra
    }

    fn sample_pixels(&mut self, kind: UpdateKind) {
        let n = self.win_ids.len().max(1) as u32;
        let total = self.cfg.pixels;
        // the frames new since the last update are the last `n_new` of the window
        let n_new = if kind == UpdateKind::Online && self.cfg.new_frame_share > 0.0 {
            (self.st.pending as u32).min(n)
        } else {
            0
        };
        if n_new == 0 || n_new == n || total < n {
            self.sample_range(0, n, 0, total);
            return;
        }
        let n_old = n - n_new;
        let want = (self.cfg.new_frame_share * total as f32 + 0.5) as u32;
        let new_total = want.clamp(n_new, total - n_old);
        let old_total = total - new_total;
        // the window's keyframes are its first `win_kf` frames
        let n_kf = (self.win_kf as u32).min(n_old);
        if self.cfg.keyframe_share > 0.0 && n_kf > 0 && n_kf < n_old {
            let n_mid = n_old - n_kf;
            let want = (self.cfg.keyframe_share * total as f32 + 0.5) as u32;
            let kf_total = want.clamp(n_kf.min(old_total), old_total.saturating_sub(n_mid));
            self.sample_range(0, n_kf, 0, kf_total);
            self.sample_range(n_kf, n_old, kf_total as usize, old_total - kf_total);
        } else {
            self.sample_range(0, n_old, 0, old_total);
        }
        self.sample_range(n_old, n, old_total as usize, new_total);
    }

    /// Turns complete triples of sampled pixels (items `3g..3g + 3`; a `planar_share` of
    /// them, spread evenly) into planarity triplets around their middle pixel: a spacing `s` in `1..=planar_spacing` and a row or a
    /// column drawn, the middle pixel moved inside the border by at least `s`, the outer two
    /// at `-s` and `+s` in the middle pixel's frame.
    fn make_triplets(&mut self) {
        let (w, h) = (self.k.width, self.k.height);
        let b = self.cfg.border;
        let total = self.cfg.pixels as usize;
        let share = self.cfg.planar_share;
        let mut first = 0;
        while first + 3 <= total {
            // triple g is a triplet when floor((g + 1) share) > floor(g share)
            let g = (first / 3) as f32;
            if ((g + 1.0) * share) as u32 == (g * share) as u32 {
                first += 3;
                continue;
            }
            let o = self.pix_off;
            let mid = self.pixels[o + first + 1];
            if self.cfg.planar_region_step > 0.0 {
                let row = self.rng.below(2) == 0;
                if let Some((a, c)) = self.region_ends(mid, row) {
                    self.pixels[o + first] = a;
                    self.pixels[o + first + 2] = c;
                }
                first += 3;
                continue;
            }
            let s = 1 + self.rng.below(self.cfg.planar_spacing);
            let row = self.rng.below(2) == 0;
            let (lo, hi_u, hi_v) = (b + s, w - 1 - b - s, h - 1 - b - s);
            let (mut a, mut c) = (mid, mid);
            if row {
                let u = mid.u.clamp(lo, hi_u);
                a.u = u - s;
                c.u = u + s;
                self.pixels[o + first + 1].u = u;
            } else {
                let v = mid.v.clamp(lo, hi_v);
                a.v = v - s;
                c.v = v + s;
                self.pixels[o + first + 1].v = v;
            }
            a.frame = mid.frame;
            c.frame = mid.frame;
            self.pixels[o + first] = a;
            self.pixels[o + first + 2] = c;
            first += 3;
        }
    }

    /// The ends of the plain run through `mid` along its row (`row`) or column (see
    /// [`MapperConfig::planar_region_step`]); `None` when either end is closer than
    /// [`PLANAR_REGION_MIN`] px.
    fn region_ends(&self, mid: PixelSample, row: bool) -> Option<(PixelSample, PixelSample)> {
        let slot = *self.win_slots.get(mid.frame as usize)?;
        let (w, h) = (self.k.width, self.k.height);
        let b = self.cfg.border;
        let (pos, lo, hi) = if row {
            (mid.u, b, w - 1 - b)
        } else {
            (mid.v, b, h - 1 - b)
        };
        let at = |p: u32| {
            let (u, v) = if row { (p, mid.v) } else { (mid.u, p) };
            crate::train::pixel::unpack_rgba8(self.backend.slot_texel(slot, u, v))
        };
        let max = self.cfg.planar_spacing;
        let thr = self.cfg.planar_region_step;
        // towards lower coordinates, then higher
        let centre = at(pos);
        let mut ends = [0u32; 2];
        for (side, end) in ends.iter_mut().enumerate() {
            let mut s = 0u32;
            let mut prev = centre;
            while s < max {
                let next = if side == 0 {
                    if pos < lo + s + 1 {
                        break;
                    }
                    pos - s - 1
                } else {
                    if pos + s + 1 > hi {
                        break;
                    }
                    pos + s + 1
                };
                let c = at(next);
                if mean_abs_diff(prev, c) > thr {
                    break;
                }
                prev = c;
                s += 1;
            }
            *end = s;
        }
        if ends[0] < PLANAR_REGION_MIN || ends[1] < PLANAR_REGION_MIN {
            return None;
        }
        let (mut a, mut c) = (mid, mid);
        if row {
            a.u = pos - ends[0];
            c.u = pos + ends[1];
        } else {
            a.v = pos - ends[0];
            c.v = pos + ends[1];
        }
        Some((a, c))
    }

    /// Draws `total` pixels spread evenly over window frames `f0..f1` into
    /// `pixels[idx0..idx0 + total]` (`total / n` each, the first `total % n` one more).
    fn sample_range(&mut self, f0: u32, f1: u32, idx0: usize, total: u32) {
        let n = f1 - f0;
        let (w, h) = (self.k.width, self.k.height);
        let b = self.cfg.border;
        let per = total / n;
        let extra = total % n;
        let mut idx = idx0;
        let mut f = 0;
        while f < n {
            let cnt = per + if f < extra { 1 } else { 0 };
            let mut c = 0;
            while c < cnt {
                let u = b + self.rng.below(w - 2 * b);
                let v = b + self.rng.below(h - 2 * b);
                self.pixels[self.pix_off + idx] = PixelSample {
                    frame: f0 + f,
                    u,
                    v,
                };
                idx += 1;
                c += 1;
            }
            f += 1;
        }
    }

    /// Counts a rejected step and, after `rejected_lr_after` in a row, lowers every group's
    /// learning rate by `rejected_lr_factor`.
    fn on_rejected_step(&mut self) -> Result<(), MapperError<B::Error>> {
        self.st.rejected_steps += 1;
        self.st.rejected_run += 1;
        let after = self.cfg.rejected_lr_after;
        if after > 0 && self.st.rejected_run >= after {
            self.st.rejected_run = 0;
            self.st.lr_reductions += 1;
            for g in Group::ALL {
                let lr = self.backend.adam_lr(g) * self.cfg.rejected_lr_factor;
                self.backend
                    .set_adam_lr(g, lr)
                    .map_err(MapperError::Backend)?;
            }
        }
        Ok(())
    }

    /// [`IterInfo::new_loss_ratio`] and [`IterInfo::new_warp_valid`] of the results of the
    /// iteration just run.
    fn new_frames_fit(&self, pixels: core::ops::Range<usize>) -> (f32, f32) {
        let n = self.win_ids.len() as u32;
        let first_new = n - (self.st.pending as u32).min(n);
        let (mut new_sum, mut new_n, mut new_valid) = (0.0f32, 0u32, 0u32);
        let (mut old_sum, mut old_n) = (0.0f32, 0u32);
        for (p, r) in self.pixels[pixels].iter().zip(self.results.iter()) {
            let l = r.color_loss + r.warp_loss;
            if p.frame >= first_new {
                new_sum += l;
                new_n += 1;
                new_valid += (r.warp_views >= self.cfg.warp.min_views) as u32;
            } else {
                old_sum += l;
                old_n += 1;
            }
        }
        if new_n == 0 {
            return (0.0, 0.0);
        }
        let valid = new_valid as f32 / new_n as f32;
        if old_n == 0 || old_sum <= 0.0 {
            return (0.0, valid);
        }
        ((new_sum / new_n as f32) / (old_sum / old_n as f32), valid)
    }

    /// The pixels (and, with `lambda_planar`, the triplets) of one iteration, written at
    /// `off` in the pixel buffer.
    fn draw_batch(&mut self, kind: UpdateKind, off: usize) {
        self.pix_off = off;
        self.sample_pixels(kind);
        if self.planar_weight(kind) > 0.0 {
            self.make_triplets();
        }
    }

    /// The planarity prior's weight in an update of `kind`.
    fn planar_weight(&self, kind: UpdateKind) -> f32 {
        if kind == UpdateKind::Refine && self.cfg.refine_lambda_planar > 0.0 {
            self.cfg.refine_lambda_planar
        } else {
            self.cfg.lambda_planar
        }
    }

    /// The backend's learning rate of every group, in [`Group::ALL`] order.
    fn backend_lrs(&self) -> [f32; NUM_GROUPS] {
        core::array::from_fn(|g| self.backend.adam_lr(Group::ALL[g]))
    }

    /// The loss settings of iteration `it` of an update of `kind`, `total` iterations into the
    /// run (the seed).
    fn iter_loss(&self, kind: UpdateKind, it: u32, total: u32) -> MappingLoss {
        let inv = 1.0 / self.cfg.pixels as f32;
        let init = kind == UpdateKind::Init;
        // An appearance-only refinement leaves the geometry's rates at 0: the terms that
        // act only on the geometry (warping, depth priors, planarity) are not computed,
        // which changes no parameter and makes its iterations cheaper.
        let geometry = kind != UpdateKind::Refine || self.cfg.refine_geometry;
        let on = |w: f32| if geometry { w } else { 0.0 };
        MappingLoss {
            lambda_color: if init {
                self.cfg.lambda_color_init
            } else if kind == UpdateKind::Refine && self.cfg.refine_lambda_color > 0.0 {
                self.cfg.refine_lambda_color
            } else {
                self.cfg.lambda_color
            },
            lambda_warp: on(self.cfg.lambda_warp),
            color_scale: inv,
            warp_scale: inv,
            color_to_geometry: match kind {
                UpdateKind::Init => it < self.cfg.init_color_iters,
                UpdateKind::Online => self.cfg.online_color_to_geometry,
                // an appearance-only refinement has no geometry to reach
                UpdateKind::Refine => self.cfg.refine_color_to_geometry && geometry,
            },
            seed: hash_u32(total ^ (self.cfg.seed as u32)),
            warp: self.cfg.warp,
            lambda_depth_prior: on(if init && it < self.cfg.depth_prior_iters {
                self.cfg.lambda_depth_prior
            } else {
                self.cfg.lambda_depth_prior_online
            }),
            depth_prior: self.cfg.depth_prior,
            depth_prior_near: if init && it < self.cfg.depth_prior_iters {
                0.0
            } else {
                self.cfg.depth_prior_near
            },
            planar: PlanarConfig {
                weight: on(self.planar_weight(kind)),
                edge: self.cfg.planar_edge,
                beta: self.cfg.planar_beta,
                gated: self.cfg.planar_gate,
            },
            lambda_plane: on(match kind {
                UpdateKind::Init => 0.0,
                UpdateKind::Online => self.cfg.lambda_plane,
                UpdateKind::Refine => self.cfg.refine_lambda_plane,
            }),
        }
    }

    /// Runs `iters` mapping iterations. Each step's batch carries its learning rates,
    /// decided before the previous step's results are read (a reduction after rejected
    /// steps applies from the step after next), so a backend that queues the next step
    /// early trains the same bits as one that does not.
    fn run_iters<F: FnMut(&IterInfo)>(
        &mut self,
        kind: UpdateKind,
        iters: u32,
        observe: &mut F,
    ) -> Result<(IterInfo, IterInfo), MapperError<B::Error>> {
        let n = self.cfg.pixels as usize;
        let inv = 1.0 / self.cfg.pixels as f32;
        let two = self.pixels.len() == 2 * n;
        let mut first = IterInfo {
            kind,
            iter: 0,
            iters,
            loss: 0.0,
            color_loss: 0.0,
            warp_loss: 0.0,
            warp_valid: 0.0,
            open_rays: 0.0,
            rejected: false,
            new_loss_ratio: 0.0,
            new_warp_valid: 0.0,
        };
        let mut last = first;
        let mut it = 0;
        let mut cur = 0;
        if iters > 0 {
            self.draw_batch(kind, cur);
        }
        let mut lr = self.backend_lrs();
        while it < iters {
            let ahead = two && it + 1 < iters;
            let lr_next = self.backend_lrs();
            let next_off = if two { n - cur } else { cur };
            if ahead {
                self.draw_batch(kind, next_off);
            }
            let total = self.st.total_iters;
            let loss = self.iter_loss(kind, it, total);
            let loss_next = self.iter_loss(kind, it + 1, total.wrapping_add(1));
            let batch = MapBatch {
                k: self.k,
                poses: &self.win_poses,
                slots: &self.win_slots,
                pixels: &self.pixels[cur..cur + n],
                loss,
                lr: Some(lr),
            };
            let next = MapBatch {
                pixels: &self.pixels[next_off..next_off + n],
                loss: loss_next,
                lr: Some(lr_next),
                ..batch
            };
            let stats = self
                .backend
                .map_step(&batch, self.results, if ahead { Some(&next) } else { None })
                .map_err(MapperError::Backend)?;
            self.st.total_iters = self.st.total_iters.wrapping_add(1);
            let mut c = 0.0f32;
            let mut wl = 0.0f32;
            let mut valid = 0u32;
            let mut open = 0u32;
            for r in self.results.iter() {
                c += r.color_loss;
                wl += r.warp_loss;
                valid += (r.warp_views >= self.cfg.warp.min_views) as u32;
                open += (r.opacity < 0.5) as u32;
            }
            let mut info = IterInfo {
                kind,
                iter: it,
                iters,
                loss: stats.loss,
                color_loss: c,
                warp_loss: wl,
                warp_valid: valid as f32 * inv,
                open_rays: open as f32 * inv,
                rejected: stats.rejected,
                new_loss_ratio: 0.0,
                new_warp_valid: 0.0,
            };
            if it == 0 && kind == UpdateKind::Online {
                (info.new_loss_ratio, info.new_warp_valid) = self.new_frames_fit(cur..cur + n);
            }
            if stats.rejected {
                self.on_rejected_step()?;
            } else {
                self.st.rejected_run = 0;
            }
            if it == 0 {
                first = info;
            }
            last = info;
            observe(&info);
            it += 1;
            if it < iters && !two {
                self.draw_batch(kind, cur);
            }
            cur = next_off;
            lr = lr_next;
        }
        Ok((first, last))
    }
}

/// Fills `out` with the rays of every pixel of a view (row-major, pixel centres), for
/// [`Backend::render`]. `out` must hold `k.width * k.height` rays.
pub fn view_rays(k: &Intrinsics, pose: &Pose, out: &mut [Ray]) -> Result<(), Error> {
    crate::error::check_len("view rays", out.len(), k.width as usize * k.height as usize)?;
    let mut i = 0;
    let mut v = 0;
    while v < k.height {
        let mut u = 0;
        while u < k.width {
            let (origin, dir) = pose.ray(k, u as f32, v as f32);
            out[i] = Ray {
                origin,
                dir,
                target: [0.0; 3],
                target_depth: 0.0,
            };
            i += 1;
            u += 1;
        }
        v += 1;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::field::model::{LossConfig, ModelConfig, ModelLayout};
    use crate::train::backend::StepStats;
    use crate::Aabb;
    use std::vec;
    use std::vec::Vec;

    /// What the mock saw of one `map_step`.
    #[derive(Clone, Debug)]
    struct Call {
        slots: Vec<u32>,
        pixels: Vec<PixelSample>,
        lambda_color: f32,
        color_to_geometry: bool,
        /// The planarity prior's weight.
        planar: f32,
        /// The first group's learning rate at the step.
        lr: f32,
    }

    /// A backend that renders every ray at depth 2 m with full opacity and records the
    /// mapping steps.
    struct Mock {
        layout: ModelLayout,
        store: ImageStore,
        uploads: Vec<u32>,
        /// The uploaded images (slot-major).
        images: Vec<u32>,
        calls: Vec<Call>,
        /// Every step reports itself rejected; the learning rates the mapper set.
        reject: bool,
        lr: [f32; crate::field::model::NUM_GROUPS],
        /// Every early-termination threshold the mapper set.
        min_t: Vec<f32>,
        /// Results that depend on the pixel's window frame `f`: colour loss `0.25 (f + 1)`,
        /// `f` valid warp views for even `f` and none for odd (otherwise 0.25 and none).
        by_frame: bool,
        /// The batch the last step promised as the next one.
        queued: Option<Queued>,
        /// Steps that came with a next batch.
        nexts: u32,
    }

    struct Queued {
        pixels: Vec<PixelSample>,
        lr: Option<[f32; crate::field::model::NUM_GROUPS]>,
        seed: u32,
    }

    impl Mock {
        fn new(slots: u32) -> Self {
            let layout =
                ModelLayout::new(&ModelConfig::paper(Aabb::new([-4.0; 3], [4.0; 3]))).unwrap();
            Self {
                layout,
                store: ImageStore {
                    width: 64,
                    height: 48,
                    slots,
                },
                uploads: Vec::new(),
                images: vec![0; 64 * 48 * slots as usize],
                calls: Vec::new(),
                reject: false,
                lr: [0.01; crate::field::model::NUM_GROUPS],
                min_t: Vec::new(),
                by_frame: false,
                queued: None,
                nexts: 0,
            }
        }
    }

    impl Backend for Mock {
        type Error = Error;
        fn layout(&self) -> &ModelLayout {
            &self.layout
        }
        fn name(&self) -> &str {
            "mock"
        }
        fn train_step(
            &mut self,
            _: &[Ray],
            _: &LossConfig,
            _: &mut [RayResult],
        ) -> Result<StepStats, Error> {
            Ok(StepStats::default())
        }
        fn render(&mut self, rays: &[Ray], out: &mut [RayResult]) -> Result<(), Error> {
            for o in out.iter_mut().take(rays.len()) {
                *o = RayResult {
                    color: [0.5; 3],
                    depth: 2.0,
                    opacity: 1.0,
                    loss: 0.0,
                };
            }
            Ok(())
        }
        fn read_params(&mut self, _: Group, _: &mut [f32]) -> Result<(), Error> {
            Ok(())
        }
        fn read_grads(&mut self, _: Group, _: &mut [i64]) -> Result<(), Error> {
            Ok(())
        }
        fn read_adam(&mut self, _: Group, _: &mut [f32], _: &mut [f32]) -> Result<(), Error> {
            Ok(())
        }
        fn write_params(&mut self, _: Group, _: &[f32], _: bool) -> Result<(), Error> {
            Ok(())
        }
        fn image_store(&self) -> ImageStore {
            self.store
        }
        fn upload_frame(&mut self, slot: u32, rgba: &[u32]) -> Result<(), Error> {
            assert_eq!(rgba.len(), self.store.slot_len());
            assert!(slot < self.store.slots);
            self.uploads.push(slot);
            let n = self.store.slot_len();
            self.images[slot as usize * n..][..n].copy_from_slice(rgba);
            Ok(())
        }
        fn slot_texel(&self, slot: u32, u: u32, v: u32) -> u32 {
            self.store
                .texel_index(slot, u, v)
                .map_or(0, |i| self.images[i])
        }
        fn map_step(
            &mut self,
            batch: &MapBatch<'_>,
            results: &mut [PixelResult],
            next: Option<&MapBatch<'_>>,
        ) -> Result<StepStats, Error> {
            crate::train::backend::window_slots(batch, &self.store)?;
            // a promised batch must be the one that comes
            if let Some(q) = self.queued.take() {
                assert_eq!(q.pixels, batch.pixels);
                assert_eq!(q.lr, batch.lr);
                assert_eq!(q.seed, batch.loss.seed);
            }
            self.queued = next.map(|b| Queued {
                pixels: b.pixels.to_vec(),
                lr: b.lr,
                seed: b.loss.seed,
            });
            self.nexts += next.is_some() as u32;
            self.calls.push(Call {
                slots: batch.slots.to_vec(),
                pixels: batch.pixels.to_vec(),
                lambda_color: batch.loss.lambda_color,
                color_to_geometry: batch.loss.color_to_geometry,
                planar: batch.loss.planar.weight,
                lr: batch.lr.map_or(self.lr[0], |l| l[0]),
            });
            for (r, p) in results.iter_mut().zip(batch.pixels) {
                let f = p.frame;
                *r = if self.by_frame {
                    PixelResult {
                        color_loss: 0.25 * (f + 1) as f32,
                        warp_views: if f % 2 == 0 { f } else { 0 },
                        ..PixelResult::default()
                    }
                } else {
                    PixelResult {
                        color_loss: 0.25,
                        ..PixelResult::default()
                    }
                };
            }
            Ok(StepStats {
                loss: 0.25 * results.len() as f32,
                rays_hit: 0,
                t: self.calls.len() as u32,
                rejected: self.reject,
            })
        }
        fn set_adam_lr(&mut self, g: Group, lr: f32) -> Result<(), Error> {
            self.lr[g as usize] = lr;
            Ok(())
        }
        fn adam_lr(&self, g: Group) -> f32 {
            self.lr[g as usize]
        }
        fn set_min_transmittance(&mut self, t: f32) -> Result<(), Error> {
            self.min_t.push(t);
            self.layout.set_min_transmittance(t)
        }
    }

    /// Pixel and result buffers for `cfg()`'s 60 pixels.
    fn buffers() -> (Vec<PixelSample>, Vec<PixelResult>) {
        (
            vec![PixelSample::default(); 60],
            vec![PixelResult::default(); 60],
        )
    }

    /// Whether `Mapper::new` refuses the configuration `c`.
    fn refused(c: MapperConfig) -> bool {
        let (mut px, mut res) = buffers();
        Mapper::new(Mock::new(c.slots_needed()), c, intr(), &mut px, &mut res).is_err()
    }

    fn cfg() -> MapperConfig {
        let mut c = MapperConfig::paper(60);
        c.init_iters = 7;
        c.init_color_iters = 3;
        c.iters = 4;
        c
    }

    /// Camera at x = 0.01 i looking along +z (every keyframe overlaps the current view).
    fn pose(i: u32) -> Pose {
        let mut p = Pose::IDENTITY;
        p.m[0][3] = 0.01 * i as f32;
        p
    }

    fn image() -> Vec<u32> {
        vec![0xff80_8080; 64 * 48]
    }

    fn push_n<'a>(m: &mut Mapper<'a, Mock>, n: u32) -> Vec<UpdateReport> {
        let img = image();
        let mut out = Vec::new();
        for _ in 0..n {
            let id = m.frames_pushed();
            if let Some(r) = m.push_frame(&img, pose(id)).unwrap() {
                out.push(r);
            }
        }
        out
    }

    #[test]
    fn initialisation_triggers_on_the_15th_frame_with_the_colour_schedule() {
        let c = cfg();
        let (mut px, mut res) = buffers();
        let mut m = Mapper::new(Mock::new(c.slots_needed()), c, intr(), &mut px, &mut res).unwrap();
        assert!(push_n(&mut m, 14).is_empty());
        assert!(!m.is_initialized());
        let r = push_n(&mut m, 1);
        assert_eq!(r.len(), 1);
        assert_eq!(r[0].kind, UpdateKind::Init);
        assert_eq!(r[0].frame, 14);
        assert_eq!(r[0].window_frames, 15);
        assert_eq!(m.window_ids(), (0..15).collect::<Vec<_>>().as_slice());
        let calls = &m.backend().calls;
        assert_eq!(calls.len(), 7);
        // colour reaches the geometry in the first 3 iterations only, lambda_c = 0.1
        let ctg: Vec<bool> = calls.iter().map(|c| c.color_to_geometry).collect();
        assert_eq!(ctg, [true, true, true, false, false, false, false]);
        assert!(calls
            .iter()
            .all(|c| c.lambda_color == 0.1 && c.slots.len() == 15));
        // 0.25 per pixel, 60 pixels: the mock's loss
        assert_eq!(r[0].last.loss, 15.0);
        assert_eq!(m.iterations(), 7);
    }

    fn intr() -> Intrinsics {
        Intrinsics {
            width: 64,
            height: 48,
            fx: 50.0,
            fy: 50.0,
            cx: 31.5,
            cy: 23.5,
        }
    }

    /// The steps of 20 pushed frames (the initialisation's 7, then 4 online updates) and of
    /// a 20-iteration refinement (windows of 4, blocks of 10) under `c`: (online, refinement).
    fn run_and_refinement_calls(mut c: MapperConfig) -> (Vec<Call>, Vec<Call>) {
        (c.refine_iters, c.refine_window, c.refine_block) = (20, 4, 10);
        let (mut px, mut res) = buffers();
        let mut m = Mapper::new(Mock::new(c.slots_needed()), c, intr(), &mut px, &mut res).unwrap();
        push_n(&mut m, 20);
        let online = m.backend().calls.len();
        m.refine(&mut |_| {}).unwrap();
        let mut calls = m.backend().calls.clone();
        let refine = calls.split_off(online);
        (calls, refine)
    }

    #[test]
    fn color_to_geometry_settings_reach_online_updates_and_the_refinement() {
        // The calls of the initialisation, the 4 online updates and a 20-iteration refinement.
        let phases = |c: MapperConfig| -> [Vec<Call>; 3] {
            let (mut run, refine) = run_and_refinement_calls(c);
            let online = run.split_off(7);
            [run, online, refine]
        };
        let ctg =
            |calls: &[Call]| -> Vec<bool> { calls.iter().map(|c| c.color_to_geometry).collect() };
        let with = |online: bool, refine_geometry: bool| {
            let mut c = cfg();
            c.online_color_to_geometry = online;
            c.refine_color_to_geometry = online;
            c.refine_geometry = refine_geometry;
            phases(c).map(|p| ctg(&p))
        };
        // off (the default): only the first `init_color_iters` initialisation iterations
        let init = [true, true, true, false, false, false, false];
        let [i, o, r] = with(false, true);
        assert_eq!(i, init);
        assert!(o.len() == 4 && r.len() == 20);
        assert!(!o.iter().any(|&b| b) && !r.iter().any(|&b| b));
        let [i, o, r] = with(true, true);
        assert_eq!(i, init, "the initialisation keeps its own schedule");
        assert!(o.len() == 4 && r.len() == 20);
        assert!(o.iter().all(|&b| b) && r.iter().all(|&b| b));
        let [_, o, r] = with(true, false);
        assert!(o.iter().all(|&b| b), "online updates");
        assert!(
            !r.iter().any(|&b| b),
            "an appearance-only refinement has no geometry"
        );
        // the refinement alone, with its own colour weight; the online updates keep theirs
        let mut c = cfg();
        c.refine_color_to_geometry = true;
        c.refine_lambda_color = 0.5;
        let [_, o, r] = phases(c);
        assert!(o
            .iter()
            .all(|c| !c.color_to_geometry && c.lambda_color == 0.001));
        assert!(r
            .iter()
            .all(|c| c.color_to_geometry && c.lambda_color == 0.5));
        assert_eq!(r.len(), 20);
        // a negative or non-finite refinement weight is refused
        refuses_bad_weights(|c, w| c.refine_lambda_color = w);
    }

    /// A configuration with `set(w)` for a negative and a non-finite weight `w` is refused.
    fn refuses_bad_weights(set: impl Fn(&mut MapperConfig, f32)) {
        for w in [-1.0, f32::NAN] {
            let mut c = cfg();
            set(&mut c, w);
            let (mut px, mut res) = buffers();
            let m = Mapper::new(Mock::new(c.slots_needed()), c, intr(), &mut px, &mut res);
            assert!(matches!(m, Err(Error::InvalidConfig(_))), "{w}");
        }
    }

    #[test]
    fn the_refinement_has_its_own_planarity_weight_and_triplets() {
        // (online, refinement) planarity weights, and whether each phase drew line triplets
        let run = |online: f32, refine: f32| -> [(Vec<f32>, bool); 2] {
            let mut c = cfg();
            c.lambda_planar = online;
            c.refine_lambda_planar = refine;
            c.planar_spacing = 4;
            let (online, refine) = run_and_refinement_calls(c);
            [online, refine].map(|calls| {
                let lines = calls
                    .iter()
                    .flat_map(|c| c.pixels.chunks_exact(3))
                    .filter(|t| crate::train::pixel::is_line_triplet(&[t[0], t[1], t[2]]))
                    .count();
                // a triplet per triple: far more than random draws would line up
                (
                    calls.iter().map(|c| c.planar).collect(),
                    lines * 2 > calls.len() * (calls[0].pixels.len() / 3),
                )
            })
        };
        let weights = |p: &(Vec<f32>, bool)| p.0.iter().all(|&w| w == p.0[0]).then(|| p.0[0]);
        let [o, r] = run(0.0, 0.0);
        assert_eq!(
            (weights(&o), o.1, weights(&r), r.1),
            (Some(0.0), false, Some(0.0), false)
        );
        let [o, r] = run(0.0, 0.2);
        assert_eq!(
            (weights(&o), o.1),
            (Some(0.0), false),
            "online stays without the prior"
        );
        assert_eq!((weights(&r), r.1), (Some(0.2), true));
        let [o, r] = run(0.1, 0.0);
        assert_eq!(
            (weights(&o), o.1, weights(&r), r.1),
            (Some(0.1), true, Some(0.1), true)
        );
        let [o, r] = run(0.1, 0.3);
        assert_eq!((weights(&o), weights(&r)), (Some(0.1), Some(0.3)));
        // the refinement's weight is checked like the others
        refuses_bad_weights(|c, w| c.refine_lambda_planar = w);
    }

    #[test]
    fn online_windows_local_set_and_keyframe_cache_follow_the_schedule() {
        let c = cfg();
        let (mut px, mut res) = buffers();
        let mut m = Mapper::new(Mock::new(c.slots_needed()), c, intr(), &mut px, &mut res).unwrap();
        push_n(&mut m, 15);
        assert!(push_n(&mut m, 4).is_empty());
        let r = push_n(&mut m, 1);
        assert_eq!(r.len(), 1);
        let r = r[0];
        assert_eq!((r.kind, r.frame), (UpdateKind::Online, 19));
        // frames 0..5 left the local set; frame 0 became a keyframe, 1..4 were dropped
        assert_eq!(
            m.local_ids().collect::<Vec<_>>(),
            (5..20).collect::<Vec<_>>()
        );
        assert_eq!(m.keyframe_ids().collect::<Vec<_>>(), [0]);
        let mut want = vec![0];
        want.extend(5..20);
        assert_eq!(m.window_ids(), want.as_slice());
        assert_eq!(
            (r.window_frames, r.window_keyframes, r.keyframes),
            (16, 1, 1)
        );
        let calls = &m.backend().calls;
        assert_eq!(calls.len(), 7 + 4);
        assert!(calls[7..]
            .iter()
            .all(|c| c.lambda_color == 0.001 && !c.color_to_geometry && c.slots.len() == 16));
        // 10 more updates: keyframes 0, 5, ..., 50; window = 5 of them + 15 local frames
        let reps = push_n(&mut m, 50);
        assert_eq!(reps.len(), 10);
        assert!(reps.iter().all(|r| r.kind == UpdateKind::Online));
        assert_eq!(
            m.keyframe_ids().collect::<Vec<_>>(),
            (0..11).map(|i| 5 * i).collect::<Vec<_>>()
        );
        assert_eq!(
            m.local_ids().collect::<Vec<_>>(),
            (55..70).collect::<Vec<_>>()
        );
        let w = m.window_ids();
        assert_eq!(w.len(), 20);
        assert!(
            w[..5].windows(2).all(|p| p[0] < p[1]) && w[..5].iter().all(|i| i % 5 == 0 && *i < 55)
        );
        assert_eq!(&w[5..], (55..70).collect::<Vec<_>>().as_slice());
        // every live frame has its own slot, and slots are recycled (never more than needed)
        let last = m.backend().calls.last().unwrap().slots.clone();
        let mut s = last.clone();
        s.sort();
        s.dedup();
        assert_eq!(s.len(), last.len());
        assert!(m.backend().uploads.iter().all(|&s| s < c.slots_needed()));
    }

    /// The final refinement runs `refine_iters` steps in blocks, each over `refine_window`
    /// held frames consecutive in push order (slots of keyframes and local frames), with
    /// the online losses and pixels spread evenly; nothing when it is off or before the
    /// initialisation.
    #[test]
    fn refinement_steps_through_windows_of_neighbouring_held_frames() {
        let mut c = cfg();
        c.refine_iters = 25;
        c.refine_window = 4;
        c.refine_block = 10;
        let (mut px, mut res) = buffers();
        let mut m = Mapper::new(Mock::new(c.slots_needed()), c, intr(), &mut px, &mut res).unwrap();
        push_n(&mut m, 10);
        assert!(m.refine(&mut |_| {}).unwrap().is_none(), "not initialised");
        push_n(&mut m, 60);
        m.flush(&mut |_| {}).unwrap();
        let held: Vec<u32> = m.keyframe_ids().chain(m.local_ids()).collect();
        assert!(held.windows(2).all(|w| w[0] < w[1]), "{held:?}");
        // slot of each held frame, in push order
        let slots: Vec<u32> = m
            .state()
            .keyframes
            .iter()
            .chain(m.state().local.iter())
            .map(|e| e.slot)
            .collect();
        let before = m.backend().calls.len();
        let mut kinds = Vec::new();
        let r = m
            .refine(&mut |i| kinds.push((i.kind, i.iter, i.iters)))
            .unwrap();
        let r = r.expect("a refinement");
        assert_eq!((r.kind, r.iters), (UpdateKind::Refine, 25));
        let calls = &m.backend().calls[before..];
        assert_eq!(calls.len(), 25);
        assert_eq!(kinds.len(), 25);
        // blocks of 10, 10, 5 iterations, each on one window; the observer counts the
        // refinement's iterations
        assert!(kinds
            .iter()
            .enumerate()
            .all(|(i, k)| *k == (UpdateKind::Refine, i as u32, 25)));
        let mut starts = Vec::new();
        for (b, block) in [&calls[0..10], &calls[10..20], &calls[20..25]]
            .into_iter()
            .enumerate()
        {
            let w = &block[0].slots;
            assert!(block.iter().all(|c| &c.slots == w), "block {b}");
            let start = slots.iter().position(|s| *s == w[0]).unwrap();
            assert_eq!(w.as_slice(), &slots[start..start + 4], "block {b}");
            starts.push(start);
            for call in block {
                assert_eq!(call.lambda_color, 0.001);
                assert!(!call.color_to_geometry);
                // 60 pixels spread evenly: 15 per window frame
                for f in 0..4 {
                    assert_eq!(call.pixels.iter().filter(|p| p.frame == f).count(), 15);
                }
            }
        }
        assert!(
            starts.iter().any(|s| *s != starts[0]),
            "random windows {starts:?}"
        );
        assert!(calls.iter().all(|c| c.lr == 0.01), "constant rates");
        // rates falling linearly per block to refine_lr_end, restored afterwards
        let mut c = cfg();
        (c.refine_iters, c.refine_window, c.refine_block) = (40, 4, 10);
        c.refine_lr_end = 0.2;
        let (mut px, mut res) = buffers();
        let mut m = Mapper::new(Mock::new(c.slots_needed()), c, intr(), &mut px, &mut res).unwrap();
        push_n(&mut m, 30);
        let before = m.backend().calls.len();
        m.refine(&mut |_| {}).unwrap();
        let lrs: Vec<f32> = m.backend().calls[before..]
            .iter()
            .step_by(10)
            .map(|c| c.lr)
            .collect();
        let want = [1.0f32, 0.8, 0.6, 0.4].map(|f| 0.01 * f);
        assert_eq!(lrs.len(), 4);
        for (a, b) in lrs.iter().zip(want) {
            assert!((a - b).abs() < 1e-8, "{lrs:?}");
        }
        assert_eq!(m.backend().adam_lr(Group::GeometryGrid), 0.01);
        // appearance only: the geometry groups' rates are 0 during it, restored afterwards
        let mut c = cfg();
        (c.refine_iters, c.refine_window, c.refine_block) = (20, 4, 10);
        c.refine_geometry = false;
        let (mut px, mut res) = buffers();
        let mut m = Mapper::new(Mock::new(c.slots_needed()), c, intr(), &mut px, &mut res).unwrap();
        push_n(&mut m, 30);
        let before = m.backend().calls.len();
        m.refine(&mut |_| {}).unwrap();
        // the mock records the geometry grid's rate (group 0)
        assert!(m.backend().calls[before..].iter().all(|c| c.lr == 0.0));
        assert_eq!(m.backend().calls.len(), before + 20);
        assert_eq!(m.backend().adam_lr(Group::GeometryGrid), 0.01);
        // off: nothing
        let mut c = cfg();
        c.refine_iters = 0;
        let (mut px, mut res) = buffers();
        let mut m = Mapper::new(Mock::new(c.slots_needed()), c, intr(), &mut px, &mut res).unwrap();
        push_n(&mut m, 20);
        assert!(m.refine(&mut |_| {}).unwrap().is_none());
        // a window of one frame or blocks of none are refused
        for (w, b) in [(1, 10), (4, 0)] {
            let mut c = cfg();
            (c.refine_iters, c.refine_window, c.refine_block) = (5, w, b);
            assert!(refused(c), "window {w}, block {b}");
        }
        for end in [0.0, 1.5, f32::NAN] {
            let mut c = cfg();
            (c.refine_iters, c.refine_lr_end) = (5, end);
            assert!(refused(c), "lr end {end}");
        }
    }

    #[test]
    fn full_keyframe_cache_is_thinned_or_drops_the_oldest() {
        for (policy, want) in [
            (KeyframeOverflow::Thin, vec![0, 10, 20]),
            (KeyframeOverflow::DropOldest, vec![5, 10, 15, 20]),
        ] {
            let mut c = cfg();
            c.max_keyframes = 4;
            c.keyframe_overflow = policy;
            let (mut px, mut res) = buffers();
            let mut m =
                Mapper::new(Mock::new(c.slots_needed()), c, intr(), &mut px, &mut res).unwrap();
            // init + 5 updates: keyframes 0, 5, 10, 15, 20 offered to a cache of 4
            push_n(&mut m, 15 + 25);
            assert_eq!(m.keyframe_ids().collect::<Vec<_>>(), want, "{policy:?}");
        }
    }

    #[test]
    fn keyframes_outside_the_view_are_not_candidates() {
        let c = cfg();
        let (mut px, mut res) = buffers();
        let mut m = Mapper::new(Mock::new(c.slots_needed()), c, intr(), &mut px, &mut res).unwrap();
        let img = image();
        // frame 0 looks along -z (rotation by pi about y): the current view's points at
        // z in [1.6, 2.5] are behind it
        let mut back = Pose::IDENTITY;
        back.m[0][0] = -1.0;
        back.m[2][2] = -1.0;
        m.push_frame(&img, back).unwrap();
        for i in 1..20 {
            m.push_frame(&img, pose(i)).unwrap();
        }
        assert_eq!(m.keyframe_ids().collect::<Vec<_>>(), [0]);
        assert_eq!(m.window_ids(), (5..20).collect::<Vec<_>>().as_slice());
        // a second update adds frame 5, which does overlap
        let r = push_n(&mut m, 5).pop().unwrap();
        assert_eq!((r.candidates, r.keyframes, r.window_keyframes), (1, 2, 1));
        assert_eq!(m.window_ids()[0], 5);
    }

    /// A keyframe that sees only a sliver of the newest frame's points is a candidate under
    /// NICE-SLAM's rule (any point) and not under a share it does not reach.
    #[test]
    fn keyframes_seeing_too_little_of_the_view_are_not_candidates() {
        let mut shares = [0.0f32; 2];
        for (i, (min, want)) in [(0.0f32, 1u32), (0.5, 0)].into_iter().enumerate() {
            let mut c = cfg();
            c.overlap_margin = 2.0;
            c.overlap_min = min;
            let (mut px, mut res) = buffers();
            let mut m =
                Mapper::new(Mock::new(c.slots_needed()), c, intr(), &mut px, &mut res).unwrap();
            let img = image();
            // frame 0 stands 1.8 m to the side: the current view's points at z in [1.6, 2.5]
            // land 36-56 px to the left in it, so it sees only the right edge of the view
            let mut side = Pose::IDENTITY;
            side.m[0][3] = 1.8;
            m.push_frame(&img, side).unwrap();
            let mut last = None;
            for f in 1..20 {
                if let Some(r) = m.push_frame(&img, pose(f)).unwrap() {
                    last = Some(r);
                }
            }
            let r = last.unwrap();
            assert_eq!(r.kind, UpdateKind::Online);
            assert_eq!(m.keyframe_ids().collect::<Vec<_>>(), [0]);
            assert_eq!(r.candidates, want, "overlap_min {min}");
            assert_eq!(r.window_keyframes, want, "overlap_min {min}");
            // the share it sees is above 0 and below one half
            let n = m.render_overlap_rays().unwrap();
            let inside = m.overlap_points_inside(side, n);
            shares[i] = inside as f32 / (n as u32 * c.overlap_points) as f32;
        }
        for s in shares {
            assert!(s > 0.0 && s < 0.5, "{s}");
        }
    }

    #[test]
    fn pixels_are_spread_evenly_and_keep_the_border() {
        let c = cfg();
        let (mut px, mut res) = buffers();
        let mut m = Mapper::new(Mock::new(c.slots_needed()), c, intr(), &mut px, &mut res).unwrap();
        push_n(&mut m, 20);
        for call in &m.backend().calls {
            let n = call.slots.len() as u32;
            let mut count = vec![0u32; n as usize];
            for p in &call.pixels {
                assert!(p.u >= 10 && p.u < 54 && p.v >= 10 && p.v < 38, "{p:?}");
                count[p.frame as usize] += 1;
            }
            // 60 pixels over 15 frames: 4 each; over 16 frames: 4 for the first 12, 3 after
            for (f, &k) in count.iter().enumerate() {
                assert_eq!(k, 60 / n + (f < (60 % n) as usize) as u32);
            }
        }
        // different iterations draw different pixels
        let calls = &m.backend().calls;
        assert_ne!(calls[0].pixels, calls[1].pixels);
    }

    /// With the planarity prior the pixels come as line triplets (rows and columns, spacing
    /// within `planar_spacing`) inside the border; a spacing that does not fit is refused.
    #[test]
    fn planarity_draws_line_triplets_inside_the_border() {
        let mut c = cfg();
        c.lambda_planar = 0.1;
        c.planar_spacing = 4;
        let (mut px, mut res) = buffers();
        let mut m = Mapper::new(Mock::new(c.slots_needed()), c, intr(), &mut px, &mut res).unwrap();
        push_n(&mut m, 20);
        let (mut rows, mut cols) = (0, 0);
        for call in &m.backend().calls {
            assert_eq!(call.pixels.len(), 60);
            for t in call.pixels.chunks_exact(3) {
                let t = [t[0], t[1], t[2]];
                assert!(crate::train::pixel::is_line_triplet(&t), "{t:?}");
                let s = (t[1].u - t[0].u) + (t[1].v - t[0].v);
                assert!((1..=4).contains(&s), "{t:?}");
                for p in t {
                    assert!(p.u >= 10 && p.u < 54 && p.v >= 10 && p.v < 38, "{p:?}");
                }
                if t[0].v == t[1].v {
                    rows += 1;
                } else {
                    cols += 1;
                }
            }
        }
        assert!(rows > 50 && cols > 50, "rows {rows} columns {cols}");
        let mut bad = cfg();
        bad.lambda_planar = 0.1;
        bad.planar_spacing = 14; // 48 px high: 2 * (10 + 14) = 48
        assert!(refused(bad));
        bad.planar_spacing = 0;
        assert!(refused(bad));
        bad.planar_spacing = 4;
        bad.planar_share = 0.0;
        assert!(refused(bad));
        // half the triples, every other one
        let mut c = cfg();
        c.lambda_planar = 0.1;
        c.planar_share = 0.5;
        let (mut px, mut res) = buffers();
        let mut m = Mapper::new(Mock::new(c.slots_needed()), c, intr(), &mut px, &mut res).unwrap();
        push_n(&mut m, 20);
        let line = |t: &[PixelSample]| crate::train::pixel::is_line_triplet(&[t[0], t[1], t[2]]);
        let mut odd = 0;
        for call in &m.backend().calls {
            for (g, t) in call.pixels.chunks_exact(3).enumerate() {
                if g % 2 == 1 {
                    assert!(line(t), "{t:?}");
                    odd += 1;
                }
            }
        }
        assert_eq!(odd, 10 * m.backend().calls.len());
    }

    /// Region triplets: on frames of plain vertical bands (colour steps before columns 20, 28
    /// and 44) and a horizontal step before row 30, every triplet's outer pixels are the ends of
    /// the plain run through its centre (or the sampling border, or `planar_spacing` away), at
    /// least `PLANAR_REGION_MIN` px from it; a triple whose centre lies nearer a step stays
    /// three independent draws.
    #[test]
    fn region_triplets_span_the_plain_run_around_their_centre() {
        let mut c = cfg();
        c.lambda_planar = 0.1;
        c.planar_spacing = 12;
        c.planar_region_step = 0.05;
        // which band column u lies in
        let band_of = |u: u32| (u >= 20) as usize + (u >= 28) as usize + (u >= 44) as usize;
        let band = |u: u32, v: u32| -> u32 {
            let g = [0x20u32, 0x60, 0x90, 0xc0][band_of(u)];
            // the step below is 0.04 in one channel only: a mean step of 0.013 (plain)
            let r = if v >= 30 { g + 10 } else { g };
            0xff00_0000 | (g << 16) | (g << 8) | r
        };
        let img: Vec<u32> = (0..48 * 64).map(|i| band(i % 64, i / 64)).collect();
        let (mut px, mut res) = buffers();
        let mut m = Mapper::new(Mock::new(c.slots_needed()), c, intr(), &mut px, &mut res).unwrap();
        for i in 0..20 {
            m.push_frame(&img, pose(i)).unwrap();
        }
        // the run of column u along a row (the border is 10 px: columns 10..=53)
        let run = |u: u32| -> (u32, u32) {
            let (lo, hi) = ([10, 20, 28, 44][band_of(u)], [19, 27, 43, 53][band_of(u)]);
            (lo.max(u.saturating_sub(12)), hi.min(u + 12))
        };
        let (mut rows, mut cols, mut loose) = (0, 0, 0);
        for call in &m.backend().calls {
            for t in call.pixels.chunks_exact(3) {
                let t = [t[0], t[1], t[2]];
                let (lo, hi) = run(t[1].u);
                let near_step = t[1].u - lo < PLANAR_REGION_MIN || hi - t[1].u < PLANAR_REGION_MIN;
                if !crate::train::pixel::is_line_triplet(&t) {
                    loose += 1;
                    continue;
                }
                if t[0].v == t[1].v {
                    assert_eq!((t[0].u, t[2].u), (lo, hi), "{t:?}");
                    assert!(!near_step, "{t:?}");
                    rows += 1;
                } else {
                    // columns: plain from the border to the border, cut at 12 px
                    let v = t[1].v;
                    assert_eq!(
                        (t[0].v, t[2].v),
                        (10.max(v.saturating_sub(12)), 37.min(v + 12)),
                        "{t:?}"
                    );
                    cols += 1;
                }
            }
        }
        assert!(
            rows > 20 && cols > 20 && loose > 20,
            "{rows} {cols} {loose}"
        );
        let mut bad = c;
        bad.planar_region_step = f32::NAN;
        assert!(refused(bad));
        // the longest run may exceed the image (64 x 48, border 10): the walk stops at the
        // border; a run shorter than the shortest accepted is refused
        let mut long = c;
        long.planar_spacing = 100;
        let (mut px, mut res) = buffers();
        assert!(Mapper::new(
            Mock::new(long.slots_needed()),
            long,
            intr(),
            &mut px,
            &mut res
        )
        .is_ok());
        bad = c;
        bad.planar_spacing = PLANAR_REGION_MIN - 1;
        assert!(refused(bad));
    }

    #[test]
    fn new_frames_get_their_share_of_pixels_online() {
        let mut c = cfg();
        c.new_frame_share = 0.5;
        let (mut px, mut res) = buffers();
        let mut m = Mapper::new(Mock::new(c.slots_needed()), c, intr(), &mut px, &mut res).unwrap();
        push_n(&mut m, 20);
        let calls = &m.backend().calls;
        assert_eq!(calls.len(), 7 + 4);
        for (i, call) in calls.iter().enumerate() {
            let n = call.slots.len();
            let mut count = vec![0u32; n];
            for p in &call.pixels {
                count[p.frame as usize] += 1;
            }
            if i < 7 {
                // initialisation: even over the 15 frames
                assert!(count.iter().all(|&k| k == 4), "{count:?}");
            } else {
                // 1 keyframe + 15 local frames, 5 of them new: 30 pixels over the 5 new
                // frames (6 each), 30 over the 11 others (3 for the first 8, 2 after)
                assert_eq!(n, 16);
                let want: Vec<u32> = (0..16)
                    .map(|f| {
                        if f >= 11 {
                            6
                        } else if f < 8 {
                            3
                        } else {
                            2
                        }
                    })
                    .collect();
                assert_eq!(count, want);
            }
        }
        let mut bad = cfg();
        bad.new_frame_share = 1.5;
        assert!(refused(bad));
    }

    #[test]
    fn rejected_steps_are_counted_and_lower_the_learning_rates() {
        let mut c = cfg();
        c.rejected_lr_after = 3;
        c.rejected_lr_factor = 0.5;
        let (mut px, mut res) = buffers();
        let mut backend = Mock::new(c.slots_needed());
        backend.reject = true;
        let mut m = Mapper::new(backend, c, intr(), &mut px, &mut res).unwrap();
        let mut seen = 0;
        let img = image();
        for id in 0..15 {
            m.push_frame_observed(&img, pose(id), &mut |i: &IterInfo| {
                seen += i.rejected as u32
            })
            .unwrap();
        }
        // the initialisation's 7 iterations, all rejected: two reductions (after 3 and 6)
        assert_eq!((m.rejected_steps(), m.lr_reductions(), seen), (7, 2, 7));
        assert_eq!(m.backend().lr, [0.0025; crate::field::model::NUM_GROUPS]);
        let mut bad = cfg();
        bad.rejected_lr_factor = 0.0;
        assert!(refused(bad));
    }

    #[test]
    fn two_pixel_batches_queue_the_same_steps_as_one() {
        // every step rejected, so the learning rates change during the run; planarity
        // triplets on, so the drawing of the next batch covers them too
        let mut c = cfg();
        c.rejected_lr_after = 3;
        c.rejected_lr_factor = 0.5;
        c.lambda_planar = 0.1;
        let run = |two: bool| {
            let n = c.pixels as usize * if two { 2 } else { 1 };
            let mut px = vec![PixelSample::default(); n];
            let (_, mut res) = buffers();
            let mut backend = Mock::new(c.slots_needed());
            backend.reject = true;
            let mut m = Mapper::new(backend, c, intr(), &mut px, &mut res).unwrap();
            let img = image();
            for id in 0..20 {
                m.push_frame(&img, pose(id)).unwrap();
            }
            let b = m.into_backend();
            assert!(b.queued.is_none(), "a promised step never came");
            (b.calls, b.nexts)
        };
        let (one, nexts_one) = run(false);
        let (two, nexts_two) = run(true);
        assert_eq!(nexts_one, 0);
        // every iteration but the last of each update (7 + 4 iterations) promised its next
        assert_eq!((one.len(), nexts_two), (11, 6 + 3));
        for (a, b) in one.iter().zip(two.iter()) {
            assert_eq!((&a.slots, &a.pixels), (&b.slots, &b.pixels));
            assert_eq!(
                (a.lambda_color, a.color_to_geometry),
                (b.lambda_color, b.color_to_geometry)
            );
            assert_eq!(a.lr.to_bits(), b.lr.to_bits());
        }
        // a reduction after the 3rd and the 6th rejected step applies from the step after
        // the next (the next one was already prepared)
        let lrs: Vec<f32> = one.iter().take(7).map(|c| c.lr).collect();
        assert_eq!(lrs, [0.01, 0.01, 0.01, 0.01, 0.005, 0.005, 0.005]);
        // the online update starts from the rates the initialisation left (two reductions)
        assert_eq!(one[7].lr, 0.0025);
    }

    #[test]
    fn online_updates_measure_their_new_frames_before_the_first_step() {
        let mut c = cfg();
        c.new_frame_share = 0.5;
        let (mut px, mut res) = buffers();
        let mut backend = Mock::new(c.slots_needed());
        backend.by_frame = true;
        let mut m = Mapper::new(backend, c, intr(), &mut px, &mut res).unwrap();
        let img = image();
        let mut infos = Vec::new();
        for id in 0..20 {
            m.push_frame_observed(&img, pose(id), &mut |i: &IterInfo| infos.push(*i))
                .unwrap();
        }
        // 7 initialisation iterations, then the online update's 4
        assert_eq!(infos.len(), 11);
        assert!(infos[..7]
            .iter()
            .all(|i| i.new_loss_ratio == 0.0 && i.new_warp_valid == 0.0));
        assert!(infos[8..]
            .iter()
            .all(|i| i.new_loss_ratio == 0.0 && i.new_warp_valid == 0.0));
        // window of 16 (1 keyframe + 15 local), frames 11..16 new: 6 pixels each, losses
        // 0.25 (f + 1); the 30 others are 3 pixels of frames 0..8 and 2 of frames 8..11.
        let new_mean = 0.25 * (12.0 + 13.0 + 14.0 + 15.0 + 16.0) / 5.0;
        let old_sum: f32 = (0..8).map(|f| 3.0 * (f + 1) as f32).sum::<f32>()
            + (8..11).map(|f| 2.0 * (f + 1) as f32).sum::<f32>();
        let old_mean = 0.25 * old_sum / 30.0;
        let want = new_mean / old_mean;
        let got = infos[7].new_loss_ratio;
        assert!((got - want).abs() < 1e-5 * want, "{got} vs {want}");
        // frames 12 and 14 have >= min_views (4) views: 12 of the 30 new pixels
        assert_eq!(infos[7].new_warp_valid, 0.4);
    }

    #[test]
    fn initialisation_runs_with_its_own_termination_threshold() {
        for (init_t, want) in [(0.0, vec![]), (0.01, vec![0.01, 0.0])] {
            let mut c = cfg();
            c.init_min_transmittance = init_t;
            let (mut px, mut res) = buffers();
            let mut m =
                Mapper::new(Mock::new(c.slots_needed()), c, intr(), &mut px, &mut res).unwrap();
            push_n(&mut m, 20);
            // set before the initialisation, the model's own (0) restored after it
            assert_eq!(m.backend().min_t, want);
            assert_eq!(m.backend().layout.config.min_transmittance, 0.0);
        }
    }

    #[test]
    fn a_restored_mapper_continues_like_the_original() {
        let mut c = cfg();
        c.max_keyframes = 4; // the cache thins on the way
        let img = image();
        let (mut px, mut res) = buffers();
        let mut a = Mapper::new(Mock::new(c.slots_needed()), c, intr(), &mut px, &mut res).unwrap();
        push_n(&mut a, 47);
        let state = a.state();
        assert!(
            state.initialized && !state.keyframes.is_empty() && state.pending > 0,
            "{state:?}"
        );
        let before = a.backend().calls.len();
        push_n(&mut a, 20);
        let (mut px2, mut res2) = buffers();
        let mut b = Mapper::restore(
            Mock::new(c.slots_needed()),
            c,
            intr(),
            &mut px2,
            &mut res2,
            &state,
        )
        .unwrap();
        assert_eq!(b.state(), state);
        for _ in 0..20 {
            let id = b.frames_pushed();
            b.push_frame(&img, pose(id)).unwrap();
        }
        let (ca, cb) = (&a.backend().calls[before..], &b.backend().calls);
        assert!(!cb.is_empty());
        assert_eq!(ca.len(), cb.len());
        for (x, y) in ca.iter().zip(cb) {
            assert_eq!((&x.slots, &x.pixels), (&y.slots, &y.pixels));
        }
        assert_eq!(a.state(), b.state());
        // a state that does not fit the configuration is an error
        let mut bad = state.clone();
        bad.free.push(0).unwrap();
        assert!(Mapper::restore(
            Mock::new(c.slots_needed()),
            c,
            intr(),
            &mut px2,
            &mut res2,
            &bad
        )
        .is_err());
    }

    #[test]
    fn keyframes_get_their_share_of_pixels_online() {
        let mut c = cfg();
        c.new_frame_share = 0.5;
        c.keyframe_share = 0.2;
        let (mut px, mut res) = buffers();
        let mut m = Mapper::new(Mock::new(c.slots_needed()), c, intr(), &mut px, &mut res).unwrap();
        push_n(&mut m, 20);
        let calls = &m.backend().calls;
        // the first online update: 1 keyframe + 15 local frames, 5 of them new: 30 pixels
        // over the new frames, 12 (0.2 x 60) on the keyframe, 18 over the 10 older local
        // frames (2 each, the first 8 one more)
        let mut count = vec![0u32; 16];
        for p in &calls[7].pixels {
            count[p.frame as usize] += 1;
        }
        let want: Vec<u32> = (0..16)
            .map(|f| match f {
                0 => 12,
                1..=8 => 2,
                9..=10 => 1,
                _ => 6,
            })
            .collect();
        assert_eq!(count, want);
        let mut bad = cfg();
        bad.new_frame_share = 0.75;
        bad.keyframe_share = 0.5;
        assert!(refused(bad));
    }

    #[test]
    fn global_keyframes_join_the_window_whatever_their_overlap() {
        for (global, want) in [(0, 0), (2, 2)] {
            let mut c = cfg();
            c.window_keyframes = 0;
            c.global_keyframes = global;
            let (mut px, mut res) = buffers();
            let mut m =
                Mapper::new(Mock::new(c.slots_needed()), c, intr(), &mut px, &mut res).unwrap();
            let reports = push_n(&mut m, 35);
            let last = reports.last().unwrap();
            assert!(last.keyframes >= 3, "{last:?}");
            assert_eq!(last.window_keyframes, want);
            assert_eq!(last.window_frames, 15 + want);
        }
    }

    #[test]
    fn flush_initialises_short_sequences_and_runs_pending_updates() {
        let c = cfg();
        let (mut px, mut res) = buffers();
        let mut m = Mapper::new(Mock::new(c.slots_needed()), c, intr(), &mut px, &mut res).unwrap();
        assert!(m.flush(&mut |_| {}).unwrap().is_none());
        push_n(&mut m, 6);
        let r = m.flush(&mut |_| {}).unwrap().unwrap();
        assert_eq!((r.kind, r.window_frames), (UpdateKind::Init, 6));
        assert!(m.flush(&mut |_| {}).unwrap().is_none());
        push_n(&mut m, 2);
        let r = m.flush(&mut |_| {}).unwrap().unwrap();
        assert_eq!((r.kind, r.window_frames), (UpdateKind::Online, 8));
    }

    #[test]
    fn bad_configurations_and_inputs_are_errors() {
        let c = cfg();
        let (mut px, mut res) = buffers();
        // too few slots
        let e = Mapper::new(
            Mock::new(c.slots_needed() - 1),
            c,
            intr(),
            &mut px,
            &mut res,
        );
        assert!(matches!(e, Err(Error::Capacity { .. })));
        let mut bad = c;
        bad.border = 5;
        let e = Mapper::new(Mock::new(c.slots_needed()), bad, intr(), &mut px, &mut res);
        assert!(matches!(e, Err(Error::InvalidConfig(_))));
        let mut bad = c;
        bad.local_frames = 30;
        let e = Mapper::new(Mock::new(600), bad, intr(), &mut px, &mut res);
        assert!(matches!(e, Err(Error::Capacity { .. })));
        let mut short = vec![PixelSample::default(); 59];
        let e = Mapper::new(Mock::new(c.slots_needed()), c, intr(), &mut short, &mut res);
        assert!(matches!(e, Err(Error::Shape { .. })));
        let mut m = Mapper::new(Mock::new(c.slots_needed()), c, intr(), &mut px, &mut res).unwrap();
        assert!(matches!(
            m.push_frame(&[0u32; 10], pose(0)),
            Err(MapperError::Core(Error::Shape { .. }))
        ));
        let mut skew = pose(0);
        skew.m[0][0] = 2.0;
        assert!(matches!(
            m.push_frame(&image(), skew),
            Err(MapperError::Core(Error::InvalidConfig(_)))
        ));
        assert_eq!(m.frames_pushed(), 0);
    }

    #[test]
    fn view_rays_cover_the_image_row_major() {
        let k = intr();
        let mut rays = vec![
            Ray {
                origin: [0.0; 3],
                dir: [0.0; 3],
                target: [0.0; 3],
                target_depth: 0.0
            };
            64 * 48
        ];
        view_rays(&k, &pose(100), &mut rays).unwrap();
        // pixel (u, v) = (3, 2): direction ((3 - 31.5)/50, (2 - 23.5)/50, 1), origin x = 1
        let r = rays[2 * 64 + 3];
        assert_eq!(r.origin, [1.0, 0.0, 0.0]);
        assert_eq!(r.dir, [-0.57, -0.43, 1.0]);
        assert!(view_rays(&k, &pose(0), &mut rays[1..]).is_err());
    }
}
