//! DIM-SLAM's multi-scale patch warping loss for one source pixel, with its gradient with
//! respect to the rendered depth of the pixel (method notes §2.4).
//!
//! # The loss
//!
//! For a source pixel `p = (u, v)` (integer, a pixel centre) of window frame `i = src` with
//! rendered centre depth `D` (camera z-depth, [`crate::field::render`]):
//!
//! 1. **Patch points.** For offsets `δ ∈ [-h, h]^2` (`h = half`, 5 gives 11x11) the 3-D points
//!    `X(δ) = T_i (D · K^-1 (p + δ))` with `K^-1 (u, v) = ((u - cx)/fx, (v - cy)/fy, 1)`
//!    ([`Intrinsics::direction`]) lie on the **fronto-parallel plane** at camera depth `D`
//!    (the direction has z = 1), exactly as in DIM-SLAM.
//! 2. **Source patch** `P_i(δ)`: the texels of frame `i` at `p + δ`, coordinates clamped to the
//!    image (the caller keeps `p` at least `h` pixels inside).
//! 3. **Warp** into every window frame `j ≠ i`, `j < n_frames`:
//!    `x = T_j^-1 X`, `(u', v', z) = (fx x/z + cx, fy y/z + cy, z)`, and the warped patch
//!    `P̂_j(δ)` is a bilinear sample of frame `j` at `(u', v')` with pixel centres at integer
//!    coordinates (our convention; DIM-SLAM's `grid_sample(align_corners=False)` has a half-pixel
//!    offset, method notes §10). Coordinates outside `[0, W-1] x [0, H-1]` are clamped to the
//!    border (border padding), and a clamped axis has zero derivative.
//! 4. **Validity** of the pair `(i, j)` is decided from the centre point only:
//!    `z > MIN_Z`, `margin < u' < W-1-margin`, `margin < v' < H-1-margin`. If fewer than
//!    `min_views` pairs are valid, the pixel contributes nothing (loss 0, gradient 0), unless
//!    `few_views_weight` is set: then a pixel with at least one valid pair (but fewer than
//!    `min_views`) contributes its loss and gradient times that weight (ours: below). A patch
//!    point (not the centre) with `z <= MIN_Z` inside a valid pair is sampled at its clamped
//!    coordinates and has zero gradient.
//! 5. **Per valid pair:** `S11 = ½ Σ_c (1 - SSIM11_c)`, `S7 = ½ Σ_c (1 - SSIM7_c)` (single
//!    Gaussian-window SSIM, [`ssim_patch`]; `S7` on the inner 7x7; DIM-SLAM divides by 2, not 3),
//!    `center = Σ_c smoothL1_β(P_i(0)_c - P̂_j(0)_c)`, and
//!    `pair = w_patch (w_patch11 S11 + w_patch7 S7) + w_center center`.
//! 6. **Loss = Σ over valid pairs** (DIM-SLAM's sum reduction; the caller scales, e.g. by
//!    Hi-Map's `λ_w` and by the number of sampled pixels if it wants a mean).
//!
//! DIM-SLAM's fixed-frame weight (×50 for the two ground-truth frames) is not reproduced: Hi-Map
//! has ground-truth poses everywhere.
//!
//! # Gradient
//!
//! Only `D` is differentiated (poses are fixed in Hi-Map). With `g(δ) = ∂pair/∂P̂_j(δ)`
//! (`-½ w_patch w_patch11 ∂SSIM11/∂b - ½ w_patch w_patch7 ∂SSIM7/∂b`, plus
//! `-w_center smoothL1'(r_c)` at the centre), the chain is
//! `∂P̂/∂D = ∂P̂/∂u' ∂u'/∂D + ∂P̂/∂v' ∂v'/∂D` where
//! - `∂P̂/∂u'` is the derivative of the bilinear interpolation (piecewise linear; at an integer
//!   coordinate the right-hand cell is used; zero on a clamped axis);
//! - `∂u'/∂D = fx (ẋ - x ż / z) / z`, `∂v'/∂D = fy (ẏ - y ż / z) / z` with
//!   `(ẋ, ẏ, ż) = ∂x/∂D = R_j^T R_i K^-1 (p + δ)`.
//!
//! # Our choices where the paper is silent
//!
//! - `few_views_weight` (0 = DIM-SLAM's rule): DIM-SLAM asks for `min_views` valid views so that
//!   an occluded or specular pair is outvoted. Space that only one or two frames have seen (a
//!   first look through a doorway, a turn) then gets no warping term at all and stays at
//!   whatever the field guessed there until more views arrive; a down-weighted term from the
//!   views it has pulls it towards them meanwhile, and the full term takes over once
//!   `min_views` frames see it. The scaled sum is `(Σ pairs) * w` and `(Σ d pairs) * w`, one
//!   multiplication after the sums, on every device.
//! - `few_views_min_grad` (0 = no test): the down-weighted term keeps only the pairs whose
//!   epipolar line crosses texture in the source patch. With `(sxx, sxy, syy)` the mean
//!   structure tensor of the patch's inner `(2h-1)^2` samples (central differences per source
//!   pixel, the three channels averaged) and `e = (fx tx - (u - cx) tz, fy ty - (v - cy) tz)`
//!   the epipolar direction through `p` towards frame `j`'s centre `t` (in the source camera),
//!   a pair is kept when `eᵀ S e >= min_grad² |e|²`, i.e. the RMS gradient along the line is
//!   at least `min_grad`. Along a line without texture (a plain or smoothly shaded wall, bands
//!   parallel to the motion) one or two views do not determine the depth.
//! - `min_grad` (0 = no test, DIM-SLAM's rule): the same test on the pairs of a pixel with
//!   `min_views` valid views. On a plain patch the loss is flat in depth however many views
//!   see it, and its gradient is noise that Adam turns into full-size steps of the plain
//!   surfaces; the test leaves them to the field's other constraints. A pixel whose pairs
//!   all fail contributes nothing (its `valid_views` is still reported).
//! - Patch size: `half` is clamped to `1..=5` (the storage is 11x11); the first SSIM uses the
//!   whole `(2h+1)^2` patch and the second the inner `min(7, 2h+1)^2`.
//! - A term whose weight is exactly 0 (e.g. `w_patch = 0` during DIM-SLAM's first 150
//!   initialisation iterations) is skipped: same value (for finite inputs), less work.
//! - `n_frames` is clamped to `poses.len()` and to [`MAX_WINDOW`] (the validity mask is one
//!   `u32`); a `src` outside the window gives the zero result.
//!
//! # Determinism
//!
//! Everything is `f32`, summed in a fixed sequential order: pairs in frame order, and inside a
//! pair the patch pixels row-major with the channels innermost, so the CPU and the GPU (which
//! runs this function per pixel) get the same bits. It obeys the kernel rules of the crate:
//! fixed-size arrays, no `Option`/`Result`, no transcendental functions at all (only `+ - * /`
//! and comparisons; `floor` of a clamped non-negative coordinate is its `as u32` cast, which is
//! defined on SPIR-V because the value is finite and in range).
//!
//! # Cost
//!
//! About 150 µs per call with 19 other frames (≈ 8 µs per pair, roughly half SSIM and half
//! warping and sampling) on one core of the 2-core development VM, release build, 320x240
//! images (measured with a throw-away harness, noisy: 140 to 200 µs).

use crate::camera::{Intrinsics, Pose, PoseRead};
use crate::loss::{
    patch_index, side_grad, smooth_l1, ssim_channel, ssim_patch_target, SsimSource, PATCH,
    PATCH_PIXELS,
};
use crate::Error;

/// The largest window (frames per call) [`warp_pixel`] handles; more are ignored.
pub const MAX_WINDOW: usize = 32;

/// Smallest camera z (metres) of a point counted as in front of a camera.
pub const MIN_Z: f32 = 1e-4;

/// Largest supported patch half-size (the patch storage is `PATCH x PATCH`).
pub const MAX_HALF: u32 = (PATCH / 2) as u32;

/// Largest supported patch stride ([`WarpConfig::stride`]).
pub const MAX_STRIDE: u32 = 8;

/// Read access to the colour images of the frames in the mapping window (RGB in `[0, 1]`).
/// `frame` indexes the window (the same index as the `poses` slice of [`warp_pixel`]); every
/// frame has the same `size() = (width, height)`, and `x < width`, `y < height` always hold
/// in the calls [`warp_pixel`] makes.
pub trait FrameImages {
    /// The images live in a CPU's memory: [`warp_pixel`] names the next view's rows to
    /// [`Self::prefetch_row`] and warps a full patch in SIMD-friendly passes
    /// (`warp_view_lanes`, the same bits). False (the default, GPUs): neither is compiled in.
    const CPU: bool = false;
    /// `(width, height)` of every frame (pixels).
    fn size(&self) -> (u32, u32);
    /// Colour (RGB in `[0, 1]`) of pixel `(x, y)` of window frame `frame`.
    fn texel(&self, frame: usize, x: u32, y: u32) -> [f32; 3];
    /// A cache hint: texels `x0..=x1` of row `y` of `frame` will be read soon (`x0 <= x1`,
    /// all inside the image). No value changes; the default does nothing.
    #[inline(always)]
    fn prefetch_row(&self, _frame: usize, _y: u32, _x0: u32, _x1: u32) {}
    /// Target depth (camera z, m) of the per-pixel depth prior on pixel `(x, y)` of `frame`
    /// (the host's plane priors, `host/src/planes.rs`; weighted by
    /// `MappingLoss::lambda_plane`); 0 = none (the default: images without priors).
    #[inline(always)]
    fn depth_prior(&self, _frame: usize, _x: u32, _y: u32) -> f32 {
        0.0
    }
    /// CPU form only (`warp_view_lanes`): the texels of the four bilinear corners
    /// `(x0, y0), (x1, y0), (x0, y1), (x1, y1)` of every patch point (`cells[p]` =
    /// `[x0, y0, x1, y1]`) of `frame`, as `texels[corner][channel][point]`: the values
    /// [`Self::texel`] gives. Images in packed form override it to convert in lanes.
    #[inline(always)]
    fn gather_corners(&self, frame: usize, cells: &[[u32; 4]; PATCH_PIXELS], texels: &mut Corners) {
        for p in 0..PATCH_PIXELS {
            let [x0, y0, x1, y1] = cells[p];
            for (k, (x, y)) in [(x0, y0), (x1, y0), (x0, y1), (x1, y1)]
                .into_iter()
                .enumerate()
            {
                let t = self.texel(frame, x, y);
                texels[k][0][p] = t[0];
                texels[k][1][p] = t[1];
                texels[k][2][p] = t[2];
            }
        }
    }
}

/// The texels of the four bilinear corners of every patch point, channel-major
/// (`[corner][channel][point]`; see [`FrameImages::gather_corners`]).
pub type Corners = [[[f32; PATCH_PIXELS]; 3]; 4];

/// Names to `images` the rows around the projected patch centre `(cu, cv)` of `frame` that
/// the warp of a patch of half size `half` will read (a hint; see
/// [`FrameImages::prefetch_row`]).
#[inline(always)]
fn prefetch_patch<I: FrameImages + ?Sized>(images: &I, frame: usize, cu: f32, cv: f32, half: i32) {
    let (w, h) = images.size();
    // The patch warps to about its own size; a few pixels more cover moderate scale changes
    // and the bilinear neighbours. `cu`, `cv` are finite and inside the margins (valid
    // centre), so the casts are exact floors of in-range values.
    let r = half + 3;
    let (u, v) = (cu as i32, cv as i32);
    let x0 = (u - r).max(0) as u32;
    let x1 = ((u + r) as u32).min(w - 1);
    let y0 = (v - r).max(0) as u32;
    let y1 = ((v + r) as u32).min(h - 1);
    let mut y = y0;
    while y <= y1 {
        images.prefetch_row(frame, y, x0, x1);
        y += 1;
    }
}

/// [`FrameImages`] over one flat buffer: frame-major, then row-major, RGB interleaved
/// (`data[((frame * height + y) * width + x) * 3 + c]`), the layout a GPU storage buffer
/// would have. An index past the end of `data` reads black (no panic).
#[derive(Clone, Copy, Debug)]
pub struct PackedImages<'a> {
    /// Width of every frame (pixels).
    pub width: u32,
    /// Height of every frame (pixels).
    pub height: u32,
    /// The interleaved RGB values of all frames.
    pub data: &'a [f32],
}

impl FrameImages for PackedImages<'_> {
    #[inline(always)]
    fn size(&self) -> (u32, u32) {
        (self.width, self.height)
    }

    #[inline(always)]
    fn texel(&self, frame: usize, x: u32, y: u32) -> [f32; 3] {
        let i =
            ((frame * self.height as usize + y as usize) * self.width as usize + x as usize) * 3;
        if i + 2 < self.data.len() {
            [self.data[i], self.data[i + 1], self.data[i + 2]]
        } else {
            [0.0; 3]
        }
    }
}

/// Settings of the warping loss. [`WarpConfig::dim_slam`] gives DIM-SLAM's values.
#[derive(Clone, Copy, Debug, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct WarpConfig {
    /// Patch half-size in pixels: 5 gives DIM-SLAM's 11x11 patch (clamped to `1..=5`).
    pub half: u32,
    /// The centre must project strictly more than `margin` pixels inside the image.
    pub margin: f32,
    /// Pairs are used only if at least this many frames see the centre.
    pub min_views: u32,
    /// Weight of the 11x11 SSIM term inside the patch term.
    pub w_patch11: f32,
    /// Weight of the inner 7x7 SSIM term inside the patch term.
    pub w_patch7: f32,
    /// Weight of the patch term.
    pub w_patch: f32,
    /// Weight of the centre-pixel smooth-L1 term.
    pub w_center: f32,
    /// Threshold `β` of the centre-pixel smooth L1.
    pub center_beta: f32,
    /// Spacing of the patch's samples in the source image (pixels, `1..=MAX_STRIDE`): 1 is
    /// DIM-SLAM's dense patch; `s` spreads the same `(2h+1)^2` samples over `(2hs+1)^2`
    /// pixels (a dilated patch, as DSO's sparse patterns), so that a pixel of a plain
    /// surface sees the textured border of its region.
    pub stride: u32,
    /// Weight (`0..=1`) of the term of a pixel whose centre at least one but fewer than
    /// `min_views` frames see validly (0 = DIM-SLAM's rule: no term below `min_views`).
    pub few_views_weight: f32,
    /// A pair of the `few_views_weight` term needs the source patch's texture along its
    /// epipolar line: the RMS image gradient along it (intensity per pixel, over the patch's
    /// inner samples and the channels) at least this (0 = no test).
    pub few_views_min_grad: f32,
    /// The same test for the pairs of a pixel with at least `min_views` valid views (the
    /// main term; 0 = no test, DIM-SLAM's rule): on a plain patch the loss is flat in depth,
    /// so its gradient is noise that moves plain walls.
    pub min_grad: f32,
}

impl WarpConfig {
    /// DIM-SLAM's values (method notes §2.4): 11x11 patch, margin 5 px, at least 4 views,
    /// `0.5 (0.2 S11 + 0.6 S7) + 0.1 smoothL1_0.1(centre)`.
    pub const fn dim_slam() -> Self {
        Self {
            half: 5,
            margin: 5.0,
            min_views: 4,
            w_patch11: 0.2,
            w_patch7: 0.6,
            w_patch: 0.5,
            w_center: 0.1,
            center_beta: 0.1,
            stride: 1,
            few_views_weight: 0.0,
            few_views_min_grad: 0.0,
            min_grad: 0.0,
        }
    }

    /// Checks the ranges: `half` in `1..=5`, `margin` finite and `>= 0`, weights and
    /// `center_beta` finite and `>= 0`, `few_views_weight` in `0..=1`.
    pub fn validate(&self) -> Result<(), Error> {
        if self.half < 1 || self.half > MAX_HALF {
            return Err(Error::InvalidConfig("warp: half must be in 1..=5"));
        }
        if self.stride < 1 || self.stride > MAX_STRIDE {
            return Err(Error::InvalidConfig("warp: stride must be in 1..=8"));
        }
        let ok = |x: f32| x.is_finite() && x >= 0.0;
        if !ok(self.margin) {
            return Err(Error::InvalidConfig("warp: margin must be finite and >= 0"));
        }
        if !(ok(self.w_patch11) && ok(self.w_patch7) && ok(self.w_patch) && ok(self.w_center)) {
            return Err(Error::InvalidConfig(
                "warp: weights must be finite and >= 0",
            ));
        }
        if !ok(self.center_beta) {
            return Err(Error::InvalidConfig(
                "warp: center_beta must be finite and >= 0",
            ));
        }
        if !ok(self.few_views_min_grad) {
            return Err(Error::InvalidConfig(
                "warp: few_views_min_grad must be finite and >= 0",
            ));
        }
        if !ok(self.min_grad) {
            return Err(Error::InvalidConfig(
                "warp: min_grad must be finite and >= 0",
            ));
        }
        if !(ok(self.few_views_weight) && self.few_views_weight <= 1.0) {
            return Err(Error::InvalidConfig(
                "warp: few_views_weight must be in 0..=1",
            ));
        }
        Ok(())
    }
}

impl Default for WarpConfig {
    fn default() -> Self {
        Self::dim_slam()
    }
}

/// Result of [`warp_pixel`].
#[derive(Clone, Copy, Debug, PartialEq, Default)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct WarpResult {
    /// Sum of the pair losses over the valid pairs (below `min_views`: 0, or times
    /// `few_views_weight` when that is set).
    pub loss: f32,
    /// `d loss / d depth`.
    pub d_depth: f32,
    /// Number of frames whose centre projection passed the validity test (reported even when
    /// it is below `min_views`).
    pub valid_views: u32,
}

type Patch = [[f32; 3]; PATCH_PIXELS];

/// Clamps a sample coordinate to `[0, max]`; returns the clamped value and whether it was
/// inside (a NaN gives `(0, false)`).
#[inline(always)]
fn clamp_coord(p: f32, max: f32) -> (f32, bool) {
    if p >= 0.0 {
        if p <= max {
            (p, true)
        } else {
            (max, false)
        }
    } else {
        (0.0, false)
    }
}

/// Bilinear sample of `frame` at `(pu, pv)` (pixel centres at integers, border clamp).
/// Returns `(value, d value / d pu, d value / d pv)`.
#[inline(always)]
fn sample_bilinear<I: FrameImages + ?Sized>(
    images: &I,
    frame: usize,
    w: u32,
    h: u32,
    pu: f32,
    pv: f32,
) -> ([f32; 3], [f32; 3], [f32; 3]) {
    let (xc, in_x) = clamp_coord(pu, (w - 1) as f32);
    let (yc, in_y) = clamp_coord(pv, (h - 1) as f32);
    // xc, yc are finite and >= 0, so the truncating cast is floor.
    // (rust-gpu 0.11 does not implement `saturating_sub`.)
    #[allow(clippy::implicit_saturating_sub)]
    let wmax = if w >= 2 { w - 2 } else { 0 };
    #[allow(clippy::implicit_saturating_sub)]
    let hmax = if h >= 2 { h - 2 } else { 0 };
    let mut x0 = xc as u32;
    if x0 > wmax {
        x0 = wmax;
    }
    let mut y0 = yc as u32;
    if y0 > hmax {
        y0 = hmax;
    }
    let x1 = if x0 + 1 < w { x0 + 1 } else { x0 };
    let y1 = if y0 + 1 < h { y0 + 1 } else { y0 };
    let fx = xc - x0 as f32;
    let fy = yc - y0 as f32;
    let gx = 1.0 - fx;
    let gy = 1.0 - fy;
    let t00 = images.texel(frame, x0, y0);
    let t10 = images.texel(frame, x1, y0);
    let t01 = images.texel(frame, x0, y1);
    let t11 = images.texel(frame, x1, y1);
    let mut val = [0.0f32; 3];
    let mut du = [0.0f32; 3];
    let mut dv = [0.0f32; 3];
    let mut c = 0;
    while c < 3 {
        let top = gx * t00[c] + fx * t10[c];
        let bot = gx * t01[c] + fx * t11[c];
        val[c] = gy * top + fy * bot;
        if in_x {
            du[c] = gy * (t10[c] - t00[c]) + fy * (t11[c] - t01[c]);
        }
        if in_y {
            dv[c] = bot - top;
        }
        c += 1;
    }
    (val, du, dv)
}

/// `R^T d` for the rotation of a camera-to-world pose (world vector into camera space).
#[inline(always)]
fn inverse_rotate(pose: &Pose, d: [f32; 3]) -> [f32; 3] {
    let m = &pose.m;
    [
        m[0][0] * d[0] + m[1][0] * d[1] + m[2][0] * d[2],
        m[0][1] * d[0] + m[1][1] * d[1] + m[2][1] * d[2],
        m[0][2] * d[0] + m[1][2] * d[1] + m[2][2] * d[2],
    ]
}

/// Whether a projected centre `(pu, pv, z)` is in front and inside the margins (NaN: false).
#[inline(always)]
fn centre_valid(pu: f32, pv: f32, z: f32, w: u32, h: u32, margin: f32) -> bool {
    let umax = (w - 1) as f32 - margin;
    let vmax = (h - 1) as f32 - margin;
    z > MIN_Z && pu > margin && pu < umax && pv > margin && pv < vmax
}

/// The derivative of the projection `(u, v)` of the camera-space point `x` with respect to
/// depth, along the camera-space direction `xd`; zero where `x` is not in front (`z <= MIN_Z`).
/// The division runs for every point and the result is selected, so a CPU computes it in
/// lanes; a discarded value never reaches the output.
#[inline(always)]
fn projection_derivative(k: &Intrinsics, x: [f32; 3], xd: [f32; 3]) -> (f32, f32) {
    let iz = crate::math::div(1.0, x[2]);
    let zr = xd[2] * iz;
    let dpu = k.fx * (xd[0] - x[0] * zr) * iz;
    let dpv = k.fy * (xd[1] - x[1] * zr) * iz;
    if x[2] > MIN_Z {
        (dpu, dpv)
    } else {
        (0.0, 0.0)
    }
}

/// The per-view patch stage of [`warp_pixel`] for a full patch (`half == MAX_HALF`), as a
/// CPU runs it: the projections of all patch points first, in straight passes over
/// structure-of-arrays copies that vectorise (the divisions 8 or 16 lanes at a time), then the
/// bilinear samples from the precomputed coordinates (independent loads the CPU overlaps).
/// Every element takes the operations of the scalar loop in the same order (`z > MIN_Z` as a
/// select), so the warped patch and its depth derivative, written to lane `lane` of `tgt`
/// and `dtgt`, are the same bits (tested against the scalar form).
#[allow(clippy::too_many_arguments)]
#[inline(never)]
fn warp_view_lanes<I: FrameImages + ?Sized>(
    images: &I,
    j: usize,
    k: &Intrinsics,
    pose_j: &Pose,
    xw: &[[f32; 3]; PATCH_PIXELS],
    dxw: &[[f32; 3]; PATCH_PIXELS],
    (tgt, dtgt, lane): (&mut PatchLanes, &mut PatchLanes, usize),
) {
    let (w, h) = images.size();
    let mut pu = [0.0f32; PATCH_PIXELS];
    let mut pv = [0.0f32; PATCH_PIXELS];
    let mut dpu = [0.0f32; PATCH_PIXELS];
    let mut dpv = [0.0f32; PATCH_PIXELS];
    for p in 0..PATCH_PIXELS {
        let x = pose_j.inverse_transform(xw[p]);
        let xd = inverse_rotate(pose_j, dxw[p]);
        (pu[p], pv[p], _) = k.project(x);
        (dpu[p], dpv[p]) = projection_derivative(k, x, xd);
    }
    // The bilinear samples of `sample_bilinear` in three passes: the cells and fractions of
    // every point (lanes), the texel loads alone (many in flight at once), then the
    // interpolation over channel-major arrays (lanes). Each element takes the scalar form's
    // operations in its order.
    // (as in `sample_bilinear`: rust-gpu 0.11 does not implement `saturating_sub`.)
    #[allow(clippy::implicit_saturating_sub)]
    let wmax = if w >= 2 { w - 2 } else { 0 };
    #[allow(clippy::implicit_saturating_sub)]
    let hmax = if h >= 2 { h - 2 } else { 0 };
    let (umax, vmax) = ((w - 1) as f32, (h - 1) as f32);
    let mut fx = [0.0f32; PATCH_PIXELS];
    let mut fy = [0.0f32; PATCH_PIXELS];
    let mut in_x = [false; PATCH_PIXELS];
    let mut in_y = [false; PATCH_PIXELS];
    let mut cells = [[0u32; 4]; PATCH_PIXELS];
    for p in 0..PATCH_PIXELS {
        let (xc, ix) = clamp_coord(pu[p], umax);
        let (yc, iy) = clamp_coord(pv[p], vmax);
        let x0 = (xc as u32).min(wmax);
        let y0 = (yc as u32).min(hmax);
        let x1 = if x0 + 1 < w { x0 + 1 } else { x0 };
        let y1 = if y0 + 1 < h { y0 + 1 } else { y0 };
        fx[p] = xc - x0 as f32;
        fy[p] = yc - y0 as f32;
        in_x[p] = ix;
        in_y[p] = iy;
        cells[p] = [x0, y0, x1, y1];
    }
    // texels[corner][channel][point], corners 00, 10, 01, 11.
    let mut texels: Corners = [[[0.0f32; PATCH_PIXELS]; 3]; 4];
    images.gather_corners(j, &cells, &mut texels);
    let mut val = [[0.0f32; PATCH_PIXELS]; 3];
    let mut dval = [[0.0f32; PATCH_PIXELS]; 3];
    for c in 0..3 {
        let (t00, t10, t01, t11) = (&texels[0][c], &texels[1][c], &texels[2][c], &texels[3][c]);
        for p in 0..PATCH_PIXELS {
            let (gx, gy) = (1.0 - fx[p], 1.0 - fy[p]);
            let top = gx * t00[p] + fx[p] * t10[p];
            let bot = gx * t01[p] + fx[p] * t11[p];
            val[c][p] = gy * top + fy[p] * bot;
            let du = if in_x[p] {
                gy * (t10[p] - t00[p]) + fy[p] * (t11[p] - t01[p])
            } else {
                0.0
            };
            let dv = if in_y[p] { bot - top } else { 0.0 };
            dval[c][p] = du * dpu[p] + dv * dpv[p];
        }
    }
    for p in 0..PATCH_PIXELS {
        for c in 0..3 {
            tgt[p][c][lane] = val[c][p];
            dtgt[p][c][lane] = dval[c][p];
        }
    }
}

/// The window's length (`n_frames` cut to the poses given), the images' size, and whether
/// `src` is one of the window's frames with non-empty images (the guard of [`warp_pixel`] and
/// [`warp_view_count`]).
#[inline(always)]
fn source_window<I: FrameImages + ?Sized, PS: PoseRead + ?Sized>(
    poses: &PS,
    n_frames: usize,
    src: usize,
    images: &I,
) -> (usize, u32, u32, bool) {
    let (w, h) = images.size();
    let n = window_len(n_frames, poses.count());
    (n, w, h, src < n && w > 0 && h > 0)
}

/// Loss of one source pixel (integer pixel `u`, `v` of window frame `src`), warped with the
/// fronto-parallel plane at rendered centre depth `depth` into every other frame of the
/// window (`0..n_frames`, `poses[j]` camera-to-world, `images` frame `j`), and its derivative
/// with respect to `depth`. Formulas, validity rules and summation order in the module docs.
#[allow(clippy::too_many_arguments)]
pub fn warp_pixel<I: FrameImages + ?Sized, PS: PoseRead + ?Sized>(
    cfg: &WarpConfig,
    k: &Intrinsics,
    poses: &PS,
    n_frames: usize,
    src: usize,
    u: u32,
    v: u32,
    depth: f32,
    images: &I,
) -> WarpResult {
    let (n, w, h, ok) = source_window(poses, n_frames, src, images);
    if !ok {
        return WarpResult::default();
    }
    let half = patch_half(cfg);
    let side = (2 * half + 1) as usize;
    let small = if side < 7 { side } else { 7 };
    // Storage index of offset (dx, dy) is (dy + 5) * PATCH + dx + 5.
    let centre = PATCH_PIXELS / 2;

    let mut xw = [[0.0f32; 3]; PATCH_PIXELS];
    let mut dxw = [[0.0f32; 3]; PATCH_PIXELS];
    let mut src_patch: Patch = [[0.0f32; 3]; PATCH_PIXELS];
    let pose_s = poses.pose(src);
    source_patch(
        k,
        &pose_s,
        images,
        src,
        (u, v, half, patch_stride(cfg)),
        depth,
        &mut xw,
        &mut dxw,
        &mut src_patch,
    );

    // Pass 1: validity of every pair from the centre point.
    let mut centres = [[0.0f32; 2]; MAX_WINDOW];
    let (mut mask, count) =
        valid_views::<I, PS>(cfg, k, poses, n, src, xw[centre], (w, h), &mut centres);
    // Fewer than `min_views`: no term, or the down-weighted one; either term keeps only the
    // pairs along whose epipolar line the source patch has texture when its test is on
    // (module docs).
    let few = count < cfg.min_views;
    let none = WarpResult {
        loss: 0.0,
        d_depth: 0.0,
        valid_views: count,
    };
    if few && cfg.few_views_weight == 0.0 {
        return none;
    }
    let min_grad = if few {
        cfg.few_views_min_grad
    } else {
        cfg.min_grad
    };
    if min_grad > 0.0 {
        mask = textured_pairs(cfg, min_grad, k, poses, (u, v), &pose_s, &src_patch, mask);
    }
    if mask == 0 {
        return none;
    }

    // The source patch's side of both SSIM terms, shared by every pair.
    let ssim_src = (
        SsimSource::new(side, &src_patch),
        SsimSource::new(small, &src_patch),
    );

    let mut loss = 0.0f32;
    let mut d_depth = 0.0f32;
    prefetch_valid_from(images, mask, 0, &centres, half);
    if I::CPU && half == MAX_HALF as i32 {
        // The CPU form: up to `LANES` valid views warped, then their pairs' losses and
        // gradients side by side (`pair_loss_lanes`), summed in view order as below.
        let mut tl: PatchLanes = [[[0.0; LANES]; 3]; PATCH_PIXELS];
        let mut dl: PatchLanes = [[[0.0; LANES]; 3]; PATCH_PIXELS];
        let mut gl: PatchLanes = [[[0.0; LANES]; 3]; PATCH_PIXELS];
        let mut j = 0;
        while j < n {
            let mut lanes = 0;
            while j < n && lanes < LANES {
                if mask & (1u32 << j) != 0 {
                    prefetch_valid_from(images, mask, j + 1, &centres, half);
                    let pose_j = poses.pose(j);
                    let out = (&mut tl, &mut dl, lanes);
                    warp_view_lanes(images, j, k, &pose_j, &xw, &dxw, out);
                    lanes += 1;
                }
                j += 1;
            }
            let pair = pair_loss_lanes(cfg, &ssim_src, &src_patch, &tl, &mut gl);
            let d_pair = chain_lanes(&gl, &dl);
            for l in 0..lanes {
                loss += pair[l];
                d_depth += d_pair[l];
            }
        }
    } else {
        let mut tgt: Patch = [[0.0f32; 3]; PATCH_PIXELS];
        let mut dtgt: Patch = [[0.0f32; 3]; PATCH_PIXELS];
        let mut g: Patch = [[0.0f32; 3]; PATCH_PIXELS];
        let mut d_b: Patch = [[0.0f32; 3]; PATCH_PIXELS];
        let lo = (MAX_HALF as i32 - half) as usize;
        let hi = lo + side;
        let mut j = 0;
        while j < n {
            if mask & (1u32 << j) == 0 {
                j += 1;
                continue;
            }
            // The next valid view's texels load while this one is computed.
            prefetch_valid_from(images, mask, j + 1, &centres, half);
            let pose_j = poses.pose(j);

            // Warped patch and its derivative with respect to depth.
            warp_view(
                images,
                j,
                k,
                &pose_j,
                (lo, hi),
                &xw,
                &dxw,
                &mut tgt,
                &mut dtgt,
                &mut g,
            );

            let pair = pair_loss(cfg, &ssim_src, &src_patch, &tgt, &mut g, &mut d_b);
            loss += pair;
            d_depth += chain_to_depth((lo, hi), &g, &dtgt);
            j += 1;
        }
    }

    if few {
        loss *= cfg.few_views_weight;
        d_depth *= cfg.few_views_weight;
    }
    WarpResult {
        loss,
        d_depth,
        valid_views: count,
    }
}

/// Frames of the window the loss may use: `n_frames`, at most the poses given and
/// [`MAX_WINDOW`].
#[inline(always)]
fn window_len(n_frames: usize, poses: usize) -> usize {
    let mut n = n_frames;
    if n > poses {
        n = poses;
    }
    if n > MAX_WINDOW {
        n = MAX_WINDOW;
    }
    n
}

/// `v` clamped to `1..=max`.
#[inline(always)]
fn clamp_from_one(v: u32, max: u32) -> i32 {
    if v > max {
        max as i32
    } else if v < 1 {
        1
    } else {
        v as i32
    }
}

/// The patch half size of `cfg`, clamped to `1..=MAX_HALF`.
#[inline(always)]
fn patch_half(cfg: &WarpConfig) -> i32 {
    clamp_from_one(cfg.half, MAX_HALF)
}

/// The patch stride of `cfg`, clamped to `1..=MAX_STRIDE`.
#[inline(always)]
fn patch_stride(cfg: &WarpConfig) -> i32 {
    clamp_from_one(cfg.stride, MAX_STRIDE)
}

/// CPU only (a no-op for other images): starts loading the texels of the first valid view
/// (bit of `mask`) at or after `from`.
#[inline(always)]
fn prefetch_valid_from<I: FrameImages + ?Sized>(
    images: &I,
    mask: u32,
    from: usize,
    centres: &[[f32; 2]; MAX_WINDOW],
    half: i32,
) {
    if !I::CPU {
        return;
    }
    let later = if from < 32 {
        mask & (u32::MAX << from)
    } else {
        0
    };
    if later != 0 {
        let next = later.trailing_zeros() as usize;
        prefetch_patch(images, next, centres[next][0], centres[next][1], half);
    }
}

/// The patch around source pixel (`u`, `v`) of half size `half` (samples `stride` pixels
/// apart) on the fronto-parallel plane
/// at `depth`: its points in the world (`xw`), their derivative with respect to depth (`dxw`)
/// and the source frame's texels (`src_patch`, the border clamped).
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn source_patch<I: FrameImages + ?Sized>(
    k: &Intrinsics,
    pose_s: &Pose,
    images: &I,
    src: usize,
    (u, v, half, stride): (u32, u32, i32, i32),
    depth: f32,
    xw: &mut [[f32; 3]; PATCH_PIXELS],
    dxw: &mut [[f32; 3]; PATCH_PIXELS],
    src_patch: &mut Patch,
) {
    let (w, h) = images.size();
    let wmax = (w - 1) as i32;
    let hmax = (h - 1) as i32;
    let mut dy = -half;
    while dy <= half {
        let py = v as i32 + dy * stride;
        let mut dx = -half;
        while dx <= half {
            let px = u as i32 + dx * stride;
            let p = ((dy + MAX_HALF as i32) as usize) * PATCH + (dx + MAX_HALF as i32) as usize;
            let dir = k.direction(px as f32, py as f32);
            xw[p] = pose_s.transform([depth * dir[0], depth * dir[1], depth * dir[2]]);
            dxw[p] = pose_s.rotate(dir);
            let cx = if px < 0 {
                0
            } else if px > wmax {
                wmax
            } else {
                px
            };
            let cy = if py < 0 {
                0
            } else if py > hmax {
                hmax
            } else {
                py
            };
            src_patch[p] = images.texel(src, cx as u32, cy as u32);
            dx += 1;
        }
        dy += 1;
    }
}

/// The pairs of `mask` along whose epipolar line (in the source image, through pixel
/// `(u, v)`) the source patch has an RMS gradient of at least `min_grad`.
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn textured_pairs<PS: PoseRead + ?Sized>(
    cfg: &WarpConfig,
    min_grad: f32,
    k: &Intrinsics,
    poses: &PS,
    (u, v): (u32, u32),
    pose_s: &Pose,
    src_patch: &Patch,
    mask: u32,
) -> u32 {
    // The structure tensor of the inner samples (central differences, per source pixel).
    let half = patch_half(cfg);
    let inv = 0.5 / patch_stride(cfg) as f32;
    let (mut sxx, mut sxy, mut syy) = (0.0f32, 0.0f32, 0.0f32);
    let mut dy = -(half - 1);
    while dy < half {
        let mut dx = -(half - 1);
        while dx < half {
            let p = ((dy + MAX_HALF as i32) as usize) * PATCH + (dx + MAX_HALF as i32) as usize;
            let mut c = 0;
            while c < 3 {
                let gx = (src_patch[p + 1][c] - src_patch[p - 1][c]) * inv;
                let gy = (src_patch[p + PATCH][c] - src_patch[p - PATCH][c]) * inv;
                sxx += gx * gx;
                sxy += gx * gy;
                syy += gy * gy;
                c += 1;
            }
            dx += 1;
        }
        dy += 1;
    }
    let side = (2 * half - 1) as f32;
    let norm = 1.0 / (side * side * 3.0);
    let (sxx, sxy, syy) = (sxx * norm, sxy * norm, syy * norm);
    let thr = min_grad * min_grad;
    let (xu, yv) = (u as f32 - k.cx, v as f32 - k.cy);
    let mut out = 0u32;
    let mut j = 0;
    while j < MAX_WINDOW {
        if mask & (1u32 << j) != 0 {
            // Frame j's centre in the source camera; the epipolar line through (u, v)
            // runs along (fx tx - (u - cx) tz, fy ty - (v - cy) tz).
            let t = pose_s.inverse_transform(poses.pose(j).origin());
            let ex = k.fx * t[0] - xu * t[2];
            let ey = k.fy * t[1] - yv * t[2];
            let n2 = ex * ex + ey * ey;
            let e = (sxx * (ex * ex) + 2.0 * sxy * (ex * ey)) + syy * (ey * ey);
            if n2 > 0.0 && e >= thr * n2 {
                out |= 1u32 << j;
            }
        }
        j += 1;
    }
    out
}

/// How many window frames (the source excluded) see pixel `(u, v)` of frame `src` at `depth`
/// by [`warp_pixel`]'s rule (the centre projects in front of the camera and `cfg.margin`
/// inside the image), without computing the loss: the planarity prior acts only where the
/// warping term has its `min_views`.
#[allow(clippy::too_many_arguments)]
#[inline(always)]
pub fn warp_view_count<I: FrameImages + ?Sized, PS: PoseRead + ?Sized>(
    cfg: &WarpConfig,
    k: &Intrinsics,
    poses: &PS,
    n_frames: usize,
    src: usize,
    u: u32,
    v: u32,
    depth: f32,
    images: &I,
) -> u32 {
    let (n, w, h, ok) = source_window(poses, n_frames, src, images);
    if !ok {
        return 0;
    }
    let dir = k.direction(u as f32, v as f32);
    let x = poses
        .pose(src)
        .transform([depth * dir[0], depth * dir[1], depth * dir[2]]);
    let mut centres = [[0.0f32; 2]; MAX_WINDOW];
    valid_views::<I, PS>(cfg, k, poses, n, src, x, (w, h), &mut centres).1
}

/// Which window frames (other than `src`) see the patch centre `x_centre` validly: a bit mask
/// and its count. On the CPU the projected centres go to `centres` (for the cache hints).
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn valid_views<I: FrameImages + ?Sized, PS: PoseRead + ?Sized>(
    cfg: &WarpConfig,
    k: &Intrinsics,
    poses: &PS,
    n: usize,
    src: usize,
    x_centre: [f32; 3],
    (w, h): (u32, u32),
    centres: &mut [[f32; 2]; MAX_WINDOW],
) -> (u32, u32) {
    let mut mask = 0u32;
    let mut count = 0u32;
    let mut j = 0;
    while j < n {
        if j != src {
            let x = poses.pose(j).inverse_transform(x_centre);
            let (pu, pv, z) = k.project(x);
            if centre_valid(pu, pv, z, w, h, cfg.margin) {
                mask |= 1u32 << j;
                count += 1;
                if I::CPU {
                    centres[j] = [pu, pv];
                }
            }
        }
        j += 1;
    }
    (mask, count)
}

/// The source patch warped into frame `j` (rows and columns `lo..hi` of the storage) and its
/// derivative with respect to depth; zeroes the patch cotangent `g` there.
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn warp_view<I: FrameImages + ?Sized>(
    images: &I,
    j: usize,
    k: &Intrinsics,
    pose_j: &Pose,
    (lo, hi): (usize, usize),
    xw: &[[f32; 3]; PATCH_PIXELS],
    dxw: &[[f32; 3]; PATCH_PIXELS],
    tgt: &mut Patch,
    dtgt: &mut Patch,
    g: &mut Patch,
) {
    let (w, h) = images.size();
    let mut r = lo;
    while r < hi {
        let mut col = lo;
        while col < hi {
            let p = r * PATCH + col;
            let x = pose_j.inverse_transform(xw[p]);
            let xd = inverse_rotate(pose_j, dxw[p]);
            let (pu, pv, _) = k.project(x);
            let (val, du, dv) = sample_bilinear(images, j, w, h, pu, pv);
            tgt[p] = val;
            let (dpu, dpv) = projection_derivative(k, x, xd);
            let mut c = 0;
            while c < 3 {
                dtgt[p][c] = du[c] * dpu + dv[c] * dpv;
                g[p][c] = 0.0;
                c += 1;
            }
            col += 1;
        }
        r += 1;
    }
}

/// One pair's loss (the SSIM terms over the source patch's two regions, prepared in `ssim_src`,
/// and the centre term), adding its cotangent with respect to the warped patch into `g`.
#[inline(always)]
fn pair_loss(
    cfg: &WarpConfig,
    (src11, src7): &(SsimSource, SsimSource),
    src_patch: &Patch,
    tgt: &Patch,
    g: &mut Patch,
    d_b: &mut Patch,
) -> f32 {
    let c11 = cfg.w_patch * cfg.w_patch11;
    let c7 = cfg.w_patch * cfg.w_patch7;
    let mut patch_term = 0.0f32;
    if c11 != 0.0 {
        let s = ssim_patch_target(src11, src_patch, tgt, d_b);
        let s11 = 0.5 * ((1.0 - s[0]) + (1.0 - s[1]) + (1.0 - s[2]));
        patch_term += cfg.w_patch11 * s11;
        add_scaled_patch(g, -0.5 * c11, d_b);
    }
    if c7 != 0.0 {
        let s = ssim_patch_target(src7, src_patch, tgt, d_b);
        let s7 = 0.5 * ((1.0 - s[0]) + (1.0 - s[1]) + (1.0 - s[2]));
        patch_term += cfg.w_patch7 * s7;
        add_scaled_patch(g, -0.5 * c7, d_b);
    }
    let mut pair = cfg.w_patch * patch_term;
    if cfg.w_center != 0.0 {
        let centre = PATCH_PIXELS / 2;
        let mut center = 0.0f32;
        let mut c = 0;
        while c < 3 {
            let (l, dl) = smooth_l1(src_patch[centre][c] - tgt[centre][c], cfg.center_beta);
            center += l;
            g[centre][c] += -cfg.w_center * dl;
            c += 1;
        }
        pair += cfg.w_center * center;
    }
    pair
}

/// Views whose pairs the CPU form of [`warp_pixel`] computes side by side.
const LANES: usize = 8;

/// A patch per lane: `[pixel][channel][lane]`.
type PatchLanes = [[[f32; LANES]; 3]; PATCH_PIXELS];

/// [`pair_loss`] for the targets of `LANES` views at once (lane `l` of `tgt`), as a CPU runs
/// it: every lane takes the operations of `pair_loss` (via `ssim_patch_target` and
/// `add_scaled_patch`, from a zero cotangent) in their order, so the pair losses and the
/// cotangents `g` are the same bits; the window-weighted sums run in SIMD lanes across the
/// views instead of one dependent chain per view.
// Lane loops index several arrays at once.
#[allow(clippy::needless_range_loop)]
#[inline(never)]
fn pair_loss_lanes(
    cfg: &WarpConfig,
    (src11, src7): &(SsimSource, SsimSource),
    src_patch: &Patch,
    tgt: &PatchLanes,
    g: &mut PatchLanes,
) -> [f32; LANES] {
    let c11 = cfg.w_patch * cfg.w_patch11;
    let c7 = cfg.w_patch * cfg.w_patch7;
    let mut patch_term = [0.0f32; LANES];
    *g = [[[0.0; LANES]; 3]; PATCH_PIXELS];
    if c11 != 0.0 {
        ssim_term_lanes(
            src11,
            src_patch,
            tgt,
            (cfg.w_patch11, -0.5 * c11),
            &mut patch_term,
            g,
        );
    }
    if c7 != 0.0 {
        ssim_term_lanes(
            src7,
            src_patch,
            tgt,
            (cfg.w_patch7, -0.5 * c7),
            &mut patch_term,
            g,
        );
    }
    let mut pair = [0.0f32; LANES];
    for l in 0..LANES {
        pair[l] = cfg.w_patch * patch_term[l];
    }
    if cfg.w_center != 0.0 {
        let centre = PATCH_PIXELS / 2;
        for l in 0..LANES {
            let mut center = 0.0f32;
            for c in 0..3 {
                let (v, dv) = smooth_l1(src_patch[centre][c] - tgt[centre][c][l], cfg.center_beta);
                center += v;
                g[centre][c][l] += -cfg.w_center * dv;
            }
            pair[l] += cfg.w_center * center;
        }
    }
    pair
}

/// One SSIM term of [`pair_loss_lanes`]: `ssim_patch_target` of every lane's target against
/// the source (`src`, `a`), its `0.5 sum_c (1 - SSIM_c)` added to `patch_term` with weight
/// `w`, and `k` times its target gradient added to `g` over the whole patch (zero outside
/// the region), as `add_scaled_patch` does.
// Lane loops index several arrays at once.
#[allow(clippy::needless_range_loop)]
#[inline(always)]
fn ssim_term_lanes(
    src: &SsimSource,
    a: &Patch,
    b: &PatchLanes,
    (w, k): (f32, f32),
    patch_term: &mut [f32; LANES],
    g: &mut PatchLanes,
) {
    let (size, win) = (src.size, &src.w);
    let mut mu_b = [[0.0f32; LANES]; 3];
    for i in 0..size * size {
        let (wk, p) = (win[i], patch_index(size, i));
        for c in 0..3 {
            for l in 0..LANES {
                mu_b[c][l] += wk * b[p][c][l];
            }
        }
    }
    let mut var_b = [[0.0f32; LANES]; 3];
    let mut cov = [[0.0f32; LANES]; 3];
    for i in 0..size * size {
        let (wk, p) = (win[i], patch_index(size, i));
        for c in 0..3 {
            let x = a[p][c] - src.mu[c];
            for l in 0..LANES {
                let y = b[p][c][l] - mu_b[c][l];
                var_b[c][l] += wk * (y * y);
                cov[c][l] += wk * (x * y);
            }
        }
    }
    // SSIM per channel and lane and its derivatives with respect to the target's moments
    // (`ssim_and_moment_grads`).
    let mut ssim = [[0.0f32; LANES]; 3];
    let mut g_mu = [[0.0f32; LANES]; 3];
    let mut g_var = [[0.0f32; LANES]; 3];
    let mut g_cov = [[0.0f32; LANES]; 3];
    for c in 0..3 {
        for l in 0..LANES {
            let (s, _, gb) =
                ssim_channel(src.mu[c], mu_b[c][l], src.var[c], var_b[c][l], cov[c][l]);
            ssim[c][l] = s;
            [g_mu[c][l], g_var[c][l], g_cov[c][l]] = gb;
        }
    }
    for l in 0..LANES {
        let t = 0.5 * ((1.0 - ssim[0][l]) + (1.0 - ssim[1][l]) + (1.0 - ssim[2][l]));
        patch_term[l] += w * t;
    }
    // The target gradient (`target_backward`) times `k`, into `g`. Outside the region
    // `add_scaled_patch` adds `k * 0`, which is `-0` (`k < 0`: the weights are validated
    // `>= 0` and a zero weight skips the term), and `x + -0` is `x` for every `x`: only the
    // region's pixels change.
    for i in 0..size * size {
        let (wk, p) = (win[i], patch_index(size, i));
        for c in 0..3 {
            let x = a[p][c] - src.mu[c];
            for l in 0..LANES {
                let y = b[p][c][l] - mu_b[c][l];
                let d = side_grad(wk, g_mu[c][l], y, x, g_var[c][l], g_cov[c][l]);
                g[p][c][l] += k * d;
            }
        }
    }
}

/// [`chain_to_depth`] of the full patch for every lane.
// Lane loops index several arrays at once.
#[allow(clippy::needless_range_loop)]
#[inline(always)]
fn chain_lanes(g: &PatchLanes, dtgt: &PatchLanes) -> [f32; LANES] {
    let mut d = [0.0f32; LANES];
    for p in 0..PATCH_PIXELS {
        for c in 0..3 {
            for l in 0..LANES {
                d[l] += g[p][c][l] * dtgt[p][c][l];
            }
        }
    }
    d
}

/// `g += k * d` over the whole patch storage.
#[inline(always)]
fn add_scaled_patch(g: &mut Patch, k: f32, d: &Patch) {
    let mut p = 0;
    while p < PATCH_PIXELS {
        let mut c = 0;
        while c < 3 {
            g[p][c] += k * d[p][c];
            c += 1;
        }
        p += 1;
    }
}

/// The pair's derivative with respect to depth: the cotangent `g` times the warped patch's
/// derivative `dtgt`, pixels row-major over rows and columns `lo..hi`, channels innermost.
#[inline(always)]
fn chain_to_depth((lo, hi): (usize, usize), g: &Patch, dtgt: &Patch) -> f32 {
    let mut d_pair = 0.0f32;
    let mut r = lo;
    while r < hi {
        let mut col = lo;
        while col < hi {
            let p = r * PATCH + col;
            let mut c = 0;
            while c < 3 {
                d_pair += g[p][c] * dtgt[p][c];
                c += 1;
            }
            col += 1;
        }
        r += 1;
    }
    d_pair
}

#[cfg(test)]
mod tests {
    use super::*;

    const W: u32 = 64;
    const H: u32 = 48;
    /// Plane of the synthetic scene: world z = PLANE_Z, facing the cameras.
    const PLANE_Z: f64 = 2.0;

    /// Powers of two, so that with the identity pose the warp of a pixel onto itself is exact.
    fn intrinsics() -> Intrinsics {
        Intrinsics {
            width: W,
            height: H,
            fx: 64.0,
            fy: 64.0,
            cx: 32.0,
            cy: 24.0,
        }
    }

    /// Camera-to-world pose from Euler angles (degrees, R = Rz Ry Rx) and a translation.
    fn pose(rx: f64, ry: f64, rz: f64, t: [f64; 3]) -> Pose {
        let (a, b, c) = (rx.to_radians(), ry.to_radians(), rz.to_radians());
        let rxm = [
            [1.0, 0.0, 0.0],
            [0.0, a.cos(), -a.sin()],
            [0.0, a.sin(), a.cos()],
        ];
        let rym = [
            [b.cos(), 0.0, b.sin()],
            [0.0, 1.0, 0.0],
            [-b.sin(), 0.0, b.cos()],
        ];
        let rzm = [
            [c.cos(), -c.sin(), 0.0],
            [c.sin(), c.cos(), 0.0],
            [0.0, 0.0, 1.0],
        ];
        let mul = |p: [[f64; 3]; 3], q: [[f64; 3]; 3]| {
            let mut o = [[0.0f64; 3]; 3];
            for i in 0..3 {
                for j in 0..3 {
                    o[i][j] = (0..3).map(|k| p[i][k] * q[k][j]).sum();
                }
            }
            o
        };
        let r = mul(rzm, mul(rym, rxm));
        let mut m = [[0.0f32; 4]; 3];
        for i in 0..3 {
            for j in 0..3 {
                m[i][j] = r[i][j] as f32;
            }
            m[i][3] = t[i] as f32;
        }
        Pose { m }
    }

    /// Smooth texture on the plane (sums of sines, wavelengths 0.3 to 0.6 m, i.e. about 10 to
    /// 19 pixels at 2 m with fx = 64), values in [0.1, 0.9].
    fn texture(x: f64, y: f64) -> [f64; 3] {
        use std::f64::consts::TAU;
        [
            0.5 + 0.2 * (TAU * x / 0.45).sin() + 0.15 * (TAU * y / 0.37 + 0.3).sin(),
            0.5 + 0.2 * (TAU * (x + y) / 0.6 + 1.0).sin() + 0.1 * (TAU * y / 0.3).cos(),
            0.5 + 0.15 * (TAU * (x - 0.5 * y) / 0.5).sin() + 0.15 * (TAU * x / 0.33 + 2.0).cos(),
        ]
    }

    /// Renders the textured plane analytically (f64) from every pose into a packed buffer.
    fn render(k: &Intrinsics, poses: &[Pose], w: u32, h: u32) -> Vec<f32> {
        render_with(k, poses, w, h, texture)
    }

    /// [`render`] with another texture on the plane.
    fn render_with(
        k: &Intrinsics,
        poses: &[Pose],
        w: u32,
        h: u32,
        texture: impl Fn(f64, f64) -> [f64; 3],
    ) -> Vec<f32> {
        let mut data = Vec::with_capacity(poses.len() * (w * h * 3) as usize);
        for p in poses {
            let m = p.m.map(|r| r.map(|x| x as f64));
            for y in 0..h {
                for x in 0..w {
                    let d = [
                        (x as f64 - k.cx as f64) / k.fx as f64,
                        (y as f64 - k.cy as f64) / k.fy as f64,
                        1.0,
                    ];
                    let dw: Vec<f64> = (0..3)
                        .map(|i| (0..3).map(|j| m[i][j] * d[j]).sum())
                        .collect();
                    let o = [m[0][3], m[1][3], m[2][3]];
                    let t = if dw[2].abs() > 1e-12 {
                        (PLANE_Z - o[2]) / dw[2]
                    } else {
                        -1.0
                    };
                    let c = if t > 0.0 {
                        texture(o[0] + t * dw[0], o[1] + t * dw[1])
                    } else {
                        [0.0; 3]
                    };
                    data.extend(c.map(|v| v as f32));
                }
            }
        }
        data
    }

    /// Five cameras looking at the plane: frame 0 at the origin with the identity rotation
    /// (so the plane is exactly fronto-parallel at depth 2 for it), the others translated by
    /// 0.1 to 0.25 m and rotated by 1 to 3 degrees.
    fn scene_poses() -> Vec<Pose> {
        vec![
            Pose::IDENTITY,
            pose(0.0, 2.0, 0.0, [0.25, 0.0, 0.0]),
            pose(-1.5, 0.0, 0.0, [-0.1, 0.2, 0.0]),
            pose(0.0, 0.0, 3.0, [-0.25, 0.0, 0.1]),
            pose(1.0, -2.0, 0.0, [0.1, -0.2, -0.05]),
        ]
    }

    fn run(
        cfg: &WarpConfig,
        poses: &[Pose],
        data: &[f32],
        src: usize,
        u: u32,
        v: u32,
        d: f32,
    ) -> WarpResult {
        let img = PackedImages {
            width: W,
            height: H,
            data,
        };
        warp_pixel(cfg, &intrinsics(), poses, poses.len(), src, u, v, d, &img)
    }

    /// [`PackedImages`] marked as CPU memory: `warp_pixel` takes its CPU form
    /// ([`warp_view_lanes`], cache hints) over the same texels.
    struct CpuImages<'a>(PackedImages<'a>);

    impl FrameImages for CpuImages<'_> {
        const CPU: bool = true;
        fn size(&self) -> (u32, u32) {
            self.0.size()
        }
        fn texel(&self, frame: usize, x: u32, y: u32) -> [f32; 3] {
            self.0.texel(frame, x, y)
        }
    }

    /// `warp_pixel` of one pixel over the plain images and over their CPU form: asserts the
    /// same loss, depth gradient and view count bit for bit, and returns the view count.
    #[allow(clippy::too_many_arguments)]
    fn same_bits(
        cfg: &WarpConfig,
        k: &Intrinsics,
        poses: &[Pose],
        src: usize,
        (u, v): (u32, u32),
        d: f32,
        img: &PackedImages<'_>,
        cpu: &CpuImages<'_>,
    ) -> u32 {
        let n = poses.len();
        let a = warp_pixel(cfg, k, poses, n, src, u, v, d, img);
        let b = warp_pixel(cfg, k, poses, n, src, u, v, d, cpu);
        assert_eq!(
            (a.loss.to_bits(), a.d_depth.to_bits(), a.valid_views),
            (b.loss.to_bits(), b.d_depth.to_bits(), b.valid_views),
            "{cfg:?} src {src} ({u}, {v}) depth {d}"
        );
        a.valid_views
    }

    /// The CPU form of the patch stage gives the scalar form's bits: every source frame, a
    /// grid of pixels (borders and margins included), depths from behind the cameras' reach to
    /// far past the plane, NaN, the full patch and a smaller one (which keeps the scalar loop).
    #[test]
    fn cpu_form_equals_the_scalar_form() {
        // Not powers of two, so that a change in the order of operations shows.
        let k = Intrinsics {
            fx: 61.3,
            fy: 59.7,
            cx: 31.4,
            cy: 23.6,
            ..intrinsics()
        };
        let poses = scene_poses();
        let data = render(&k, &poses, W, H);
        let img = PackedImages {
            width: W,
            height: H,
            data: &data,
        };
        let cpu = CpuImages(img);
        let mut compared = 0;
        for (half, stride) in [(5u32, 1u32), (3, 1), (5, 3)] {
            let cfg = WarpConfig {
                half,
                min_views: 1,
                margin: 1.0,
                stride,
                ..WarpConfig::dim_slam()
            };
            for src in 0..poses.len() {
                for v in (0..H).step_by(3) {
                    for u in (0..W).step_by(3) {
                        for d in [0.05f32, 0.7, 1.9, 2.0, 2.3, 9.0, f32::NAN] {
                            let views = same_bits(&cfg, &k, &poses, src, (u, v), d, &img, &cpu);
                            compared += (views > 0) as usize;
                        }
                    }
                }
            }
        }
        assert!(compared > 1000, "only {compared} pixels had valid views");

        // A window of 12 frames: up to 11 valid views, i.e. a full group of `LANES` views and
        // a partial one, and the weight variants whose terms are skipped.
        let mut poses = scene_poses();
        for i in 1..8 {
            let f = i as f64;
            poses.push(pose(
                0.3 * f,
                -0.4 * f,
                0.2 * f,
                [0.03 * f, -0.02 * f, 0.01 * f],
            ));
        }
        let data = render(&k, &poses, W, H);
        let img = PackedImages {
            width: W,
            height: H,
            data: &data,
        };
        let cpu = CpuImages(img);
        let base = WarpConfig {
            min_views: 1,
            margin: 1.0,
            ..WarpConfig::dim_slam()
        };
        let mut most = 0;
        for cfg in [
            base,
            WarpConfig {
                w_patch11: 0.0,
                ..base
            },
            WarpConfig {
                w_patch7: 0.0,
                w_center: 0.0,
                ..base
            },
            WarpConfig {
                w_patch: 0.0,
                ..base
            },
        ] {
            for src in [0, 3, 9] {
                for v in (0..H).step_by(5) {
                    for u in (0..W).step_by(5) {
                        for d in [0.7f32, 1.9, 2.0, 2.3] {
                            let views = same_bits(&cfg, &k, &poses, src, (u, v), d, &img, &cpu);
                            most = most.max(views);
                        }
                    }
                }
            }
        }
        assert!(most > LANES as u32, "at most {most} valid views");
    }

    #[test]
    fn config_defaults_and_validation() {
        let c = WarpConfig::dim_slam();
        assert_eq!((c.half, c.margin, c.min_views), (5, 5.0, 4));
        assert_eq!(
            (
                c.w_patch11,
                c.w_patch7,
                c.w_patch,
                c.w_center,
                c.center_beta
            ),
            (0.2, 0.6, 0.5, 0.1, 0.1)
        );
        assert_eq!(c.few_views_weight, 0.0);
        assert_eq!(c, WarpConfig::default());
        assert!(c.validate().is_ok());
        for bad in [
            WarpConfig { half: 0, ..c },
            WarpConfig { half: 6, ..c },
            WarpConfig { stride: 0, ..c },
            WarpConfig { stride: 9, ..c },
            WarpConfig { margin: -1.0, ..c },
            WarpConfig {
                w_patch: f32::NAN,
                ..c
            },
            WarpConfig {
                w_center: -0.1,
                ..c
            },
            WarpConfig {
                center_beta: f32::INFINITY,
                ..c
            },
            WarpConfig {
                few_views_weight: 1.5,
                ..c
            },
            WarpConfig {
                few_views_weight: f32::NAN,
                ..c
            },
            WarpConfig {
                few_views_min_grad: -0.01,
                ..c
            },
            WarpConfig {
                few_views_min_grad: f32::INFINITY,
                ..c
            },
        ] {
            assert!(
                matches!(bad.validate(), Err(Error::InvalidConfig(_))),
                "{bad:?}"
            );
        }
    }

    #[test]
    fn packed_images_layout_and_bounds() {
        // 2 frames of 2x1: frame 1, pixel (1, 0) starts at ((1 * 1 + 0) * 2 + 1) * 3 = 9.
        let data: Vec<f32> = (0..12).map(|i| i as f32).collect();
        let img = PackedImages {
            width: 2,
            height: 1,
            data: &data,
        };
        assert_eq!(img.texel(1, 1, 0), [9.0, 10.0, 11.0]);
        assert_eq!(img.texel(0, 1, 0), [3.0, 4.0, 5.0]);
        assert_eq!(img.texel(2, 0, 0), [0.0; 3]);
    }

    /// Identical frames (every pose the identity, every image the same): with power-of-two
    /// intrinsics and depth 2 each patch point projects exactly onto its own pixel
    /// (`64 * (2 (u - 32) / 64) / 2 + 32 = u` in exact f32 steps), the bilinear fractions are 0,
    /// the warped patch equals the source patch bit for bit, SSIM is exactly 1 (`A1 = B1`,
    /// `A2 = B2` since `2 cov = var_a + var_b`), the centre difference is 0, and the SSIM and
    /// smooth-L1 gradients vanish exactly: loss 0, gradient 0, 4 views.
    #[test]
    fn identical_frames_give_zero() {
        let poses = vec![Pose::IDENTITY; 5];
        let data = render(&intrinsics(), &poses[..1], W, H).repeat(5);
        for (u, v) in [(32, 24), (20, 30), (41, 17)] {
            let r = run(&WarpConfig::dim_slam(), &poses, &data, 2, u, v, 2.0);
            assert_eq!(
                r,
                WarpResult {
                    loss: 0.0,
                    d_depth: 0.0,
                    valid_views: 4
                },
                "{u} {v}"
            );
        }
    }

    /// Constant images, source frame 0.5, the four others 0.55, identical poses. Per pair and
    /// channel: SSIM = (2 0.5 0.55 + C1) / (0.25 + 0.3025 + C1) = 0.5501 / 0.5526 = 0.9954759
    /// (var = cov = 0), so S11 = S7 = 1.5 (1 - 0.9954759) = 0.00678610; patch term
    /// 0.5 (0.2 + 0.6) 0.00678610 = 0.00271444; centre 3 smoothL1_0.1(-0.05) = 3 0.0125, times
    /// 0.1 = 0.00375; pair 0.00646444; 4 pairs 0.0258578. Constant images have zero bilinear
    /// slope, so the gradient is exactly 0.
    #[test]
    fn constant_brightness_shift_golden() {
        let poses = vec![Pose::IDENTITY; 5];
        let n = (W * H * 3) as usize;
        let mut data = vec![0.55f32; 5 * n];
        data[..n].fill(0.5);
        let r = run(&WarpConfig::dim_slam(), &poses, &data, 0, 30, 20, 1.7);
        assert_eq!(r.valid_views, 4);
        assert!((r.loss - 0.0258578).abs() < 2e-6, "{}", r.loss);
        assert_eq!(r.d_depth, 0.0);
        // Only the centre term: 4 0.1 0.0375 = 0.015.
        let cfg = WarpConfig {
            w_patch: 0.0,
            ..WarpConfig::dim_slam()
        };
        let r = run(&cfg, &poses, &data, 0, 30, 20, 1.7);
        assert!((r.loss - 0.015).abs() < 1e-7, "{}", r.loss);
    }

    #[test]
    fn true_depth_is_the_minimum() {
        let poses = scene_poses();
        let data = render(&intrinsics(), &poses, W, H);
        let cfg = WarpConfig::dim_slam();
        for (u, v) in [(32, 24), (27, 20), (37, 28), (30, 27)] {
            let at = |d: f32| run(&cfg, &poses, &data, 0, u, v, d);
            let (lo, mid, hi) = (at(1.8), at(2.0), at(2.2));
            assert_eq!((lo.valid_views, mid.valid_views, hi.valid_views), (4, 4, 4));
            // At the true depth only the bilinear error remains.
            assert!(
                mid.loss < 0.2 * lo.loss && mid.loss < 0.2 * hi.loss,
                "{u} {v}: {lo:?} {mid:?} {hi:?}"
            );
            // The gradient points towards 2.0 from both sides, also closer in.
            assert!(
                lo.d_depth < 0.0 && hi.d_depth > 0.0,
                "{u} {v}: {lo:?} {hi:?}"
            );
            let (l2, h2) = (at(1.95), at(2.05));
            assert!(
                l2.d_depth < 0.0 && h2.d_depth > 0.0,
                "{u} {v}: {l2:?} {h2:?}"
            );
        }
    }

    /// A pixel in the middle of a plain square (plain for 12.8 px around it in frame 0) sees
    /// only the plain colour through the dense 11x11 patch at every depth from 1.8 to 2.2 m
    /// (the parallax of the 0.25 m baselines moves the warped patch by at most 1.8 px): its
    /// loss has no minimum and its gradient is exactly zero. With the same 11x11 samples 3 px
    /// apart the patch reaches the square's textured surroundings, and the true depth (2 m)
    /// is the minimum again, with the gradient pointing towards it.
    #[test]
    fn a_dilated_patch_reaches_the_border_of_a_plain_region() {
        let poses = scene_poses();
        let plain = |x: f64, y: f64| {
            if x.abs() < 0.4 && y.abs() < 0.4 {
                [0.4, 0.5, 0.6]
            } else {
                texture(x, y)
            }
        };
        let data = render_with(&intrinsics(), &poses, W, H, plain);
        let dense = WarpConfig::dim_slam();
        for d in [1.8f32, 1.9, 2.0, 2.1, 2.2] {
            let r = run(&dense, &poses, &data, 0, 32, 24, d);
            assert_eq!(r.valid_views, 4, "{d}");
            assert_eq!(r.d_depth, 0.0, "{d}: {r:?}");
        }
        let dilated = WarpConfig { stride: 3, ..dense };
        let at = |d: f32| run(&dilated, &poses, &data, 0, 32, 24, d);
        let (lo, mid, hi) = (at(1.8), at(2.0), at(2.2));
        assert!(
            mid.loss < 0.5 * lo.loss && mid.loss < 0.5 * hi.loss,
            "{lo:?} {mid:?} {hi:?}"
        );
        assert!(lo.d_depth < 0.0 && hi.d_depth > 0.0, "{lo:?} {hi:?}");
    }

    /// Central finite difference of the loss on depth, in f32, step h = 1e-3 (moves the
    /// warped points by ~0.005 px). Error budget: f32 rounding of the loss (~1e-7 relative of
    /// a loss <= 1, / 2h gives ~1e-4) plus the kinks of the piecewise-linear bilinear
    /// interpolation that some of the 484 warped points cross inside +-h (the slope of the
    /// smooth texture changes by ~0.05 per pixel). Tolerance |analytic - fd| <= 1e-3 +
    /// 5e-3 |fd|; measured worst case 5.1e-3 at |fd| = 1.77 (half the tolerance), typical 1e-4.
    #[test]
    fn gradient_matches_finite_difference() {
        let poses = scene_poses();
        let data = render(&intrinsics(), &poses, W, H);
        let dim = WarpConfig::dim_slam();
        let configs = [
            dim,
            // Small 7x7 patch (both SSIM terms on 7x7), patch term only, 1 view.
            WarpConfig {
                half: 3,
                min_views: 1,
                w_center: 0.0,
                ..dim
            },
            // Centre term only.
            WarpConfig {
                w_patch: 0.0,
                ..dim
            },
            // A dilated patch: 11x11 samples 2 px apart.
            WarpConfig { stride: 2, ..dim },
        ];
        let h = 1e-3f32;
        let mut max_g = 0.0f32;
        for cfg in &configs {
            for (src, u, v) in [
                (0, 32, 24),
                (0, 27, 20),
                (0, 37, 28),
                (3, 30, 27),
                (2, 33, 22),
            ] {
                for d in [1.7f32, 1.8, 1.9, 2.05, 2.2, 2.3] {
                    let r = run(cfg, &poses, &data, src, u, v, d);
                    assert!(
                        r.valid_views == 4 && r.loss > 0.0,
                        "{cfg:?} {src} {u} {v} {d}: {r:?}"
                    );
                    let lp = run(cfg, &poses, &data, src, u, v, d + h).loss;
                    let lm = run(cfg, &poses, &data, src, u, v, d - h).loss;
                    let fd = (lp - lm) / (2.0 * h);
                    assert!(
                        (r.d_depth - fd).abs() <= 1e-3 + 5e-3 * fd.abs(),
                        "{cfg:?} {src} {u} {v} {d}: {} vs {fd}",
                        r.d_depth
                    );
                    max_g = max_g.max(r.d_depth.abs());
                }
            }
        }
        // Not vacuous: the gradients are O(1).
        assert!(max_g > 1.0, "{max_g}");
    }

    /// Validity from the centre projection, with exact dyadic arithmetic: source = identity,
    /// pixel (16, 24), depth 2, so the centre is X = (-0.5, 0, 2). A frame translated by
    /// (tx, ty, 0) without rotation sees it at u' = 16 - 32 tx, v' = 24 - 32 ty, exactly.
    /// The margins are open intervals: 5 < u' < 58 and 5 < v' < 42.
    #[test]
    fn validity_margins_and_behind() {
        let t = |tx: f64, ty: f64| pose(0.0, 0.0, 0.0, [tx, ty, 0.0]);
        let frames: Vec<(Pose, bool)> = vec![
            (Pose::IDENTITY, true),                        // source (never counted)
            (t(0.328125, 0.0), true),                      // u' = 5.5
            (t(0.34375, 0.0), false),                      // u' = 5.0: on the margin, out
            (pose(0.0, 180.0, 0.0, [0.0; 3]), false),      // looks away: z = -2
            (t(0.0, 0.0), true),                           // same view
            (t(-1.3125, 0.0), false),                      // u' = 58.0, out
            (t(-1.296875, 0.0), true),                     // u' = 57.5
            (t(0.0, 0.59375), false),                      // v' = 5.0, out
            (t(0.0, 0.578125), true),                      // v' = 5.5
            (t(0.0, -0.5625), false),                      // v' = 42.0, out
            (t(0.0, -0.546875), true),                     // v' = 41.5
            (t(0.0, 0.0), true),                           // same view again
            (pose(0.0, 0.0, 0.0, [0.0, 0.0, 2.5]), false), // plane behind: z = -0.5
        ];
        let poses: Vec<Pose> = frames.iter().map(|f| f.0).collect();
        let data = render(&intrinsics(), &poses, W, H);
        let k = intrinsics();
        let expected = frames.iter().skip(1).filter(|f| f.1).count() as u32;
        assert_eq!(expected, 6);
        let cfg = WarpConfig {
            min_views: 1,
            ..WarpConfig::dim_slam()
        };
        let full = run(&cfg, &poses, &data, 0, 16, 24, 2.0);
        assert_eq!(full.valid_views, expected);
        // The loss equals that of the window holding only the valid frames, bit for bit
        // (same pairs, same order), so the invalid frames contributed nothing.
        let keep: Vec<usize> = (0..frames.len())
            .filter(|&j| j == 0 || frames[j].1)
            .collect();
        let kp: Vec<Pose> = keep.iter().map(|&j| poses[j]).collect();
        let n = (W * H * 3) as usize;
        let kd: Vec<f32> = keep
            .iter()
            .flat_map(|&j| data[j * n..(j + 1) * n].iter().copied())
            .collect();
        let sub = run(&cfg, &kp, &kd, 0, 16, 24, 2.0);
        assert_eq!(sub.valid_views, expected);
        assert_eq!(
            (full.loss.to_bits(), full.d_depth.to_bits()),
            (sub.loss.to_bits(), sub.d_depth.to_bits())
        );
        // ...and it is not trivially zero (depth 2 is the true depth, so only the bilinear
        // error of the half-pixel shifts remains, ~7e-4; an excluded frame counted by mistake
        // would add a pair and change the bits above).
        assert!(full.loss > 1e-4 && full.d_depth != 0.0, "{full:?}");
        // min_views above the count: nothing, but the count is reported.
        for mv in [expected + 1, 100] {
            let r = run(
                &WarpConfig {
                    min_views: mv,
                    ..cfg
                },
                &poses,
                &data,
                0,
                16,
                24,
                2.0,
            );
            assert_eq!(
                r,
                WarpResult {
                    loss: 0.0,
                    d_depth: 0.0,
                    valid_views: expected
                }
            );
        }
        let r = run(
            &WarpConfig {
                min_views: expected,
                ..cfg
            },
            &poses,
            &data,
            0,
            16,
            24,
            2.0,
        );
        assert_eq!(r, full);
        // Below min_views with `few_views_weight`: the same pairs, their sums scaled once.
        for w in [0.25f32, 0.3, 1.0] {
            let few = WarpConfig {
                min_views: expected + 1,
                few_views_weight: w,
                ..cfg
            };
            let r = run(&few, &poses, &data, 0, 16, 24, 2.0);
            assert_eq!(r.valid_views, expected);
            assert_eq!(
                (r.loss.to_bits(), r.d_depth.to_bits()),
                ((full.loss * w).to_bits(), (full.d_depth * w).to_bits()),
                "weight {w}"
            );
            // At min_views the weight does not act; with no valid view there is no term.
            let at = WarpConfig {
                min_views: expected,
                ..few
            };
            assert_eq!(run(&at, &poses, &data, 0, 16, 24, 2.0), full);
            let none = run(&few, &poses, &data, 0, 16, 24, f32::NAN);
            assert_eq!((none.loss, none.d_depth, none.valid_views), (0.0, 0.0, 0));
        }
        // Depth -1 puts the centre at (0.25, 0, -1), behind every camera except the one
        // looking away (frame 3, R = diag(-1, 1, -1)), which sees it at (-0.25, 0, 1), i.e.
        // u' = 64 (-0.25) + 32 = 16, v' = 24: one view. A NaN depth is valid nowhere.
        let r = run(&cfg, &poses, &data, 0, 16, 24, -1.0);
        assert_eq!(r.valid_views, 1);
        let r = run(&cfg, &poses, &data, 0, 16, 24, f32::NAN);
        assert_eq!(
            r,
            WarpResult {
                loss: 0.0,
                d_depth: 0.0,
                valid_views: 0
            }
        );
        // n_frames limits the window; a source outside it gives the zero result.
        let img = PackedImages {
            width: W,
            height: H,
            data: &data,
        };
        let r = warp_pixel(&cfg, &k, &poses[..], 3, 0, 16, 24, 2.0, &img);
        assert_eq!(r.valid_views, 1);
        let r = warp_pixel(&cfg, &k, &poses[..], 3, 3, 16, 24, 2.0, &img);
        assert_eq!(r, WarpResult::default());
        let r = warp_pixel(&cfg, &k, &poses[..], 1000, 0, 16, 24, 2.0, &img);
        assert_eq!(r, full);
    }

    /// The texture test of the few-views term: a patch of vertical stripes (gradient 0.1
    /// per pixel along x, none along y) keeps the pairs whose epipolar line through the
    /// pixel runs along x (a sideways baseline, or one along the optical axis for a pixel
    /// beside the principal point) and drops those along y; the RMS gradient along x is 0.1
    /// (up to rounding), so a threshold just below keeps and one just above drops.
    #[test]
    fn few_views_texture_test_follows_the_epipolar_line() {
        let k = intrinsics();
        let mut patch: Patch = [[0.0; 3]; PATCH_PIXELS];
        for (p, px) in patch.iter_mut().enumerate() {
            let dx = (p % PATCH) as f32 - MAX_HALF as f32;
            *px = [0.5 + 0.1 * dx; 3];
        }
        let at = |t: [f32; 3]| {
            let mut m = Pose::IDENTITY;
            (m.m[0][3], m.m[1][3], m.m[2][3]) = (t[0], t[1], t[2]);
            m
        };
        // frames 1..4: along x, along y, along z, along x and y
        let poses = [
            Pose::IDENTITY,
            at([0.1, 0.0, 0.0]),
            at([0.0, 0.1, 0.0]),
            at([0.0, 0.0, 0.2]),
            at([0.1, 0.1, 0.0]),
        ];
        let cfg = WarpConfig::dim_slam();
        let test = |min_grad: f32, (u, v): (u32, u32)| {
            textured_pairs(
                &cfg,
                min_grad,
                &k,
                &poses[..],
                (u, v),
                &poses[0],
                &patch,
                0b11110,
            )
        };
        // beside the principal point (cx + 10): z moves along x too; on it, z gives no line
        assert_eq!(test(0.099, (42, 24)), 0b00010 | 0b01000);
        assert_eq!(test(0.099, (32, 24)), 0b00010);
        // the diagonal baseline: RMS 0.1 / sqrt(2) along it
        assert_eq!(test(0.07, (32, 24)), 0b10010);
        assert_eq!(test(0.072, (32, 24)), 0b00010);
        assert_eq!(test(0.101, (42, 24)), 0);
        // and a flat patch keeps nothing
        let flat: Patch = [[0.3; 3]; PATCH_PIXELS];
        assert_eq!(
            textured_pairs(
                &cfg,
                1e-6,
                &k,
                &poses[..],
                (32, 24),
                &poses[0],
                &flat,
                0b11110
            ),
            0
        );
    }

    /// A grazing view: camera 1 cm in front of the plane, 5 cm to the left of the centre point,
    /// looking along +x (90 degrees about y). Its centre is valid (camera coordinates
    /// (-0.01, 0, 0.05), u' = 64 (-0.2) + 32 = 19.2, v' = 24), but the left columns of the
    /// patch (world x < -0.05) are behind it and the next ones project far outside the image.
    /// Those points are clamped with zero gradient: the result stays finite and the gradient
    /// still matches the finite difference. The warp is ~25x more sensitive to depth here
    /// (du'/dD = -64 / 0.05 = -1280 px/m at the centre), so the step is h = 2^-14 (0.08 px,
    /// exact in f32 next to these depths); same tolerance as above, measured worst 0.085 at
    /// |fd| = 38 (0.2 %).
    #[test]
    fn grazing_view_stays_finite() {
        let poses = vec![Pose::IDENTITY, pose(0.0, 90.0, 0.0, [-0.05, 0.0, 1.99])];
        let data = render(&intrinsics(), &poses, W, H);
        let cfg = WarpConfig {
            min_views: 1,
            ..WarpConfig::dim_slam()
        };
        let h = 1.0f32 / 16384.0;
        for d in [1.995f32, 2.0, 2.003] {
            let r = run(&cfg, &poses, &data, 0, 32, 24, d);
            assert_eq!(r.valid_views, 1, "{d}");
            assert!(
                r.loss.is_finite() && r.loss > 0.0 && r.d_depth.is_finite(),
                "{d}: {r:?}"
            );
            let fd = (run(&cfg, &poses, &data, 0, 32, 24, d + h).loss
                - run(&cfg, &poses, &data, 0, 32, 24, d - h).loss)
                / (2.0 * h);
            assert!(
                (r.d_depth - fd).abs() <= 1e-3 + 5e-3 * fd.abs(),
                "{d}: {} vs {fd}",
                r.d_depth
            );
        }
    }
}
