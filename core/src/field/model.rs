//! The Hi-Map field: two feature grids, two decoders and the renderer, evaluated per sample and
//! per ray, forward and backward. This is the per-ray kernel that every backend runs: the
//! single-threaded CPU step in [`crate::train::backend`], the host's multi-threaded backend and the
//! Vulkan shaders all call [`ray_forward`] and [`ray_train`].
//!
//! Per sample at world position p (grid coordinates p̂ = `Aabb::normalize(p)` in [-1, 1]):
//! - geometry: `s = MLP_g(F_g(p))[0]`, the signed distance in metres (linear output);
//! - appearance (dual path): `rgb = sigmoid(MLP_a([p̂, F_a(p)]))`; with `dual_path` off the
//!   position input is dropped (`MLP_a(F_a(p))`), the paper's ablation.
//!
//! Parameters live in five groups ([`Group`]), each a flat `f32` buffer described by the
//! layouts in [`ModelLayout`]. Gradients go to a [`ModelGradSink`], one call per contribution.

use crate::field::grid::{self, GridConfig, GridLayout, MAX_GRID_FEATURES};
use crate::field::mlp::{self, MlpLayout, MlpScratch, MAX_OUT, MAX_WIDTH};
#[cfg(not(target_arch = "spirv"))]
use crate::field::mlp::{MlpLanes, LANES};
use crate::field::render::{self, RayOutput, RenderMode, MAX_SAMPLES};
use crate::math;
use crate::{Aabb, Error, GradSink, ParamRead};

/// The parameter groups, in buffer order.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
#[repr(u32)]
pub enum Group {
    /// The geometry feature grid `F_g`.
    GeometryGrid = 0,
    /// The appearance feature grid `F_a`.
    AppearanceGrid = 1,
    /// The geometry decoder `MLP_g` (features to signed distance).
    GeometryMlp = 2,
    /// The appearance decoder `MLP_a` (features, and the position with the dual path, to
    /// colour).
    AppearanceMlp = 3,
    /// The SDF-to-density sharpness beta (one value).
    Beta = 4,
}

/// Number of parameter groups.
pub const NUM_GROUPS: usize = 5;

impl Group {
    /// Every group, in buffer order.
    pub const ALL: [Group; NUM_GROUPS] = [
        Group::GeometryGrid,
        Group::AppearanceGrid,
        Group::GeometryMlp,
        Group::AppearanceMlp,
        Group::Beta,
    ];

    /// Tensor-name friendly name.
    pub const fn name(self) -> &'static str {
        match self {
            Group::GeometryGrid => "geometry_grid",
            Group::AppearanceGrid => "appearance_grid",
            Group::GeometryMlp => "geometry_mlp",
            Group::AppearanceMlp => "appearance_mlp",
            Group::Beta => "beta",
        }
    }
}

/// One value per parameter group, indexed by [`Group`] (`x[Group::Beta]`) instead of a bare
/// number. Dereferences to the array in [`Group::ALL`] order for iteration and for the code
/// that walks every group alike.
///
/// # Examples
///
/// ```rust
/// use himap_core::field::model::{Group, PerGroup};
///
/// let mut lr = PerGroup::from_fn(|g| if g == Group::Beta { 1e-3 } else { 1e-2 });
/// lr[Group::GeometryGrid] = 0.05;
/// assert_eq!(lr[Group::Beta], 1e-3);
/// assert_eq!(lr[0], 0.05); // by position in `Group::ALL`
/// assert_eq!(lr.iter_groups().count(), 5);
/// ```
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
pub struct PerGroup<T>(pub [T; NUM_GROUPS]);

impl<T> PerGroup<T> {
    /// `f(group)` for every group, in [`Group::ALL`] order.
    pub fn from_fn(mut f: impl FnMut(Group) -> T) -> Self {
        Self(core::array::from_fn(|g| f(Group::ALL[g])))
    }

    /// `f` applied to every group's value.
    pub fn map<U>(self, f: impl FnMut(T) -> U) -> PerGroup<U> {
        PerGroup(self.0.map(f))
    }

    /// `(group, value)` pairs in [`Group::ALL`] order.
    pub fn iter_groups(&self) -> impl Iterator<Item = (Group, &T)> {
        Group::ALL.into_iter().zip(self.0.iter())
    }
}

impl<T> core::ops::Index<Group> for PerGroup<T> {
    type Output = T;
    fn index(&self, g: Group) -> &T {
        &self.0[g as usize]
    }
}

impl<T> core::ops::IndexMut<Group> for PerGroup<T> {
    fn index_mut(&mut self, g: Group) -> &mut T {
        &mut self.0[g as usize]
    }
}

/// By position in [`Group::ALL`], for the code that walks every group alike.
impl<T> core::ops::Index<usize> for PerGroup<T> {
    type Output = T;
    fn index(&self, g: usize) -> &T {
        &self.0[g]
    }
}

impl<T> core::ops::IndexMut<usize> for PerGroup<T> {
    fn index_mut(&mut self, g: usize) -> &mut T {
        &mut self.0[g]
    }
}

impl<T> core::ops::Deref for PerGroup<T> {
    type Target = [T; NUM_GROUPS];
    fn deref(&self) -> &[T; NUM_GROUPS] {
        &self.0
    }
}

impl<T> core::ops::DerefMut for PerGroup<T> {
    fn deref_mut(&mut self) -> &mut [T; NUM_GROUPS] {
        &mut self.0
    }
}

impl<T> From<[T; NUM_GROUPS]> for PerGroup<T> {
    fn from(a: [T; NUM_GROUPS]) -> Self {
        Self(a)
    }
}

/// Everything that fixes the shape and behaviour of the field.
///
/// # Examples
///
/// Build the paper's field over a 1 m cube, initialise its parameters and evaluate it at a
/// point:
///
/// ```rust
/// use himap_core::field::model::{
///     color_at, sdf_at, Group, ModelConfig, ModelLayout, Params, SampleScratch,
/// };
/// use himap_core::Aabb;
///
/// let mut config = ModelConfig::paper(Aabb::new([0.0; 3], [1.0; 3]));
/// let layout = ModelLayout::new(&config).unwrap();
/// // One flat buffer per parameter group, initialised deterministically from a seed.
/// let init = |layout: &ModelLayout| -> Vec<Vec<f32>> {
///     Group::ALL
///         .iter()
///         .map(|&g| {
///             let mut v = vec![0.0; layout.group_len(g)];
///             layout.init_group(g, &mut v, 7).unwrap();
///             v
///         })
///         .collect()
/// };
/// let p = init(&layout);
/// assert_eq!(p.iter().map(Vec::len).sum::<usize>(), layout.param_count());
/// assert_eq!(p[Group::Beta as usize], [10.0]);
/// let params = Params {
///     geometry_grid: &p[0][..],
///     appearance_grid: &p[1][..],
///     geometry_mlp: &p[2][..],
///     appearance_mlp: &p[3][..],
///     beta: p[4][0],
/// };
/// let mut scratch = SampleScratch::new();
/// let x = [0.3, 0.5, 0.7];
/// let sdf = sdf_at(&layout, &params, x, &mut scratch);
/// assert!(sdf.is_finite());
/// let rgb = color_at(&layout, &params, x, &mut scratch);
/// assert!(rgb.iter().all(|c| (0.0..=1.0).contains(c)));
///
/// // `sdf_bias_init` shifts the initial signed distance (metres) towards free space.
/// config.sdf_bias_init = 0.5;
/// let biased = ModelLayout::new(&config).unwrap();
/// let q = init(&biased);
/// let params = Params { geometry_mlp: &q[2][..], ..params };
/// let shifted = sdf_at(&biased, &params, x, &mut scratch);
/// assert!((shifted - sdf - 0.5).abs() < 1e-5);
/// ```
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ModelConfig {
    /// Scene box in world coordinates (metres).
    pub aabb: Aabb,
    /// Levels, channels and cell sizes of the geometry grid.
    pub geometry_grid: GridConfig,
    /// Levels, channels and cell sizes of the appearance grid.
    pub appearance_grid: GridConfig,
    /// Hidden units per decoder layer (paper: 32).
    pub hidden: u32,
    /// Hidden ReLU layers per decoder (the paper's "2 layers": two hidden layers + output).
    pub hidden_layers: u32,
    /// Dual path: the appearance decoder also sees the normalised position.
    pub dual_path: bool,
    /// How per-sample SDF values become rendering weights (Hi-Map: [`RenderMode::SdfDensity`]).
    pub render_mode: RenderMode,
    /// Samples per ray (stratified on [near, far] of the ray's box intersection).
    pub samples: u32,
    /// Initial beta of the SDF-to-density proxy (paper: 10).
    pub beta_init: f32,
    /// Standard deviation of the N(0, std^2) grid initialisation.
    pub grid_init_std: f32,
    /// Initial bias of the SDF output (metres); a positive value starts the field as free space.
    pub sdf_bias_init: f32,
    /// Farthest ray depth sampled (in units of the ray parameter `t`: metres of z-depth for
    /// camera rays, whose direction has z = 1 in the camera frame); a ray's samples span
    /// `[near, min(far, max_depth)]` of its box intersection. 0 = no limit (the box exit).
    /// A large scene box (a building, the default box around the first camera) otherwise
    /// spreads the samples over tens of metres.
    pub max_depth: f32,
    /// Samples beyond `max_depth` (0 = none): a ray whose box exit lies beyond `max_depth`
    /// gets this many more, stratified uniformly in inverse depth (disparity) on
    /// `[max_depth, min(exit, far_depth)]`, so that surfaces of a large space beyond
    /// `max_depth` are reached at the cost of a few samples (the near spacing unchanged).
    pub far_samples: u32,
    /// Farthest depth of the `far_samples` (same units as `max_depth`; must exceed it when
    /// `far_samples` > 0).
    pub far_depth: f32,
    /// Early ray termination: compositing stops after the first sample past which the
    /// transmittance is below this (0 = never; [`render`]'s module docs). The samples behind
    /// a surface then cost nothing on the CPU (not evaluated) and nothing in any backward.
    pub min_transmittance: f32,
}

impl ModelConfig {
    /// The paper's field over `aabb`: geometry 6 levels (64..2 cm, 2 channels), appearance
    /// 2 levels (24 cm, 2 cm, 32 channels), 32 hidden units, two hidden layers, dual path,
    /// SDF-as-density with beta 10, 48 samples per ray.
    pub const fn paper(aabb: Aabb) -> Self {
        Self {
            aabb,
            geometry_grid: GridConfig::hi_map_geometry(),
            appearance_grid: GridConfig::hi_map_appearance(),
            hidden: 32,
            hidden_layers: 2,
            dual_path: true,
            render_mode: RenderMode::SdfDensity,
            samples: 48,
            beta_init: 10.0,
            grid_init_std: 0.01,
            sdf_bias_init: 0.0,
            max_depth: 0.0,
            far_samples: 0,
            far_depth: 0.0,
            min_transmittance: 0.0,
        }
    }

    /// Whether rays get [`Self::far_samples`] beyond [`Self::max_depth`].
    #[inline(always)]
    pub fn has_far_segment(&self) -> bool {
        self.far_samples > 0 && self.max_depth > 0.0 && self.far_depth > self.max_depth
    }

    /// The most samples a ray can have: `samples`, plus `far_samples` when rays get them
    /// (at most `MAX_SAMPLES`, at least 1). Per-ray buffers are this long.
    #[inline(always)]
    pub fn max_ray_samples(&self) -> usize {
        let mut n = self.samples as usize;
        if self.has_far_segment() {
            n += self.far_samples as usize;
        }
        if n > MAX_SAMPLES {
            MAX_SAMPLES
        } else if n == 0 {
            1
        } else {
            n
        }
    }
}

/// The shapes and offsets of all parameter groups.
///
/// # Examples
///
/// ```rust
/// use himap_core::field::model::{Group, ModelConfig, ModelLayout, NUM_GROUPS};
/// use himap_core::{Aabb, Error};
///
/// let config = ModelConfig::paper(Aabb::new([-1.0; 3], [1.0; 3]));
/// let layout = ModelLayout::new(&config).unwrap();
/// // Geometry decoder: grid features in, one signed distance out; appearance decoder: the
/// // normalised position (dual path) and the grid features in, RGB out.
/// assert_eq!(layout.geometry_mlp.n_out, 1);
/// assert_eq!(layout.appearance_mlp.n_in as usize, 3 + layout.appearance_grid.feature_dim());
/// assert_eq!(layout.group_len(Group::Beta), 1);
/// assert_eq!(layout.group_lens().len(), NUM_GROUPS);
/// assert_eq!(layout.group_lens().iter().sum::<usize>(), layout.param_count());
///
/// // Invalid configurations are errors, not panics.
/// let empty = ModelConfig::paper(Aabb::new([0.0; 3], [0.0; 3]));
/// assert!(matches!(ModelLayout::new(&empty), Err(Error::InvalidConfig(_))));
/// ```
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ModelLayout {
    /// The configuration the layouts were built from.
    pub config: ModelConfig,
    /// Layout of the geometry grid (group [`Group::GeometryGrid`]).
    pub geometry_grid: GridLayout,
    /// Layout of the appearance grid (group [`Group::AppearanceGrid`]).
    pub appearance_grid: GridLayout,
    /// Layout of the geometry decoder (group [`Group::GeometryMlp`]).
    pub geometry_mlp: MlpLayout,
    /// Layout of the appearance decoder (group [`Group::AppearanceMlp`]).
    pub appearance_mlp: MlpLayout,
}

impl ModelLayout {
    /// Changes the early-termination threshold ([`ModelConfig::min_transmittance`], in
    /// [0, 1); the shapes stay as they are).
    pub fn set_min_transmittance(&mut self, t: f32) -> Result<(), Error> {
        if !(0.0..1.0).contains(&t) {
            return Err(Error::InvalidConfig("min_transmittance must be in [0, 1)"));
        }
        self.config.min_transmittance = t;
        Ok(())
    }

    /// Builds and validates every layout.
    pub fn new(config: &ModelConfig) -> Result<Self, Error> {
        if !config.aabb.is_valid() {
            return Err(Error::InvalidConfig(
                "scene box must be finite with positive extent",
            ));
        }
        if config.samples == 0 || config.samples as usize > MAX_SAMPLES {
            return Err(Error::Capacity {
                what: "samples per ray",
                needed: config.samples as u64,
                capacity: MAX_SAMPLES as u64,
            });
        }
        if config.far_samples > 0 {
            if !(config.max_depth > 0.0 && config.far_depth > config.max_depth) {
                return Err(Error::InvalidConfig(
                    "far_samples needs max_depth > 0 and far_depth > max_depth",
                ));
            }
            if config.samples as usize + config.far_samples as usize > MAX_SAMPLES {
                return Err(Error::Capacity {
                    what: "samples plus far samples per ray",
                    needed: config.samples as u64 + config.far_samples as u64,
                    capacity: MAX_SAMPLES as u64,
                });
            }
        }
        if !(config.beta_init.is_finite() && config.beta_init > 0.0) {
            return Err(Error::InvalidConfig(
                "beta_init must be finite and positive",
            ));
        }
        let geometry_grid = GridLayout::new(&config.geometry_grid, config.aabb)?;
        let appearance_grid = GridLayout::new(&config.appearance_grid, config.aabb)?;
        let geo_in = geometry_grid.feature_dim() as u32;
        let app_in = appearance_grid.feature_dim() as u32 + if config.dual_path { 3 } else { 0 };
        if app_in as usize > MAX_WIDTH {
            return Err(Error::Capacity {
                what: "appearance decoder inputs",
                needed: app_in as u64,
                capacity: MAX_WIDTH as u64,
            });
        }
        let geometry_mlp = MlpLayout::new(geo_in, config.hidden, config.hidden_layers, 1)?;
        let appearance_mlp = MlpLayout::new(app_in, config.hidden, config.hidden_layers, 3)?;
        Ok(Self {
            config: *config,
            geometry_grid,
            appearance_grid,
            geometry_mlp,
            appearance_mlp,
        })
    }

    /// Number of `f32` parameters of a group.
    pub fn group_len(&self, g: Group) -> usize {
        match g {
            Group::GeometryGrid => self.geometry_grid.param_count as usize,
            Group::AppearanceGrid => self.appearance_grid.param_count as usize,
            Group::GeometryMlp => self.geometry_mlp.param_count as usize,
            Group::AppearanceMlp => self.appearance_mlp.param_count as usize,
            Group::Beta => 1,
        }
    }

    /// Lengths of all groups, in [`Group::ALL`] order.
    pub fn group_lens(&self) -> [usize; NUM_GROUPS] {
        let mut out = [0; NUM_GROUPS];
        let mut i = 0;
        while i < NUM_GROUPS {
            out[i] = self.group_len(Group::ALL[i]);
            i += 1;
        }
        out
    }

    /// Total parameter count.
    pub fn param_count(&self) -> usize {
        let l = self.group_lens();
        l[0] + l[1] + l[2] + l[3] + l[4]
    }

    /// Initialises one group's parameters (deterministic for `seed`).
    pub fn init_group(&self, g: Group, params: &mut [f32], seed: u32) -> Result<(), Error> {
        crate::error::check_len(g.name(), params.len(), self.group_len(g))?;
        let s = Self::group_seed(seed, g);
        match g {
            Group::GeometryGrid => {
                grid::grid_init(&self.geometry_grid, params, s, self.config.grid_init_std)
            }
            Group::AppearanceGrid => {
                grid::grid_init(&self.appearance_grid, params, s, self.config.grid_init_std)
            }
            Group::GeometryMlp => {
                mlp::mlp_init(&self.geometry_mlp, params, s)?;
                let out_bias =
                    self.geometry_mlp.bias_offsets[self.geometry_mlp.hidden_layers as usize];
                params[out_bias as usize] += self.config.sdf_bias_init;
                Ok(())
            }
            Group::AppearanceMlp => mlp::mlp_init(&self.appearance_mlp, params, s),
            Group::Beta => {
                params[0] = self.config.beta_init;
                Ok(())
            }
        }
    }

    /// The seed [`Self::init_group`] draws group `g` with.
    pub fn group_seed(seed: u32, g: Group) -> u32 {
        seed.wrapping_mul(16).wrapping_add(g as u32)
    }

    /// Whether [`Self::init_grid_part`] can fill group `g` in parts (the grids, whose values
    /// depend on the parameter index alone).
    pub fn is_grid(g: Group) -> bool {
        matches!(g, Group::GeometryGrid | Group::AppearanceGrid)
    }

    /// [`Self::init_group`]'s values for parameters `start..start + params.len()` of a grid
    /// group: the same bits as the whole group's initialisation, so parts can be filled on
    /// several threads. Errors for other groups, a part past the group's end or an invalid
    /// initialisation scale.
    pub fn init_grid_part(
        &self,
        g: Group,
        params: &mut [f32],
        start: usize,
        seed: u32,
    ) -> Result<(), Error> {
        if !Self::is_grid(g) || start + params.len() > self.group_len(g) {
            return Err(Error::InvalidConfig(
                "init_grid_part: a part of a grid group",
            ));
        }
        let std = self.config.grid_init_std;
        grid::grid_init_part(params, start, Self::group_seed(seed, g), std)
    }
}

/// Read access to the five parameter groups (beta is group 4, one value).
pub struct Params<'a, P: ParamRead + ?Sized> {
    /// Group [`Group::GeometryGrid`].
    pub geometry_grid: &'a P,
    /// Group [`Group::AppearanceGrid`].
    pub appearance_grid: &'a P,
    /// Group [`Group::GeometryMlp`].
    pub geometry_mlp: &'a P,
    /// Group [`Group::AppearanceMlp`].
    pub appearance_mlp: &'a P,
    /// Group [`Group::Beta`]: the SDF-to-density sharpness.
    pub beta: f32,
}

/// Receives gradient contributions for all groups.
pub trait ModelGradSink {
    /// Whether [`Self::prefetch`] does anything (the backward then announces each sample's
    /// gradient rows of the grids' finest levels one sample ahead; sinks without caches leave
    /// it false and pay nothing).
    const PREFETCH: bool = false;

    /// Whether [`Self::add_layer`] takes a decoder layer's contributions in one call (see
    /// [`GradSink::LAYERS`]).
    const LAYERS: bool = false;

    /// Adds one gradient contribution `g` to parameter `i` of `group`.
    fn add(&mut self, group: Group, i: usize, g: f32);

    /// [`GradSink::add_layer`] for `group`.
    #[inline(always)]
    #[allow(clippy::too_many_arguments)]
    fn add_layer(
        &mut self,
        group: Group,
        w_off: usize,
        b_off: usize,
        gs: &[f32; MAX_WIDTH],
        fan_out: usize,
        xs: &[f32; MAX_WIDTH],
        fan_in: usize,
    ) {
        let mut j = 0;
        while j < fan_out && j < MAX_WIDTH {
            let g = gs[j];
            if g != 0.0 {
                self.add(group, b_off + j, g);
                self.add_scaled(group, w_off + j * fan_in, g, xs, fan_in);
            }
            j += 1;
        }
    }

    /// A cache hint: contributions to `group` from `offset` on will follow soon. It changes no
    /// value (host sinks over large buffers overlap the memory latency of the next sample's
    /// rows with the current sample's work).
    #[inline(always)]
    fn prefetch(&mut self, _group: Group, _offset: usize) {}

    /// `add(group, offset + i, g * xs[i])` for every `i < n` (see
    /// [`GradSink::add_scaled`]).
    #[inline(always)]
    fn add_scaled(&mut self, group: Group, offset: usize, g: f32, xs: &[f32; MAX_WIDTH], n: usize) {
        let mut i = 0;
        while i < n && i < MAX_WIDTH {
            self.add(group, offset + i, g * xs[i]);
            i += 1;
        }
    }

    /// `add_scaled(group, offsets[k], gs[k], xs, n)` for each `k` in order (see
    /// [`GradSink::add_scaled_rows`]).
    #[inline(always)]
    fn add_scaled_rows<const R: usize>(
        &mut self,
        group: Group,
        offsets: [usize; R],
        gs: [f32; R],
        xs: &[f32; MAX_WIDTH],
        n: usize,
    ) {
        let mut k = 0;
        while k < R {
            self.add_scaled(group, offsets[k], gs[k], xs, n);
            k += 1;
        }
    }
}

/// Adapts a [`ModelGradSink`] to one group's [`GradSink`].
pub struct GroupSink<'s, S: ModelGradSink> {
    /// The sink of all groups.
    pub inner: &'s mut S,
    /// The group every contribution goes to.
    pub group: Group,
}

impl<S: ModelGradSink> GradSink for GroupSink<'_, S> {
    const LAYERS: bool = S::LAYERS;

    #[inline(always)]
    fn add(&mut self, i: usize, g: f32) {
        self.inner.add(self.group, i, g);
    }

    #[inline(always)]
    fn add_layer(
        &mut self,
        w_off: usize,
        b_off: usize,
        gs: &[f32; MAX_WIDTH],
        fan_out: usize,
        xs: &[f32; MAX_WIDTH],
        fan_in: usize,
    ) {
        self.inner
            .add_layer(self.group, w_off, b_off, gs, fan_out, xs, fan_in);
    }

    #[inline(always)]
    fn add_scaled(&mut self, offset: usize, g: f32, xs: &[f32; MAX_WIDTH], n: usize) {
        self.inner.add_scaled(self.group, offset, g, xs, n);
    }

    #[inline(always)]
    fn add_scaled_rows<const R: usize>(
        &mut self,
        offsets: [usize; R],
        gs: [f32; R],
        xs: &[f32; MAX_WIDTH],
        n: usize,
    ) {
        self.inner.add_scaled_rows(self.group, offsets, gs, xs, n);
    }
}

impl ModelGradSink for crate::NullSink {
    #[inline(always)]
    fn add(&mut self, _group: Group, _i: usize, _g: f32) {}
}

/// One training or rendering ray: world origin, unnormalised direction whose camera-z
/// component is 1 (so t is camera depth), and its targets.
#[derive(Clone, Copy, Debug, PartialEq)]
#[repr(C)]
pub struct Ray {
    /// Origin (the camera centre; world coordinates, metres).
    pub origin: [f32; 3],
    /// Direction in world coordinates, not normalised (camera-z component 1).
    pub dir: [f32; 3],
    /// Target colour in [0, 1].
    pub target: [f32; 3],
    /// Target depth (camera z, metres); <= 0 means none.
    pub target_depth: f32,
}

/// Per-ray samples and field values produced by [`ray_forward`].
pub struct RayCache {
    /// Samples in use (0 when the ray misses the box; fewer than the ray's samples after an
    /// early termination).
    pub n: usize,
    /// Depth of each sample along the ray (the ray parameter: camera z, metres).
    pub t: [f32; MAX_SAMPLES],
    /// Signed distance at each sample (metres).
    pub sdf: [f32; MAX_SAMPLES],
    /// Colour at each sample (RGB in [0, 1]).
    pub rgb: [[f32; 3]; MAX_SAMPLES],
    /// The composited colour, depth, opacity and per-sample weights.
    pub out: RayOutput,
}

impl RayCache {
    /// An empty cache (no samples, all zeros).
    pub const fn new() -> Self {
        Self {
            n: 0,
            t: [0.0; MAX_SAMPLES],
            sdf: [0.0; MAX_SAMPLES],
            rgb: [[0.0; 3]; MAX_SAMPLES],
            out: RayOutput::zeroed(),
        }
    }
}

impl Default for RayCache {
    fn default() -> Self {
        Self::new()
    }
}

/// Scratch space for one sample's evaluation.
pub struct SampleScratch {
    /// Geometry grid features of the last evaluated point.
    pub geo_feat: [f32; MAX_GRID_FEATURES],
    /// Appearance grid features of the last evaluated point.
    pub app_feat: [f32; MAX_GRID_FEATURES],
    /// Input of the last decoder run.
    pub mlp_in: [f32; MAX_WIDTH],
    /// Activations of the last decoder run.
    pub mlp: MlpScratch,
    /// Outputs of the last decoder run.
    pub mlp_out: [f32; MAX_OUT],
}

impl SampleScratch {
    /// All-zero scratch.
    pub const fn new() -> Self {
        Self {
            geo_feat: [0.0; MAX_GRID_FEATURES],
            app_feat: [0.0; MAX_GRID_FEATURES],
            mlp_in: [0.0; MAX_WIDTH],
            mlp: MlpScratch::new(),
            mlp_out: [0.0; MAX_OUT],
        }
    }
}

impl Default for SampleScratch {
    fn default() -> Self {
        Self::new()
    }
}

#[inline(always)]
fn geometry_input(
    layout: &ModelLayout,
    feat: &[f32; MAX_GRID_FEATURES],
    mlp_in: &mut [f32; MAX_WIDTH],
) {
    // (a 128-step scalar loop per sample was 5 % of a CPU training step)
    mlp::copy_prefix(mlp_in, feat, layout.geometry_grid.feature_dim());
}

#[inline(always)]
fn appearance_input(
    layout: &ModelLayout,
    pn: [f32; 3],
    feat: &[f32; MAX_GRID_FEATURES],
    mlp_in: &mut [f32; MAX_WIDTH],
) -> usize {
    let n = layout.appearance_grid.feature_dim();
    let off = if layout.config.dual_path { 3 } else { 0 };
    // Bulk copies on the CPU, the element loop in the shaders (as in `geometry_input`).
    #[cfg(not(target_arch = "spirv"))]
    {
        let n = n.min(MAX_WIDTH - off);
        mlp_in[..off].copy_from_slice(&pn[..off]);
        mlp_in[off..off + n].copy_from_slice(&feat[..n]);
        mlp_in[off + n..].fill(0.0);
    }
    #[cfg(target_arch = "spirv")]
    {
        let mut i = 0;
        while i < MAX_WIDTH {
            mlp_in[i] = if i < off {
                pn[i]
            } else if i < off + n {
                feat[i - off]
            } else {
                0.0
            };
            i += 1;
        }
    }
    off
}

/// Signed distance (metres) at a world point.
pub fn sdf_at<P: ParamRead + ?Sized>(
    layout: &ModelLayout,
    params: &Params<'_, P>,
    p: [f32; 3],
    s: &mut SampleScratch,
) -> f32 {
    sdf_eval(
        layout,
        params,
        p,
        &mut s.geo_feat,
        &mut s.mlp_in,
        &mut s.mlp,
        &mut s.mlp_out,
    )
}

/// [`sdf_at`] over the scratch's parts (the decoder's activations go to `mlp`).
#[inline(always)]
fn sdf_eval<P: ParamRead + ?Sized>(
    layout: &ModelLayout,
    params: &Params<'_, P>,
    p: [f32; 3],
    feat: &mut [f32; MAX_GRID_FEATURES],
    mlp_in: &mut [f32; MAX_WIDTH],
    mlp: &mut MlpScratch,
    out: &mut [f32; MAX_OUT],
) -> f32 {
    grid::grid_forward(&layout.geometry_grid, params.geometry_grid, p, feat);
    geometry_input(layout, feat, mlp_in);
    mlp::mlp_forward(&layout.geometry_mlp, params.geometry_mlp, mlp_in, mlp, out);
    out[0]
}

/// Colour in [0, 1] at a world point.
pub fn color_at<P: ParamRead + ?Sized>(
    layout: &ModelLayout,
    params: &Params<'_, P>,
    p: [f32; 3],
    s: &mut SampleScratch,
) -> [f32; 3] {
    color_eval(
        layout,
        params,
        p,
        &mut s.app_feat,
        &mut s.mlp_in,
        &mut s.mlp,
        &mut s.mlp_out,
    )
}

/// [`color_at`] over the scratch's parts (the decoder's activations go to `mlp`).
#[inline(always)]
fn color_eval<P: ParamRead + ?Sized>(
    layout: &ModelLayout,
    params: &Params<'_, P>,
    p: [f32; 3],
    feat: &mut [f32; MAX_GRID_FEATURES],
    mlp_in: &mut [f32; MAX_WIDTH],
    mlp: &mut MlpScratch,
    out: &mut [f32; MAX_OUT],
) -> [f32; 3] {
    grid::grid_forward(&layout.appearance_grid, params.appearance_grid, p, feat);
    let pn = layout.config.aabb.normalize(p);
    appearance_input(layout, pn, feat, mlp_in);
    mlp::mlp_forward(
        &layout.appearance_mlp,
        params.appearance_mlp,
        mlp_in,
        mlp,
        out,
    );
    [
        math::sigmoid(out[0]),
        math::sigmoid(out[1]),
        math::sigmoid(out[2]),
    ]
}

/// Backward of [`sdf_at`]: contributions to the geometry grid and MLP.
pub fn sdf_backward<P: ParamRead + ?Sized, S: ModelGradSink>(
    layout: &ModelLayout,
    params: &Params<'_, P>,
    p: [f32; 3],
    d_sdf: f32,
    s: &mut SampleScratch,
    sink: &mut S,
) {
    // Recompute the forward activations (the GPU's per-sample pass stores nothing).
    sdf_at(layout, params, p, s);
    sdf_backward_taped(layout, params, p, d_sdf, &s.mlp, sink);
}

/// [`sdf_backward`] from the geometry decoder's activations `mlp` of the forward at `p` (kept
/// by [`SampleTape`]): the same contributions without recomputing the forward.
pub fn sdf_backward_taped<P: ParamRead + ?Sized, S: ModelGradSink>(
    layout: &ModelLayout,
    params: &Params<'_, P>,
    p: [f32; 3],
    d_sdf: f32,
    mlp: &MlpScratch,
    sink: &mut S,
) {
    let d_feat = sdf_decoder_backward(layout, params, d_sdf, mlp, sink);
    let mut gs = GroupSink {
        inner: sink,
        group: Group::GeometryGrid,
    };
    grid::grid_backward(
        &layout.geometry_grid,
        params.geometry_grid,
        p,
        &d_feat,
        &mut gs,
    );
}

/// The geometry decoder's part of [`sdf_backward_taped`]: its parameter contributions, and
/// dL/dfeatures for the grid.
#[inline(always)]
fn sdf_decoder_backward<P: ParamRead + ?Sized, S: ModelGradSink>(
    layout: &ModelLayout,
    params: &Params<'_, P>,
    d_sdf: f32,
    mlp: &MlpScratch,
    sink: &mut S,
) -> [f32; MAX_GRID_FEATURES] {
    let mut d_out = [0.0f32; MAX_OUT];
    d_out[0] = d_sdf;
    let mut d_in = [0.0f32; MAX_WIDTH];
    {
        let mut gs = GroupSink {
            inner: sink,
            group: Group::GeometryMlp,
        };
        mlp::mlp_backward(
            &layout.geometry_mlp,
            params.geometry_mlp,
            mlp,
            &d_out,
            &mut d_in,
            &mut gs,
        );
    }
    let n = layout.geometry_grid.feature_dim();
    let mut d_feat = [0.0f32; MAX_GRID_FEATURES];
    let mut i = 0;
    while i < n {
        d_feat[i] = d_in[i];
        i += 1;
    }
    d_feat
}

/// Backward of [`color_at`]: contributions to the appearance grid and MLP.
pub fn color_backward<P: ParamRead + ?Sized, S: ModelGradSink>(
    layout: &ModelLayout,
    params: &Params<'_, P>,
    p: [f32; 3],
    d_rgb: [f32; 3],
    s: &mut SampleScratch,
    sink: &mut S,
) {
    let rgb = color_at(layout, params, p, s);
    color_backward_taped(layout, params, p, d_rgb, rgb, &s.mlp, sink);
}

/// [`color_backward`] from the colour `rgb` and the appearance decoder's activations `mlp` of
/// the forward at `p` (kept by [`SampleTape`]), without recomputing the forward.
pub fn color_backward_taped<P: ParamRead + ?Sized, S: ModelGradSink>(
    layout: &ModelLayout,
    params: &Params<'_, P>,
    p: [f32; 3],
    d_rgb: [f32; 3],
    rgb: [f32; 3],
    mlp: &MlpScratch,
    sink: &mut S,
) {
    let d_feat = color_decoder_backward(layout, params, d_rgb, rgb, mlp, sink);
    let mut gs = GroupSink {
        inner: sink,
        group: Group::AppearanceGrid,
    };
    grid::grid_backward(
        &layout.appearance_grid,
        params.appearance_grid,
        p,
        &d_feat,
        &mut gs,
    );
}

/// The appearance decoder's part of [`color_backward_taped`]: its parameter contributions,
/// and dL/dfeatures for the grid.
#[inline(always)]
fn color_decoder_backward<P: ParamRead + ?Sized, S: ModelGradSink>(
    layout: &ModelLayout,
    params: &Params<'_, P>,
    d_rgb: [f32; 3],
    rgb: [f32; 3],
    mlp: &MlpScratch,
    sink: &mut S,
) -> [f32; MAX_GRID_FEATURES] {
    let mut d_out = [0.0f32; MAX_OUT];
    let mut c = 0;
    while c < 3 {
        d_out[c] = d_rgb[c] * rgb[c] * (1.0 - rgb[c]);
        c += 1;
    }
    let mut d_in = [0.0f32; MAX_WIDTH];
    {
        let mut gs = GroupSink {
            inner: sink,
            group: Group::AppearanceMlp,
        };
        mlp::mlp_backward(
            &layout.appearance_mlp,
            params.appearance_mlp,
            mlp,
            &d_out,
            &mut d_in,
            &mut gs,
        );
    }
    let n = layout.appearance_grid.feature_dim();
    let off = if layout.config.dual_path { 3 } else { 0 };
    let mut d_feat = [0.0f32; MAX_GRID_FEATURES];
    let mut i = 0;
    while i < n {
        d_feat[i] = d_in[off + i];
        i += 1;
    }
    d_feat
}

#[inline(always)]
fn point_on_ray(ray: &Ray, t: f32) -> [f32; 3] {
    [
        ray.origin[0] + t * ray.dir[0],
        ray.origin[1] + t * ray.dir[1],
        ray.origin[2] + t * ray.dir[2],
    ]
}

/// A ray's sample segments: `n_near` stratified samples on `[near, mid]`, then `n - n_near`
/// stratified in inverse depth on `[mid, far]` (none unless the far segment applies).
#[derive(Clone, Copy)]
struct Segments {
    near: f32,
    mid: f32,
    far: f32,
    n_near: usize,
    n: usize,
}

/// The segments of `ray`: the box intersection, cut at `max_depth`; when the box exit lies
/// beyond `max_depth` and [`ModelConfig::has_far_segment`], `far_samples` more up to
/// `min(exit, far_depth)`. `n = 0` when the ray misses the box.
#[inline(always)]
fn ray_segments(layout: &ModelLayout, ray: &Ray) -> Segments {
    let c = &layout.config;
    let (near, exit, hit) = render::ray_aabb(ray.origin, ray.dir, &c.aabb);
    let mut mid = exit;
    let limit = c.max_depth;
    if limit > 0.0 && mid > limit {
        mid = limit;
    }
    let mut seg = Segments {
        near,
        mid,
        far: mid,
        n_near: 0,
        n: 0,
    };
    if !(hit && mid > near) {
        return seg;
    }
    let n = c.samples as usize;
    seg.n_near = if n > MAX_SAMPLES { MAX_SAMPLES } else { n };
    seg.n = seg.n_near;
    if c.has_far_segment() && exit > mid {
        seg.far = if exit < c.far_depth {
            exit
        } else {
            c.far_depth
        };
        let total = seg.n_near + c.far_samples as usize;
        seg.n = if total > MAX_SAMPLES {
            MAX_SAMPLES
        } else {
            total
        };
    }
    seg
}

/// Where a ray's samples lie: the depth of its first sample bin's start, of its last one's
/// end, and its sample count (`layout.config.samples`, plus `far_samples` when the far
/// segment applies, at most `MAX_SAMPLES`; 0 when the ray misses the box).
#[inline(always)]
pub fn ray_span(layout: &ModelLayout, ray: &Ray) -> (f32, f32, usize) {
    let s = ray_segments(layout, ray);
    (s.near, s.far, s.n)
}

/// Sample `k < seg.n` of a ray.
#[inline(always)]
fn segment_sample(seg: &Segments, seed: u32, ray_id: u32, jitter: bool, k: usize) -> f32 {
    if k < seg.n_near {
        render::stratified_sample(seg.near, seg.mid, seg.n_near, seed, ray_id, jitter, k)
    } else {
        render::disparity_sample(
            seg.mid,
            seg.far,
            seg.n - seg.n_near,
            seed,
            ray_id,
            jitter,
            k,
            k - seg.n_near,
        )
    }
}

/// The sample depths of a ray: `t[0..n]` stratified between the ray's entry into the scene
/// box and `max_depth` (or the box exit), then the far segment's (jittered with
/// `seed`/`ray_id` when `jitter`, bin centres otherwise); entries past `n` are the last
/// depth. Returns `n` ([`ray_span`]). Stage 1 of [`ray_forward`]; [`ray_sample`] gives one
/// of them.
pub fn ray_samples(
    layout: &ModelLayout,
    ray: &Ray,
    ray_id: u32,
    seed: u32,
    jitter: bool,
    t: &mut [f32; MAX_SAMPLES],
) -> usize {
    let seg = ray_segments(layout, ray);
    if seg.n > 0 {
        if seg.n == seg.n_near {
            render::stratified_samples(seg.near, seg.mid, seg.n, seed, ray_id, jitter, t);
        } else {
            let mut k = 0;
            while k < MAX_SAMPLES {
                t[k] = if k < seg.n {
                    segment_sample(&seg, seed, ray_id, jitter, k)
                } else {
                    seg.far
                };
                k += 1;
            }
        }
    }
    seg.n
}

/// Depth `t_k` of sample `k` of a ray, the same bits as [`ray_samples`] writes, and the ray's
/// sample count `n` (`t_k` is meaningless when `k >= n`). The GPU runs it once per (ray,
/// sample) invocation.
#[inline(always)]
pub fn ray_sample(
    layout: &ModelLayout,
    ray: &Ray,
    ray_id: u32,
    seed: u32,
    jitter: bool,
    k: usize,
) -> (f32, usize) {
    let seg = ray_segments(layout, ray);
    if k >= seg.n {
        return (seg.far, seg.n);
    }
    (segment_sample(&seg, seed, ray_id, jitter, k), seg.n)
}

/// Signed distance and colour at depth `t` along `ray` (stage 2 of [`ray_forward`], one
/// sample).
#[inline(always)]
pub fn sample_forward<P: ParamRead + ?Sized>(
    layout: &ModelLayout,
    params: &Params<'_, P>,
    ray: &Ray,
    t: f32,
    s: &mut SampleScratch,
) -> (f32, [f32; 3]) {
    let p = point_on_ray(ray, t);
    let sdf = sdf_at(layout, params, p, s);
    (sdf, color_at(layout, params, p, s))
}

/// Composites `cache.t/sdf/rgb[0..cache.n]` into `cache.out` (stage 3 of [`ray_forward`]);
/// `n = 0` renders nothing (all zeros). With early termination
/// (`ModelConfig::min_transmittance`) `cache.n` becomes the number of samples used, which
/// the backward then covers.
#[inline(always)]
pub fn ray_composite(layout: &ModelLayout, beta: f32, cache: &mut RayCache) {
    if cache.n == 0 {
        cache.out = RayOutput::zeroed();
        return;
    }
    cache.n = render::render_forward(
        layout.config.render_mode,
        cache.n,
        &cache.sdf,
        &cache.rgb,
        &cache.t,
        beta,
        layout.config.min_transmittance,
        &mut cache.out,
    );
}

/// Samples a ray inside the scene box, evaluates the field and renders colour, depth and
/// opacity into `cache`. A ray that misses the box renders nothing (n = 0, all zeros).
/// `jitter` selects stratified jitter (training) or bin centres (rendering and evaluation).
/// The three stages ([`ray_samples`], [`sample_forward`] per sample, [`ray_composite`]) are
/// public so that a GPU can run them as separate passes with the same results.
#[allow(clippy::too_many_arguments)]
pub fn ray_forward<P: ParamRead + ?Sized>(
    layout: &ModelLayout,
    params: &Params<'_, P>,
    ray: &Ray,
    ray_id: u32,
    seed: u32,
    jitter: bool,
    cache: &mut RayCache,
    s: &mut SampleScratch,
) {
    ray_forward_taped(
        layout,
        params,
        ray,
        ray_id,
        seed,
        jitter,
        cache,
        s,
        &mut Recompute,
    );
}

/// How a ray's forward keeps what its backward needs: [`Recompute`] keeps nothing (the
/// backward evaluates each sample again, as the GPU's per-sample pass does), [`StoredTape`]
/// keeps both decoders' activations of every sample. Both give the same bits: the backward
/// reads the activations of the same forward calls.
pub trait SampleTape {
    /// [`sample_forward`] of sample `i` at depth `t`.
    fn forward<P: ParamRead + ?Sized>(
        &mut self,
        layout: &ModelLayout,
        params: &Params<'_, P>,
        ray: &Ray,
        i: usize,
        t: f32,
        s: &mut SampleScratch,
    ) -> (f32, [f32; 3]);

    /// [`SampleTape::forward`] for a render, which runs no backward: the same values; the tape
    /// need not keep what only a backward reads (by default the forward itself).
    #[inline(always)]
    fn render_forward<P: ParamRead + ?Sized>(
        &mut self,
        layout: &ModelLayout,
        params: &Params<'_, P>,
        ray: &Ray,
        i: usize,
        t: f32,
        s: &mut SampleScratch,
    ) -> (f32, [f32; 3]) {
        self.forward(layout, params, ray, i, t, s)
    }

    /// The signed distance of [`SampleTape::forward`] alone (the same bits), for renders that
    /// need depth and opacity only ([`ray_depth_forward_taped`]); the tape keeps nothing a
    /// backward could use.
    fn sdf_forward<P: ParamRead + ?Sized>(
        &mut self,
        layout: &ModelLayout,
        params: &Params<'_, P>,
        ray: &Ray,
        _i: usize,
        t: f32,
        s: &mut SampleScratch,
    ) -> f32 {
        sdf_at(layout, params, point_on_ray(ray, t), s)
    }

    /// [`sample_backward`] of sample `i` (depth `t`, colour `rgb` from the forward).
    #[allow(clippy::too_many_arguments)]
    fn backward<P: ParamRead + ?Sized, S: ModelGradSink>(
        &self,
        layout: &ModelLayout,
        params: &Params<'_, P>,
        ray: &Ray,
        i: usize,
        t: f32,
        rgb: [f32; 3],
        d_sdf: f32,
        d_rgb: [f32; 3],
        s: &mut SampleScratch,
        sink: &mut S,
    );

    /// Whether [`SampleTape::forward_lanes`] evaluates samples side by side (the CPU's
    /// lanes); a ray's forward then takes them [`LANES`] at a time. Host-side.
    #[cfg(not(target_arch = "spirv"))]
    #[inline(always)]
    fn has_lanes(&self) -> bool {
        false
    }

    /// [`SampleTape::forward`] (`keep`; a render's [`SampleTape::render_forward`] otherwise)
    /// of samples `i..i + k` at depths `ts[..k]`, `k = min(LANES, ts.len())` (`ts` holds the
    /// depths of the ray's remaining samples, `ts[k]` the next one's, for the cache hint):
    /// sample `i + l`'s signed distance and colour to `sdf[l]` and `rgb[l]`, the same bits as
    /// one at a time (the default, [`forward_one_at_a_time`]). Host-side.
    #[cfg(not(target_arch = "spirv"))]
    #[allow(clippy::too_many_arguments)]
    #[inline(always)]
    fn forward_lanes<P: ParamRead + ?Sized>(
        &mut self,
        layout: &ModelLayout,
        params: &Params<'_, P>,
        ray: &Ray,
        i: usize,
        ts: &[f32],
        keep: bool,
        s: &mut SampleScratch,
        sdf: &mut [f32; LANES],
        rgb: &mut [[f32; 3]; LANES],
    ) {
        forward_one_at_a_time(self, layout, params, ray, i, ts, keep, s, sdf, rgb);
    }

    /// Whether a render may evaluate the appearance of only the samples whose rendering
    /// weight is not zero ([`ray_forward_taped`]): each other sample adds `+0 * c = +0` to the
    /// colour, the same bits, provided its colour `c` is not NaN, which the tape's owner must
    /// have shown ([`crate::field::negligible::appearance_output_finite`]). Host-side.
    #[cfg(not(target_arch = "spirv"))]
    #[inline(always)]
    fn lazy_color(&self) -> bool {
        false
    }

    /// A render's forward of the samples at depths `ts[..min(LANES, ts.len())]` for one part:
    /// with `GEO` their signed distances into `sdf`, with `APP` their colours into `rgb`, the
    /// bits of [`SampleTape::forward_lanes`] (which the default runs, computing both).
    /// Host-side.
    #[cfg(not(target_arch = "spirv"))]
    #[allow(clippy::too_many_arguments)]
    #[inline(always)]
    fn render_lanes_part<P: ParamRead + ?Sized, const GEO: bool, const APP: bool>(
        &mut self,
        layout: &ModelLayout,
        params: &Params<'_, P>,
        ray: &Ray,
        ts: &[f32],
        s: &mut SampleScratch,
        sdf: &mut [f32; LANES],
        rgb: &mut [[f32; 3]; LANES],
    ) {
        self.forward_lanes(layout, params, ray, 0, ts, false, s, sdf, rgb);
    }

    /// A cache hint: the forward of the sample at depth `t` comes next (nothing by default;
    /// no value changes).
    #[inline(always)]
    fn prefetch<P: ParamRead + ?Sized>(
        &self,
        _layout: &ModelLayout,
        _params: &Params<'_, P>,
        _ray: &Ray,
        _t: f32,
    ) {
    }
}

/// [`SampleTape::forward_lanes`]'s samples one at a time: each with the cache hint for the
/// next, through [`SampleTape::forward`] (`keep`) or [`SampleTape::render_forward`].
#[cfg(not(target_arch = "spirv"))]
#[allow(clippy::too_many_arguments)]
#[inline(always)]
fn forward_one_at_a_time<T: SampleTape + ?Sized, P: ParamRead + ?Sized>(
    tape: &mut T,
    layout: &ModelLayout,
    params: &Params<'_, P>,
    ray: &Ray,
    i: usize,
    ts: &[f32],
    keep: bool,
    s: &mut SampleScratch,
    sdf: &mut [f32; LANES],
    rgb: &mut [[f32; 3]; LANES],
) {
    for (l, &t) in ts.iter().take(LANES).enumerate() {
        if let Some(&next) = ts.get(l + 1) {
            tape.prefetch(layout, params, ray, next);
        }
        (sdf[l], rgb[l]) = if keep {
            tape.forward(layout, params, ray, i + l, t, s)
        } else {
            tape.render_forward(layout, params, ray, i + l, t, s)
        };
    }
}

/// A CPU's cache hint for parameter rows, which `himap-core` cannot issue itself (it is
/// `unsafe`-free and runs on GPUs): [`StoredTape`] names to it, one sample ahead, the rows of
/// the appearance grid's finest level (the planes too large for the caches) that the next
/// sample's forward reads. The hint changes no value.
pub trait RowHint {
    /// Whether [`Self::prefetch`] does anything (tapes without a hint skip naming the rows).
    const ACTIVE: bool = false;

    /// Asks for `row` (one grid row: its channels) to be brought towards the cache.
    #[inline(always)]
    fn prefetch(_row: &[f32]) {}

    /// Whether this CPU runs [`RowHint::mlp_forward_lanes`] fast enough for a ray's samples
    /// to go through the decoders [`LANES`] at a time (false by default: the portable form
    /// is correct but slower than one sample at a time, since compilers vectorise it across
    /// the units; ARCHITECTURE.md).
    #[cfg(not(target_arch = "spirv"))]
    #[inline(always)]
    fn lanes_pay() -> bool {
        false
    }

    /// [`mlp::mlp_forward_lanes`] (which it is by default): a CPU may run it with its own
    /// vector instructions, every lane the same bits (tested where it does).
    #[cfg(not(target_arch = "spirv"))]
    #[inline(always)]
    fn mlp_forward_lanes(
        layout: &MlpLayout,
        wt: &[f32],
        lanes: &mut MlpLanes,
        out: &mut [[f32; LANES]; MAX_OUT],
    ) {
        mlp::mlp_forward_lanes(layout, wt, lanes, out);
    }
}

/// Names to `H` the 12 plane rows (each its channels) of level `l` of grid `g` (parameters
/// `sl`) that a forward at `p` reads ([`grid::for_each_plane_row`]).
#[inline(always)]
fn hint_plane_rows<H: RowHint>(g: &GridLayout, sl: &[f32], l: usize, p: [f32; 3]) {
    let nc = g.channels as usize;
    grid::for_each_plane_row(g, l, p, |o| {
        if let Some(row) = sl.get(o..o + nc) {
            H::prefetch(row);
        }
    });
}

/// No cache hint.
pub struct NoHint;

impl RowHint for NoHint {}

/// The tape that keeps nothing: the backward recomputes each sample's forward.
pub struct Recompute;

impl SampleTape for Recompute {
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
        sample_forward(layout, params, ray, t, s)
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
}

/// A tape over caller-owned storage: the geometry and appearance decoders' activations of
/// every sample (`geometry[i]`, `appearance[i]`, at least as many as the ray has samples;
/// samples past the end are recomputed). The forward runs the decoders with
/// [`mlp::mlp_forward_transposed`] on `geometry_wt` / `appearance_wt`, the decoders' weights
/// as [`mlp::transpose_weights`] lays them out (same bits as [`mlp::mlp_forward`]).
pub struct StoredTape<'a, H: RowHint = NoHint> {
    /// Geometry decoder activations, one entry per sample.
    pub geometry: &'a mut [MlpScratch],
    /// Appearance decoder activations, one entry per sample.
    pub appearance: &'a mut [MlpScratch],
    /// The geometry decoder's weights, transposed ([`mlp::transpose_weights`]).
    pub geometry_wt: &'a [f32],
    /// The appearance decoder's weights, transposed ([`mlp::transpose_weights`]).
    pub appearance_wt: &'a [f32],
    /// Factor rows the grids' backward reuses from sample to sample
    /// ([`grid::grid_backward_rows_with`]; any contents).
    pub grid_rows: &'a core::cell::RefCell<[[f32; MAX_WIDTH]; 6]>,
    /// The grids' term factors of every sample, [`grid_tape_len`] floats per sample: whether
    /// each grid's were kept (1 or 0), then the geometry's and the appearance's
    /// ([`grid::grid_forward_rows_keep`]), which the backward multiplies by the features'
    /// cotangents instead of interpolating the grids again. May be empty (the backward then
    /// interpolates; samples past its end likewise).
    pub grid_kept: &'a mut [f32],
    /// The cache hint ([`NoHint`] or the CPU's).
    pub hint: core::marker::PhantomData<H>,
    /// Lanes for the geometry and the appearance decoder: with them (and a hint whose
    /// [`RowHint::lanes_pay`]) a ray's forward evaluates [`LANES`] samples side by side
    /// ([`RowHint::mlp_forward_lanes`], the same bits), without them one at a time. Host-side.
    #[cfg(not(target_arch = "spirv"))]
    pub lanes: Option<&'a mut [MlpLanes; 2]>,
    /// The decoders' weight bounds for this step's parameters: with them, the backward skips a
    /// sample's decoder branch whose contributions provably all round to 0 quanta
    /// ([`crate::field::negligible`]; the same sums). `None`: every branch runs. Host-side.
    #[cfg(not(target_arch = "spirv"))]
    pub bounds: Option<crate::field::negligible::DecoderBounds>,
    /// Counts of the backward's sample branches with a non-zero cotangent that met the
    /// bounds (`.0`) and of those skipped as negligible (`.1`), for the profile. Host-side.
    #[cfg(not(target_arch = "spirv"))]
    pub negligible_counts: core::cell::Cell<(u64, u64)>,
    /// [`SampleTape::lazy_color`]: set only where the appearance decoder's output is shown
    /// finite for every sample of the current parameters. Host-side.
    #[cfg(not(target_arch = "spirv"))]
    pub lazy_color: bool,
}

/// Floats per sample of [`StoredTape::grid_kept`] for `layout`: two flags, then the term
/// factors of the geometry and of the appearance grid ([`grid::kept_len`]).
pub fn grid_tape_len(layout: &ModelLayout) -> usize {
    2 + grid::kept_len(&layout.geometry_grid) + grid::kept_len(&layout.appearance_grid)
}

/// One sample's record of [`StoredTape::grid_kept`], split into its flags, the geometry's and
/// the appearance's factors; `None` when the slice does not hold sample `i`.
#[inline(always)]
#[allow(clippy::type_complexity)]
fn kept_record<'k>(
    layout: &ModelLayout,
    kept: &'k mut [f32],
    i: usize,
) -> Option<(&'k mut [f32], &'k mut [f32], &'k mut [f32])> {
    let n = grid_tape_len(layout);
    let rec = kept.get_mut(i * n..(i + 1) * n)?;
    let (flags, rest) = rec.split_at_mut(2);
    let (geo, app) = rest.split_at_mut(grid::kept_len(&layout.geometry_grid));
    Some((flags, geo, app))
}

impl<H: RowHint> SampleTape for StoredTape<'_, H> {
    #[inline(always)]
    fn prefetch<P: ParamRead + ?Sized>(
        &self,
        layout: &ModelLayout,
        params: &Params<'_, P>,
        ray: &Ray,
        t: f32,
    ) {
        if !H::ACTIVE {
            return;
        }
        let Some(sl) = params.appearance_grid.as_slice() else {
            return;
        };
        let g = &layout.appearance_grid;
        hint_plane_rows::<H>(
            g,
            sl,
            (g.levels as usize).saturating_sub(1),
            point_on_ray(ray, t),
        );
    }

    #[cfg(not(target_arch = "spirv"))]
    #[inline(always)]
    fn has_lanes(&self) -> bool {
        self.lanes.is_some() && H::lanes_pay()
    }

    #[cfg(not(target_arch = "spirv"))]
    #[inline(always)]
    fn forward_lanes<P: ParamRead + ?Sized>(
        &mut self,
        layout: &ModelLayout,
        params: &Params<'_, P>,
        ray: &Ray,
        i: usize,
        ts: &[f32],
        keep: bool,
        s: &mut SampleScratch,
        sdf: &mut [f32; LANES],
        rgb: &mut [[f32; 3]; LANES],
    ) {
        if keep {
            self.lanes_forward::<P, true, true, true>(layout, params, ray, i, ts, s, sdf, rgb);
        } else {
            self.lanes_forward::<P, false, true, true>(layout, params, ray, i, ts, s, sdf, rgb);
        }
    }

    #[cfg(not(target_arch = "spirv"))]
    #[inline(always)]
    fn lazy_color(&self) -> bool {
        self.lazy_color
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
        sdf: &mut [f32; LANES],
        rgb: &mut [[f32; 3]; LANES],
    ) {
        self.lanes_forward::<P, false, GEO, APP>(layout, params, ray, 0, ts, s, sdf, rgb);
    }

    #[inline(always)]
    fn forward<P: ParamRead + ?Sized>(
        &mut self,
        layout: &ModelLayout,
        params: &Params<'_, P>,
        ray: &Ray,
        i: usize,
        t: f32,
        s: &mut SampleScratch,
    ) -> (f32, [f32; 3]) {
        let (Some(g), Some(a)) = (self.geometry.get_mut(i), self.appearance.get_mut(i)) else {
            return sample_forward(layout, params, ray, t, s);
        };
        let p = point_on_ray(ray, t);
        // Without a record (samples past the buffer's end) nothing is kept.
        let (flags, kg, ka) = match kept_record(layout, self.grid_kept, i) {
            Some((f, kg, ka)) => (Some(f), Some(kg), Some(ka)),
            None => (None, None, None),
        };
        let (sdf, keep_g) = sdf_eval_keep(layout, params, self.geometry_wt, p, s, g, kg);
        let (rgb, keep_a) = color_eval_keep(layout, params, self.appearance_wt, p, s, a, ka);
        if let Some(f) = flags {
            f[0] = if keep_g { 1.0 } else { 0.0 };
            f[1] = if keep_a { 1.0 } else { 0.0 };
        }
        (sdf, rgb)
    }

    #[inline(always)]
    fn sdf_forward<P: ParamRead + ?Sized>(
        &mut self,
        layout: &ModelLayout,
        params: &Params<'_, P>,
        ray: &Ray,
        i: usize,
        t: f32,
        s: &mut SampleScratch,
    ) -> f32 {
        let p = point_on_ray(ray, t);
        let Some(g) = self.geometry.get_mut(i) else {
            return sdf_at(layout, params, p, s);
        };
        sdf_eval_transposed(layout, params, self.geometry_wt, p, s, g)
    }

    #[inline(always)]
    fn render_forward<P: ParamRead + ?Sized>(
        &mut self,
        layout: &ModelLayout,
        params: &Params<'_, P>,
        ray: &Ray,
        i: usize,
        t: f32,
        s: &mut SampleScratch,
    ) -> (f32, [f32; 3]) {
        let (Some(g), Some(a)) = (self.geometry.get_mut(i), self.appearance.get_mut(i)) else {
            return sample_forward(layout, params, ray, t, s);
        };
        let p = point_on_ray(ray, t);
        let sdf = sdf_eval_transposed(layout, params, self.geometry_wt, p, s, g);
        (
            sdf,
            color_eval_transposed(layout, params, self.appearance_wt, p, s, a),
        )
    }

    #[inline(always)]
    fn backward<P: ParamRead + ?Sized, S: ModelGradSink>(
        &self,
        layout: &ModelLayout,
        params: &Params<'_, P>,
        ray: &Ray,
        i: usize,
        t: f32,
        rgb: [f32; 3],
        d_sdf: f32,
        d_rgb: [f32; 3],
        s: &mut SampleScratch,
        sink: &mut S,
    ) {
        let (Some(g), Some(a)) = (self.geometry.get(i), self.appearance.get(i)) else {
            return sample_backward(layout, params, ray, t, d_sdf, d_rgb, s, sink);
        };
        let p = point_on_ray(ray, t);
        let n = grid_tape_len(layout);
        let rec = self.grid_kept.get(i * n..(i + 1) * n);
        let ng = grid::kept_len(&layout.geometry_grid);
        // The kept factors of a grid, when the forward kept them.
        let kept = |k: usize, range: core::ops::Range<usize>| match rec {
            Some(r) if r[k] == 1.0 => r.get(range),
            _ => None,
        };
        if d_sdf != 0.0 && !self.negligible(layout, Branch::Geometry, d_sdf, [0.0; 3], rgb, g, rec)
        {
            let d_feat = sdf_decoder_backward(layout, params, d_sdf, g, sink);
            let mut gs = GroupSink {
                inner: &mut *sink,
                group: Group::GeometryGrid,
            };
            grid_backward_reusing(
                &layout.geometry_grid,
                params.geometry_grid,
                p,
                &d_feat,
                &mut gs,
                self.grid_rows,
                kept(0, 2..2 + ng),
            );
        }
        let colored = d_rgb[0] != 0.0 || d_rgb[1] != 0.0 || d_rgb[2] != 0.0;
        if colored && !self.negligible(layout, Branch::Appearance, 0.0, d_rgb, rgb, a, rec) {
            let d_feat = color_decoder_backward(layout, params, d_rgb, rgb, a, sink);
            let mut gs = GroupSink {
                inner: sink,
                group: Group::AppearanceGrid,
            };
            grid_backward_reusing(
                &layout.appearance_grid,
                params.appearance_grid,
                p,
                &d_feat,
                &mut gs,
                self.grid_rows,
                kept(1, 2 + ng..n),
            );
        }
    }
}

/// A decoder branch of a sample's backward.
#[derive(Clone, Copy, PartialEq, Eq)]
enum Branch {
    Geometry,
    Appearance,
}

#[cfg(target_arch = "spirv")]
impl<H: RowHint> StoredTape<'_, H> {
    /// The shaders never skip a branch.
    #[inline(always)]
    #[allow(clippy::too_many_arguments)]
    fn negligible(
        &self,
        _layout: &ModelLayout,
        _branch: Branch,
        _d_sdf: f32,
        _d_rgb: [f32; 3],
        _rgb: [f32; 3],
        _act: &MlpScratch,
        _rec: Option<&[f32]>,
    ) -> bool {
        false
    }
}

#[cfg(not(target_arch = "spirv"))]
impl<H: RowHint> StoredTape<'_, H> {
    /// Whether a sample's `branch` (its decoder's backward from `d_sdf` or from `d_rgb` and
    /// `rgb`, then its grid's through the kept term factors in `rec`) provably adds only
    /// zeros ([`crate::field::negligible::branch_negligible`]); false without bounds, without
    /// kept factors, or for cotangents of 2^-40 and more.
    #[inline(always)]
    #[allow(clippy::too_many_arguments)]
    fn negligible(
        &self,
        layout: &ModelLayout,
        branch: Branch,
        d_sdf: f32,
        d_rgb: [f32; 3],
        rgb: [f32; 3],
        act: &MlpScratch,
        rec: Option<&[f32]>,
    ) -> bool {
        use crate::field::negligible::{below_gate, branch_negligible, color_top, sdf_top};
        let Some(bounds) = &self.bounds else {
            return false;
        };
        // The gate first: a branch with a cotangent of 2^-40 or more costs one compare.
        let (gated, mlp, w, flag) = match branch {
            Branch::Geometry => (below_gate(d_sdf), &layout.geometry_mlp, &bounds.geometry, 0),
            Branch::Appearance => (
                d_rgb.iter().all(|&d| below_gate(d)),
                &layout.appearance_mlp,
                &bounds.appearance,
                1,
            ),
        };
        let skip = gated && {
            let ng = grid::kept_len(&layout.geometry_grid);
            let range = if flag == 0 {
                2..2 + ng
            } else {
                2 + ng..grid_tape_len(layout)
            };
            let kept = match rec {
                Some(r) if r[flag] == 1.0 && !range.is_empty() => r.get(range),
                _ => None,
            };
            kept.is_some_and(|kept| {
                let top = match branch {
                    Branch::Geometry => sdf_top(d_sdf),
                    Branch::Appearance => color_top(d_rgb, rgb),
                };
                branch_negligible(mlp, act, w, top, kept)
            })
        };
        let (seen, skipped) = self.negligible_counts.get();
        self.negligible_counts
            .set((seen + 1, skipped + skip as u64));
        skip
    }
    /// [`SampleTape::forward_lanes`] (`KEEP`: the training forward, which records every
    /// sample's grid factors and decoder activations as [`SampleTape::forward`] does; `!KEEP`:
    /// a render, which records nothing). The grids and the
    /// decoders' inputs sample by sample (the functions of the one-sample forward), then both
    /// decoders for all samples at once in lanes ([`mlp::mlp_forward_lanes`]): each sample's
    /// bits. Samples the tape has no record for, or no lanes, go one at a time.
    #[allow(clippy::too_many_arguments)]
    #[inline(always)]
    fn lanes_forward<P: ParamRead + ?Sized, const KEEP: bool, const GEO: bool, const APP: bool>(
        &mut self,
        layout: &ModelLayout,
        params: &Params<'_, P>,
        ray: &Ray,
        i: usize,
        ts: &[f32],
        s: &mut SampleScratch,
        sdf: &mut [f32; LANES],
        rgb: &mut [[f32; 3]; LANES],
    ) {
        // A part alone only for a render (a training forward keeps both decoders' records).
        const { assert!(!KEEP || (GEO && APP)) };
        let k = ts.len().min(LANES);
        let recorded = !KEEP || (i + k <= self.geometry.len() && i + k <= self.appearance.len());
        let lanes = match self.lanes.take() {
            Some(l) if recorded => l,
            other => {
                self.lanes = other;
                let keep = KEEP;
                return forward_one_at_a_time(self, layout, params, ray, i, ts, keep, s, sdf, rgb);
            }
        };
        let [gl, al] = &mut *lanes;
        let (gm, am) = (&layout.geometry_mlp, &layout.appearance_mlp);
        let (gn, an) = (gm.dims().0, am.dims().0);
        for (l, &t) in ts.iter().take(LANES).enumerate() {
            // The cache hint one sample ahead in a ray's first group; the later groups'
            // samples were named during the previous group's decoders (below).
            if i == 0 && APP {
                if let Some(&next) = ts.get(l + 1) {
                    self.prefetch(layout, params, ray, next);
                }
            }
            let p = point_on_ray(ray, t);
            let (flags, kg, ka) = if KEEP {
                match kept_record(layout, self.grid_kept, i + l) {
                    Some((f, kg, ka)) => (Some(f), Some(kg), Some(ka)),
                    None => (None, None, None),
                }
            } else {
                (None, None, None)
            };
            let mut keep_g = false;
            if GEO {
                keep_g = grid_forward_keeping(
                    &layout.geometry_grid,
                    params.geometry_grid,
                    p,
                    &mut s.geo_feat,
                    kg,
                );
                geometry_input(layout, &s.geo_feat, &mut s.mlp_in);
                for (a, &v) in gl.act[0][..gn].iter_mut().zip(&s.mlp_in[..gn]) {
                    a[l] = v;
                }
                if KEEP {
                    self.geometry[i + l].act[0][..gn].copy_from_slice(&s.mlp_in[..gn]);
                }
            }
            let mut keep_a = false;
            if APP {
                keep_a = grid_forward_keeping(
                    &layout.appearance_grid,
                    params.appearance_grid,
                    p,
                    &mut s.app_feat,
                    ka,
                );
                let pn = layout.config.aabb.normalize(p);
                appearance_input(layout, pn, &s.app_feat, &mut s.mlp_in);
                for (a, &v) in al.act[0][..an].iter_mut().zip(&s.mlp_in[..an]) {
                    a[l] = v;
                }
                if KEEP {
                    self.appearance[i + l].act[0][..an].copy_from_slice(&s.mlp_in[..an]);
                }
            }
            if let Some(f) = flags {
                f[0] = if keep_g { 1.0 } else { 0.0 };
                f[1] = if keep_a { 1.0 } else { 0.0 };
            }
        }
        // The next group's rows load while the decoders run: the appearance's finest level
        // (as one sample ahead) and the geometry's two finest.
        for &t in ts.iter().skip(k).take(LANES) {
            if APP {
                self.prefetch(layout, params, ray, t);
            }
            if let (true, true, Some(sl)) = (GEO, H::ACTIVE, params.geometry_grid.as_slice()) {
                let g = &layout.geometry_grid;
                let p = point_on_ray(ray, t);
                for lv in (g.levels as usize).saturating_sub(GROUP_HINT_LEVELS)..g.levels as usize {
                    hint_plane_rows::<H>(g, sl, lv, p);
                }
            }
        }
        let mut go = [[0.0f32; LANES]; MAX_OUT];
        let mut ao = [[0.0f32; LANES]; MAX_OUT];
        if GEO {
            H::mlp_forward_lanes(gm, self.geometry_wt, gl, &mut go);
        }
        if APP {
            H::mlp_forward_lanes(am, self.appearance_wt, al, &mut ao);
        }
        for l in 0..k {
            if GEO {
                sdf[l] = go[0][l];
            }
            if APP {
                rgb[l] = [
                    math::sigmoid(ao[0][l]),
                    math::sigmoid(ao[1][l]),
                    math::sigmoid(ao[2][l]),
                ];
            }
        }
        if KEEP {
            // The hidden activations into each sample's record, for the decoders' backward.
            lanes_to_tape(gm, gl, &mut self.geometry[i..i + k]);
            lanes_to_tape(am, al, &mut self.appearance[i..i + k]);
        }
        self.lanes = Some(lanes);
    }
}

/// The hidden activations of lane `l` of `lanes` into `tape[l]` (sample by sample, what
/// [`mlp::mlp_forward_transposed`] leaves in its scratch).
#[cfg(not(target_arch = "spirv"))]
#[inline(always)]
fn lanes_to_tape(m: &MlpLayout, lanes: &MlpLanes, tape: &mut [MlpScratch]) {
    let (_, hidden, layers, _) = m.dims();
    for (l, rec) in tape.iter_mut().enumerate() {
        for (dst, src) in rec.act[1..=layers].iter_mut().zip(&lanes.act[1..=layers]) {
            for (d, a) in dst[..hidden].iter_mut().zip(src) {
                *d = a[l];
            }
        }
    }
}

/// [`sdf_at`] in the CPU's fast forms: the grid's rows when the parameters are one slice and
/// the geometry decoder over its transposed weights `wt` ([`mlp::transpose_weights`]), its
/// activations into `act`. The same bits as [`sdf_at`] (tested).
#[inline(always)]
fn sdf_eval_transposed<P: ParamRead + ?Sized>(
    layout: &ModelLayout,
    params: &Params<'_, P>,
    wt: &[f32],
    p: [f32; 3],
    s: &mut SampleScratch,
    act: &mut MlpScratch,
) -> f32 {
    sdf_eval_keep(layout, params, wt, p, s, act, None).0
}

/// [`color_at`] in the CPU's fast forms (see [`sdf_eval_transposed`]; `wt` the appearance
/// decoder's transposed weights). The same bits as [`color_at`] (tested).
#[inline(always)]
fn color_eval_transposed<P: ParamRead + ?Sized>(
    layout: &ModelLayout,
    params: &Params<'_, P>,
    wt: &[f32],
    p: [f32; 3],
    s: &mut SampleScratch,
    act: &mut MlpScratch,
) -> [f32; 3] {
    color_eval_keep(layout, params, wt, p, s, act, None).0
}

/// [`sdf_eval_transposed`] keeping the geometry grid's term factors in `kept` when given
/// ([`grid::grid_forward_rows_keep`]; true when it kept them). The same bits.
#[inline(always)]
fn sdf_eval_keep<P: ParamRead + ?Sized>(
    layout: &ModelLayout,
    params: &Params<'_, P>,
    wt: &[f32],
    p: [f32; 3],
    s: &mut SampleScratch,
    act: &mut MlpScratch,
    kept: Option<&mut [f32]>,
) -> (f32, bool) {
    let keep = grid_forward_keeping(
        &layout.geometry_grid,
        params.geometry_grid,
        p,
        &mut s.geo_feat,
        kept,
    );
    geometry_input(layout, &s.geo_feat, &mut s.mlp_in);
    let gm = &layout.geometry_mlp;
    mlp::mlp_forward_transposed(gm, wt, &s.mlp_in, act, &mut s.mlp_out);
    (s.mlp_out[0], keep)
}

/// [`color_eval_transposed`] keeping the appearance grid's term factors in `kept` when given
/// (see [`sdf_eval_keep`]). The same bits.
#[inline(always)]
fn color_eval_keep<P: ParamRead + ?Sized>(
    layout: &ModelLayout,
    params: &Params<'_, P>,
    wt: &[f32],
    p: [f32; 3],
    s: &mut SampleScratch,
    act: &mut MlpScratch,
    kept: Option<&mut [f32]>,
) -> ([f32; 3], bool) {
    let keep = grid_forward_keeping(
        &layout.appearance_grid,
        params.appearance_grid,
        p,
        &mut s.app_feat,
        kept,
    );
    let pn = layout.config.aabb.normalize(p);
    appearance_input(layout, pn, &s.app_feat, &mut s.mlp_in);
    let am = &layout.appearance_mlp;
    mlp::mlp_forward_transposed(am, wt, &s.mlp_in, act, &mut s.mlp_out);
    let o = &s.mlp_out;
    (
        [
            math::sigmoid(o[0]),
            math::sigmoid(o[1]),
            math::sigmoid(o[2]),
        ],
        keep,
    )
}

/// [`grid::grid_forward_rows_keep`] when the parameters are one slice and `kept` is given,
/// [`grid::grid_forward_rows`] for a slice without `kept`, [`grid::grid_forward`] otherwise
/// (the same features every way; true when the factors were kept).
#[inline(always)]
fn grid_forward_keeping<P: ParamRead + ?Sized>(
    layout: &GridLayout,
    params: &P,
    p: [f32; 3],
    out: &mut [f32; MAX_GRID_FEATURES],
    kept: Option<&mut [f32]>,
) -> bool {
    match (params.as_slice(), kept) {
        (Some(sl), Some(k)) => grid::grid_forward_rows_keep(layout, sl, p, out, k),
        (Some(sl), None) => {
            grid::grid_forward_rows(layout, sl, p, out);
            false
        }
        (None, _) => {
            grid::grid_forward(layout, params, p, out);
            false
        }
    }
}

/// [`sdf_at`] for point queries on the CPU (mesh extraction): the grid's rows and the
/// decoder over its transposed weights `wt` ([`mlp::transpose_weights`]), its activations
/// into `act`. The same bits.
pub fn sdf_at_transposed<P: ParamRead + ?Sized>(
    layout: &ModelLayout,
    params: &Params<'_, P>,
    wt: &[f32],
    p: [f32; 3],
    s: &mut SampleScratch,
    act: &mut MlpScratch,
) -> f32 {
    sdf_eval_transposed(layout, params, wt, p, s, act)
}

/// [`color_at`] for point queries on the CPU (mesh vertex colours; see
/// [`sdf_at_transposed`]). The same bits.
pub fn color_at_transposed<P: ParamRead + ?Sized>(
    layout: &ModelLayout,
    params: &Params<'_, P>,
    wt: &[f32],
    p: [f32; 3],
    s: &mut SampleScratch,
    act: &mut MlpScratch,
) -> [f32; 3] {
    color_eval_transposed(layout, params, wt, p, s, act)
}

/// [`grid_backward_any`] with the factor rows of the slice form taken from `rows` (the same
/// calls and values).
#[inline(always)]
fn grid_backward_reusing<P: ParamRead + ?Sized, S: GradSink>(
    layout: &GridLayout,
    params: &P,
    p: [f32; 3],
    d_feat: &[f32; MAX_GRID_FEATURES],
    sink: &mut S,
    rows: &core::cell::RefCell<[[f32; MAX_WIDTH]; 6]>,
    kept: Option<&[f32]>,
) {
    match (params.as_slice(), rows.try_borrow_mut(), kept) {
        (Some(_), Ok(mut gl), Some(k)) => {
            grid::grid_backward_rows_kept(layout, p, d_feat, k, sink, &mut gl)
        }
        (Some(sl), Ok(mut gl), None) => {
            grid::grid_backward_rows_with(layout, sl, p, d_feat, sink, &mut gl)
        }
        _ => grid_backward_any(layout, params, p, d_feat, sink),
    }
}

/// [`grid::grid_backward_rows`] when the parameters are one slice, the parameter
/// contributions of [`grid::grid_backward`] otherwise (the same either way).
#[inline(always)]
fn grid_backward_any<P: ParamRead + ?Sized, S: GradSink>(
    layout: &GridLayout,
    params: &P,
    p: [f32; 3],
    d_feat: &[f32; MAX_GRID_FEATURES],
    sink: &mut S,
) {
    match params.as_slice() {
        Some(sl) => grid::grid_backward_rows(layout, sl, p, d_feat, sink),
        None => {
            grid::grid_backward(layout, params, p, d_feat, sink);
        }
    }
}

/// [`ray_forward`] through a [`SampleTape`].
#[allow(clippy::too_many_arguments)]
pub fn ray_forward_taped<P: ParamRead + ?Sized, T: SampleTape>(
    layout: &ModelLayout,
    params: &Params<'_, P>,
    ray: &Ray,
    ray_id: u32,
    seed: u32,
    jitter: bool,
    cache: &mut RayCache,
    s: &mut SampleScratch,
    tape: &mut T,
) {
    ray_forward_with::<P, T, false>(layout, params, ray, ray_id, seed, jitter, cache, s, tape);
}

/// [`ray_forward_taped`] for depth and opacity alone: the same samples, signed distances,
/// early termination and compositing (so the same `depth`, `opacity`, weights and `n` bits),
/// without the appearance grid and decoder; every sample's colour is 0, so `out.color` is 0.
/// For renders that only place surfaces (mesh culling, the surface level, planarity
/// partners); about half of a sample's forward is its appearance.
#[allow(clippy::too_many_arguments)]
pub fn ray_depth_forward_taped<P: ParamRead + ?Sized, T: SampleTape>(
    layout: &ModelLayout,
    params: &Params<'_, P>,
    ray: &Ray,
    ray_id: u32,
    seed: u32,
    jitter: bool,
    cache: &mut RayCache,
    s: &mut SampleScratch,
    tape: &mut T,
) {
    ray_forward_with::<P, T, true>(layout, params, ray, ray_id, seed, jitter, cache, s, tape);
}

/// The forward of [`ray_forward_taped`] (`DEPTH_ONLY` false) and
/// [`ray_depth_forward_taped`] (true: [`SampleTape::sdf_forward`], colour 0).
#[allow(clippy::too_many_arguments)]
#[inline(always)]
fn ray_forward_with<P: ParamRead + ?Sized, T: SampleTape, const DEPTH_ONLY: bool>(
    layout: &ModelLayout,
    params: &Params<'_, P>,
    ray: &Ray,
    ray_id: u32,
    seed: u32,
    jitter: bool,
    cache: &mut RayCache,
    s: &mut SampleScratch,
    tape: &mut T,
) {
    let n = ray_samples(layout, ray, ray_id, seed, jitter, &mut cache.t);
    // Samples are evaluated only up to where the compositing will stop (the same
    // transmittance bits as `render_forward`; the GPU evaluates them all, which gives the
    // same rendering).
    let (mode, t_min) = (layout.config.render_mode, layout.config.min_transmittance);
    // (A ray with a non-finite origin or direction takes the full forward: its positions,
    // and so its colours, may be NaN where the geometry's are not.)
    #[cfg(not(target_arch = "spirv"))]
    if !DEPTH_ONLY
        && tape.has_lanes()
        && tape.lazy_color()
        && ray.origin.iter().chain(&ray.dir).all(|v| v.is_finite())
    {
        // The signed distances first ([`LANES`] at a time, the same termination), then the
        // weights, then the colours of the samples with a weight: a sample of weight +0 adds
        // `+0 * c = +0` to the colour whatever its (finite, `lazy_color`) colour, so it is
        // left at 0 and the compositing gives the same bits.
        let (mut sdf, mut rgb) = ([0.0f32; LANES], [[0.0f32; 3]; LANES]);
        let mut trans = 1.0f32;
        let mut i = 0;
        'geo: while i < n {
            tape.render_lanes_part::<P, true, false>(
                layout,
                params,
                ray,
                &cache.t[i..n],
                s,
                &mut sdf,
                &mut rgb,
            );
            for &d in sdf.iter().take(n - i) {
                cache.sdf[i] = d;
                cache.rgb[i] = [0.0; 3];
                i += 1;
                if t_min > 0.0 {
                    trans *= render::transmittance_factor(mode, params.beta, d);
                    if trans < t_min {
                        break 'geo;
                    }
                }
            }
        }
        cache.n = i;
        ray_composite(layout, params.beta, cache);
        let (mut idx, mut ts, mut m) = ([0usize; LANES], [0.0f32; LANES], 0);
        for k in 0..cache.n {
            if cache.out.weights[k] != 0.0 {
                idx[m] = k;
                ts[m] = cache.t[k];
                m += 1;
            }
            if m == LANES || (m > 0 && k + 1 == cache.n) {
                tape.render_lanes_part::<P, false, true>(
                    layout,
                    params,
                    ray,
                    &ts[..m],
                    s,
                    &mut sdf,
                    &mut rgb,
                );
                for (&j, &c) in idx[..m].iter().zip(&rgb) {
                    cache.rgb[j] = c;
                }
                m = 0;
            }
        }
        ray_composite(layout, params.beta, cache);
        return;
    }
    #[cfg(not(target_arch = "spirv"))]
    if !DEPTH_ONLY && tape.has_lanes() {
        // [`LANES`] samples at a time: the same samples and bits; the compositing stops at
        // the same sample, the rest of its group computed and dropped.
        let (mut sdf, mut rgb) = ([0.0f32; LANES], [[0.0f32; 3]; LANES]);
        let mut trans = 1.0f32;
        let mut i = 0;
        'ray: while i < n {
            tape.forward_lanes(
                layout,
                params,
                ray,
                i,
                &cache.t[i..n],
                true,
                s,
                &mut sdf,
                &mut rgb,
            );
            for l in 0..(n - i).min(LANES) {
                cache.sdf[i] = sdf[l];
                cache.rgb[i] = rgb[l];
                i += 1;
                if t_min > 0.0 {
                    trans *= render::transmittance_factor(mode, params.beta, sdf[l]);
                    if trans < t_min {
                        break 'ray;
                    }
                }
            }
        }
        cache.n = i;
        ray_composite(layout, params.beta, cache);
        return;
    }
    let mut trans = 1.0f32;
    let mut i = 0;
    while i < n {
        if !DEPTH_ONLY && i + 1 < n {
            tape.prefetch(layout, params, ray, cache.t[i + 1]);
        }
        let (sdf, rgb) = if DEPTH_ONLY {
            let sdf = tape.sdf_forward(layout, params, ray, i, cache.t[i], s);
            (sdf, [0.0; 3])
        } else {
            tape.forward(layout, params, ray, i, cache.t[i], s)
        };
        cache.sdf[i] = sdf;
        cache.rgb[i] = rgb;
        i += 1;
        if t_min > 0.0 {
            trans *= render::transmittance_factor(mode, params.beta, sdf);
            if trans < t_min {
                break;
            }
        }
    }
    cache.n = i;
    ray_composite(layout, params.beta, cache);
}

/// Loss weights and switches of one training step.
#[derive(Clone, Copy, Debug, PartialEq)]
#[repr(C)]
pub struct LossConfig {
    /// Weight of the L1 colour term (paper: 0.1 during initialisation, 0.001 online).
    pub lambda_color: f32,
    /// Weight of an L1 depth term against `Ray::target_depth` (0 in monocular mapping; used by
    /// tests and the `dump-step` cross-check to exercise the depth path).
    pub lambda_depth: f32,
    /// Scale applied to every ray's loss (1 / batch size for a mean).
    pub ray_scale: f32,
    /// Whether the colour loss reaches the geometry (false = detached rendering weights).
    pub color_to_geometry: bool,
    /// Stratified jitter seed for this step.
    pub seed: u32,
}

/// What one training ray produced.
#[derive(Clone, Copy, Debug, PartialEq, Default)]
pub struct RayResult {
    /// Rendered colour (RGB in [0, 1]).
    pub color: [f32; 3],
    /// Rendered depth (camera z, metres).
    pub depth: f32,
    /// Rendered opacity (sum of the rendering weights).
    pub opacity: f32,
    /// This ray's scaled loss contribution.
    pub loss: f32,
}

/// Forward, loss and backward for one ray. The loss of the ray is
/// `ray_scale * (lambda_color * sum_c |C_c - target_c| + lambda_depth * |D - target_depth|)`
/// (the depth term only when `target_depth > 0`). Gradients go to `sink`.
#[allow(clippy::too_many_arguments)]
pub fn ray_train<P: ParamRead + ?Sized, S: ModelGradSink, T: SampleTape>(
    layout: &ModelLayout,
    params: &Params<'_, P>,
    ray: &Ray,
    ray_id: u32,
    loss: &LossConfig,
    cache: &mut RayCache,
    s: &mut SampleScratch,
    tape: &mut T,
    sink: &mut S,
) -> RayResult {
    ray_forward_taped(layout, params, ray, ray_id, loss.seed, true, cache, s, tape);
    let (result, d_color, d_depth) = ray_loss(ray, &cache.out, loss);
    if cache.n == 0 {
        return result;
    }
    ray_backward(
        layout,
        params,
        ray,
        d_color,
        d_depth,
        0.0,
        loss.color_to_geometry,
        cache,
        s,
        tape,
        sink,
    );
    result
}

/// The loss of [`ray_train`] for a rendered ray: the ray's result and the cotangents of the
/// rendered colour and depth.
#[inline(always)]
pub fn ray_loss(ray: &Ray, out: &RayOutput, loss: &LossConfig) -> (RayResult, [f32; 3], f32) {
    let (l1, d_c) = crate::loss::l1_color(out.color, ray.target);
    let mut value = loss.lambda_color * l1;
    let k = loss.ray_scale * loss.lambda_color;
    let d_color = [k * d_c[0], k * d_c[1], k * d_c[2]];
    let mut d_depth = 0.0;
    if ray.target_depth > 0.0 && loss.lambda_depth != 0.0 {
        let diff = out.depth - ray.target_depth;
        value += loss.lambda_depth * math::abs(diff);
        let sign = if diff > 0.0 {
            1.0
        } else if diff < 0.0 {
            -1.0
        } else {
            0.0
        };
        d_depth = loss.ray_scale * loss.lambda_depth * sign;
    }
    let result = RayResult {
        color: out.color,
        depth: out.depth,
        opacity: out.opacity,
        loss: loss.ray_scale * value,
    };
    (result, d_color, d_depth)
}

/// Backward of [`sample_forward`] for one sample at depth `t` along `ray`: `d_sdf` into the
/// geometry groups, `d_rgb` into the appearance groups (each skipped when zero).
#[allow(clippy::too_many_arguments)]
#[inline(always)]
pub fn sample_backward<P: ParamRead + ?Sized, S: ModelGradSink>(
    layout: &ModelLayout,
    params: &Params<'_, P>,
    ray: &Ray,
    t: f32,
    d_sdf: f32,
    d_rgb: [f32; 3],
    s: &mut SampleScratch,
    sink: &mut S,
) {
    let p = point_on_ray(ray, t);
    if d_sdf != 0.0 {
        sdf_backward(layout, params, p, d_sdf, s, sink);
    }
    if d_rgb[0] != 0.0 || d_rgb[1] != 0.0 || d_rgb[2] != 0.0 {
        color_backward(layout, params, p, d_rgb, s, sink);
    }
}

/// Backward of [`ray_composite`]: the per-sample cotangents `d_sdf`, `d_rgb` and `d_beta`
/// from those of the rendered colour, depth and opacity.
#[allow(clippy::too_many_arguments)]
#[inline(always)]
pub fn ray_composite_backward(
    layout: &ModelLayout,
    beta: f32,
    cache: &RayCache,
    d_color: [f32; 3],
    d_depth: f32,
    d_opacity: f32,
    color_to_geometry: bool,
    d_sdf: &mut [f32; MAX_SAMPLES],
    d_rgb: &mut [[f32; 3]; MAX_SAMPLES],
    d_beta: &mut f32,
) {
    render::render_backward(
        layout.config.render_mode,
        cache.n,
        &cache.sdf,
        &cache.rgb,
        &cache.t,
        beta,
        &cache.out,
        d_color,
        d_depth,
        d_opacity,
        color_to_geometry,
        d_sdf,
        d_rgb,
        d_beta,
    );
}

/// The geometry grid's finest levels whose rows a ray's next group of samples names to the
/// cache while the decoders of the current group run ([`SampleTape::forward_lanes`]).
#[cfg(not(target_arch = "spirv"))]
const GROUP_HINT_LEVELS: usize = 2;

/// The geometry grid's finest levels whose gradient rows the backward announces.
const GEOMETRY_HINT_LEVELS: usize = 2;

/// How many samples ahead the backward announces gradient rows (two: the rows of one sample
/// ahead were still in flight; three: slower, ARCHITECTURE.md).
const GRAD_HINT_AHEAD: usize = 2;

/// Announces to `sink` the plane rows of the grids' finest levels (the geometry's last two,
/// the appearance's last) that the backward of the sample at depth `t` adds into (the same
/// skips as [`sample_backward`]): a cache hint, no value changes. The coarser levels' rows and
/// the lines stay cached; naming them too cost as much as it saved (ARCHITECTURE.md).
#[inline(always)]
fn prefetch_sample_grads<S: ModelGradSink>(
    layout: &ModelLayout,
    ray: &Ray,
    t: f32,
    d_sdf: f32,
    d_rgb: [f32; 3],
    sink: &mut S,
) {
    let p = point_on_ray(ray, t);
    if d_sdf != 0.0 {
        let g = &layout.geometry_grid;
        for l in (g.levels as usize).saturating_sub(GEOMETRY_HINT_LEVELS)..g.levels as usize {
            grid::for_each_plane_row(g, l, p, |o| sink.prefetch(Group::GeometryGrid, o));
        }
    }
    if d_rgb[0] != 0.0 || d_rgb[1] != 0.0 || d_rgb[2] != 0.0 {
        let g = &layout.appearance_grid;
        for l in (g.levels as usize).saturating_sub(1)..g.levels as usize {
            grid::for_each_plane_row(g, l, p, |o| sink.prefetch(Group::AppearanceGrid, o));
        }
    }
}

/// Backward from the rendered colour, depth and opacity of a ray whose forward is in `cache`.
#[allow(clippy::too_many_arguments)]
pub fn ray_backward<P: ParamRead + ?Sized, S: ModelGradSink, T: SampleTape>(
    layout: &ModelLayout,
    params: &Params<'_, P>,
    ray: &Ray,
    d_color: [f32; 3],
    d_depth: f32,
    d_opacity: f32,
    color_to_geometry: bool,
    cache: &RayCache,
    s: &mut SampleScratch,
    tape: &T,
    sink: &mut S,
) {
    let n = cache.n;
    if n == 0 {
        return;
    }
    let mut d_sdf = [0.0f32; MAX_SAMPLES];
    let mut d_rgb = [[0.0f32; 3]; MAX_SAMPLES];
    let mut d_beta = 0.0f32;
    ray_composite_backward(
        layout,
        params.beta,
        cache,
        d_color,
        d_depth,
        d_opacity,
        color_to_geometry,
        &mut d_sdf,
        &mut d_rgb,
        &mut d_beta,
    );
    if S::PREFETCH {
        for j in 0..GRAD_HINT_AHEAD.min(n) {
            prefetch_sample_grads(layout, ray, cache.t[j], d_sdf[j], d_rgb[j], sink);
        }
    }
    let mut i = 0;
    while i < n {
        if S::PREFETCH && i + GRAD_HINT_AHEAD < n {
            let j = i + GRAD_HINT_AHEAD;
            prefetch_sample_grads(layout, ray, cache.t[j], d_sdf[j], d_rgb[j], sink);
        }
        tape.backward(
            layout,
            params,
            ray,
            i,
            cache.t[i],
            cache.rgb[i],
            d_sdf[i],
            d_rgb[i],
            s,
            sink,
        );
        i += 1;
    }
    sink.add(Group::Beta, 0, d_beta);
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::SplitMix;
    use std::vec;
    use std::vec::Vec;

    /// A hint that names nothing and takes the core's portable lanes (the tests' way to run
    /// a ray's samples through them).
    struct PortableLanes;

    impl RowHint for PortableLanes {
        fn lanes_pay() -> bool {
            true
        }
    }

    fn small(mode: RenderMode, kind: crate::field::grid::GridKind) -> ModelLayout {
        let mut geo = GridConfig::hi_map_geometry().with_kind(kind);
        geo.levels = 2;
        geo.cell_sizes = [0.5, 0.25, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0];
        let mut app = GridConfig::hi_map_appearance().with_kind(kind);
        app.channels = 3;
        app.cell_sizes = [0.5, 0.25, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0];
        let cfg = ModelConfig {
            aabb: Aabb::new([-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]),
            geometry_grid: geo,
            appearance_grid: app,
            hidden: 8,
            hidden_layers: 2,
            dual_path: true,
            render_mode: mode,
            samples: 12,
            beta_init: 5.0,
            grid_init_std: 0.2,
            sdf_bias_init: 0.2,
            max_depth: 0.0,
            far_samples: 0,
            far_depth: 0.0,
            min_transmittance: 0.0,
        };
        ModelLayout::new(&cfg).unwrap()
    }

    fn init(layout: &ModelLayout) -> [Vec<f32>; NUM_GROUPS] {
        let mut p: [Vec<f32>; NUM_GROUPS] = Default::default();
        for (g, v) in p.iter_mut().enumerate() {
            *v = vec![0.0; layout.group_len(Group::ALL[g])];
            layout.init_group(Group::ALL[g], v, 11).unwrap();
        }
        p
    }

    fn rays(n: usize) -> Vec<Ray> {
        let mut r = SplitMix::new(3);
        (0..n)
            .map(|_| {
                let mut u = |a: f32, b: f32| a + (b - a) * r.unit();
                Ray {
                    origin: [u(-0.4, 0.4), u(-0.4, 0.4), u(-0.4, 0.4)],
                    dir: [u(-1.0, 1.0), u(-1.0, 1.0), u(0.5, 1.0)],
                    target: [u(0.0, 1.0), u(0.0, 1.0), u(0.0, 1.0)],
                    target_depth: u(0.2, 1.0),
                }
            })
            .collect()
    }

    #[test]
    fn one_sample_equals_the_ray_s_samples() {
        let layout = small(
            RenderMode::SdfDensity,
            crate::field::grid::GridKind::Factorized,
        );
        let mut t = [0.0f32; MAX_SAMPLES];
        let mut hits = 0;
        for (i, r) in rays(20).iter().enumerate() {
            for jitter in [false, true] {
                let n = ray_samples(&layout, r, i as u32, 7, jitter, &mut t);
                hits += (n > 0) as usize;
                for (k, want) in t.iter().enumerate().take(n) {
                    let (tk, nk) = ray_sample(&layout, r, i as u32, 7, jitter, k);
                    assert_eq!(
                        (tk.to_bits(), nk),
                        (want.to_bits(), n),
                        "ray {i} sample {k}"
                    );
                }
            }
        }
        assert!(hits > 10);
    }

    #[test]
    fn far_samples_extend_rays_beyond_max_depth_in_inverse_depth() {
        // A 20 m box, samples to 2 m, 6 far samples to 8 m: a ray along +x from the centre
        // leaves the box at 10 m, so it gets 12 + 6 samples, the far ones in [2, 8] with bins
        // equal in 1/t (bin centres without jitter: 1/t = 1/2 - (j + 0.5) (1/2 - 1/8) / 6).
        let base = small(
            RenderMode::SdfDensity,
            crate::field::grid::GridKind::Factorized,
        );
        let mut cfg = base.config;
        cfg.aabb = Aabb::new([-10.0, -10.0, -10.0], [10.0, 10.0, 10.0]);
        cfg.max_depth = 2.0;
        cfg.far_samples = 6;
        cfg.far_depth = 8.0;
        let layout = ModelLayout::new(&cfg).unwrap();
        assert_eq!(cfg.max_ray_samples(), 18);
        let ray = Ray {
            origin: [0.0; 3],
            dir: [1.0, 0.0, 0.0],
            target: [0.0; 3],
            target_depth: 0.0,
        };
        let mut t = [0.0f32; MAX_SAMPLES];
        let n = ray_samples(&layout, &ray, 3, 5, false, &mut t);
        assert_eq!(n, 18);
        for j in 0..6 {
            let want = 1.0 / (0.5 - (j as f64 + 0.5) * (0.5 - 0.125) / 6.0);
            assert!(
                (t[12 + j] as f64 - want).abs() < 1e-5 * want,
                "far sample {j}"
            );
        }
        // Jittered: non-decreasing, inside [0, 8], near ones below 2 m, and one sample
        // alone has the bits of the whole ray's.
        let n = ray_samples(&layout, &ray, 3, 5, true, &mut t);
        assert_eq!(n, 18);
        assert!(t[..n].windows(2).all(|w| w[0] <= w[1]));
        assert!(t[..12].iter().all(|&x| (0.0..=2.0).contains(&x)));
        assert!(t[12..n].iter().all(|&x| (2.0..=8.0).contains(&x)));
        for (k, want) in t.iter().enumerate().take(n) {
            let (tk, nk) = ray_sample(&layout, &ray, 3, 5, true, k);
            assert_eq!((tk.to_bits(), nk), (want.to_bits(), n));
        }
        assert_eq!(ray_span(&layout, &ray), (0.0, 8.0, 18));
        // A ray that leaves the box before max_depth gets no far samples; one that leaves it
        // between max_depth and far_depth gets them up to the exit.
        let near_wall = Ray {
            origin: [9.0, 0.0, 0.0],
            ..ray
        };
        assert_eq!(ray_samples(&layout, &near_wall, 0, 0, true, &mut t), 12);
        let mid_wall = Ray {
            origin: [5.0, 0.0, 0.0],
            ..ray
        };
        assert_eq!(ray_span(&layout, &mid_wall), (0.0, 5.0, 18));
        // Off unless far_depth exceeds max_depth; too many samples in all is an error.
        let mut off = cfg;
        off.far_samples = 0;
        assert_eq!(
            ray_samples(&ModelLayout::new(&off).unwrap(), &ray, 0, 0, true, &mut t),
            12
        );
        let mut bad = cfg;
        bad.far_depth = 2.0;
        assert!(ModelLayout::new(&bad).is_err());
        bad.far_depth = 8.0;
        bad.far_samples = MAX_SAMPLES as u32;
        assert!(ModelLayout::new(&bad).is_err());
    }

    struct F64Sink {
        g: [Vec<f64>; NUM_GROUPS],
    }

    impl ModelGradSink for F64Sink {
        fn add(&mut self, group: Group, i: usize, g: f32) {
            self.g[group as usize][i] += g as f64;
        }
    }

    /// `(L(p + h e) - L(p - h e)) / 2h` for parameter `i` of group `g`.
    fn central_difference(
        layout: &ModelLayout,
        p: &[Vec<f32>; NUM_GROUPS],
        rays: &[Ray],
        loss: &LossConfig,
        g: usize,
        i: usize,
        h: f32,
    ) -> f64 {
        let mut pp = p.clone();
        pp[g][i] += h;
        let (lp, _) = total_loss(layout, &pp, rays, loss);
        pp[g][i] -= 2.0 * h;
        let (lm, _) = total_loss(layout, &pp, rays, loss);
        (lp - lm) / (2.0 * h as f64)
    }

    /// The finite-difference checks' loss: colour and depth L1, mean over `n` rays.
    fn fd_loss(n: usize) -> LossConfig {
        LossConfig {
            lambda_color: 1.0,
            lambda_depth: 0.5,
            ray_scale: 1.0 / n as f32,
            color_to_geometry: true,
            seed: 5,
        }
    }

    /// Both decoders' weights transposed ([`mlp::transpose_weights`]), as the stored tapes
    /// read them.
    fn transposed(layout: &ModelLayout, p: &[Vec<f32>; NUM_GROUPS]) -> [Vec<f32>; 2] {
        let mut wt: [Vec<f32>; 2] = [vec![0.0; p[2].len()], vec![0.0; p[3].len()]];
        mlp::transpose_weights(&layout.geometry_mlp, &p[2], &mut wt[0]).unwrap();
        mlp::transpose_weights(&layout.appearance_mlp, &p[3], &mut wt[1]).unwrap();
        wt
    }

    fn params_of(p: &[Vec<f32>; NUM_GROUPS]) -> Params<'_, [f32]> {
        Params {
            geometry_grid: &p[0][..],
            appearance_grid: &p[1][..],
            geometry_mlp: &p[2][..],
            appearance_mlp: &p[3][..],
            beta: p[4][0],
        }
    }

    /// Total loss over the batch (f64 sum of per-ray f32 losses).
    fn total_loss(
        layout: &ModelLayout,
        p: &[Vec<f32>; NUM_GROUPS],
        rays: &[Ray],
        loss: &LossConfig,
    ) -> (f64, [Vec<f64>; NUM_GROUPS]) {
        let params = params_of(p);
        let mut sink = F64Sink {
            g: core::array::from_fn(|g| vec![0.0; p[g].len()]),
        };
        let mut cache = RayCache::new();
        let mut s = SampleScratch::new();
        // The stored tape (what the CPU backends run); the recomputing one is checked against
        // it bit for bit by the host's thread-invariance tests.
        let wt = transposed(layout, p);
        let total = with_tape(layout, &wt, None, false, |tape| {
            let mut total = 0.0f64;
            for (i, r) in rays.iter().enumerate() {
                total += ray_train(
                    layout, &params, r, i as u32, loss, &mut cache, &mut s, tape, &mut sink,
                )
                .loss as f64;
            }
            total
        });
        (total, sink.g)
    }

    /// Central finite differences of the whole training loss (colour + depth L1, rendering,
    /// decoders, grids) against the analytic gradients, for a sample of parameters of every
    /// group, for SDF-density and occupancy rendering and both grid kinds. Step h = 5e-2 (grids), 1e-2 (beta: the
    /// loss is close to linear in each grid value) / 1e-3 (decoders); tolerance
    /// |a - fd| <= 1e-2 max|g| + 1e-2 |fd| per group. The f32 loss limits the finite difference
    /// to ~5e-7 absolute and L1/ReLU kinks make a few entries noisy, so at most 5% of the
    /// checked entries may miss. (The exact cross-check is `scripts/crosscheck_step.py`.)
    #[test]
    fn whole_step_gradient_matches_finite_differences() {
        // SdfDirect normalises the weights over the ray: its whole-step gradients are
        // cancellations ~1e-5 that an f32 finite difference cannot resolve. Its renderer is
        // finite-difference checked in `render`, and the whole step against PyTorch autograd
        // by `scripts/crosscheck_step.py`.
        for mode in [RenderMode::SdfDensity, RenderMode::Occupancy] {
            for kind in [
                crate::field::grid::GridKind::Factorized,
                crate::field::grid::GridKind::Dense,
            ] {
                let layout = small(mode, kind);
                let p = init(&layout);
                let rays = rays(24);
                let loss = fd_loss(24);
                let (_, grads) = total_loss(&layout, &p, &rays, &loss);
                let mut pick = SplitMix::new(9);
                let (mut checked, mut missed) = (0, 0);
                for g in 0..NUM_GROUPS {
                    let gmax = grads[g].iter().fold(0.0f64, |m, x| m.max(x.abs()));
                    let n = p[g].len();
                    // the parameters with the largest gradients plus random ones
                    let mut idx: Vec<usize> = (0..n).collect();
                    idx.sort_by(|&a, &b| {
                        grads[g][b].abs().partial_cmp(&grads[g][a].abs()).unwrap()
                    });
                    idx.truncate(6);
                    for _ in 0..6 {
                        idx.push(pick.below(n as u32) as usize);
                    }
                    let h = match g {
                        0 | 1 => 5e-2,
                        2 | 3 => 1e-3,
                        _ => 1e-2,
                    };
                    for &i in &idx {
                        let fd = central_difference(&layout, &p, &rays, &loss, g, i, h);
                        let a = grads[g][i];
                        checked += 1;
                        if (a - fd).abs() > 1e-2 * gmax + 1e-2 * fd.abs() {
                            missed += 1;
                            std::println!(
                                "{mode:?} {kind:?} group {g} idx {i}: analytic {a:.6e} fd {fd:.6e}"
                            );
                        }
                    }
                    assert!(
                        gmax > 0.0,
                        "{mode:?} {kind:?}: group {g} has no gradient at all"
                    );
                }
                assert!(
                    missed * 100 <= checked * 5,
                    "{mode:?} {kind:?}: {missed}/{checked} mismatches"
                );
            }
        }
    }

    /// The point queries in the CPU's fast forms give [`sdf_at`]'s and [`color_at`]'s bits at
    /// points inside, on the border of and outside the box.
    #[test]
    fn transposed_point_queries_equal_the_plain_ones() {
        let layout = small(
            RenderMode::SdfDensity,
            crate::field::grid::GridKind::Factorized,
        );
        let p = init(&layout);
        let params = params_of(&p);
        let wt = transposed(&layout, &p);
        let (mut s, mut q) = (SampleScratch::new(), SampleScratch::new());
        let mut act = MlpScratch::new();
        let mut r = SplitMix::new(17);
        let mut differ = 0;
        for k in 0..500 {
            let x = match k {
                0 => [1.0, 1.0, 1.0],
                1 => [-1.0, 0.3, 1.0],
                _ => [0; 3].map(|_| (r.unit() - 0.5) * 2.4),
            };
            let (a, b) = (
                sdf_at(&layout, &params, x, &mut s),
                sdf_at_transposed(&layout, &params, &wt[0], x, &mut q, &mut act),
            );
            assert_eq!(a.to_bits(), b.to_bits(), "sdf at {x:?}");
            let (a, b) = (
                color_at(&layout, &params, x, &mut s),
                color_at_transposed(&layout, &params, &wt[1], x, &mut q, &mut act),
            );
            assert_eq!(a.map(f32::to_bits), b.map(f32::to_bits), "colour at {x:?}");
            differ += (a != color_at(&layout, &params, [0.0; 3], &mut s)) as usize;
        }
        assert!(differ > 400, "the colour hardly varies ({differ})");
    }

    /// The depth-only forward gives the full forward's samples, signed distances, weights,
    /// depth, opacity and sample count bit for bit (both tapes, every render mode, with and
    /// without early termination) and a colour of 0.
    #[test]
    fn depth_only_forward_equals_the_full_forward() {
        for mode in [
            RenderMode::SdfDensity,
            RenderMode::Occupancy,
            RenderMode::SdfDirect,
        ] {
            for t_min in [0.0, 0.3] {
                let mut layout = small(mode, crate::field::grid::GridKind::Factorized);
                layout.config.min_transmittance = t_min;
                let p = init(&layout);
                let params = params_of(&p);
                let wt = transposed(&layout, &p);
                let mut geometry = vec![MlpScratch::new(); MAX_SAMPLES];
                let mut appearance = vec![MlpScratch::new(); MAX_SAMPLES];
                let mut s = SampleScratch::new();
                let rows = core::cell::RefCell::new([[0.0f32; MAX_WIDTH]; 6]);
                let mut kept = vec![0.0f32; MAX_SAMPLES * grid_tape_len(&layout)];
                let (mut opaque, mut cut) = (0, 0);
                for (i, r) in rays(24).iter().enumerate() {
                    for jitter in [false, true] {
                        let mut full = RayCache::new();
                        ray_forward(&layout, &params, r, i as u32, 4, jitter, &mut full, &mut s);
                        for stored in [false, true] {
                            let mut d = RayCache::new();
                            if stored {
                                let mut tape = StoredTape {
                                    geometry: &mut geometry,
                                    appearance: &mut appearance,
                                    geometry_wt: &wt[0],
                                    appearance_wt: &wt[1],
                                    grid_rows: &rows,
                                    grid_kept: &mut kept,
                                    hint: core::marker::PhantomData::<NoHint>,
                                    lanes: None,
                                    bounds: None,
                                    negligible_counts: Default::default(),
                                    lazy_color: false,
                                };
                                ray_depth_forward_taped(
                                    &layout, &params, r, i as u32, 4, jitter, &mut d, &mut s,
                                    &mut tape,
                                );
                            } else {
                                ray_depth_forward_taped(
                                    &layout,
                                    &params,
                                    r,
                                    i as u32,
                                    4,
                                    jitter,
                                    &mut d,
                                    &mut s,
                                    &mut Recompute,
                                );
                            }
                            let what = format!("{mode:?} t_min {t_min} ray {i} stored {stored}");
                            assert_eq!(d.n, full.n, "{what}");
                            for k in 0..full.n {
                                assert_eq!(d.t[k].to_bits(), full.t[k].to_bits(), "{what}");
                                assert_eq!(d.sdf[k].to_bits(), full.sdf[k].to_bits(), "{what}");
                                assert_eq!(
                                    d.out.weights[k].to_bits(),
                                    full.out.weights[k].to_bits(),
                                    "{what}"
                                );
                            }
                            assert_eq!(d.out.depth.to_bits(), full.out.depth.to_bits(), "{what}");
                            assert_eq!(
                                d.out.opacity.to_bits(),
                                full.out.opacity.to_bits(),
                                "{what}"
                            );
                            assert_eq!(d.out.color, [0.0; 3], "{what}");
                        }
                        opaque += (full.out.opacity > 0.5) as usize;
                        cut += (full.n < layout.config.samples as usize && full.n > 0) as usize;
                    }
                }
                assert!(
                    opaque > 5,
                    "{mode:?}: too few opaque rays to compare ({opaque})"
                );
                if t_min > 0.0 && mode != RenderMode::SdfDirect {
                    assert!(cut > 0, "{mode:?}: no ray stopped early");
                }
            }
        }
    }

    /// Early ray termination: evaluating samples one at a time and stopping where the
    /// compositing stops (the CPU's `ray_forward_taped`) gives the same rendering bits as
    /// evaluating every sample first (the GPU's passes) and compositing; rays do stop early;
    /// and the gradient of the cut ray still matches finite differences.
    #[test]
    fn early_termination_same_bits_either_way_and_correct_gradient() {
        for mode in [RenderMode::SdfDensity, RenderMode::Occupancy] {
            let mut layout = small(mode, crate::field::grid::GridKind::Factorized);
            layout.config.min_transmittance = 0.3;
            let mut p = init(&layout);
            // A steep field (beta 40): rays that reach negative SDF turn opaque within a
            // sample or two, the others stay nearly transparent.
            p[4][0] = 40.0;
            // A varied field (geometry grid x 20) around 0.25 m: some rays meet "solid" space
            // at different depths, some none.
            let gm = &layout.geometry_mlp;
            let out_bias = gm.bias_offsets[gm.hidden_layers as usize] as usize;
            p[2][out_bias] = 0.25;
            p[0].iter_mut().for_each(|x| *x *= 20.0);
            let params = params_of(&p);
            let mut s = SampleScratch::new();
            let (mut stopped, mut full) = (0, 0);
            for (i, r) in rays(40).iter().enumerate() {
                let mut a = RayCache::new();
                ray_forward(&layout, &params, r, i as u32, 3, true, &mut a, &mut s);
                let mut b = RayCache::new();
                b.n = ray_samples(&layout, r, i as u32, 3, true, &mut b.t);
                let n_all = b.n;
                for k in 0..b.n {
                    let (sdf, rgb) = sample_forward(&layout, &params, r, b.t[k], &mut s);
                    b.sdf[k] = sdf;
                    b.rgb[k] = rgb;
                }
                ray_composite(&layout, params.beta, &mut b);
                assert_eq!(a.n, b.n, "{mode:?} ray {i}");
                let bits = |c: &RayCache| {
                    let o = &c.out;
                    let mut v = vec![o.depth.to_bits(), o.opacity.to_bits()];
                    v.extend(o.color.iter().map(|x| x.to_bits()));
                    v.extend(o.weights.iter().map(|x| x.to_bits()));
                    v
                };
                assert_eq!(bits(&a), bits(&b), "{mode:?} ray {i}");
                if n_all > 0 {
                    if a.n < n_all {
                        stopped += 1;
                        assert!(a.out.trans[a.n - 1] >= 0.3);
                        assert!(a.out.weights[a.n..].iter().all(|&w| w == 0.0));
                    } else {
                        full += 1;
                    }
                }
            }
            assert!(
                stopped >= 5 && full >= 1,
                "{mode:?}: {stopped} stopped, {full} not"
            );
            // Finite differences of the cut ray's loss (away from the cut, the cut point does
            // not move under small steps; tolerance as the whole-step check).
            let rays = rays(12);
            let loss = fd_loss(12);
            let (_, grads) = total_loss(&layout, &p, &rays, &loss);
            let (mut checked, mut missed) = (0, 0);
            for g in [2usize, 3] {
                let gmax = grads[g].iter().fold(0.0f64, |m, x| m.max(x.abs()));
                assert!(gmax > 0.0, "{mode:?}: group {g} has no gradient");
                let mut idx: Vec<usize> = (0..p[g].len()).collect();
                idx.sort_by(|&a, &b| grads[g][b].abs().partial_cmp(&grads[g][a].abs()).unwrap());
                for &i in idx.iter().take(8) {
                    let fd = central_difference(&layout, &p, &rays, &loss, g, i, 1e-3);
                    checked += 1;
                    missed += ((grads[g][i] - fd).abs() > 1e-2 * gmax + 1e-2 * fd.abs()) as usize;
                }
            }
            assert!(missed * 100 <= checked * 10, "{mode:?}: {missed}/{checked}");
        }
    }

    #[test]
    fn detached_colour_sends_no_colour_gradient_to_geometry() {
        let layout = small(
            RenderMode::SdfDensity,
            crate::field::grid::GridKind::Factorized,
        );
        let p = init(&layout);
        let rays = rays(8);
        let colour_only = LossConfig {
            lambda_color: 1.0,
            lambda_depth: 0.0,
            ray_scale: 0.125,
            color_to_geometry: false,
            seed: 1,
        };
        let (_, g) = total_loss(&layout, &p, &rays, &colour_only);
        assert!(g[0].iter().all(|&x| x == 0.0) && g[2].iter().all(|&x| x == 0.0) && g[4][0] == 0.0);
        assert!(g[1].iter().any(|&x| x != 0.0) && g[3].iter().any(|&x| x != 0.0));
        let attached = LossConfig {
            color_to_geometry: true,
            ..colour_only
        };
        let (_, g) = total_loss(&layout, &p, &rays, &attached);
        assert!(g[0].iter().any(|&x| x != 0.0) && g[4][0] != 0.0);
    }

    #[test]
    fn layout_errors_and_counts() {
        let l = small(
            RenderMode::SdfDensity,
            crate::field::grid::GridKind::Factorized,
        );
        assert_eq!(l.group_len(Group::Beta), 1);
        assert_eq!(l.geometry_mlp.n_in, 4);
        assert_eq!(l.appearance_mlp.n_in, 3 + 6);
        assert_eq!(l.param_count(), l.group_lens().iter().sum::<usize>());
        let mut cfg = l.config;
        cfg.samples = 0;
        assert!(matches!(
            ModelLayout::new(&cfg),
            Err(Error::Capacity { .. })
        ));
        cfg.samples = 1000;
        assert!(matches!(
            ModelLayout::new(&cfg),
            Err(Error::Capacity { .. })
        ));
        cfg.samples = 8;
        cfg.aabb = Aabb::new([0.0; 3], [0.0, 1.0, 1.0]);
        assert!(ModelLayout::new(&cfg).is_err());
        let mut p = vec![0.0; 3];
        assert!(matches!(
            l.init_group(Group::GeometryMlp, &mut p, 0),
            Err(Error::Shape { .. })
        ));
    }

    #[test]
    fn ray_missing_the_box_renders_nothing_and_has_no_gradient() {
        let layout = small(
            RenderMode::SdfDensity,
            crate::field::grid::GridKind::Factorized,
        );
        let p = init(&layout);
        let ray = Ray {
            origin: [5.0, 5.0, 5.0],
            dir: [1.0, 0.0, 0.0],
            target: [0.5; 3],
            target_depth: 1.0,
        };
        let loss = LossConfig {
            lambda_color: 1.0,
            lambda_depth: 1.0,
            ray_scale: 1.0,
            color_to_geometry: true,
            seed: 0,
        };
        let (l, g) = total_loss(&layout, &p, &[ray], &loss);
        assert!(g.iter().all(|v| v.iter().all(|&x| x == 0.0)));
        // colour 0 against 0.5 in three channels, depth 0 against 1
        assert!((l - (1.5 + 1.0)).abs() < 1e-6, "{l}");
    }

    /// Converts every contribution to fixed point (as the backends do) and counts them.
    struct CountingFixedSink {
        g: [Vec<i64>; NUM_GROUPS],
        calls: usize,
    }

    impl ModelGradSink for CountingFixedSink {
        fn add(&mut self, group: Group, i: usize, g: f32) {
            let v = &mut self.g[group as usize][i];
            *v = v.wrapping_add(crate::train::fixed::to_fixed(g));
            self.calls += 1;
        }
    }

    /// Runs `f` on a stored tape with lanes (portable) over fresh storage for `layout`'s
    /// decoders `wt`, with the given bounds and lazy-colour switch.
    fn with_tape<R>(
        layout: &ModelLayout,
        wt: &[Vec<f32>; 2],
        bounds: Option<crate::field::negligible::DecoderBounds>,
        lazy_color: bool,
        f: impl FnOnce(&mut StoredTape<'_, PortableLanes>) -> R,
    ) -> R {
        let mut geometry = vec![MlpScratch::new(); MAX_SAMPLES];
        let mut appearance = vec![MlpScratch::new(); MAX_SAMPLES];
        let rows = core::cell::RefCell::new([[0.0f32; MAX_WIDTH]; 6]);
        let mut kept = vec![0.0f32; MAX_SAMPLES * grid_tape_len(layout)];
        let mut lanes = [MlpLanes::new(), MlpLanes::new()];
        let mut tape = StoredTape {
            geometry: &mut geometry,
            appearance: &mut appearance,
            geometry_wt: &wt[0],
            appearance_wt: &wt[1],
            grid_rows: &rows,
            grid_kept: &mut kept,
            hint: core::marker::PhantomData::<PortableLanes>,
            lanes: Some(&mut lanes),
            bounds,
            negligible_counts: Default::default(),
            lazy_color,
        };
        f(&mut tape)
    }

    /// With the decoders' weight bounds the stored tape skips the sample branches whose
    /// contributions all round to 0 quanta: the fixed-point sums are those of the tape without
    /// bounds, bit for bit, on fields whose surfaces are near, far (most samples' cotangents
    /// subnormal) and in between, while fewer contributions are made where samples are far.
    #[test]
    fn negligible_branches_keep_the_fixed_point_sums() {
        use crate::field::negligible::{DecoderBounds, LayerBounds};
        let mut mixed = false;
        for (bias, beta) in [(0.0f32, 10.0f32), (0.6, 30.0), (2.0, 30.0), (4.0, 60.0)] {
            let layout = small(
                RenderMode::SdfDensity,
                crate::field::grid::GridKind::Factorized,
            );
            let mut p = init(&layout);
            // The geometry decoder's output bias moves every surface away from the rays.
            let out_bias = layout.geometry_mlp.bias_offsets[layout.geometry_mlp.dims().2];
            p[2][out_bias as usize] = bias;
            p[4][0] = beta;
            let params = params_of(&p);
            let wt = transposed(&layout, &p);
            let loss = fd_loss(24);
            let bounds = DecoderBounds {
                geometry: LayerBounds::of(&layout.geometry_mlp, &p[2][..]),
                appearance: LayerBounds::of(&layout.appearance_mlp, &p[3][..]),
            };
            let mut runs = Vec::new();
            for b in [None, Some(bounds)] {
                let sink = with_tape(&layout, &wt, b, false, |tape| {
                    let mut sink = CountingFixedSink {
                        g: core::array::from_fn(|g| vec![0; p[g].len()]),
                        calls: 0,
                    };
                    let (mut cache, mut s) = (RayCache::new(), SampleScratch::new());
                    for (i, r) in rays(48).iter().enumerate() {
                        ray_train(
                            &layout, &params, r, i as u32, &loss, &mut cache, &mut s, tape,
                            &mut sink,
                        );
                    }
                    sink
                });
                runs.push(sink);
            }
            assert_eq!(runs[0].g, runs[1].g, "bias {bias}, beta {beta}");
            assert!(runs[1].calls <= runs[0].calls);
            // A field where some branches were skipped and others still add quanta.
            mixed |= runs[1].calls < runs[0].calls && runs[1].g.iter().flatten().any(|&v| v != 0);
        }
        assert!(
            mixed,
            "no field had both skipped branches and non-zero sums"
        );
    }

    /// A render that evaluates the colours of only the samples with a weight gives the full
    /// render's bits (colour, depth, opacity, weights, sample count) for every render mode, with
    /// and without early termination, on near and far fields; some samples do have a zero
    /// weight on the far ones.
    #[test]
    fn lazy_color_renders_the_same_bits() {
        let mut zero_weights = 0;
        for mode in [
            RenderMode::SdfDensity,
            RenderMode::Occupancy,
            RenderMode::SdfDirect,
        ] {
            for t_min in [0.0, 1e-4] {
                for (bias, beta) in [(0.0f32, 10.0f32), (0.6, 30.0), (2.0, 30.0)] {
                    let mut layout = small(mode, crate::field::grid::GridKind::Factorized);
                    layout.config.min_transmittance = t_min;
                    let mut p = init(&layout);
                    let out_bias = layout.geometry_mlp.bias_offsets[layout.geometry_mlp.dims().2];
                    p[2][out_bias as usize] = bias;
                    p[4][0] = beta;
                    let params = params_of(&p);
                    let wt = transposed(&layout, &p);
                    for (i, r) in rays(24).iter().enumerate() {
                        let mut outs = Vec::new();
                        for lazy in [false, true] {
                            let cache = with_tape(&layout, &wt, None, lazy, |tape| {
                                let (mut cache, mut s) = (RayCache::new(), SampleScratch::new());
                                ray_forward_taped(
                                    &layout, &params, r, i as u32, 3, false, &mut cache, &mut s,
                                    tape,
                                );
                                cache
                            });
                            outs.push(cache);
                        }
                        let (a, b) = (&outs[0], &outs[1]);
                        let what = format!("{mode:?} t_min {t_min} bias {bias} ray {i}");
                        assert_eq!(a.n, b.n, "{what}");
                        assert_eq!(a.out.color.map(f32::to_bits), b.out.color.map(f32::to_bits));
                        assert_eq!(a.out.depth.to_bits(), b.out.depth.to_bits(), "{what}");
                        assert_eq!(a.out.opacity.to_bits(), b.out.opacity.to_bits(), "{what}");
                        for k in 0..a.n {
                            assert_eq!(a.out.weights[k].to_bits(), b.out.weights[k].to_bits());
                            zero_weights += (a.out.weights[k] == 0.0) as usize;
                        }
                    }
                }
            }
        }
        assert!(
            zero_weights > 100,
            "only {zero_weights} samples of zero weight"
        );
    }

    /// A ray's training forward and backward with the decoders in lanes give the one-sample
    /// forms' bits: outputs, sample count, every sample's signed distance and colour, and
    /// every gradient contribution (the same sums in the same order), for every render mode,
    /// with and without early termination; renders likewise, and a tape too short for the
    /// ray's samples falls back to one at a time.
    #[test]
    fn lanes_forward_equals_one_sample_at_a_time() {
        let mut cut = 0;
        for mode in [
            RenderMode::SdfDensity,
            RenderMode::Occupancy,
            RenderMode::SdfDirect,
        ] {
            for t_min in [0.0, 0.3] {
                let mut layout = small(mode, crate::field::grid::GridKind::Factorized);
                layout.config.min_transmittance = t_min;
                let p = init(&layout);
                let params = params_of(&p);
                let wt = transposed(&layout, &p);
                let loss = fd_loss(24);
                for (i, r) in rays(24).iter().enumerate() {
                    let mut runs = Vec::new();
                    // one at a time; lanes; lanes over a tape shorter than the ray
                    for (with_lanes, tape_len) in
                        [(false, MAX_SAMPLES), (true, MAX_SAMPLES), (true, 5)]
                    {
                        let mut geometry = vec![MlpScratch::new(); tape_len];
                        let mut appearance = vec![MlpScratch::new(); tape_len];
                        let rows = core::cell::RefCell::new([[0.0f32; MAX_WIDTH]; 6]);
                        let mut kept = vec![0.0f32; MAX_SAMPLES * grid_tape_len(&layout)];
                        let mut lanes = [MlpLanes::new(), MlpLanes::new()];
                        let mut tape = StoredTape {
                            geometry: &mut geometry,
                            appearance: &mut appearance,
                            geometry_wt: &wt[0],
                            appearance_wt: &wt[1],
                            grid_rows: &rows,
                            grid_kept: &mut kept,
                            hint: core::marker::PhantomData::<PortableLanes>,
                            lanes: if with_lanes { Some(&mut lanes) } else { None },
                            bounds: None,
                            negligible_counts: Default::default(),
                            lazy_color: false,
                        };
                        let mut sink = F64Sink {
                            g: core::array::from_fn(|g| vec![0.0; p[g].len()]),
                        };
                        let (mut cache, mut s) = (RayCache::new(), SampleScratch::new());
                        let res = ray_train(
                            &layout, &params, r, i as u32, &loss, &mut cache, &mut s, &mut tape,
                            &mut sink,
                        );
                        let mut render = RayCache::new();
                        ray_forward_taped(
                            &layout,
                            &params,
                            r,
                            i as u32,
                            3,
                            false,
                            &mut render,
                            &mut s,
                            &mut tape,
                        );
                        runs.push((res, cache, sink.g, render));
                    }
                    let (res0, c0, g0, r0) = &runs[0];
                    cut += (c0.n < ray_span(&layout, r).2) as usize;
                    for (k, (res, c, g, rr)) in runs.iter().enumerate().skip(1) {
                        let what = format!("{mode:?} t_min {t_min} ray {i} run {k}");
                        assert_eq!(res.loss.to_bits(), res0.loss.to_bits(), "{what}");
                        assert_eq!(res.color.map(f32::to_bits), res0.color.map(f32::to_bits));
                        assert_eq!(c.n, c0.n, "{what}");
                        for j in 0..c0.n {
                            assert_eq!(c.sdf[j].to_bits(), c0.sdf[j].to_bits(), "{what}");
                            assert_eq!(c.rgb[j].map(f32::to_bits), c0.rgb[j].map(f32::to_bits));
                        }
                        for (a, b) in g.iter().zip(g0.iter()) {
                            assert!(
                                a.iter().zip(b).all(|(x, y)| x.to_bits() == y.to_bits()),
                                "{what}: gradients"
                            );
                        }
                        assert_eq!(rr.n, r0.n, "{what}");
                        assert_eq!(
                            rr.out.color.map(f32::to_bits),
                            r0.out.color.map(f32::to_bits)
                        );
                        assert_eq!(rr.out.depth.to_bits(), r0.out.depth.to_bits(), "{what}");
                    }
                }
            }
        }
        // (SdfDirect does not terminate early: the modes with a transmittance do)
        assert!(cut > 0, "no ray terminated early");
    }
}
