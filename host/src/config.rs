//! The one configuration of a mapping run (TOML), with the `paper` and `small` presets.
//!
//! Every field has a default (the `small` preset), so a TOML file only lists what it changes;
//! unknown keys are errors. `himap map --preset paper --print-config` style inspection is done
//! with [`Config::to_toml`].
//!
//! # Scene bounds
//!
//! The field lives in an axis-aligned box, chosen in this order:
//! 1. `scene.min` / `scene.max` from the configuration (both must be given);
//! 2. the `scene_box` of the dataset's own metadata (`scene.json` of a synthetic sequence)
//!    grown by `scene.synthetic_margin` (0.1 m) on every side;
//! 3. otherwise a default box placed around the **first** camera, the only pose a robot knows
//!    when it starts (nothing reads a later pose): `scene.default_horizontal` (24 m) on each
//!    horizontal side, centred on the camera, and from `scene.default_below` (2 m) below to
//!    `scene.default_above` (3 m) above it. "Up" is the world axis closest to the first
//!    camera's image up direction (`-y` of the camera frame). This box grows as the camera
//!    walks (`scene.grow`, [`crate::grow`]). A camera that leaves the box (a given one, or a
//!    default one that cannot grow) is warned about (`frames_outside_box` in summary.json).
//!
//! Rays are sampled up to `model.max_depth` (6 m) from the camera, so a large box does not
//! spread the samples; the map's memory for the box is printed before mapping and checked
//! against `scene.memory_budget_mb`.

use std::path::Path;

use anyhow::{bail, Context};
use himap_core::camera::Pose;
use himap_core::field::grid::{GridConfig, GridKind, MAX_LEVELS};
use himap_core::field::model::{ModelConfig, PerGroup};
use himap_core::field::render::RenderMode;
use himap_core::loss::warp::WarpConfig;
use himap_core::mapper::{KeyframeOverflow, MapperConfig};
use himap_core::train::adam::AdamConfig;
use himap_core::Aabb;
use serde::{Deserialize, Serialize};

/// A grid's levels (coarsest first) and channels per level.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct GridSection {
    /// Channels per level.
    pub channels: u32,
    /// Cell size of each level in metres, coarsest first (1 to 8 levels).
    pub cell_sizes: Vec<f32>,
}

/// The field.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ModelSection {
    /// "factorized" (Hi-Map, TensoRF VM) or "dense" (the "no factorization" ablation).
    #[serde(with = "GridKindDef")]
    pub grid_kind: GridKind,
    pub geometry: GridSection,
    pub appearance: GridSection,
    /// Hidden units per decoder layer (paper: 32).
    pub hidden: u32,
    /// Hidden layers per decoder (paper's "2 layers").
    pub hidden_layers: u32,
    /// Appearance decoder also sees the position (Hi-Map's dual path); false = ablation.
    pub dual_path: bool,
    /// "sdf-density" (Hi-Map), "sdf-direct" or "occupancy" (ablations).
    #[serde(with = "RenderModeDef")]
    pub render_mode: RenderMode,
    /// Samples per ray (not in the paper).
    pub samples: u32,
    /// Initial beta of the SDF-to-density proxy (paper: 10).
    pub beta_init: f32,
    /// Std of the N(0, std^2) grid initialisation.
    pub grid_init_std: f32,
    /// Initial SDF output bias in metres (> 0 starts the field as free space).
    pub sdf_bias_init: f32,
    /// Geometric initialisation before mapping: "none" (random grids + `sdf_bias_init`) or
    /// "sphere" (fit the geometry to the inverted sphere of radius `geo_init_radius` around
    /// the first camera centre, see `himap::geo_init`).
    pub geo_init: GeoInit,
    /// Radius (m) of the initial sphere.
    pub geo_init_radius: f32,
    /// Outside the sphere the target is cut at `-geo_init_solid` (m): shallow enough that a
    /// camera walking into space not seen yet gets gradients.
    pub geo_init_solid: f32,
    /// Farthest sampled depth along a camera ray (m, z-depth; 0 = up to the box exit).
    pub max_depth: f32,
    /// Samples beyond `max_depth` (0 = none): a ray that leaves the box beyond `max_depth`
    /// gets this many more, spaced uniformly in inverse depth up to `far_depth`, so that a
    /// space larger than `max_depth` (a hall, an open office) is reached without spreading
    /// the near samples.
    pub far_samples: u32,
    /// Farthest depth of the `far_samples` (m, z-depth; must exceed `max_depth`).
    pub far_depth: f32,
    /// Early ray termination: a ray's compositing stops once its transmittance is below this
    /// (0 = never, the presets' default). The samples behind the first surface are then
    /// neither evaluated on the CPU nor back-propagated on any backend; the cut-off weight is
    /// below this value. 1e-4 maps whole sequences 1.4-1.9x faster with the same quality on
    /// ICL, 7-Scenes and the house, but changes the demo room's mesh (ARCHITECTURE.md).
    pub min_transmittance: f32,
    /// Adam iterations (4096 random points each, lr 0.01) of the sphere fit.
    pub geo_init_iters: u32,
}

/// `[mapper.warp]`: deserializes straight into the core's [`WarpConfig`] (its fields and
/// their meaning are documented there; serde's remote derive checks this list against it).
#[derive(Serialize, Deserialize)]
#[serde(remote = "WarpConfig", deny_unknown_fields)]
struct WarpDef {
    half: u32,
    margin: f32,
    min_views: u32,
    w_patch11: f32,
    w_patch7: f32,
    w_patch: f32,
    w_center: f32,
    center_beta: f32,
    #[serde(default = "one_u32")]
    stride: u32,
    // added after checkpoints existed: absent means DIM-SLAM's rule (no term below min_views)
    #[serde(default)]
    few_views_weight: f32,
    // added after checkpoints existed: absent means no texture test
    #[serde(default)]
    few_views_min_grad: f32,
    // added after checkpoints existed: absent means no texture test on the main term
    #[serde(default)]
    min_grad: f32,
}

fn one_u32() -> u32 {
    1
}

/// `model.grid_kind`: "factorized" or "dense" (the core's [`GridKind`]).
#[derive(Serialize, Deserialize)]
#[serde(remote = "GridKind", rename_all = "kebab-case")]
enum GridKindDef {
    Factorized,
    Dense,
}

/// `model.render_mode`: "sdf-density", "sdf-direct" or "occupancy" (the core's
/// [`RenderMode`]).
#[derive(Serialize, Deserialize)]
#[serde(remote = "RenderMode", rename_all = "kebab-case")]
enum RenderModeDef {
    SdfDensity,
    SdfDirect,
    Occupancy,
}

/// `model.geo_init`: the geometric initialisation before mapping.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum GeoInit {
    /// Random grids and `sdf_bias_init`.
    None,
    /// The geometry fitted to an inverted sphere around the first camera centre.
    Sphere,
}

/// `mapper.keyframe_overflow`: "thin" or "drop-oldest".
#[derive(Serialize, Deserialize)]
#[serde(remote = "KeyframeOverflow", rename_all = "kebab-case")]
enum OverflowDef {
    Thin,
    DropOldest,
}

/// `[mapper]`: deserializes straight into the core's [`MapperConfig`] (its fields and their
/// meaning are documented there; serde's remote derive checks this list against it). The
/// seed is the configuration's top-level `seed`.
#[derive(Serialize, Deserialize)]
#[serde(remote = "MapperConfig", deny_unknown_fields)]
struct MapperDef {
    local_frames: u32,
    window_keyframes: u32,
    global_keyframes: u32,
    update_every: u32,
    init_frames: u32,
    init_iters: u32,
    init_color_iters: u32,
    // added after checkpoints existed: absent means the behaviour before it (off)
    #[serde(default)]
    online_color_to_geometry: bool,
    iters: u32,
    pixels: u32,
    border: u32,
    new_frame_share: f32,
    keyframe_share: f32,
    lambda_color_init: f32,
    lambda_color: f32,
    lambda_warp: f32,
    #[serde(with = "WarpDef")]
    warp: WarpConfig,
    lambda_depth_prior: f32,
    depth_prior: f32,
    depth_prior_iters: u32,
    lambda_depth_prior_online: f32,
    depth_prior_near: f32,
    lambda_planar: f32,
    planar_edge: f32,
    planar_beta: f32,
    planar_spacing: u32,
    planar_share: f32,
    planar_region_step: f32,
    planar_gate: bool,
    rejected_lr_after: u32,
    rejected_lr_factor: f32,
    init_min_transmittance: f32,
    refine_iters: u32,
    refine_window: u32,
    refine_block: u32,
    refine_lr_end: f32,
    refine_geometry: bool,
    // added after checkpoints existed: absent means the behaviour before them (a detached
    // colour at the online weight)
    #[serde(default)]
    refine_color_to_geometry: bool,
    #[serde(default)]
    refine_lambda_color: f32,
    #[serde(default)]
    refine_lambda_planar: f32,
    #[serde(default)]
    lambda_plane: f32,
    #[serde(default)]
    refine_lambda_plane: f32,
    max_keyframes: u32,
    #[serde(with = "OverflowDef")]
    keyframe_overflow: KeyframeOverflow,
    overlap_pixels: u32,
    overlap_points: u32,
    overlap_margin: f32,
    // added after checkpoints existed: absent means any overlap (the behaviour before it)
    #[serde(default)]
    overlap_min: f32,
    #[serde(skip)]
    seed: u64,
}

/// Adam learning rates (betas 0.9, 0.999, eps 1e-8).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct AdamSection {
    /// Both grids (paper 0.01).
    pub grid_lr: f32,
    /// Both decoders (paper 1e-5).
    pub mlp_lr: f32,
    /// Beta of the density proxy.
    pub beta_lr: f32,
    /// Appearance decoder only, when set (default: `mlp_lr`).
    pub appearance_mlp_lr: Option<f32>,
}

/// Scene box (see the module documentation).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SceneSection {
    pub min: Option<[f32; 3]>,
    pub max: Option<[f32; 3]>,
    /// Margin around a synthetic `scene.json` box (m).
    pub synthetic_margin: f32,
    /// The default box around the first camera (see the module documentation): horizontal
    /// side (m), and how far it reaches below and above the camera along "up" (m).
    pub default_horizontal: f32,
    pub default_below: f32,
    pub default_above: f32,
    /// Largest memory the map of the scene box may take (MB: parameters, Adam moments and the
    /// CPU backend's gradient buffers); a larger map is an error before anything is allocated.
    pub memory_budget_mb: f64,
    /// Whether the default box grows as the camera walks ([`crate::grow`]):
    /// every horizontal face closer to a pushed camera than `grow_margin` (m; 0 = the rays'
    /// reach, 1.25 `model.max_depth`) moves out by `grow_step` (m), and the bottom or top face
    /// closer than `grow_margin_up` (m; 0 = never along "up") by `grow_step_up` (m), within
    /// `memory_budget_mb`. A box from the configuration or the dataset never grows.
    pub grow: bool,
    pub grow_margin: f32,
    pub grow_step: f32,
    pub grow_margin_up: f32,
    pub grow_step_up: f32,
}

/// Evaluation and outputs of `himap map`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct EvalSection {
    /// Evaluate every k-th mapping update (1 = all, 0 = never).
    pub every: u32,
    /// Render the evaluation view at this fraction of the input resolution (0 < scale <= 1).
    pub scale: f32,
    /// Frames whose renders are written to `renders/` (spread over the sequence).
    pub renders: u32,
    /// Marching-cubes spacing (m) of `mesh.ply`.
    pub mesh_resolution: f32,
    /// SDF value (m) of the extracted surface. Absent = the level of the surfaces the field
    /// renders: the median SDF at the rendered depth of 8 views spread over the sequence
    /// (`himap::mapper_cli::rendered_surface_level`), else [`Config::surface_level`]. Hi-Map's
    /// density `beta sig(-beta s)` has no `delta t` factor, so a sample is already half opaque
    /// at `s = ln(beta / ln 2 - 1) / beta` (0.26 m at beta 10) and the field need not reach 0
    /// in front of a surface (ICL gave an empty mesh at level 0).
    pub mesh_level: Option<f32>,
    /// Without `mesh_level`: the level is estimated again in cubes of this side (m) from the
    /// rendered surface points of the views that cut `mesh.ply` (their median SDF, within
    /// `mesh_level_spread` of the whole map's level, interpolated between the cubes), so that
    /// each room's surface lies where the renders put it (0 = one level for the whole map).
    pub mesh_level_cell: f32,
    /// The most a cube's level of `mesh_level_cell` may differ from the whole map's (m).
    pub mesh_level_spread: f32,
    /// Surface samples per mesh of Accuracy / Completion.
    pub mesh_samples: usize,
    /// Culling of the reconstruction for the mesh metrics: "none", "frustum", "occlusion";
    /// "auto" = none with a ground-truth mesh, frustum with a depth ground truth.
    pub cull: String,
    /// After mapping, re-render every k-th frame of the whole sequence from the final map and
    /// report its averages (`final_*` in summary.json), so forgetting of early regions shows
    /// (0 = off).
    pub final_every: u32,
    /// `mesh.ply` keeps the faces some mapped view saw: a face with a vertex within this
    /// distance (m) of a surface point some view rendered (its depth back-projected;
    /// `mesh_full.ply` keeps every face of the observed region). A distance in space, not
    /// along the ray: a surface seen at a grazing angle (a ceiling far ahead of the walk) is
    /// kept when the mesh lies a few cm off the rendered depth, which along the ray is tens
    /// of cm.
    pub observed_margin: f32,
    /// The most mapped views whose rendered depth (a quarter of the mapping size) decides what
    /// was seen, spread evenly over the pushed frames: every frame up to this many. A surface
    /// only a few frames saw (a ceiling at the top of the image far ahead of the walk) is
    /// missed by a sparser subset; each view costs about 0.04 s on 2 cores at 320x240.
    pub observed_views: u32,
    /// `mesh.ply` is extracted again on a grid this many times finer than `mesh_resolution`
    /// (1 = not), only in the cells around the faces some view saw (`mesh_full.ply` keeps
    /// `mesh_resolution`), and coarser when the finer mesh would exceed `mesh_max_faces`
    /// (its faces estimated as the seen faces times the squared ratio of the spacings). The
    /// field's SDF is flat near its surfaces: a finer grid places the level set more
    /// faithfully (ARCHITECTURE.md, issue #11).
    pub mesh_refine: u32,
    /// The most faces `mesh_refine`'s finer `mesh.ply` should have (a larger seen surface gets
    /// a coarser grid; estimated before extracting, so a mesh can exceed it by a few %).
    pub mesh_max_faces: usize,
}

/// Everything of a mapping run.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Config {
    /// Seed of the initialisation, pixel sampling and keyframe choice.
    pub seed: u64,
    pub model: ModelSection,
    /// The mapping schedule and its losses (`himap_core::mapper::MapperConfig`; its `seed`
    /// is [`Config::seed`]).
    #[serde(with = "MapperDef")]
    pub mapper: MapperConfig,
    pub adam: AdamSection,
    pub scene: SceneSection,
    pub eval: EvalSection,
    /// How to read the dataset: the colour camera and the depth images' own camera when the
    /// files' are not right (`[dataset.camera]`, `[dataset.depth_camera]`: width, height, fx,
    /// fy, cx, cy), the colour camera's centre in the pose and depth camera's frame
    /// (`colour_offset = [x, y, z]`, metres), depth scale, layout. Empty = what the dataset's
    /// files say.
    pub dataset: crate::dataset::DatasetConfig,
    /// Plane priors of plain regions (`crate::planes`; off unless a weight is set).
    pub planes: crate::planes::PlaneSection,
}

impl Default for Config {
    fn default() -> Self {
        Self::small()
    }
}
impl Default for ModelSection {
    fn default() -> Self {
        Config::small().model
    }
}
impl Default for AdamSection {
    fn default() -> Self {
        Config::small().adam
    }
}
impl Default for SceneSection {
    fn default() -> Self {
        Config::small().scene
    }
}
impl Default for EvalSection {
    fn default() -> Self {
        Config::small().eval
    }
}
fn grid_section(g: &GridConfig) -> GridSection {
    GridSection {
        channels: g.channels,
        cell_sizes: g.cell_sizes[..g.levels as usize].to_vec(),
    }
}

/// Lays `top` over `base`: tables merge recursively, everything else replaces.
fn merge_tables(base: &mut toml::Table, top: toml::Table) {
    for (k, v) in top {
        match (base.get_mut(&k), v) {
            (Some(toml::Value::Table(b)), toml::Value::Table(t)) => merge_tables(b, t),
            (_, v) => {
                base.insert(k, v);
            }
        }
    }
}

impl Config {
    /// The paper's values (48 samples per ray and 4096 pixels per iteration are ours: the
    /// paper does not give them).
    pub fn paper() -> Self {
        Self {
            seed: 0,
            model: ModelSection {
                grid_kind: GridKind::Factorized,
                geometry: grid_section(&GridConfig::hi_map_geometry()),
                appearance: grid_section(&GridConfig::hi_map_appearance()),
                hidden: 32,
                hidden_layers: 2,
                dual_path: true,
                render_mode: RenderMode::SdfDensity,
                samples: 48,
                beta_init: 10.0,
                grid_init_std: 0.01,
                sdf_bias_init: 0.3,
                geo_init: GeoInit::None,
                geo_init_radius: 1.5,
                geo_init_solid: 0.3,
                max_depth: 6.0,
                far_samples: 0,
                far_depth: 0.0,
                min_transmittance: 0.0,
                geo_init_iters: 200,
            },
            mapper: MapperConfig {
                keyframe_overflow: KeyframeOverflow::Thin,
                seed: 0,
                ..MapperConfig::paper(4096)
            },
            adam: AdamSection {
                grid_lr: 0.01,
                mlp_lr: 1e-5,
                beta_lr: 1e-5,
                appearance_mlp_lr: None,
            },
            scene: SceneSection {
                min: None,
                max: None,
                synthetic_margin: 0.1,
                default_horizontal: 24.0,
                default_below: 2.0,
                default_above: 3.0,
                memory_budget_mb: 8192.0,
                grow: true,
                grow_margin: 0.0,
                grow_step: 6.0,
                grow_margin_up: 1.0,
                grow_step_up: 2.0,
            },
            eval: EvalSection {
                every: 1,
                scale: 0.5,
                renders: 4,
                mesh_resolution: 0.02,
                mesh_level: None,
                mesh_level_cell: 1.5,
                mesh_level_spread: 0.1,
                mesh_samples: 200_000,
                cull: "auto".into(),
                final_every: 10,
                observed_margin: 0.08,
                observed_views: 1000,
                mesh_refine: 1,
                mesh_max_faces: 2_000_000,
            },
            dataset: crate::dataset::DatasetConfig::default(),
            planes: crate::planes::PlaneSection::default(),
        }
    }

    /// Sized for a 2-core CPU; the paper's model and mapper (`paper`) except:
    /// - geometry 5 levels, 64..4 cm (the paper has 6, to 2 cm); appearance 24 / 2 cm with 16
    ///   channels (the paper's levels, 32 channels);
    /// - 300 initialisation iterations, 512 pixels per iteration, 60 online iterations (the
    ///   paper's 20, tripled with the time early termination saves);
    /// - early ray termination online (`model.min_transmittance` 1e-4; none during the
    ///   initialisation, `mapper.init_min_transmittance` 0);
    /// - decoder learning rate 1e-3 (the paper's 1e-5 barely moves in 300 iterations) and
    ///   `adam.beta_lr` 0.1 (our SDF is in metres, the peers' in truncation units);
    /// - `model.geo_init` "sphere" (an inverted 1.5 m sphere around the first camera) with
    ///   the depth prior of the first 60 iterations and online for collapsed views, its solid
    ///   far field cut at -0.1 m (`model.geo_init_solid`; -0.3 m before: space first seen
    ///   late, a room through a doorway, stayed solid in front of the truth for longer; the
    ///   worst 5-update stretch of the newest frames' depth fell on four synthetic walks,
    ///   e.g. house seed 0 78.9 -> 62.1 cm, hall 87.4 -> 73.8 cm);
    /// - online colour weight 0.1 (0.001 sat at Adam's eps) and 75 % of the pixels on the
    ///   frames new since the last update;
    /// - a warping term from 3 valid views (`mapper.warp.min_views`; DIM-SLAM's 4 in
    ///   `paper`): space the newest frames look into for the first time gets the term while
    ///   they still see it (house walk 7, frames 0..115, three mapping seeds each: mean Depth
    ///   L1 of the newest frame 26.4-29.2 cm and worst 5-update window 46-55 cm, against
    ///   31.9-37.0 and 58-80 cm with 4 over four seeds; ICL 6.7 -> 6.2 cm), and below that
    ///   a down-weighted term from the views a pixel has (`mapper.warp.few_views_weight`
    ///   0.75, 0.5 before the full term's texture test; DIM-SLAM's rule gives none): house
    ///   walks 7 and 17, frames 0..115, three mapping seeds each: mean Depth L1 of the newest
    ///   frame 20.8 and 22.3 cm at 0.5 against 27.4 and 40.0 cm without (the first look of
    ///   walk 17 at frame 19: 218 -> 98 cm); with the test, 0.75 against 0.5: worst 5-update
    ///   window 33.4 and 32.7 against 36.7 and 33.5 cm, whole walks 0 and 17 41.1 -> 37.7
    ///   and 39.0 -> 33.6 cm; its
    ///   pairs only where the source patch has texture along their epipolar line (RMS
    ///   gradient >= 0.01 per pixel, `mapper.warp.few_views_min_grad`; 2-3x real frames'
    ///   noise floor at 320x240): house walk 0's third room of plain and smoothly shaded
    ///   walls, frames 0..250, two mapping seeds, worst 5-update window 80 and 86 -> 69 and
    ///   69 cm; and the full term's pairs too need an RMS gradient of 0.005 along their line
    ///   (`mapper.warp.min_grad`; on a plain patch the loss is flat in depth and its
    ///   gradient noise moved plain walls: house seed 29, frames 0..275, worst 5-update
    ///   window 68.3 -> 42.3 cm; 0.01 cost ICL's Depth L1 its bar, 6.5 -> 9.8 cm);
    /// - a final refinement of 2000 iterations (1000 before the plane priors) whose colour
    ///   loss, weighted 10, reaches the
    ///   geometry (`mapper.refine_color_to_geometry`, `refine_lambda_color`): every view is
    ///   held by then, and the final maps of four whole sequences gained 0.9-2.7 dB;
    ///   with plane priors on the plain regions of every held frame (`[planes]`,
    ///   `mapper.refine_lambda_plane` 10, refreshed every 250 iterations from the map: a
    ///   plane fitted to the rendered depth of each plain region's textured border): the
    ///   house's mesh accuracy 8.3 -> 4.6 cm, 7-Scenes' completion ratio 47.6 -> 55.4 %, the
    ///   final maps +0.9 to +1.3 dB over 1000 iterations with the priors;
    /// - online plane priors (`mapper.lambda_plane` 1) for the local frames' plain regions
    ///   that meet the floor along a line: the vertical plane through that line
    ///   (`planes.online = "floor"`; the floor is the densest height band of the rendered
    ///   points below the cameras): a plain wall first seen at a grazing angle renders where
    ///   earlier rays stopped carving, while the textured floor at its base is placed; house
    ///   walks 7 and 17, frames 0..115, three mapping seeds: worst 5-update window 33.4 /
    ///   32.7 -> 29.7 / 28.3 cm;
    /// - 16 far samples per ray beyond `max_depth` (6 m), in inverse depth up to 20 m, for
    ///   the rays that have not left the box by then (a hall's far walls: its final map's
    ///   Depth L1 83 -> 10 cm, the house and 7-Scenes unchanged within their spread).
    ///
    /// Each was measured; the numbers and the runs are in ARCHITECTURE.md ("Mapping quality of
    /// the `small` preset" and the sections after it).
    pub fn small() -> Self {
        let mut c = Self::paper();
        c.adam.mlp_lr = 1e-3;
        c.adam.beta_lr = 0.1;
        c.model.geo_init = GeoInit::Sphere;
        c.model.geo_init_solid = 0.1;
        c.model.geometry.cell_sizes = vec![0.64, 0.32, 0.16, 0.08, 0.04];
        c.model.appearance = GridSection {
            channels: 16,
            cell_sizes: vec![0.24, 0.02],
        };
        c.mapper.lambda_color = 0.1;
        c.mapper.init_iters = 300;
        c.mapper.init_color_iters = 100;
        c.mapper.depth_prior_iters = 60;
        c.mapper.lambda_depth_prior_online = 1.0;
        c.mapper.depth_prior_near = 0.5;
        c.mapper.pixels = 512;
        c.mapper.new_frame_share = 0.75;
        c.mapper.max_keyframes = 128;
        c.mapper.warp.min_views = 3;
        c.mapper.warp.few_views_weight = 0.75;
        c.mapper.warp.few_views_min_grad = 0.01;
        c.mapper.warp.min_grad = 0.005;
        c.mapper.iters = 60;
        c.mapper.refine_iters = 2000;
        c.mapper.refine_color_to_geometry = true;
        c.mapper.refine_lambda_color = 10.0;
        c.mapper.refine_lambda_plane = 10.0;
        // online plane priors for plain walls, through where they meet the floor
        c.mapper.lambda_plane = 1.0;
        c.planes.online = crate::planes::PriorSource::Floor;
        c.model.min_transmittance = 1e-4;
        c.model.far_samples = 16;
        c.model.far_depth = 20.0;
        c.eval.mesh_resolution = 0.04;
        // mesh.ply at 1 cm where the views saw surfaces (NICE-SLAM's spacing), at most 2 M faces.
        c.eval.mesh_refine = 4;
        // The peers' 200 000 surface samples per mesh (50 000 understated a 3-room house's
        // completion ratio by 13 points: ARCHITECTURE.md).
        c.eval.mesh_samples = 200_000;
        c
    }

    /// A named preset.
    pub fn preset(name: &str) -> anyhow::Result<Self> {
        match name {
            "small" => Ok(Self::small()),
            "paper" => Ok(Self::paper()),
            "demo" => Ok(Self::demo()),
            other => bail!("unknown preset '{other}': use small, paper or demo"),
        }
    }

    /// `himap demo`'s preset: `small` with the schedule before early termination (20 online
    /// iterations, `model.min_transmittance` 0), DIM-SLAM's 4 warping views and without the
    /// final refinement (on the demo
    /// room it lifts the final map 23.7 -> 25.0 dB but moves the mesh to 5.01 / 6.62 cm,
    /// 63.1 %, and doubles the time), the one the demo room's mesh bars were set
    /// with. The demo is 60 frames of one small room, where time is not the issue, and its
    /// mesh reacts chaotically to any change of the step (ARCHITECTURE.md: with the `small`
    /// schedule its seed 0 gives 6.23 / 7.10 cm, 58.9 % instead of 4.06 / 5.75 cm, 70.6 %,
    /// seeds 1 and 2 better); longer sequences gain 1-2.7 dB from `small`'s.
    pub fn demo() -> Self {
        let mut c = Self::small();
        // One small room: no wall beyond max_depth, and the bars were set without them.
        c.model.far_samples = 0;
        c.mapper.iters = 20;
        c.mapper.refine_iters = 0;
        c.model.min_transmittance = 0.0;
        // DIM-SLAM's 4 views: the room's bars were set with it (3 gives 3.87 / 5.72 cm, 73.9 %
        // and a final map 1.6 dB lower on the demo room: ARCHITECTURE.md, forty-third session).
        c.mapper.warp.min_views = 4;
        // and no term below them (DIM-SLAM's rule; measured with the weight: ARCHITECTURE.md)
        c.mapper.warp.few_views_weight = 0.0;
        // and DIM-SLAM's full term on every pixel (no texture test of its pairs)
        c.mapper.warp.min_grad = 0.0;
        // and no online plane priors (with the floor's: 4.09 / 6.05 cm, 71.4 %, final map
        // 20.7 dB against 3.86 / 4.82 cm, 76.8 %, 23.6 dB: ARCHITECTURE.md, fifty-third session)
        c.mapper.lambda_plane = 0.0;
        c
    }

    /// Reads a TOML file (missing fields take the `small` preset's values).
    pub fn from_file(path: &Path) -> anyhow::Result<Self> {
        Self::from_file_over(path, &Self::small())
    }

    /// Reads a TOML file laid over `base`: every field the file leaves out, at any depth
    /// (e.g. `[model.geometry]` giving only `cell_sizes`), keeps `base`'s value.
    pub fn from_file_over(path: &Path, base: &Config) -> anyhow::Result<Self> {
        let text = std::fs::read_to_string(path)
            .with_context(|| format!("reading configuration {}", path.display()))?;
        Self::from_toml_over(&text, base)
            .with_context(|| format!("in configuration {}", path.display()))
    }

    /// Parses TOML laid over the `small` preset.
    pub fn from_toml(text: &str) -> anyhow::Result<Self> {
        Self::from_toml_over(text, &Self::small())
    }

    /// Parses TOML laid over `base` (tables merge key by key, arrays and values replace);
    /// unknown keys are errors.
    pub fn from_toml_over(text: &str, base: &Config) -> anyhow::Result<Self> {
        let user: toml::Table = toml::from_str(text).context("parsing TOML")?;
        let mut merged: toml::Table =
            toml::from_str(&base.to_toml()).expect("a configuration parses back");
        merge_tables(&mut merged, user);
        let c: Config = toml::Value::Table(merged)
            .try_into()
            .context("parsing TOML")?;
        c.validate()?;
        Ok(c)
    }

    pub fn to_toml(&self) -> String {
        toml::to_string_pretty(self).expect("the configuration serialises")
    }

    /// Checks what the core does not check itself (names, presence of both bounds, eval).
    pub fn validate(&self) -> anyhow::Result<()> {
        if !(self.model.geo_init_radius > 0.0 && self.model.geo_init_radius.is_finite()) {
            bail!("model.geo_init_radius must be positive");
        }
        if !(self.model.geo_init_solid > 0.0 && self.model.geo_init_solid.is_finite()) {
            bail!("model.geo_init_solid must be positive");
        }
        let tm = self.model.min_transmittance;
        if !((0.0..1.0).contains(&tm)) {
            bail!("model.min_transmittance must be in [0, 1) (0 = no early ray termination)");
        }
        if !(self.model.max_depth >= 0.0 && self.model.max_depth.is_finite()) {
            bail!("model.max_depth must be >= 0 (0 = up to the box exit)");
        }
        let s = &self.scene;
        if !(s.grow_step > 0.0 && s.grow_step.is_finite()) {
            bail!("scene.grow_step must be positive");
        }
        if !(s.grow_margin >= 0.0 && s.grow_margin.is_finite()) {
            bail!("scene.grow_margin must be >= 0 (0 = model.max_depth)");
        }
        if !(s.grow_step_up > 0.0 && s.grow_step_up.is_finite()) {
            bail!("scene.grow_step_up must be positive");
        }
        if !(s.grow_margin_up >= 0.0 && s.grow_margin_up.is_finite()) {
            bail!("scene.grow_margin_up must be >= 0 (0 = the box never grows along up)");
        }
        if !(self.eval.observed_margin > 0.0 && self.eval.observed_margin.is_finite()) {
            bail!("eval.observed_margin must be positive");
        }
        if !(self.eval.mesh_level_cell >= 0.0 && self.eval.mesh_level_cell.is_finite()) {
            bail!("eval.mesh_level_cell must be >= 0 (0 = one level for the whole map)");
        }
        if !(self.eval.mesh_level_spread >= 0.0 && self.eval.mesh_level_spread.is_finite()) {
            bail!("eval.mesh_level_spread must be >= 0");
        }
        if self.eval.observed_views == 0 {
            bail!("eval.observed_views must be at least 1");
        }
        if self.scene.min.is_some() != self.scene.max.is_some() {
            bail!("scene.min and scene.max must be given together");
        }
        self.planes.validate()?;
        if !(self.eval.scale > 0.0 && self.eval.scale <= 1.0) {
            bail!("eval.scale must be in (0, 1]");
        }
        if !(self.eval.mesh_resolution > 0.0 && self.eval.mesh_resolution.is_finite()) {
            bail!("eval.mesh_resolution must be positive");
        }
        if self.eval.mesh_refine == 0 {
            bail!("eval.mesh_refine must be at least 1 (1 = mesh.ply at eval.mesh_resolution)");
        }
        if !["auto", "none", "frustum", "occlusion"].contains(&self.eval.cull.as_str()) {
            bail!("eval.cull must be auto, none, frustum or occlusion");
        }
        for (name, lr) in [
            ("grid_lr", self.adam.grid_lr),
            ("mlp_lr", self.adam.mlp_lr),
            ("beta_lr", self.adam.beta_lr),
        ] {
            if !(lr.is_finite() && lr >= 0.0) {
                bail!("adam.{name} must be finite and >= 0");
            }
        }
        for (name, g) in [
            ("geometry", &self.model.geometry),
            ("appearance", &self.model.appearance),
        ] {
            if g.cell_sizes.is_empty() || g.cell_sizes.len() > MAX_LEVELS {
                bail!("model.{name}.cell_sizes must have 1 to {MAX_LEVELS} levels");
            }
        }
        Ok(())
    }

    /// The SDF level of the surface the renderer draws with a trained `beta`: where one
    /// sample's opacity reaches 1/2. `SdfDensity`: `1 - exp(-beta sig(-beta s)) = 1/2`, i.e.
    /// `s = ln(beta / ln 2 - 1) / beta` (0 when `beta <= 2 ln 2`); `Occupancy`
    /// (`alpha = sig(-beta s)`) and `SdfDirect` (bell centred on 0): 0. `eval.mesh_level`
    /// overrides it.
    pub fn surface_level(&self, beta: f32) -> f32 {
        if let Some(l) = self.eval.mesh_level {
            return l;
        }
        match self.model.render_mode {
            RenderMode::SdfDensity => {
                let r = beta / std::f32::consts::LN_2;
                if beta.is_finite() && r > 2.0 {
                    (r - 1.0).ln() / beta
                } else {
                    0.0
                }
            }
            _ => 0.0,
        }
    }

    fn grid(&self, g: &GridSection) -> anyhow::Result<GridConfig> {
        let mut cell_sizes = [0.0; MAX_LEVELS];
        cell_sizes[..g.cell_sizes.len()].copy_from_slice(&g.cell_sizes);
        Ok(GridConfig {
            kind: self.model.grid_kind,
            levels: g.cell_sizes.len() as u32,
            channels: g.channels,
            cell_sizes,
        })
    }

    /// The core's field configuration over `aabb`.
    pub fn model_config(&self, aabb: Aabb) -> anyhow::Result<ModelConfig> {
        self.validate()?;
        let m = &self.model;
        Ok(ModelConfig {
            aabb,
            geometry_grid: self.grid(&m.geometry)?,
            appearance_grid: self.grid(&m.appearance)?,
            hidden: m.hidden,
            hidden_layers: m.hidden_layers,
            dual_path: m.dual_path,
            render_mode: self.model.render_mode,
            samples: m.samples,
            beta_init: m.beta_init,
            grid_init_std: m.grid_init_std,
            sdf_bias_init: m.sdf_bias_init,
            max_depth: m.max_depth,
            far_samples: m.far_samples,
            far_depth: m.far_depth,
            min_transmittance: m.min_transmittance,
        })
    }

    /// The core's mapper configuration.
    pub fn mapper_config(&self) -> anyhow::Result<MapperConfig> {
        Ok(MapperConfig {
            seed: self.seed,
            ..self.mapper
        })
    }

    /// Adam settings per group, in `Group::ALL` order.
    pub fn adam_config(&self) -> PerGroup<AdamConfig> {
        let a = &self.adam;
        PerGroup([
            AdamConfig::new(a.grid_lr),
            AdamConfig::new(a.grid_lr),
            AdamConfig::new(a.mlp_lr),
            AdamConfig::new(a.appearance_mlp_lr.unwrap_or(a.mlp_lr)),
            AdamConfig::new(a.beta_lr),
        ])
    }

    /// The scene box (see the module documentation) and where it came from, knowing only the
    /// dataset's metadata and the first camera's pose.
    pub fn scene_bounds(
        &self,
        dataset_dir: &Path,
        first: &Pose,
    ) -> anyhow::Result<(Aabb, &'static str)> {
        if let (Some(min), Some(max)) = (self.scene.min, self.scene.max) {
            let b = Aabb::new(min, max);
            if !b.is_valid() {
                bail!("scene.min/max do not form a box with positive extent");
            }
            return Ok((b, "config"));
        }
        let sj = dataset_dir.join("scene.json");
        if sj.is_file() {
            let (_, b) = crate::synth::read_scene_json(&sj)?;
            let m = self.scene.synthetic_margin;
            return Ok((
                Aabb::new(b.min.map(|x| x - m), b.max.map(|x| x + m)),
                "scene.json",
            ));
        }
        let s = &self.scene;
        if !(s.default_horizontal > 0.0 && s.default_below + s.default_above > 0.0) {
            bail!(
                "scene.default_horizontal and scene.default_below + default_above must be positive"
            );
        }
        let o = first.origin();
        let up = up_axis(first);
        let up_world = first.rotate([0.0, -1.0, 0.0]);
        let sign = if up_world[up] >= 0.0 { 1.0 } else { -1.0 };
        let mut lo = [0.0f32; 3];
        let mut hi = [0.0f32; 3];
        for a in 0..3 {
            if a == up {
                let (b, t) = (o[a] - sign * s.default_below, o[a] + sign * s.default_above);
                (lo[a], hi[a]) = (b.min(t), b.max(t));
            } else {
                (lo[a], hi[a]) = (
                    o[a] - 0.5 * s.default_horizontal,
                    o[a] + 0.5 * s.default_horizontal,
                );
            }
        }
        let b = Aabb::new(lo, hi);
        if !b.is_valid() {
            bail!("could not place the default scene box around the first camera {o:?}");
        }
        Ok((b, DEFAULT_BOX))
    }
}

/// Where the default box comes from ([`Config::scene_bounds`]; the only box that grows).
pub const DEFAULT_BOX: &str = "default around the first camera";

/// The world axis closest to the camera's image up (`-y` of the camera frame): "up" of the
/// default box, which grows along the other two.
pub fn up_axis(first: &Pose) -> usize {
    let up_world = first.rotate([0.0, -1.0, 0.0]);
    (0..3)
        .max_by(|&a, &b| up_world[a].abs().total_cmp(&up_world[b].abs()))
        .unwrap_or(1)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn presets_round_trip_through_toml_and_build_core_configs() {
        for c in [Config::small(), Config::paper()] {
            let back = Config::from_toml(&c.to_toml()).unwrap();
            assert_eq!(back, c);
            let aabb = Aabb::new([-1.0; 3], [1.0; 3]);
            let mc = c.model_config(aabb).unwrap();
            himap_core::field::model::ModelLayout::new(&mc).unwrap();
            c.mapper_config().unwrap();
        }
        let p = Config::paper()
            .model_config(Aabb::new([0.0; 3], [1.0; 3]))
            .unwrap();
        assert_eq!(p.geometry_grid, GridConfig::hi_map_geometry());
        assert_eq!(p.samples, 48);
        assert_eq!(Config::paper().mapper.init_iters, 1500);
    }

    #[test]
    fn dataset_cameras_come_from_the_file_and_round_trip() {
        let text = "[dataset.camera]\nwidth = 640\nheight = 480\nfx = 525.0\nfy = 525.0\n\
                    cx = 319.5\ncy = 239.5\n[dataset.depth_camera]\nwidth = 640\n\
                    height = 480\nfx = 585.0\nfy = 585.0\ncx = 320.0\ncy = 240.0\n";
        let c = Config::from_toml_over(text, &Config::small()).unwrap();
        let cam = c.dataset.camera.unwrap();
        assert_eq!((cam.fx, cam.cx, cam.distortion), (525.0, 319.5, None));
        assert_eq!(c.dataset.depth_camera.unwrap().fx, 585.0);
        assert_eq!(Config::from_toml(&c.to_toml()).unwrap(), c);
        // Nothing given: the files decide.
        assert_eq!(
            Config::small().dataset,
            crate::dataset::DatasetConfig::default()
        );
        assert!(Config::from_toml_over("[dataset.camera]\nfx = 1.0\n", &Config::small()).is_err());
    }

    #[test]
    fn files_lay_over_the_chosen_preset_at_any_depth() {
        let text = "[model.geometry]\ncell_sizes = [0.5, 0.25]\n[mapper.warp]\nhalf = 3\n";
        let c = Config::from_toml_over(text, &Config::paper()).unwrap();
        assert_eq!(c.model.geometry.cell_sizes, vec![0.5, 0.25]);
        assert_eq!(
            c.model.geometry.channels,
            Config::paper().model.geometry.channels
        );
        assert_eq!(c.mapper.warp.half, 3);
        assert_eq!(
            c.mapper.warp.min_views,
            Config::paper().mapper.warp.min_views
        );
        assert_eq!(c.mapper.init_iters, Config::paper().mapper.init_iters);
        let s = Config::from_toml(text).unwrap();
        assert_eq!(s.mapper.init_iters, Config::small().mapper.init_iters);
        let e = Config::from_toml_over("[model.geometry]\ncels = 1\n", &Config::paper());
        assert!(format!("{:#}", e.unwrap_err()).contains("cels"));
    }

    /// `[mapper]` is the core's `MapperConfig` itself: every key of it, the overflow policy by
    /// name, the seed from the top level (a `mapper.seed` key is unknown).
    #[test]
    fn mapper_section_deserializes_into_the_core_config() {
        let text = "seed = 7\n[mapper]\nkeyframe_overflow = \"drop-oldest\"\niters = 3\n\
                    [mapper.warp]\nhalf = 3\n";
        let m = Config::from_toml(text).unwrap().mapper_config().unwrap();
        assert_eq!(m.keyframe_overflow, KeyframeOverflow::DropOldest);
        assert_eq!((m.iters, m.warp.half, m.seed), (3, 3, 7));
        let small = Config::small().mapper;
        assert_eq!(
            (m.local_frames, m.warp.margin),
            (small.local_frames, small.warp.margin)
        );
        let e = Config::from_toml("[mapper]\nkeyframe_overflow = \"newest\"\n").unwrap_err();
        let msg = format!("{e:#}");
        assert!(msg.contains("thin") && msg.contains("drop-oldest"), "{msg}");
        assert!(Config::from_toml("[mapper]\nseed = 3\n").is_err());
        assert!(Config::from_toml("[mapper.warp]\nradius = 3\n").is_err());
    }

    #[test]
    fn partial_files_take_defaults_and_bad_values_are_clear_errors() {
        let c = Config::from_toml("[mapper]\niters = 3\n[model]\nrender_mode = \"occupancy\"\n")
            .unwrap();
        assert_eq!(c.mapper.iters, 3);
        assert_eq!(c.model.render_mode, RenderMode::Occupancy);
        assert_eq!(c.mapper.pixels, Config::small().mapper.pixels);
        let e = Config::from_toml("[model]\nrender_mode = \"nerf\"\n").unwrap_err();
        assert!(format!("{e:#}").contains("nerf"), "{e:#}");
        let e = Config::from_toml("[mapper]\nitres = 3\n").unwrap_err();
        assert!(format!("{e:#}").contains("itres"), "{e:#}");
        let e = Config::from_toml("[scene]\nmin = [0.0, 0.0, 0.0]\n").unwrap_err();
        assert!(format!("{e:#}").contains("together"), "{e:#}");
        // a map saved before `eval.observed_views` existed reads the preset's 1000
        let c = Config::from_toml("[eval]\nobserved_margin = 0.15\n").unwrap();
        assert_eq!(c.eval.observed_views, 1000);
        let e = Config::from_toml("[eval]\nobserved_views = 0\n").unwrap_err();
        assert!(format!("{e:#}").contains("observed_views"), "{e:#}");
    }

    #[test]
    fn default_box_is_placed_around_the_first_camera_with_its_up_axis() {
        let c = Config::small();
        // identity: camera y points down in the world, so world -y is up
        let (b, src) = c
            .scene_bounds(Path::new("/nonexistent"), &Pose::IDENTITY)
            .unwrap();
        assert_eq!(src, "default around the first camera");
        assert_eq!(b, Aabb::new([-12.0, -3.0, -12.0], [12.0, 2.0, 12.0]));
        // a camera at (1, 2, 3) whose image up is world +z (camera -y = world +z)
        let p = Pose {
            m: [
                [1.0, 0.0, 0.0, 1.0],
                [0.0, 0.0, 1.0, 2.0],
                [0.0, -1.0, 0.0, 3.0],
            ],
        };
        let (b, _) = c.scene_bounds(Path::new("/nonexistent"), &p).unwrap();
        assert_eq!(b, Aabb::new([-11.0, -10.0, 1.0], [13.0, 14.0, 6.0]));
        let mut c2 = c.clone();
        c2.scene.min = Some([-1.0; 3]);
        c2.scene.max = Some([2.0; 3]);
        let (b, src) = c2.scene_bounds(Path::new("/x"), &p).unwrap();
        assert_eq!((b, src), (Aabb::new([-1.0; 3], [2.0; 3]), "config"));
        c2.scene.min = None;
        c2.scene.max = None;
        c2.scene.default_horizontal = 0.0;
        assert!(c2.scene_bounds(Path::new("/x"), &p).is_err());
    }
}
