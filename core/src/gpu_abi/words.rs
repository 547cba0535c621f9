//! Layouts and scene constants as flat `u32` words (f32 fields as their bits), the form in
//! which they reach the shaders through a storage buffer.
//!
//! Both directions live here, so the shader (decode) and the Vulkan host (encode) share one
//! definition. Decoders never panic: words past the end of the slice read as 0.
//!
//! | item | words | order |
//! |---|---|---|
//! | [`Aabb`] | [`AABB`] = 6 | min x y z, max x y z |
//! | [`Pose`] | [`POSE`] = 12 | `m` row-major |
//! | [`Intrinsics`] | [`INTRINSICS`] = 6 | width, height, fx, fy, cx, cy |
//! | [`GridLayout`] | [`GRID_LAYOUT`] = 98 | kind, levels, channels, param_count, aabb (6), then per level (8): res (3), offset, plane_offsets (3), line_offsets (3), count |
//! | [`MlpLayout`] | [`MLP_LAYOUT`] = 15 | n_in, hidden, hidden_layers, n_out, param_count, weight_offsets (5), bias_offsets (5) |
//! | [`GridConfig`] | [`GRID_CONFIG`] = 11 | kind, levels, channels, cell_sizes (8) |
//! | [`ModelConfig`] | [`MODEL_CONFIG`] = 40 | aabb (6), geometry grid config (11), appearance grid config (11), hidden, hidden_layers, dual_path, render_mode, samples, beta_init, grid_init_std, sdf_bias_init, max_depth, min_transmittance, far_samples, far_depth |
//! | [`ModelLayout`] | [`MODEL_LAYOUT`] = 263 | config, geometry grid layout, appearance grid layout, geometry MLP layout, appearance MLP layout |
//! | [`MappingLoss`] | [`MAPPING_LOSS`] = 26 | lambda_color, lambda_warp, color_scale, warp_scale, color_to_geometry, seed, warp (half, margin, min_views, w_patch11, w_patch7, w_patch, w_center, center_beta), lambda_depth_prior, depth_prior, depth_prior_near, planar (weight, edge, beta), warp stride, planar gated, lambda_plane, warp few_views_weight, warp few_views_min_grad, warp min_grad |
//! | window | [`WINDOW`] = 451 | intrinsics, frames, image width, image height, slots ([`MAX_WINDOW`]), poses ([`MAX_WINDOW`] x [`POSE`]), mapping loss, where the depth priors start in the image buffer ([`WINDOW_PRIORS`]) |

use crate::camera::{Intrinsics, Pose, PoseRead};
use crate::field::grid::{GridConfig, GridKind, GridLayout, LevelLayout, MAX_LEVELS};
use crate::field::mlp::{MlpLayout, MAX_HIDDEN_LAYERS};
use crate::field::model::{ModelConfig, ModelLayout};
use crate::field::render::RenderMode;
use crate::loss::planar::PlanarConfig;
use crate::loss::warp::{WarpConfig, MAX_WINDOW};
use crate::train::pixel::MappingLoss;
use crate::Aabb;

/// Words of an [`Aabb`].
pub const AABB: usize = 6;
/// Words of a [`Pose`].
pub const POSE: usize = 12;
/// Words of an [`Intrinsics`].
pub const INTRINSICS: usize = 6;
/// Words of one [`LevelLayout`].
pub const LEVEL_LAYOUT: usize = 11;
/// Words of a [`GridLayout`].
pub const GRID_LAYOUT: usize = 4 + AABB + MAX_LEVELS * LEVEL_LAYOUT;
/// Words of an [`MlpLayout`].
pub const MLP_LAYOUT: usize = 5 + 2 * (MAX_HIDDEN_LAYERS + 1);

/// Words of a [`GridConfig`].
pub const GRID_CONFIG: usize = 3 + MAX_LEVELS;
/// Words of a [`ModelConfig`].
pub const MODEL_CONFIG: usize = AABB + 2 * GRID_CONFIG + 12;
/// Words of a [`ModelLayout`].
pub const MODEL_LAYOUT: usize = MODEL_CONFIG + 2 * GRID_LAYOUT + 2 * MLP_LAYOUT;

/// Offset of the two grid split points after the model layout in the model words (see
/// [`split`]).
pub const SPLITS: usize = MODEL_LAYOUT;
/// Words of the model buffer the shaders read: the layout, then the split points of the
/// geometry and the appearance grid.
pub const MODEL_WORDS: usize = MODEL_LAYOUT + 2;

/// Split point `k` (0: geometry grid, 1: appearance grid): the number of the group's
/// parameters in its first binding; `u32::MAX` (or a missing word, read as 0 and treated as
/// "no split" only if the host wrote it so) means all of them.
#[inline(always)]
pub fn split(w: &[u32], k: usize) -> usize {
    let s = word(w, SPLITS + k);
    if s == u32::MAX {
        usize::MAX
    } else {
        s as usize
    }
}

/// Words of a [`MappingLoss`].
pub const MAPPING_LOSS: usize = 26;
/// Offset of the slot table in the window words.
pub const WINDOW_SLOTS: usize = INTRINSICS + 3;
/// Offset of the poses in the window words.
pub const WINDOW_POSES: usize = WINDOW_SLOTS + MAX_WINDOW;
/// Offset of the mapping loss in the window words.
pub const WINDOW_LOSS: usize = WINDOW_POSES + MAX_WINDOW * POSE;
/// Offset of the per-pixel depth priors' word in the window words: where the targets start
/// in the image store's buffer (in words, one `f32` per pixel after the RGBA8 slots;
/// 0 = the store has none).
pub const WINDOW_PRIORS: usize = WINDOW_LOSS + MAPPING_LOSS;
/// Words of a mapping window (see the table above).
pub const WINDOW: usize = WINDOW_PRIORS + 1;

/// Word `i`, or 0 past the end.
#[inline(always)]
pub fn word(w: &[u32], i: usize) -> u32 {
    if i < w.len() {
        w[i]
    } else {
        0
    }
}

#[inline(always)]
fn fword(w: &[u32], i: usize) -> f32 {
    f32::from_bits(word(w, i))
}

#[inline(always)]
fn put(w: &mut [u32], i: usize, v: u32) {
    if i < w.len() {
        w[i] = v;
    }
}

/// Decodes an [`Aabb`] from the [`AABB`] words at `at` (words past the end of `w`
/// read as 0).
pub fn aabb_from_words(w: &[u32], at: usize) -> Aabb {
    Aabb {
        min: [fword(w, at), fword(w, at + 1), fword(w, at + 2)],
        max: [fword(w, at + 3), fword(w, at + 4), fword(w, at + 5)],
    }
}

/// Encodes an [`Aabb`] into the [`AABB`] words at `at` (words past the end of `w`
/// are skipped).
pub fn aabb_to_words(b: &Aabb, w: &mut [u32], at: usize) {
    let mut a = 0;
    while a < 3 {
        put(w, at + a, b.min[a].to_bits());
        put(w, at + 3 + a, b.max[a].to_bits());
        a += 1;
    }
}

/// Decodes a [`Pose`] from the [`POSE`] words at `at` (words past the end of `w`
/// read as 0).
pub fn pose_from_words(w: &[u32], at: usize) -> Pose {
    let mut m = [[0.0f32; 4]; 3];
    let mut r = 0;
    while r < 3 {
        let mut c = 0;
        while c < 4 {
            m[r][c] = fword(w, at + r * 4 + c);
            c += 1;
        }
        r += 1;
    }
    Pose { m }
}

/// Encodes a [`Pose`] into the [`POSE`] words at `at` (words past the end of `w`
/// are skipped).
pub fn pose_to_words(p: &Pose, w: &mut [u32], at: usize) {
    let mut r = 0;
    while r < 3 {
        let mut c = 0;
        while c < 4 {
            put(w, at + r * 4 + c, p.m[r][c].to_bits());
            c += 1;
        }
        r += 1;
    }
}

/// Decodes an [`Intrinsics`] from the [`INTRINSICS`] words at `at` (words past the end of `w`
/// read as 0).
pub fn intrinsics_from_words(w: &[u32], at: usize) -> Intrinsics {
    Intrinsics {
        width: word(w, at),
        height: word(w, at + 1),
        fx: fword(w, at + 2),
        fy: fword(w, at + 3),
        cx: fword(w, at + 4),
        cy: fword(w, at + 5),
    }
}

/// Encodes an [`Intrinsics`] into the [`INTRINSICS`] words at `at` (words past the end of `w`
/// are skipped).
pub fn intrinsics_to_words(k: &Intrinsics, w: &mut [u32], at: usize) {
    put(w, at, k.width);
    put(w, at + 1, k.height);
    put(w, at + 2, k.fx.to_bits());
    put(w, at + 3, k.fy.to_bits());
    put(w, at + 4, k.cx.to_bits());
    put(w, at + 5, k.cy.to_bits());
}

fn u32x3(w: &[u32], at: usize) -> [u32; 3] {
    [word(w, at), word(w, at + 1), word(w, at + 2)]
}

fn put_u32x3(w: &mut [u32], at: usize, v: [u32; 3]) {
    put(w, at, v[0]);
    put(w, at + 1, v[1]);
    put(w, at + 2, v[2]);
}

/// Decodes a [`GridLayout`] from the [`GRID_LAYOUT`] words at `at` (words past the end of `w`
/// read as 0).
pub fn grid_layout_from_words(w: &[u32], at: usize) -> GridLayout {
    let kind = grid_kind(word(w, at));
    let mut level = [LevelLayout {
        res: [0; 3],
        offset: 0,
        plane_offsets: [0; 3],
        line_offsets: [0; 3],
        count: 0,
    }; MAX_LEVELS];
    let mut l = 0;
    while l < MAX_LEVELS {
        let b = at + 4 + AABB + l * LEVEL_LAYOUT;
        level[l] = LevelLayout {
            res: u32x3(w, b),
            offset: word(w, b + 3),
            plane_offsets: u32x3(w, b + 4),
            line_offsets: u32x3(w, b + 7),
            count: word(w, b + 10),
        };
        l += 1;
    }
    GridLayout {
        kind,
        levels: word(w, at + 1),
        channels: word(w, at + 2),
        aabb: aabb_from_words(w, at + 4),
        level,
        param_count: word(w, at + 3),
    }
}

/// Encodes a [`GridLayout`] into the [`GRID_LAYOUT`] words at `at` (words past the end of `w`
/// are skipped).
pub fn grid_layout_to_words(g: &GridLayout, w: &mut [u32], at: usize) {
    put(w, at, g.kind as u32);
    put(w, at + 1, g.levels);
    put(w, at + 2, g.channels);
    put(w, at + 3, g.param_count);
    aabb_to_words(&g.aabb, w, at + 4);
    let mut l = 0;
    while l < MAX_LEVELS {
        let b = at + 4 + AABB + l * LEVEL_LAYOUT;
        let lv = &g.level[l];
        put_u32x3(w, b, lv.res);
        put(w, b + 3, lv.offset);
        put_u32x3(w, b + 4, lv.plane_offsets);
        put_u32x3(w, b + 7, lv.line_offsets);
        put(w, b + 10, lv.count);
        l += 1;
    }
}

/// Decodes an [`MlpLayout`] from the [`MLP_LAYOUT`] words at `at` (words past the end of `w`
/// read as 0).
pub fn mlp_layout_from_words(w: &[u32], at: usize) -> MlpLayout {
    let mut weight_offsets = [0u32; MAX_HIDDEN_LAYERS + 1];
    let mut bias_offsets = [0u32; MAX_HIDDEN_LAYERS + 1];
    let mut k = 0;
    while k <= MAX_HIDDEN_LAYERS {
        weight_offsets[k] = word(w, at + 5 + k);
        bias_offsets[k] = word(w, at + 6 + MAX_HIDDEN_LAYERS + k);
        k += 1;
    }
    MlpLayout {
        n_in: word(w, at),
        hidden: word(w, at + 1),
        hidden_layers: word(w, at + 2),
        n_out: word(w, at + 3),
        weight_offsets,
        bias_offsets,
        param_count: word(w, at + 4),
    }
}

/// Encodes an [`MlpLayout`] into the [`MLP_LAYOUT`] words at `at` (words past the end of `w`
/// are skipped).
pub fn mlp_layout_to_words(m: &MlpLayout, w: &mut [u32], at: usize) {
    put(w, at, m.n_in);
    put(w, at + 1, m.hidden);
    put(w, at + 2, m.hidden_layers);
    put(w, at + 3, m.n_out);
    put(w, at + 4, m.param_count);
    let mut k = 0;
    while k <= MAX_HIDDEN_LAYERS {
        put(w, at + 5 + k, m.weight_offsets[k]);
        put(w, at + 6 + MAX_HIDDEN_LAYERS + k, m.bias_offsets[k]);
        k += 1;
    }
}

fn grid_kind(w: u32) -> GridKind {
    if w == GridKind::Dense as u32 {
        GridKind::Dense
    } else {
        GridKind::Factorized
    }
}

fn render_mode(w: u32) -> RenderMode {
    if w == RenderMode::SdfDirect as u32 {
        RenderMode::SdfDirect
    } else if w == RenderMode::Occupancy as u32 {
        RenderMode::Occupancy
    } else {
        RenderMode::SdfDensity
    }
}

/// Decodes a [`GridConfig`] from the [`GRID_CONFIG`] words at `at` (words past the end of `w`
/// read as 0).
pub fn grid_config_from_words(w: &[u32], at: usize) -> GridConfig {
    let mut cell_sizes = [0.0f32; MAX_LEVELS];
    let mut l = 0;
    while l < MAX_LEVELS {
        cell_sizes[l] = fword(w, at + 3 + l);
        l += 1;
    }
    GridConfig {
        kind: grid_kind(word(w, at)),
        levels: word(w, at + 1),
        channels: word(w, at + 2),
        cell_sizes,
    }
}

/// Encodes a [`GridConfig`] into the [`GRID_CONFIG`] words at `at` (words past the end of `w`
/// are skipped).
pub fn grid_config_to_words(c: &GridConfig, w: &mut [u32], at: usize) {
    put(w, at, c.kind as u32);
    put(w, at + 1, c.levels);
    put(w, at + 2, c.channels);
    let mut l = 0;
    while l < MAX_LEVELS {
        put(w, at + 3 + l, c.cell_sizes[l].to_bits());
        l += 1;
    }
}

/// Decodes a [`ModelConfig`] from the [`MODEL_CONFIG`] words at `at` (words past the end of `w`
/// read as 0).
pub fn model_config_from_words(w: &[u32], at: usize) -> ModelConfig {
    let b = at + AABB + 2 * GRID_CONFIG;
    ModelConfig {
        aabb: aabb_from_words(w, at),
        geometry_grid: grid_config_from_words(w, at + AABB),
        appearance_grid: grid_config_from_words(w, at + AABB + GRID_CONFIG),
        hidden: word(w, b),
        hidden_layers: word(w, b + 1),
        dual_path: word(w, b + 2) != 0,
        render_mode: render_mode(word(w, b + 3)),
        samples: word(w, b + 4),
        beta_init: fword(w, b + 5),
        grid_init_std: fword(w, b + 6),
        sdf_bias_init: fword(w, b + 7),
        max_depth: fword(w, b + 8),
        min_transmittance: fword(w, b + 9),
        far_samples: word(w, b + 10),
        far_depth: fword(w, b + 11),
    }
}

/// Encodes a [`ModelConfig`] into the [`MODEL_CONFIG`] words at `at` (words past the end of `w`
/// are skipped).
pub fn model_config_to_words(c: &ModelConfig, w: &mut [u32], at: usize) {
    aabb_to_words(&c.aabb, w, at);
    grid_config_to_words(&c.geometry_grid, w, at + AABB);
    grid_config_to_words(&c.appearance_grid, w, at + AABB + GRID_CONFIG);
    let b = at + AABB + 2 * GRID_CONFIG;
    put(w, b, c.hidden);
    put(w, b + 1, c.hidden_layers);
    put(w, b + 2, c.dual_path as u32);
    put(w, b + 3, c.render_mode as u32);
    put(w, b + 4, c.samples);
    put(w, b + 5, c.beta_init.to_bits());
    put(w, b + 6, c.grid_init_std.to_bits());
    put(w, b + 7, c.sdf_bias_init.to_bits());
    put(w, b + 8, c.max_depth.to_bits());
    put(w, b + 9, c.min_transmittance.to_bits());
    put(w, b + 10, c.far_samples);
    put(w, b + 11, c.far_depth.to_bits());
}

/// Decodes a [`ModelLayout`] without re-validating it (the host built it with
/// `ModelLayout::new`).
pub fn model_layout_from_words(w: &[u32], at: usize) -> ModelLayout {
    let g = at + MODEL_CONFIG;
    let m = g + 2 * GRID_LAYOUT;
    ModelLayout {
        config: model_config_from_words(w, at),
        geometry_grid: grid_layout_from_words(w, g),
        appearance_grid: grid_layout_from_words(w, g + GRID_LAYOUT),
        geometry_mlp: mlp_layout_from_words(w, m),
        appearance_mlp: mlp_layout_from_words(w, m + MLP_LAYOUT),
    }
}

/// Encodes a [`ModelLayout`] into the [`MODEL_LAYOUT`] words at `at` (words past the end of `w`
/// are skipped).
pub fn model_layout_to_words(l: &ModelLayout, w: &mut [u32], at: usize) {
    let g = at + MODEL_CONFIG;
    let m = g + 2 * GRID_LAYOUT;
    model_config_to_words(&l.config, w, at);
    grid_layout_to_words(&l.geometry_grid, w, g);
    grid_layout_to_words(&l.appearance_grid, w, g + GRID_LAYOUT);
    mlp_layout_to_words(&l.geometry_mlp, w, m);
    mlp_layout_to_words(&l.appearance_mlp, w, m + MLP_LAYOUT);
}

/// Decodes a [`MappingLoss`] from the [`MAPPING_LOSS`] words at `at` (words past the end of `w`
/// read as 0).
pub fn mapping_loss_from_words(w: &[u32], at: usize) -> MappingLoss {
    MappingLoss {
        lambda_color: fword(w, at),
        lambda_warp: fword(w, at + 1),
        color_scale: fword(w, at + 2),
        warp_scale: fword(w, at + 3),
        color_to_geometry: word(w, at + 4) != 0,
        seed: word(w, at + 5),
        warp: WarpConfig {
            half: word(w, at + 6),
            margin: fword(w, at + 7),
            min_views: word(w, at + 8),
            w_patch11: fword(w, at + 9),
            w_patch7: fword(w, at + 10),
            w_patch: fword(w, at + 11),
            w_center: fword(w, at + 12),
            center_beta: fword(w, at + 13),
            stride: word(w, at + 20),
            few_views_weight: fword(w, at + 23),
            few_views_min_grad: fword(w, at + 24),
            min_grad: fword(w, at + 25),
        },
        lambda_depth_prior: fword(w, at + 14),
        depth_prior: fword(w, at + 15),
        depth_prior_near: fword(w, at + 16),
        planar: PlanarConfig {
            weight: fword(w, at + 17),
            edge: fword(w, at + 18),
            beta: fword(w, at + 19),
            gated: word(w, at + 21) != 0,
        },
        lambda_plane: fword(w, at + 22),
    }
}

/// Encodes a [`MappingLoss`] into the [`MAPPING_LOSS`] words at `at` (words past the end of `w`
/// are skipped).
pub fn mapping_loss_to_words(l: &MappingLoss, w: &mut [u32], at: usize) {
    put(w, at, l.lambda_color.to_bits());
    put(w, at + 1, l.lambda_warp.to_bits());
    put(w, at + 2, l.color_scale.to_bits());
    put(w, at + 3, l.warp_scale.to_bits());
    put(w, at + 4, l.color_to_geometry as u32);
    put(w, at + 5, l.seed);
    put(w, at + 6, l.warp.half);
    put(w, at + 7, l.warp.margin.to_bits());
    put(w, at + 8, l.warp.min_views);
    put(w, at + 9, l.warp.w_patch11.to_bits());
    put(w, at + 10, l.warp.w_patch7.to_bits());
    put(w, at + 11, l.warp.w_patch.to_bits());
    put(w, at + 12, l.warp.w_center.to_bits());
    put(w, at + 13, l.warp.center_beta.to_bits());
    put(w, at + 14, l.lambda_depth_prior.to_bits());
    put(w, at + 15, l.depth_prior.to_bits());
    put(w, at + 16, l.depth_prior_near.to_bits());
    put(w, at + 17, l.planar.weight.to_bits());
    put(w, at + 18, l.planar.edge.to_bits());
    put(w, at + 19, l.planar.beta.to_bits());
    put(w, at + 20, l.warp.stride);
    put(w, at + 21, l.planar.gated as u32);
    put(w, at + 22, l.lambda_plane.to_bits());
    put(w, at + 23, l.warp.few_views_weight.to_bits());
    put(w, at + 24, l.warp.few_views_min_grad.to_bits());
    put(w, at + 25, l.warp.min_grad.to_bits());
}

/// Window frame count, image size and slot table from window words at 0.
pub fn window_frames(w: &[u32]) -> (usize, u32, u32, [u32; MAX_WINDOW]) {
    let mut slots = [0u32; MAX_WINDOW];
    let mut i = 0;
    while i < MAX_WINDOW {
        slots[i] = word(w, WINDOW_SLOTS + i);
        i += 1;
    }
    let n = word(w, INTRINSICS) as usize;
    let n = if n > MAX_WINDOW { MAX_WINDOW } else { n };
    (n, word(w, INTRINSICS + 1), word(w, INTRINSICS + 2), slots)
}

/// Encodes a mapping window at 0 of `w` (at least [`WINDOW`] words); frames past
/// [`MAX_WINDOW`] are dropped (the host validates the window first).
pub fn window_to_words(
    k: &Intrinsics,
    image: (u32, u32),
    slots: &[u32],
    poses: &[Pose],
    loss: &MappingLoss,
    w: &mut [u32],
) {
    intrinsics_to_words(k, w, 0);
    let n = poses.len().min(MAX_WINDOW);
    put(w, INTRINSICS, n as u32);
    put(w, INTRINSICS + 1, image.0);
    put(w, INTRINSICS + 2, image.1);
    let mut i = 0;
    while i < n {
        put(
            w,
            WINDOW_SLOTS + i,
            if i < slots.len() { slots[i] } else { 0 },
        );
        pose_to_words(&poses[i], w, WINDOW_POSES + i * POSE);
        i += 1;
    }
    mapping_loss_to_words(loss, w, WINDOW_LOSS);
    put(w, WINDOW_PRIORS, 0);
}

/// The window's poses read straight from the words (a [`PoseRead`] over a storage buffer).
pub struct WordPoses<'a> {
    /// The window words (poses at [`WINDOW_POSES`]).
    pub words: &'a [u32],
    /// Number of frames in the window.
    pub n: usize,
}

impl PoseRead for WordPoses<'_> {
    #[inline(always)]
    fn count(&self) -> usize {
        self.n
    }

    #[inline(always)]
    fn pose(&self, i: usize) -> Pose {
        if i < self.n {
            pose_from_words(self.words, WINDOW_POSES + i * POSE)
        } else {
            Pose::IDENTITY
        }
    }
}

#[cfg(test)]
mod tests {
    use crate::camera::{Intrinsics, Pose};
    use crate::field::grid::{GridConfig, GridKind, GridLayout};
    use crate::gpu_abi::words;
    use crate::Aabb;

    #[test]
    fn words_round_trip() {
        let aabb = Aabb::new([-1.0, -2.0, 0.5], [3.0, 1.0, 2.75]);
        for kind in [GridKind::Factorized, GridKind::Dense] {
            let g = GridLayout::new(&GridConfig::hi_map_geometry().with_kind(kind), aabb).unwrap();
            let mut w = [0u32; words::GRID_LAYOUT];
            words::grid_layout_to_words(&g, &mut w, 0);
            assert_eq!(words::grid_layout_from_words(&w, 0), g);
            // Words past the end of a short buffer read as zeros instead of panicking.
            let short = words::grid_layout_from_words(&w[..3], 0);
            assert_eq!((short.levels, short.param_count), (g.levels, 0));
            assert_eq!((short.aabb.max, short.level[0].res), ([0.0; 3], [0; 3]));
        }
        let pose = Pose {
            m: [
                [0.0, 0.0, 1.0, 1.5],
                [0.0, 1.0, 0.0, -2.0],
                [-1.0, 0.0, 0.0, 3.25],
            ],
        };
        let k = Intrinsics {
            width: 1200,
            height: 680,
            fx: 600.0,
            fy: 600.5,
            cx: 599.5,
            cy: 339.5,
        };
        let mut w = [0u32; words::AABB + words::POSE + words::INTRINSICS];
        words::aabb_to_words(&aabb, &mut w, 0);
        words::pose_to_words(&pose, &mut w, 6);
        words::intrinsics_to_words(&k, &mut w, 18);
        assert_eq!(words::aabb_from_words(&w, 0), aabb);
        assert_eq!(words::pose_from_words(&w, 6), pose);
        assert_eq!(words::intrinsics_from_words(&w, 18), k);
        assert_eq!(w[0], (-1.0f32).to_bits());
        assert_eq!(w[18], 1200);
        // The whole model layout (what train/render/query shaders decode), every render mode.
        for mode in [
            crate::field::render::RenderMode::SdfDensity,
            crate::field::render::RenderMode::SdfDirect,
            crate::field::render::RenderMode::Occupancy,
        ] {
            let mut cfg = crate::field::model::ModelConfig::paper(aabb);
            cfg.render_mode = mode;
            cfg.dual_path = mode != crate::field::render::RenderMode::SdfDirect;
            cfg.appearance_grid = cfg.appearance_grid.with_kind(GridKind::Dense);
            cfg.appearance_grid.cell_sizes[1] = 0.5;
            let l = crate::field::model::ModelLayout::new(&cfg).unwrap();
            let mut w = vec![0u32; words::MODEL_LAYOUT];
            words::model_layout_to_words(&l, &mut w, 0);
            assert_eq!(words::model_layout_from_words(&w, 0), l);
        }
    }
}
