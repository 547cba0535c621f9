//! The per-pixel mapping kernel of Hi-Map's online optimisation: render one pixel of a window
//! frame, take the L1 colour loss against the frame and DIM-SLAM's warping loss through the
//! rendered depth, and back-propagate both into the field. Every backend runs
//! [`pixel_train`] once per sampled pixel.
//!
//! Images of the frames are stored as packed RGBA8 (`u32` per pixel, R in the low byte) in
//! "slots"; the window names which slot each window frame uses. Colour values are
//! `byte / 255` (exact and identical on every target).

use crate::camera::{Intrinsics, Pose, PoseRead};
use crate::field::model::{
    ray_backward, ray_forward_taped, LossConfig, ModelGradSink, ModelLayout, Params, Ray, RayCache,
    SampleScratch, SampleTape,
};
use crate::field::render::RayOutput;
use crate::loss::planar::{planarity_spaced, PlanarConfig};
use crate::loss::warp::{
    warp_pixel, warp_view_count, Corners, FrameImages, WarpConfig, MAX_WINDOW,
};
use crate::loss::PATCH_PIXELS;
use crate::ParamRead;

/// Packs an RGB colour in [0, 1] into RGBA8 (alpha 255), rounding to nearest.
///
/// # Examples
///
/// ```rust
/// use himap_core::train::pixel::{pack_rgba8, unpack_rgba8};
///
/// let p = pack_rgba8([1.0, 0.0, 0.5]);
/// assert_eq!(p, 0xff80_00ff); // R in the low byte, alpha 255 on top
/// assert_eq!(unpack_rgba8(p), [1.0, 0.0, 128.0 / 255.0]);
/// ```
#[inline]
pub fn pack_rgba8(rgb: [f32; 3]) -> u32 {
    let q = |x: f32| -> u32 {
        let v = crate::math::clamp(x, 0.0, 1.0) * 255.0 + 0.5;
        v as u32
    };
    q(rgb[0]) | (q(rgb[1]) << 8) | (q(rgb[2]) << 16) | (255 << 24)
}

/// Unpacks RGBA8 into RGB in [0, 1] as `byte * (1/255)`: a multiplication (exact IEEE
/// rounding on every device) rather than a division (real GPUs may be 2.5 ULP off).
#[inline(always)]
pub fn unpack_rgba8(p: u32) -> [f32; 3] {
    [
        (p & 0xff) as f32 * RGBA8_INV,
        ((p >> 8) & 0xff) as f32 * RGBA8_INV,
        ((p >> 16) & 0xff) as f32 * RGBA8_INV,
    ]
}

/// The scale of [`unpack_rgba8`]: a byte `b` is the colour `b as f32 * RGBA8_INV`.
const RGBA8_INV: f32 = 1.0 / 255.0;

/// The frames of a mapping window, read from slot storage: window frame `i` lives in slot
/// `slots[i]` of `pixels` (slot-major, then row-major RGBA8).
pub struct WindowImages<'a, P: SlotPixels + ?Sized> {
    /// Width of every slot image (pixels).
    pub width: u32,
    /// Height of every slot image (pixels).
    pub height: u32,
    /// Slot of each window frame (entries past the window's length are unused).
    pub slots: [u32; MAX_WINDOW],
    /// The whole slot store.
    pub pixels: &'a P,
    /// Where the per-pixel depth-prior targets start in `pixels` (words, one `f32` per pixel
    /// after the slots, as a device buffer holds them; [`crate::gpu_abi::words::WINDOW_PRIORS`]);
    /// 0: the store's own [`SlotPixels::depth_prior`].
    pub priors: u32,
}

/// Read access to slot-major packed RGBA8 pixels (implemented for `[u32]`; a GPU backend
/// implements it over its storage buffer).
pub trait SlotPixels {
    /// The pixels live in a CPU's memory (see [`FrameImages::CPU`]).
    const CPU: bool = false;
    /// Packed RGBA8 pixel `i` of the store (0 past the end for a slice).
    fn pixel(&self, i: usize) -> u32;
    /// A cache hint: pixel `i` will be read soon. No value changes; the default does nothing.
    #[inline(always)]
    fn prefetch(&self, _i: usize) {}
    /// Target depth of the per-pixel depth prior of pixel `i` of the store
    /// ([`FrameImages::depth_prior`]); the default: 0, none.
    #[inline(always)]
    fn depth_prior(&self, _i: usize) -> f32 {
        0.0
    }
}

impl SlotPixels for [u32] {
    #[inline(always)]
    fn pixel(&self, i: usize) -> u32 {
        if i < self.len() {
            self[i]
        } else {
            0
        }
    }
}

impl<P: SlotPixels + ?Sized> WindowImages<'_, P> {
    /// Index of texel `(x, y)` of window frame `frame` in `pixels`.
    #[inline(always)]
    fn index(&self, frame: usize, x: u32, y: u32) -> usize {
        let f = if frame < MAX_WINDOW { frame } else { 0 };
        let slot = self.slots[f] as usize;
        (slot * self.height as usize + y as usize) * self.width as usize + x as usize
    }
}

impl<P: SlotPixels + ?Sized> FrameImages for WindowImages<'_, P> {
    const CPU: bool = P::CPU;

    #[inline(always)]
    fn size(&self) -> (u32, u32) {
        (self.width, self.height)
    }

    #[inline(always)]
    fn texel(&self, frame: usize, x: u32, y: u32) -> [f32; 3] {
        unpack_rgba8(self.pixels.pixel(self.index(frame, x, y)))
    }

    #[inline(always)]
    fn depth_prior(&self, frame: usize, x: u32, y: u32) -> f32 {
        let i = self.index(frame, x, y);
        if self.priors == 0 {
            self.pixels.depth_prior(i)
        } else {
            f32::from_bits(self.pixels.pixel(self.priors as usize + i))
        }
    }

    /// Names the first and the last texel of the span (a patch row spans at most a few
    /// cache lines; the hardware's adjacent-line fetch covers the middle).
    #[inline(always)]
    fn prefetch_row(&self, frame: usize, y: u32, x0: u32, x1: u32) {
        self.pixels.prefetch(self.index(frame, x0, y));
        self.pixels.prefetch(self.index(frame, x1, y));
    }

    /// The packed words first (nothing but loads, many in flight), then [`unpack_rgba8`]'s
    /// conversion over whole channel rows (SIMD lanes; the same operations per value).
    #[inline(always)]
    fn gather_corners(&self, frame: usize, cells: &[[u32; 4]; PATCH_PIXELS], texels: &mut Corners) {
        let mut words = [[0u32; PATCH_PIXELS]; 4];
        for p in 0..PATCH_PIXELS {
            let [x0, y0, x1, y1] = cells[p];
            words[0][p] = self.pixels.pixel(self.index(frame, x0, y0));
            words[1][p] = self.pixels.pixel(self.index(frame, x1, y0));
            words[2][p] = self.pixels.pixel(self.index(frame, x0, y1));
            words[3][p] = self.pixels.pixel(self.index(frame, x1, y1));
        }
        for (corner, words) in texels.iter_mut().zip(&words) {
            for (c, channel) in corner.iter_mut().enumerate() {
                let shift = 8 * c as u32;
                for (t, &w) in channel.iter_mut().zip(words) {
                    *t = ((w >> shift) & 0xff) as f32 * RGBA8_INV;
                }
            }
        }
    }
}

/// One sampled pixel: window frame index and integer pixel coordinates.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
#[repr(C)]
pub struct PixelSample {
    /// Index of the frame in the mapping window.
    pub frame: u32,
    /// Column (pixels, 0 = left).
    pub u: u32,
    /// Row (pixels, 0 = top).
    pub v: u32,
}

/// Loss weights and switches of one mapping iteration.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct MappingLoss {
    /// Hi-Map's lambda_c (0.1 during initialisation, 0.001 online).
    pub lambda_color: f32,
    /// Hi-Map's lambda_w (1.0).
    pub lambda_warp: f32,
    /// Scale of every pixel's colour term (1 / pixels: a mean over the batch).
    pub color_scale: f32,
    /// Scale of every pixel's warping term (1 / pixels: a mean over sampled pixels of
    /// DIM-SLAM's per-pixel sum over valid pairs).
    pub warp_scale: f32,
    /// Whether the colour loss reaches the geometry (Hi-Map: only for the first 250
    /// initialisation iterations).
    pub color_to_geometry: bool,
    /// Stratified jitter seed of this iteration.
    pub seed: u32,
    /// Settings of DIM-SLAM's warping loss.
    pub warp: WarpConfig,
    /// Weight of DIM-SLAM's "fake depth" prior `smoothL1_0.1(D - depth_prior)` (scaled by
    /// `color_scale`), which pulls the rendered depth towards a plausible value during the
    /// first initialisation iterations so that the warping loss has valid views. 0 = off.
    pub lambda_depth_prior: f32,
    /// Target depth of the prior (camera z, metres; DIM-SLAM uses 1.5).
    pub depth_prior: f32,
    /// When > 0, the prior only acts on pixels whose rendered depth is below this (m): the
    /// online guard for views that collapse onto the camera in space not explored yet (the
    /// camera is in free space, so nothing is that close). 0 = every pixel.
    pub depth_prior_near: f32,
    /// The edge-aware planarity prior on the rendered depth of pixel triplets (items `3g`,
    /// `3g + 1`, `3g + 2` of the batch; see [`crate::loss::planar`]), scaled by
    /// `color_scale`. `weight` 0 = off.
    pub planar: PlanarConfig,
    /// Weight of the per-pixel depth prior ([`FrameImages::depth_prior`]: the host's plane
    /// priors of plain regions), `smoothL1_0.05(D - target)` scaled by `color_scale`, on the
    /// pixels that have a target. 0 = off.
    pub lambda_plane: f32,
}

/// The planarity triplet a batch item belongs to: its three pixels, their rendered depths
/// (the item's own is filled in from its forward) and which of the three the item is.
#[derive(Clone, Copy, Debug, PartialEq, Default)]
pub struct PixelTriplet {
    /// The triplet's three pixels, in batch order.
    pub pixels: [PixelSample; 3],
    /// Their rendered depths (camera z, metres).
    pub depth: [f32; 3],
    /// 0, 1 or 2; anything else: the item belongs to no triplet.
    pub member: u32,
}

impl PixelTriplet {
    /// No triplet.
    pub const NONE: Self = Self {
        pixels: [PixelSample {
            frame: 0,
            u: 0,
            v: 0,
        }; 3],
        depth: [0.0; 3],
        member: 3,
    };
}

/// Item `i` of a batch of `n` belongs to triplet `i / 3` when the triplet is complete (the
/// last `n % 3` items belong to none): `(first item, member)`.
#[inline(always)]
pub fn triplet_of(i: usize, n: usize) -> Option<(usize, usize)> {
    let first = i - i % 3;
    if first + 3 <= n {
        Some((first, i - first))
    } else {
        None
    }
}

/// Whether three samples are pixels `b - s_a`, `b`, `b + s_c` (`s_a, s_c > 0`) along a row
/// or a column of one frame: the shape the planarity prior needs (others are ignored).
#[inline(always)]
pub fn is_line_triplet(p: &[PixelSample; 3]) -> bool {
    let [a, b, c] = *p;
    if a.frame != b.frame || c.frame != b.frame {
        return false;
    }
    let row = a.v == b.v && c.v == b.v && a.u < b.u && b.u < c.u;
    let col = a.u == b.u && c.u == b.u && a.v < b.v && b.v < c.v;
    row || col
}

/// The spacings `[s_a, s_c]` of a line triplet ([`is_line_triplet`]) along its line.
#[inline(always)]
pub fn triplet_spacing(p: &[PixelSample; 3]) -> [u32; 2] {
    let [a, b, c] = *p;
    if a.v == b.v {
        [b.u.wrapping_sub(a.u), c.u.wrapping_sub(b.u)]
    } else {
        [b.v.wrapping_sub(a.v), c.v.wrapping_sub(b.v)]
    }
}

/// `v[m]` for `m` in 0..3 without a bounds check (`v[2]` past it).
#[inline(always)]
fn pick(v: [f32; 3], m: u32) -> f32 {
    if m == 0 {
        v[0]
    } else if m == 1 {
        v[1]
    } else {
        v[2]
    }
}

/// Transition (m) of the smooth L1 of the per-pixel depth prior ([`FrameImages::depth_prior`]).
pub const DEPTH_PRIOR_BETA: f32 = 0.05;

/// What one sampled pixel produced.
#[derive(Clone, Copy, Debug, PartialEq, Default)]
pub struct PixelResult {
    /// Rendered colour (RGB in [0, 1]).
    pub color: [f32; 3],
    /// Rendered depth (camera z, metres).
    pub depth: f32,
    /// Rendered opacity (sum of the rendering weights).
    pub opacity: f32,
    /// Scaled colour loss of the pixel.
    pub color_loss: f32,
    /// Scaled warping loss of the pixel.
    pub warp_loss: f32,
    /// Valid warp pairs (0 when fewer than `min_views`).
    pub warp_views: u32,
}

/// The window every pixel of an iteration refers to.
pub struct WindowView<'a, I: FrameImages + ?Sized, PS: PoseRead + ?Sized = [Pose]> {
    /// Intrinsics shared by every window frame.
    pub k: Intrinsics,
    /// Camera-to-world poses of the window frames.
    pub poses: &'a PS,
    /// The window frames' images.
    pub images: &'a I,
}

/// The camera ray through a sampled pixel, with the pixel's colour as target (no target
/// depth: monocular). `None`-free for kernels: a frame outside the window gives a zero ray
/// and `false`.
#[inline(always)]
pub fn pixel_ray<I: FrameImages + ?Sized, PS: PoseRead + ?Sized>(
    window: &WindowView<'_, I, PS>,
    px: PixelSample,
) -> (Ray, bool) {
    let f = px.frame as usize;
    if f >= window.poses.count() {
        let z = [0.0f32; 3];
        return (
            Ray {
                origin: z,
                dir: z,
                target: z,
                target_depth: 0.0,
            },
            false,
        );
    }
    let pose = window.poses.pose(f);
    let (origin, dir) = pose.ray(&window.k, px.u as f32, px.v as f32);
    let target = window.images.texel(f, px.u, px.v);
    (
        Ray {
            origin,
            dir,
            target,
            target_depth: 0.0,
        },
        true,
    )
}

/// The losses of [`pixel_train`] for a rendered pixel (`out` from `n` samples): the pixel's
/// result and the cotangents of the rendered colour and depth.
#[inline(always)]
pub fn pixel_loss<I: FrameImages + ?Sized, PS: PoseRead + ?Sized>(
    window: &WindowView<'_, I, PS>,
    px: PixelSample,
    ray: &Ray,
    out: &RayOutput,
    n: usize,
    loss: &MappingLoss,
    triplet: &PixelTriplet,
) -> (PixelResult, [f32; 3], f32) {
    let (l1, d_c) = crate::loss::l1_color(out.color, ray.target);
    let kc = loss.color_scale * loss.lambda_color;
    let d_color = [kc * d_c[0], kc * d_c[1], kc * d_c[2]];
    let mut result = PixelResult {
        color: out.color,
        depth: out.depth,
        opacity: out.opacity,
        color_loss: kc * l1,
        warp_loss: 0.0,
        warp_views: 0,
    };
    let mut d_depth = 0.0;
    if loss.lambda_warp != 0.0 && n > 0 {
        let w = warp_pixel(
            &loss.warp,
            &window.k,
            window.poses,
            window.poses.count(),
            px.frame as usize,
            px.u,
            px.v,
            out.depth,
            window.images,
        );
        let kw = loss.warp_scale * loss.lambda_warp;
        result.warp_loss = kw * w.loss;
        result.warp_views = w.valid_views;
        d_depth = kw * w.d_depth;
    }
    if loss.lambda_depth_prior != 0.0
        && n > 0
        && (loss.depth_prior_near <= 0.0 || out.depth < loss.depth_prior_near)
    {
        let (v, dv) = crate::loss::smooth_l1(out.depth - loss.depth_prior, 0.1);
        let kp = loss.color_scale * loss.lambda_depth_prior;
        result.color_loss += kp * v;
        d_depth += kp * dv;
    }
    if loss.lambda_plane != 0.0 && n > 0 {
        let target = window.images.depth_prior(px.frame as usize, px.u, px.v);
        if target > 0.0 {
            let (v, dv) = crate::loss::smooth_l1(out.depth - target, DEPTH_PRIOR_BETA);
            let kp = loss.color_scale * loss.lambda_plane;
            result.color_loss += kp * v;
            d_depth += kp * dv;
        }
    }
    let m = triplet.member;
    if loss.planar.weight != 0.0
        && n > 0
        && m < 3
        && is_line_triplet(&triplet.pixels)
        && (triplet.pixels[0].frame as usize) < window.poses.count()
        && (!loss.planar.gated
            || centre_has_views(
                window,
                triplet,
                if m == 1 { out.depth } else { triplet.depth[1] },
                loss,
            ))
    {
        let f = triplet.pixels[0].frame as usize;
        let texel = |p: PixelSample| window.images.texel(f, p.u, p.v);
        let rgb = [
            texel(triplet.pixels[0]),
            texel(triplet.pixels[1]),
            texel(triplet.pixels[2]),
        ];
        let mut depth = triplet.depth;
        if m == 0 {
            depth[0] = out.depth;
        } else if m == 1 {
            depth[1] = out.depth;
        } else {
            depth[2] = out.depth;
        }
        let (v, g) = planarity_spaced(depth, &rgb, &loss.planar, triplet_spacing(&triplet.pixels));
        let kp = loss.color_scale * loss.planar.weight;
        // each of the three items reports a third of the triplet's loss
        result.color_loss += kp * v * crate::loss::planar::THIRD;
        d_depth += kp * pick(g, m);
    }
    (result, d_color, d_depth)
}

/// Whether the centre of a planarity triplet, at its rendered depth `depth`, has the warping
/// term's `min_views` valid views: the prior shapes plain surfaces the window sees, not space
/// only the newest frames look into (there, carrying a near edge's depth along an image line
/// into the unexplored room beyond broke the exploration front; ARCHITECTURE.md). All three
/// items of a triplet decide from the same centre depth.
#[inline(always)]
fn centre_has_views<I: FrameImages + ?Sized, PS: PoseRead + ?Sized>(
    window: &WindowView<'_, I, PS>,
    triplet: &PixelTriplet,
    depth: f32,
    loss: &MappingLoss,
) -> bool {
    let c = triplet.pixels[1];
    warp_view_count(
        &loss.warp,
        &window.k,
        window.poses,
        window.poses.count(),
        c.frame as usize,
        c.u,
        c.v,
        depth,
        window.images,
    ) >= loss.warp.min_views
}

/// Forward, losses and backward for one sampled pixel. `pixel_id` seeds the stratified jitter
/// (use the pixel's index in the batch); `triplet` gives the other two rendered depths of the
/// pixel's planarity triplet ([`PixelTriplet::NONE`] without one; see [`triplet_depth`]). Stages: [`pixel_ray`], `ray_forward`, [`pixel_loss`],
/// `ray_backward` (a GPU runs them as separate passes with the same results).
#[allow(clippy::too_many_arguments)]
pub fn pixel_train<
    P: ParamRead + ?Sized,
    I: FrameImages + ?Sized,
    PS: PoseRead + ?Sized,
    S: ModelGradSink,
    T: SampleTape,
>(
    layout: &ModelLayout,
    params: &Params<'_, P>,
    window: &WindowView<'_, I, PS>,
    px: PixelSample,
    pixel_id: u32,
    loss: &MappingLoss,
    triplet: &PixelTriplet,
    cache: &mut RayCache,
    scratch: &mut SampleScratch,
    tape: &mut T,
    sink: &mut S,
) -> PixelResult {
    let (ray, ok) = pixel_ray(window, px);
    if !ok {
        return PixelResult::default();
    }
    ray_forward_taped(
        layout, params, &ray, pixel_id, loss.seed, true, cache, scratch, tape,
    );
    let (result, d_color, d_depth) =
        pixel_loss(window, px, &ray, &cache.out, cache.n, loss, triplet);
    ray_backward(
        layout,
        params,
        &ray,
        d_color,
        d_depth,
        0.0,
        loss.color_to_geometry,
        cache,
        scratch,
        tape,
        sink,
    );
    result
}

/// The rendered depth of batch item `id` at pixel `px`, as that item's own forward renders it
/// (same ray, id, seed and jitter, so the same bits): a planarity partner's depth on the CPU
/// (the GPU composites the partner's sample records instead). 0 outside the window.
#[allow(clippy::too_many_arguments)]
pub fn triplet_depth<P: ParamRead + ?Sized, I: FrameImages + ?Sized, PS: PoseRead + ?Sized>(
    layout: &ModelLayout,
    params: &Params<'_, P>,
    window: &WindowView<'_, I, PS>,
    px: PixelSample,
    id: u32,
    loss: &MappingLoss,
    cache: &mut RayCache,
    scratch: &mut SampleScratch,
) -> f32 {
    let (ray, ok) = pixel_ray(window, px);
    if !ok {
        return 0.0;
    }
    // Depth alone: the same bits as the partner's own item's forward renders.
    crate::field::model::ray_depth_forward_taped(
        layout,
        params,
        &ray,
        id,
        loss.seed,
        true,
        cache,
        scratch,
        &mut crate::field::model::Recompute,
    );
    cache.out.depth
}

/// Convenience: the [`LossConfig`] of a plain colour step equivalent to a mapping loss without
/// the warping term (used by tests).
pub fn colour_only(loss: &MappingLoss) -> LossConfig {
    LossConfig {
        lambda_color: loss.lambda_color,
        lambda_depth: 0.0,
        ray_scale: loss.color_scale,
        color_to_geometry: loss.color_to_geometry,
        seed: loss.seed,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rgba8_round_trip_is_exact_on_byte_values() {
        for b in 0..=255u32 {
            let p = b | ((255 - b) << 8) | ((b / 2) << 16) | (255 << 24);
            assert_eq!(pack_rgba8(unpack_rgba8(p)), p);
        }
        assert_eq!(
            pack_rgba8([2.0, -1.0, 0.5]),
            255 | (128 << 16) | (255 << 24)
        );
    }

    #[test]
    fn window_images_reads_the_right_slot() {
        let (w, h) = (4u32, 3u32);
        let mut px = std::vec![0u32; (w * h * 3) as usize];
        // slot 2, pixel (1, 2)
        px[((2 * h + 2) * w + 1) as usize] = 51 | (102 << 8) | (255 << 16);
        let mut slots = [0u32; MAX_WINDOW];
        slots[1] = 2;
        let imgs = WindowImages {
            width: w,
            height: h,
            slots,
            pixels: &px[..],
            priors: 0,
        };
        let inv = 1.0f32 / 255.0;
        assert_eq!(imgs.texel(1, 1, 2), [51.0 * inv, 102.0 * inv, 255.0 * inv]);
        assert!((imgs.texel(1, 1, 2)[0] - 0.2).abs() < 1e-6);
        assert_eq!(imgs.texel(0, 1, 2), [0.0, 0.0, 0.0]);
    }

    /// The packed images' corner gather (words first, the conversion in lanes) gives
    /// [`FrameImages::texel`]'s values for every corner, channel and point, in every slot.
    #[test]
    fn corner_gather_equals_the_texels() {
        let (w, h) = (13u32, 7u32);
        let mut rng = crate::rng::SplitMix::new(5);
        let px: std::vec::Vec<u32> = (0..w * h * 3)
            .map(|_| (rng.unit() * u32::MAX as f32) as u32 ^ rng.below(1 << 20))
            .collect();
        let mut slots = [0u32; MAX_WINDOW];
        slots[0] = 2;
        slots[1] = 0;
        let imgs = WindowImages {
            width: w,
            height: h,
            slots,
            pixels: &px[..],
            priors: 0,
        };
        for frame in 0..2 {
            let mut cells = [[0u32; 4]; PATCH_PIXELS];
            for c in cells.iter_mut() {
                let (x0, y0) = (rng.below(w - 1), rng.below(h - 1));
                *c = [x0, y0, x0 + 1, y0 + 1];
            }
            let mut got: Corners = [[[0.0; PATCH_PIXELS]; 3]; 4];
            imgs.gather_corners(frame, &cells, &mut got);
            for (p, &[x0, y0, x1, y1]) in cells.iter().enumerate() {
                for (k, (x, y)) in [(x0, y0), (x1, y0), (x0, y1), (x1, y1)]
                    .into_iter()
                    .enumerate()
                {
                    let t = imgs.texel(frame, x, y);
                    for c in 0..3 {
                        assert_eq!(
                            got[k][c][p].to_bits(),
                            t[c].to_bits(),
                            "{frame} {p} {k} {c}"
                        );
                    }
                }
            }
        }
    }

    /// A mapping loss with every term off (colour and warp scales `scale`, the depth prior's
    /// target 1.5 m); tests switch on the term they check.
    fn terms_off(scale: f32) -> MappingLoss {
        MappingLoss {
            lambda_color: 0.0,
            lambda_warp: 0.0,
            color_scale: scale,
            warp_scale: scale,
            color_to_geometry: true,
            seed: 0,
            warp: WarpConfig::dim_slam(),
            lambda_depth_prior: 0.0,
            depth_prior: 1.5,
            depth_prior_near: 0.0,
            planar: PlanarConfig::OFF,
            lambda_plane: 0.0,
        }
    }

    /// A one-frame window over `px` (`w x h`, slot 0) seen by the identity camera with focal
    /// `w / 2` and the principal point at the centre.
    fn one_frame<'a>(
        w: u32,
        h: u32,
        px: &'a [u32],
        poses: &'a [Pose],
        imgs: &'a mut Option<WindowImages<'a, [u32]>>,
    ) -> WindowView<'a, WindowImages<'a, [u32]>> {
        let imgs = imgs.insert(WindowImages {
            width: w,
            height: h,
            slots: [0u32; MAX_WINDOW],
            pixels: px,
            priors: 0,
        });
        WindowView {
            k: Intrinsics {
                width: w,
                height: h,
                fx: 0.5 * w as f32,
                fy: 0.5 * w as f32,
                cx: 0.5 * (w - 1) as f32,
                cy: 0.5 * (h - 1) as f32,
            },
            poses,
            images: imgs,
        }
    }

    /// The per-pixel depth prior (plane priors): `lambda_plane * color_scale *
    /// smoothL1_0.05(D - target)` on pixels with a target, nothing on those without (0) or with
    /// the weight 0; the targets read after the slots (the device layout, `priors` > 0) as
    /// from the store's own `depth_prior`. Hand-computed values.
    #[test]
    fn per_pixel_depth_prior_golden() {
        let (w, h) = (4u32, 3u32);
        // the slot's pixels, then one target per pixel: pixel 0 at 2 m, pixel 1 none
        let mut px = std::vec![0u32; 2 * (w * h) as usize];
        px[(w * h) as usize] = 2.0f32.to_bits();
        let poses = [Pose::IDENTITY];
        let mut imgs = None;
        let mut window = one_frame(w, h, &px, &poses, &mut imgs);
        let mut loss = MappingLoss {
            lambda_plane: 4.0,
            ..terms_off(0.5)
        };
        let ray = Ray {
            origin: [0.0; 3],
            dir: [0.0, 0.0, 1.0],
            target: [0.0; 3],
            target_depth: 0.0,
        };
        let run = |window: &WindowView<'_, WindowImages<'_, [u32]>>,
                   u: u32,
                   depth: f32,
                   loss: &MappingLoss| {
            let mut out = RayOutput::zeroed();
            out.depth = depth;
            let (r, _, d) = pixel_loss(
                window,
                PixelSample { frame: 0, u, v: 0 },
                &ray,
                &out,
                4,
                loss,
                &PixelTriplet::NONE,
            );
            (r.color_loss, d)
        };
        // the store's own priors: none
        assert_eq!(run(&window, 0, 2.3, &loss), (0.0, 0.0));
        let imgs = WindowImages {
            priors: w * h,
            ..*window.images
        };
        window.images = &imgs;
        // |D - 2| = 0.3 > 0.05: loss 0.3 - 0.025 = 0.275 times 0.5 * 4 = 2; slope 1 times 2
        let (l, d) = run(&window, 0, 2.3, &loss);
        assert!((l - 0.55).abs() < 1e-6 && d == 2.0, "{l} {d}");
        // D - 2 = -0.02 (inside the quadratic part): 0.5 * 0.0004 / 0.05 * 2, slope -0.4 * 2
        let (l, d) = run(&window, 0, 1.98, &loss);
        assert!(
            (l - 0.008).abs() < 1e-6 && (d + 0.8).abs() < 1e-5,
            "{l} {d}"
        );
        // pixel 1 has no target; the weight 0 turns it off
        assert_eq!(run(&window, 1, 2.3, &loss), (0.0, 0.0));
        loss.lambda_plane = 0.0;
        assert_eq!(run(&window, 0, 2.3, &loss), (0.0, 0.0));
    }

    /// The depth prior acts on every pixel without `depth_prior_near`, and with it only on the
    /// pixels rendered closer than it: hand-computed smooth-L1 cotangents.
    #[test]
    fn depth_prior_near_gates_the_prior_by_the_rendered_depth() {
        let (w, h) = (4u32, 3u32);
        let px = std::vec![0u32; (w * h) as usize];
        let poses = [Pose::IDENTITY];
        let mut imgs = None;
        let window = one_frame(w, h, &px, &poses, &mut imgs);
        let mut loss = MappingLoss {
            lambda_depth_prior: 2.0,
            ..terms_off(0.5)
        };
        let ray = Ray {
            origin: [0.0; 3],
            dir: [0.0, 0.0, 1.0],
            target: [0.0; 3],
            target_depth: 0.0,
        };
        let px0 = PixelSample::default();
        let d_depth = |depth: f32, loss: &MappingLoss| {
            let mut out = RayOutput::zeroed();
            out.depth = depth;
            pixel_loss(&window, px0, &ray, &out, 4, loss, &PixelTriplet::NONE).2
        };
        // |D - 1.5| > 0.1: smooth L1's slope -1, times color_scale * lambda = 1
        assert_eq!(d_depth(0.2, &loss), -1.0);
        assert_eq!(d_depth(0.8, &loss), -1.0);
        loss.depth_prior_near = 0.5;
        assert_eq!(d_depth(0.2, &loss), -1.0);
        assert_eq!(d_depth(0.8, &loss), 0.0);
        assert_eq!(d_depth(3.0, &loss), 0.0);
    }

    /// The planarity term: each member of a line triplet gets its own component of the
    /// triplet's gradient (`color_scale * weight * d planarity / d depth`) and a third of its
    /// loss; a triplet that is not a line, or an item of none, gets nothing, nor a triplet
    /// whose centre has fewer than `min_views` (4) valid warp views.
    #[test]
    fn planarity_gives_each_member_its_component() {
        let (w, h) = (40u32, 30u32);
        let px = std::vec![0xff80_8080u32; (w * h) as usize];
        // five frames at one pose: the centre projects inside the other four
        let poses = [Pose::IDENTITY; 5];
        let mut imgs = None;
        let window = one_frame(w, h, &px, &poses, &mut imgs);
        let planar = PlanarConfig {
            weight: 2.0,
            edge: 10.0,
            beta: 0.05,
            gated: true,
        };
        let loss = MappingLoss {
            planar,
            ..terms_off(0.25)
        };
        let ray = Ray {
            origin: [0.0; 3],
            dir: [0.0, 0.0, 1.0],
            target: [0.5; 3],
            target_depth: 0.0,
        };
        let at = |u, v| PixelSample { frame: 0, u, v };
        let depths = [1.0f32, 2.0, 1.0];
        let grey = [unpack_rgba8(0xff80_8080); 3];
        let (v, g) = crate::loss::planar::planarity(depths, &grey, &planar);
        let run = |pixels: [PixelSample; 3], member: u32| {
            let t = PixelTriplet {
                pixels,
                depth: depths,
                member,
            };
            let mut out = RayOutput::zeroed();
            out.depth = if member < 3 {
                depths[member as usize]
            } else {
                1.0
            };
            let (r, _, d) = pixel_loss(&window, pixels[1], &ray, &out, 4, &loss, &t);
            (r.color_loss, d)
        };
        let line = [at(18, 15), at(20, 15), at(22, 15)];
        for m in 0..3u32 {
            let (l, d) = run(line, m);
            assert_eq!(d, 0.25 * 2.0 * g[m as usize], "member {m}");
            assert_eq!(l, 0.25 * 2.0 * v * (1.0 / 3.0));
        }
        assert_eq!(run(line, 3), (0.0, 0.0));
        // unequal spacings: the interpolating plane's term
        let (_, gs) = crate::loss::planar::planarity_spaced(depths, &grey, &planar, [2, 1]);
        let (_, d) = run([at(18, 15), at(20, 15), at(21, 15)], 0);
        assert_eq!(d, 0.25 * 2.0 * gs[0]);
        // off the line, out of order, or not one frame: no term
        assert_eq!(run([at(18, 15), at(20, 16), at(22, 15)], 0), (0.0, 0.0));
        assert_eq!(run([at(22, 15), at(20, 15), at(18, 15)], 0), (0.0, 0.0));
        let mut other = line;
        other[2].frame = 1;
        assert_eq!(run(other, 0), (0.0, 0.0));
        // a centre near the border (outside the warp margin in every other view) or a window
        // of four frames (three other views): no term for any member
        let edge = [at(0, 2), at(2, 2), at(4, 2)];
        let t = |pixels, depth: [f32; 3], member| PixelTriplet {
            pixels,
            depth,
            member,
        };
        let mut out = RayOutput::zeroed();
        out.depth = 1.0;
        for m in 0..3u32 {
            let (r, _, d) = pixel_loss(&window, edge[1], &ray, &out, 4, &loss, &t(edge, depths, m));
            assert_eq!((r.color_loss, d), (0.0, 0.0), "member {m}");
        }
        let mut imgs4 = None;
        let window4 = one_frame(w, h, &px, &poses[..4], &mut imgs4);
        for m in 0..3u32 {
            let (r, _, d) =
                pixel_loss(&window4, line[1], &ray, &out, 4, &loss, &t(line, depths, m));
            assert_eq!((r.color_loss, d), (0.0, 0.0), "member {m}");
        }
    }
}
