//! Multi-resolution feature grids: factorized (TensoRF VM per level) and dense trilinear.
//!
//! A grid maps a world position `p` (metres) to a feature vector of `levels * channels` values,
//! level-major: feature `l * C + c` is channel `c` of level `l` (level 0 is the coarsest).
//!
//! # Coordinates
//!
//! The scene box ([`crate::Aabb`]) maps to normalized coordinates in [-1, 1] per axis with
//! align-corners semantics and border clamping (exactly [`crate::Aabb::normalize`]). A level
//! with cell size `s` has `res_a = ceil(extent_a / s) + 1` vertices on axis `a` (at least 2), so
//! the vertex spacing is `extent_a / (res_a - 1) <= s`. A normalized coordinate `x` becomes the
//! continuous vertex index `u = (x + 1) / 2 * (res - 1)`; the cell is `i = floor(u)` clamped to
//! `[0, res - 2]` and the fraction `f = u - i` lies in [0, 1] (f = 1 only on the last vertex).
//!
//! # Factorized level (TensoRF "VM", channel-wise)
//!
//! `F_c(p) = vx_c(x) * Myz_c(y, z) + vy_c(y) * Mxz_c(x, z) + vz_c(z) * Mxy_c(x, y)`: the three
//! planes are interpolated bilinearly, the three lines linearly.
//!
//! # Dense level
//!
//! `F_c(p)` is the trilinear interpolation of a `res_x * res_y * res_z` vertex grid.
//!
//! # Memory layout (shared by the CPU and the GPU)
//!
//! One flat `f32` buffer of [`GridLayout::param_count`] values. Levels follow each other
//! (level `l` starts at [`LevelLayout::offset`]). Inside a factorized level, in this order:
//!
//! | block   | size            | index of (vertex, channel `c`)         |
//! |---------|-----------------|----------------------------------------|
//! | plane xy| `rx * ry * C`   | `plane_offsets[0] + (iy * rx + ix) * C + c` |
//! | plane xz| `rx * rz * C`   | `plane_offsets[1] + (iz * rx + ix) * C + c` |
//! | plane yz| `ry * rz * C`   | `plane_offsets[2] + (iz * ry + iy) * C + c` |
//! | line x  | `rx * C`        | `line_offsets[0] + ix * C + c`         |
//! | line y  | `ry * C`        | `line_offsets[1] + iy * C + c`         |
//! | line z  | `rz * C`        | `line_offsets[2] + iz * C + c`         |
//!
//! i.e. plane `ab` is row-major over `(b, a)` with the channel last. All offsets in the tables
//! are absolute indices into the flat buffer. A dense level is one block,
//! `offset + ((iz * ry + iy) * rx + ix) * C + c`.
//!
//! # Gradients
//!
//! [`grid_backward`] sends every (parameter, contribution) pair of one sample as its own
//! [`crate::GradSink::add`] call (no pre-summing), so fixed-point accumulation is independent
//! of order, and returns dL/dp in world units.
//!
//! The per-sample functions are kernels (also compiled to SPIR-V): plain f32 arithmetic, no
//! `libm`, no panicking paths for any layout built by [`GridLayout::new`].

use crate::{math, Aabb, Error, GradSink, ParamRead};

/// Largest number of levels a grid may have.
pub const MAX_LEVELS: usize = 8;
/// Largest feature dimension (`levels * channels`) of a grid; the size of the feature arrays
/// passed to [`grid_forward`] and [`grid_backward`].
pub const MAX_GRID_FEATURES: usize = 128;

/// Largest number of vertices per axis of one level: continuous vertex indices stay exact
/// integers in f32 below 2^24.
const MAX_AXIS_VERTICES: u64 = 1 << 24;

/// Relative tolerance of the `ceil` in the vertex count: a box that exceeds a whole number of
/// cells by less than `1e-5` of its extent (0.04 mm on a 4 m box; f32 rounding of
/// `extent / cell` is below 5e-7 relative) gets no extra vertex; positions in that sliver clamp
/// to the last vertex. Without it, `4.0 / 0.02` could become 201 cells instead of 200 depending
/// on how the decimal inputs round.
const CEIL_REL_TOL: f32 = 1e-5;

/// How each level of a grid stores its features.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[repr(u32)]
pub enum GridKind {
    /// TensoRF vector-matrix factorization: three planes and three lines per level.
    Factorized = 0,
    /// A dense 3-D vertex grid, trilinear interpolation (the "no factorization" ablation).
    Dense = 1,
}

/// What a grid looks like, independent of the scene box.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct GridConfig {
    /// Factorized or dense levels.
    pub kind: GridKind,
    /// Number of levels, 1 ..= [`MAX_LEVELS`].
    pub levels: u32,
    /// Feature channels per level (>= 1); `levels * channels <= MAX_GRID_FEATURES`.
    pub channels: u32,
    /// Cell size of each level in metres, level 0 the coarsest. Entries from `levels` on are
    /// ignored.
    pub cell_sizes: [f32; MAX_LEVELS],
}

impl GridConfig {
    /// Hi-Map's geometry grid: factorized, 6 levels of 64, 32, 16, 8, 4 and 2 cm, 2 channels.
    pub const fn hi_map_geometry() -> Self {
        Self {
            kind: GridKind::Factorized,
            levels: 6,
            channels: 2,
            cell_sizes: [0.64, 0.32, 0.16, 0.08, 0.04, 0.02, 0.0, 0.0],
        }
    }

    /// Hi-Map's appearance grid: factorized, 2 levels of 24 and 2 cm, 32 channels.
    pub const fn hi_map_appearance() -> Self {
        Self {
            kind: GridKind::Factorized,
            levels: 2,
            channels: 32,
            cell_sizes: [0.24, 0.02, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
        }
    }

    /// The same configuration with another [`GridKind`] (e.g. the dense ablation).
    pub const fn with_kind(self, kind: GridKind) -> Self {
        Self { kind, ..self }
    }
}

/// Where one level lives in the flat parameter buffer (see the module docs for the layout).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LevelLayout {
    /// Vertices per axis (x, y, z), each >= 2.
    pub res: [u32; 3],
    /// Index of the level's first parameter.
    pub offset: u32,
    /// Absolute index of the first parameter of plane xy, xz, yz (factorized; 0 for dense).
    pub plane_offsets: [u32; 3],
    /// Absolute index of the first parameter of line x, y, z (factorized; 0 for dense).
    pub line_offsets: [u32; 3],
    /// Number of parameters of the level.
    pub count: u32,
}

impl LevelLayout {
    const UNUSED: Self = Self {
        res: [0; 3],
        offset: 0,
        plane_offsets: [0; 3],
        line_offsets: [0; 3],
        count: 0,
    };
}

/// The offset table of a grid over a scene box: computed once on the host by
/// [`GridLayout::new`] and shared by every CPU and GPU kernel.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct GridLayout {
    /// Factorized or dense levels.
    pub kind: GridKind,
    /// Number of levels in use.
    pub levels: u32,
    /// Channels per level.
    pub channels: u32,
    /// The scene box the grid covers.
    pub aabb: Aabb,
    /// Per-level tables; entries from `levels` on are all zero.
    pub level: [LevelLayout; MAX_LEVELS],
    /// Total number of parameters (length of the flat buffer).
    pub param_count: u32,
}

/// `ceil(extent / cell) + 1` (at least 2), with the tolerance [`CEIL_REL_TOL`].
fn vertices_per_axis(extent: f32, cell: f32) -> Result<u32, Error> {
    let q = math::div(extent, cell);
    // Also rejects an infinite quotient (a huge box or a subnormal cell size).
    let fits = q < (MAX_AXIS_VERTICES - 2) as f32;
    if !fits {
        return Err(Error::Capacity {
            what: "grid vertices per axis",
            needed: if q < u64::MAX as f32 {
                q as u64 + 2
            } else {
                u64::MAX
            },
            capacity: MAX_AXIS_VERTICES,
        });
    }
    let mut cells = q as u32; // q > 0: truncation is floor
    if q - cells as f32 > q * CEIL_REL_TOL {
        cells += 1;
    }
    if cells < 1 {
        cells = 1;
    }
    Ok(cells + 1)
}

/// The level, channel and box checks of [`GridLayout::new`].
fn check_grid_config(cfg: &GridConfig, aabb: &Aabb) -> Result<(), Error> {
    if cfg.levels == 0 {
        return Err(Error::InvalidConfig("grid: levels must be at least 1"));
    }
    if cfg.levels as usize > MAX_LEVELS {
        return Err(Error::Capacity {
            what: "grid levels",
            needed: cfg.levels as u64,
            capacity: MAX_LEVELS as u64,
        });
    }
    if cfg.channels == 0 {
        return Err(Error::InvalidConfig("grid: channels must be at least 1"));
    }
    let features = cfg.levels as u64 * cfg.channels as u64;
    if features > MAX_GRID_FEATURES as u64 {
        return Err(Error::Capacity {
            what: "grid features (levels * channels)",
            needed: features,
            capacity: MAX_GRID_FEATURES as u64,
        });
    }
    if !aabb.is_valid() {
        return Err(Error::InvalidConfig(
            "grid: box must be finite with a positive extent on every axis",
        ));
    }
    Ok(())
}

/// Vertices per axis of every used level of `cfg` over `aabb` (checked cell sizes).
fn level_resolutions(cfg: &GridConfig, aabb: &Aabb) -> Result<[[u32; 3]; MAX_LEVELS], Error> {
    let extent = aabb.extent();
    let mut res_all = [[0u32; 3]; MAX_LEVELS];
    let mut l = 0;
    while l < cfg.levels as usize {
        let cell = cfg.cell_sizes[l];
        if !(cell.is_finite() && cell > 0.0) {
            return Err(Error::InvalidConfig(
                "grid: cell sizes must be finite and positive",
            ));
        }
        let mut a = 0;
        while a < 3 {
            res_all[l][a] = vertices_per_axis(extent[a], cell)?;
            a += 1;
        }
        l += 1;
    }
    Ok(res_all)
}

/// Per used level: its offset, the offsets of its planes xy, xz, yz and lines x, y, z
/// (factorized), and its parameter count; and the total. In `u64` with saturation, for the
/// caller to check against `u32`.
fn level_offsets(
    cfg: &GridConfig,
    res_all: &[[u32; 3]; MAX_LEVELS],
) -> ([[u64; 8]; MAX_LEVELS], u64) {
    let ch = cfg.channels as u64;
    let mut offset: u64 = 0;
    let mut offsets = [[0u64; 8]; MAX_LEVELS];
    let mut l = 0;
    while l < cfg.levels as usize {
        let [rx, ry, rz] = res_all[l].map(|r| r as u64);
        let o = &mut offsets[l];
        o[0] = offset;
        let count = match cfg.kind {
            GridKind::Factorized => {
                let sizes = [rx * ry, rx * rz, ry * rz, rx, ry, rz];
                let mut at = offset;
                let mut b = 0;
                while b < 6 {
                    o[1 + b] = at;
                    at = at.saturating_add(sizes[b] * ch);
                    b += 1;
                }
                at - offset
            }
            GridKind::Dense => rx.saturating_mul(ry).saturating_mul(rz).saturating_mul(ch),
        };
        o[7] = count;
        offset = offset.saturating_add(count);
        l += 1;
    }
    (offsets, offset)
}

impl GridLayout {
    /// Builds the offset table of `cfg` over `aabb`.
    ///
    /// Errors: [`Error::InvalidConfig`] for zero levels or channels, a non-finite or
    /// non-positive cell size of a used level, or an invalid box; [`Error::Capacity`] for more
    /// than [`MAX_LEVELS`] levels, more than [`MAX_GRID_FEATURES`] features, more than 2^24
    /// vertices on an axis, or more parameters than fit in a `u32`.
    pub fn new(cfg: &GridConfig, aabb: Aabb) -> Result<Self, Error> {
        check_grid_config(cfg, &aabb)?;
        let nl = cfg.levels as usize;
        let res_all = level_resolutions(cfg, &aabb)?;
        let (offsets, total) = level_offsets(cfg, &res_all);
        if total > u32::MAX as u64 {
            return Err(Error::Capacity {
                what: "grid parameters",
                needed: total,
                capacity: u32::MAX as u64,
            });
        }
        let mut level = [LevelLayout::UNUSED; MAX_LEVELS];
        let mut l = 0;
        while l < nl {
            let o = offsets[l];
            let factorized = cfg.kind == GridKind::Factorized;
            let f = |v: u64| if factorized { v as u32 } else { 0 };
            level[l] = LevelLayout {
                res: res_all[l],
                offset: o[0] as u32,
                plane_offsets: [f(o[1]), f(o[2]), f(o[3])],
                line_offsets: [f(o[4]), f(o[5]), f(o[6])],
                count: o[7] as u32,
            };
            l += 1;
        }
        Ok(Self {
            kind: cfg.kind,
            levels: cfg.levels,
            channels: cfg.channels,
            aabb,
            level,
            param_count: total as u32,
        })
    }

    /// Length of the feature vector, `levels * channels`.
    pub fn feature_dim(&self) -> usize {
        self.levels as usize * self.channels as usize
    }
}

/// Fills `params` with N(0, std^2) draws: `params[i] = std * rng::normal(seed, 0, i)`.
///
/// Errors: [`Error::Shape`] if `params.len() != layout.param_count`;
/// [`Error::InvalidConfig`] if `std` is negative or not finite.
pub fn grid_init(
    layout: &GridLayout,
    params: &mut [f32],
    seed: u32,
    std: f32,
) -> Result<(), Error> {
    crate::error::check_len("grid parameters", params.len(), layout.param_count as usize)?;
    grid_init_part(params, 0, seed, std)
}

/// The values [`grid_init`] gives parameters `start..start + params.len()` (each depends on
/// its index alone, so parts of a grid may be filled in parallel with the whole grid's bits).
/// Errors for a scale that is not finite and non-negative.
pub fn grid_init_part(params: &mut [f32], start: usize, seed: u32, std: f32) -> Result<(), Error> {
    if !(std.is_finite() && std >= 0.0) {
        return Err(Error::InvalidConfig(
            "grid: init std must be finite and >= 0",
        ));
    }
    for (i, p) in params.iter_mut().enumerate() {
        *p = std * crate::rng::normal(seed, 0, (start + i) as u32);
    }
    Ok(())
}

// ---------------------------------------------------------------------------------------------
// Kernels
// ---------------------------------------------------------------------------------------------

/// Levels and channels a kernel may use without leaving the feature arrays (a layout from
/// [`GridLayout::new`] passes unchanged; a corrupted one is clamped rather than panicking).
#[inline(always)]
fn kernel_dims(layout: &GridLayout) -> (usize, usize) {
    let mut nl = layout.levels as usize;
    if nl > MAX_LEVELS {
        nl = MAX_LEVELS;
    }
    let mut nc = layout.channels as usize;
    if nl > 0 && nl * nc > MAX_GRID_FEATURES {
        nc = MAX_GRID_FEATURES / nl;
    }
    (nl, nc)
}

/// Normalized coordinates (bit-identical to [`Aabb::normalize`]) and, per axis, whether the
/// position was inside the box (not clamped; false for NaN).
#[inline(always)]
#[allow(clippy::manual_range_contains)]
fn normalize_with_mask(aabb: &Aabb, p: [f32; 3]) -> ([f32; 3], [bool; 3]) {
    let mut xn = [0.0f32; 3];
    // Written out: rust-gpu cannot lower a memset with a `bool` pattern (`[false; 3]`).
    let mut inside = [false, false, false];
    let mut a = 0;
    while a < 3 {
        let x = math::div(p[a] - aabb.min[a], aabb.max[a] - aabb.min[a]) * 2.0 - 1.0;
        inside[a] = x >= -1.0 && x <= 1.0;
        xn[a] = math::clamp(x, -1.0, 1.0);
        a += 1;
    }
    (xn, inside)
}

/// Cell index and fraction of every axis at one level.
#[derive(Clone, Copy)]
struct Cell {
    i: [usize; 3],
    f: [f32; 3],
}

/// Locates the normalized position `xn` in a level with `res` vertices per axis.
#[inline(always)]
fn locate(xn: [f32; 3], res: [u32; 3]) -> Cell {
    let mut cell = Cell {
        i: [0; 3],
        f: [0.0; 3],
    };
    let mut a = 0;
    while a < 3 {
        let r = if res[a] < 2 { 2 } else { res[a] };
        let mut u = (xn[a] + 1.0) * 0.5 * (r - 1) as f32;
        // NaN positions (and, defensively, negatives) go to the first vertex.
        let valid = u >= 0.0;
        if !valid {
            u = 0.0;
        }
        let mut i = u as u32; // u >= 0: truncation is floor
        if i > r - 2 {
            i = r - 2;
        }
        cell.i[a] = i as usize;
        cell.f[a] = u - i as f32;
        a += 1;
    }
    cell
}

#[inline(always)]
fn lerp(a0: f32, a1: f32, f: f32) -> f32 {
    a0 * (1.0 - f) + a1 * f
}

/// Flat indices (without the channel) of the corners a factorized level reads at one cell.
/// Planes: `[p00, p10, p01, p11]` where the first digit steps the plane's first axis.
#[derive(Clone, Copy)]
struct VmCorners {
    xy: [usize; 4],
    xz: [usize; 4],
    yz: [usize; 4],
    x: [usize; 2],
    y: [usize; 2],
    z: [usize; 2],
}

#[inline(always)]
fn plane_corners(base: u32, ia: usize, ib: usize, ra: usize, nc: usize) -> [usize; 4] {
    let p00 = base as usize + (ib * ra + ia) * nc;
    [p00, p00 + nc, p00 + ra * nc, p00 + ra * nc + nc]
}

#[inline(always)]
fn line_corners(base: u32, ia: usize, nc: usize) -> [usize; 2] {
    let p0 = base as usize + ia * nc;
    [p0, p0 + nc]
}

#[inline(always)]
fn vm_corners(lv: &LevelLayout, nc: usize, cell: &Cell) -> VmCorners {
    let rx = lv.res[0] as usize;
    let ry = lv.res[1] as usize;
    let [ix, iy, iz] = cell.i;
    VmCorners {
        xy: plane_corners(lv.plane_offsets[0], ix, iy, rx, nc),
        xz: plane_corners(lv.plane_offsets[1], ix, iz, rx, nc),
        yz: plane_corners(lv.plane_offsets[2], iy, iz, ry, nc),
        x: line_corners(lv.line_offsets[0], ix, nc),
        y: line_corners(lv.line_offsets[1], iy, nc),
        z: line_corners(lv.line_offsets[2], iz, nc),
    }
}

/// The values of one channel of a factorized level at one cell.
#[derive(Clone, Copy)]
struct VmValues {
    xy: [f32; 4],
    xz: [f32; 4],
    yz: [f32; 4],
    x: [f32; 2],
    y: [f32; 2],
    z: [f32; 2],
}

#[inline(always)]
fn read4<P: ParamRead + ?Sized>(params: &P, p: [usize; 4], c: usize) -> [f32; 4] {
    [
        params.at(p[0] + c),
        params.at(p[1] + c),
        params.at(p[2] + c),
        params.at(p[3] + c),
    ]
}

#[inline(always)]
fn read2<P: ParamRead + ?Sized>(params: &P, p: [usize; 2], c: usize) -> [f32; 2] {
    [params.at(p[0] + c), params.at(p[1] + c)]
}

#[inline(always)]
fn vm_values<P: ParamRead + ?Sized>(params: &P, k: &VmCorners, c: usize) -> VmValues {
    VmValues {
        xy: read4(params, k.xy, c),
        xz: read4(params, k.xz, c),
        yz: read4(params, k.yz, c),
        x: read2(params, k.x, c),
        y: read2(params, k.y, c),
        z: read2(params, k.z, c),
    }
}

/// Bilinear interpolation of plane corners `[p00, p10, p01, p11]`.
#[inline(always)]
fn bilerp(p: [f32; 4], fa: f32, fb: f32) -> f32 {
    lerp(lerp(p[0], p[1], fa), lerp(p[2], p[3], fa), fb)
}

/// Interpolated lines and planes of one channel: `[vx, vy, vz]`, `[mxy, mxz, myz]`.
#[inline(always)]
fn vm_interp(v: &VmValues, f: [f32; 3]) -> ([f32; 3], [f32; 3]) {
    let [fx, fy, fz] = f;
    (
        [
            lerp(v.x[0], v.x[1], fx),
            lerp(v.y[0], v.y[1], fy),
            lerp(v.z[0], v.z[1], fz),
        ],
        [
            bilerp(v.xy, fx, fy),
            bilerp(v.xz, fx, fz),
            bilerp(v.yz, fy, fz),
        ],
    )
}

/// Base index (without the channel) and the strides of the corner cell of a dense level.
#[inline(always)]
fn dense_base(lv: &LevelLayout, nc: usize, cell: &Cell) -> (usize, [usize; 3]) {
    let rx = lv.res[0] as usize;
    let ry = lv.res[1] as usize;
    let [ix, iy, iz] = cell.i;
    let base = lv.offset as usize + ((iz * ry + iy) * rx + ix) * nc;
    (base, [nc, rx * nc, rx * ry * nc])
}

/// The 8 corner values of one channel of a dense level, index `dx + 2 dy + 4 dz`.
#[inline(always)]
fn dense_values<P: ParamRead + ?Sized>(params: &P, base: usize, s: [usize; 3]) -> [f32; 8] {
    let mut v = [0.0f32; 8];
    let mut k = 0;
    while k < 8 {
        let idx = base + (k & 1) * s[0] + ((k >> 1) & 1) * s[1] + (k >> 2) * s[2];
        v[k] = params.at(idx);
        k += 1;
    }
    v
}

#[inline(always)]
fn trilerp(v: &[f32; 8], f: [f32; 3]) -> f32 {
    let [fx, fy, fz] = f;
    let c00 = lerp(v[0], v[1], fx);
    let c10 = lerp(v[2], v[3], fx);
    let c01 = lerp(v[4], v[5], fx);
    let c11 = lerp(v[6], v[7], fx);
    lerp(lerp(c00, c10, fy), lerp(c01, c11, fy), fz)
}

/// Evaluates the grid at world position `p` (metres). Writes `out[l * C + c]` for every level
/// `l` and channel `c` and sets the rest of `out` to 0. Positions outside the box clamp to its
/// border.
pub fn grid_forward<P: ParamRead + ?Sized>(
    layout: &GridLayout,
    params: &P,
    p: [f32; 3],
    out: &mut [f32; MAX_GRID_FEATURES],
) {
    let mut k = 0;
    while k < MAX_GRID_FEATURES {
        out[k] = 0.0;
        k += 1;
    }
    let (nl, nc) = kernel_dims(layout);
    let (xn, _) = normalize_with_mask(&layout.aabb, p);
    let dense = layout.kind == GridKind::Dense;
    let mut l = 0;
    while l < nl {
        let lv = &layout.level[l];
        let cell = locate(xn, lv.res);
        if dense {
            let (base, s) = dense_base(lv, nc, &cell);
            let mut c = 0;
            while c < nc {
                let v = dense_values(params, base + c, s);
                out[l * nc + c] = trilerp(&v, cell.f);
                c += 1;
            }
        } else {
            let corners = vm_corners(lv, nc, &cell);
            let mut c = 0;
            while c < nc {
                let v = vm_values(params, &corners, c);
                let (line, plane) = vm_interp(&v, cell.f);
                out[l * nc + c] = line[0] * plane[2] + line[1] * plane[1] + line[2] * plane[0];
                c += 1;
            }
        }
        l += 1;
    }
}

/// Back-propagates `d_feat` (dL/dfeature, same layout as [`grid_forward`]'s output) through
/// the grid at `p`.
///
/// Parameter gradients go to `sink` (index = flat parameter index), one `add` per
/// (parameter, contribution) pair. Returns dL/dp in world units (per metre); an axis on which
/// `p` lies outside the box (so the position was clamped) gets 0.
pub fn grid_backward<P: ParamRead + ?Sized, S: GradSink>(
    layout: &GridLayout,
    params: &P,
    p: [f32; 3],
    d_feat: &[f32; MAX_GRID_FEATURES],
    sink: &mut S,
) -> [f32; 3] {
    let (nl, nc) = kernel_dims(layout);
    let (xn, inside) = normalize_with_mask(&layout.aabb, p);
    let extent = layout.aabb.extent();
    let dense = layout.kind == GridKind::Dense;
    let mut d_p = [0.0f32; 3];
    let mut l = 0;
    while l < nl {
        let lv = &layout.level[l];
        let cell = locate(xn, lv.res);
        // dL/du, u the continuous vertex index of this level.
        let d_u = if dense {
            dense_level_backward(params, lv, nc, &cell, d_feat, l * nc, sink)
        } else {
            vm_level_backward(params, lv, nc, &cell, d_feat, l * nc, sink)
        };
        // du/dp = (res - 1) / 2 * 2 / extent.
        let mut a = 0;
        while a < 3 {
            let r = if lv.res[a] < 2 { 2 } else { lv.res[a] };
            d_p[a] += d_u[a] * math::div((r - 1) as f32, extent[a]);
            a += 1;
        }
        l += 1;
    }
    let mut a = 0;
    while a < 3 {
        if !inside[a] {
            d_p[a] = 0.0;
        }
        a += 1;
    }
    d_p
}

/// One dense level of [`grid_backward`]: the eight corner weights times each channel's
/// gradient `d_feat[off + c]` into `sink`, and the gradient with respect to the continuous
/// vertex index of the level (channels summed in order).
#[inline(always)]
fn dense_level_backward<P: ParamRead + ?Sized, S: GradSink>(
    params: &P,
    lv: &LevelLayout,
    nc: usize,
    cell: &Cell,
    d_feat: &[f32; MAX_GRID_FEATURES],
    off: usize,
    sink: &mut S,
) -> [f32; 3] {
    let [fx, fy, fz] = cell.f;
    let (base, s) = dense_base(lv, nc, cell);
    let wx = [1.0 - fx, fx];
    let wy = [1.0 - fy, fy];
    let wz = [1.0 - fz, fz];
    let mut d_u = [0.0f32; 3];
    let mut c = 0;
    while c < nc {
        let g = d_feat[off + c];
        let v = dense_values(params, base + c, s);
        let mut k = 0;
        while k < 8 {
            let (dx, dy, dz) = (k & 1, (k >> 1) & 1, k >> 2);
            let idx = base + c + dx * s[0] + dy * s[1] + dz * s[2];
            sink.add(idx, g * (wx[dx] * wy[dy] * wz[dz]));
            k += 1;
        }
        // Edge differences along x (pairs k, k+1), y (k, k+2), z (k, k+4).
        let ddx = lerp(
            lerp(v[1] - v[0], v[3] - v[2], fy),
            lerp(v[5] - v[4], v[7] - v[6], fy),
            fz,
        );
        let ddy = lerp(
            lerp(v[2] - v[0], v[3] - v[1], fx),
            lerp(v[6] - v[4], v[7] - v[5], fx),
            fz,
        );
        let ddz = lerp(
            lerp(v[4] - v[0], v[5] - v[1], fx),
            lerp(v[6] - v[2], v[7] - v[3], fx),
            fy,
        );
        d_u[0] += g * ddx;
        d_u[1] += g * ddy;
        d_u[2] += g * ddz;
        c += 1;
    }
    d_u
}

/// One factorized (VM) level of [`grid_backward`]: the line and plane corner contributions of
/// each channel's gradient `d_feat[off + c]` into `sink`, and the gradient with respect to the
/// continuous vertex index of the level (channels summed in order).
#[inline(always)]
fn vm_level_backward<P: ParamRead + ?Sized, S: GradSink>(
    params: &P,
    lv: &LevelLayout,
    nc: usize,
    cell: &Cell,
    d_feat: &[f32; MAX_GRID_FEATURES],
    off: usize,
    sink: &mut S,
) -> [f32; 3] {
    let [fx, fy, fz] = cell.f;
    let k = vm_corners(lv, nc, cell);
    let mut d_u = [0.0f32; 3];
    let mut c = 0;
    while c < nc {
        let g = d_feat[off + c];
        let v = vm_values(params, &k, c);
        let ([vx, vy, vz], [mxy, mxz, myz]) = vm_interp(&v, cell.f);
        // Lines: F = vx * myz + vy * mxz + vz * mxy.
        let gx = g * myz;
        let gy = g * mxz;
        let gz = g * mxy;
        sink.add(k.x[0] + c, gx * (1.0 - fx));
        sink.add(k.x[1] + c, gx * fx);
        sink.add(k.y[0] + c, gy * (1.0 - fy));
        sink.add(k.y[1] + c, gy * fy);
        sink.add(k.z[0] + c, gz * (1.0 - fz));
        sink.add(k.z[1] + c, gz * fz);
        // Planes.
        plane_backward(sink, k.xy, c, g * vz, fx, fy);
        plane_backward(sink, k.xz, c, g * vy, fx, fz);
        plane_backward(sink, k.yz, c, g * vx, fy, fz);
        // Position: each term depends on each axis through exactly one factor.
        let dvx = v.x[1] - v.x[0];
        let dvy = v.y[1] - v.y[0];
        let dvz = v.z[1] - v.z[0];
        let dxy_dx = lerp(v.xy[1] - v.xy[0], v.xy[3] - v.xy[2], fy);
        let dxy_dy = lerp(v.xy[2] - v.xy[0], v.xy[3] - v.xy[1], fx);
        let dxz_dx = lerp(v.xz[1] - v.xz[0], v.xz[3] - v.xz[2], fz);
        let dxz_dz = lerp(v.xz[2] - v.xz[0], v.xz[3] - v.xz[1], fx);
        let dyz_dy = lerp(v.yz[1] - v.yz[0], v.yz[3] - v.yz[2], fz);
        let dyz_dz = lerp(v.yz[2] - v.yz[0], v.yz[3] - v.yz[1], fy);
        d_u[0] += g * (dvx * myz + vy * dxz_dx + vz * dxy_dx);
        d_u[1] += g * (vx * dyz_dy + dvy * mxz + vz * dxy_dy);
        d_u[2] += g * (vx * dyz_dz + vy * dxz_dz + dvz * mxy);
        c += 1;
    }
    d_u
}

/// The 18 corner rows (`nc` channels each) a factorized level reads at one cell, or `None` when
/// a row would leave `params` (only a corrupted layout).
#[inline(always)]
fn vm_rows<'p>(params: &'p [f32], k: &VmCorners, nc: usize) -> Option<[&'p [f32]; 18]> {
    let r = |i: usize| params.get(i..i + nc);
    Some([
        r(k.xy[0])?,
        r(k.xy[1])?,
        r(k.xy[2])?,
        r(k.xy[3])?,
        r(k.xz[0])?,
        r(k.xz[1])?,
        r(k.xz[2])?,
        r(k.xz[3])?,
        r(k.yz[0])?,
        r(k.yz[1])?,
        r(k.yz[2])?,
        r(k.yz[3])?,
        r(k.x[0])?,
        r(k.x[1])?,
        r(k.y[0])?,
        r(k.y[1])?,
        r(k.z[0])?,
        r(k.z[1])?,
    ])
}

impl VmValues {
    /// The values from the 18 rows of [`vm_rows`]' order (planes xy, xz, yz, then lines x,
    /// y, z); `at(j)` reads row `j`. Host-side.
    #[inline(always)]
    fn from_rows(at: impl Fn(usize) -> f32) -> Self {
        VmValues {
            xy: [at(0), at(1), at(2), at(3)],
            xz: [at(4), at(5), at(6), at(7)],
            yz: [at(8), at(9), at(10), at(11)],
            x: [at(12), at(13)],
            y: [at(14), at(15)],
            z: [at(16), at(17)],
        }
    }
}

/// Lines `[vx, vy, vz]` and planes `[mxy, mxz, myz]` of channel `c` from [`vm_rows`], the
/// operations of [`vm_interp`].
#[inline(always)]
fn vm_interp_rows(r: &[&[f32]; 18], c: usize, f: [f32; 3]) -> ([f32; 3], [f32; 3]) {
    vm_interp(&VmValues::from_rows(|j| r[j][c]), f)
}

/// [`grid_forward`] over a parameter slice with a level's channels side by side (what a CPU
/// runs in SIMD lanes): every feature is the same sequence of operations, so the same bits
/// (tested). Dense grids and corrupted layouts take [`grid_forward`]. Host-side; the GPU runs
/// [`grid_forward`].
#[inline]
pub fn grid_forward_rows(
    layout: &GridLayout,
    params: &[f32],
    p: [f32; 3],
    out: &mut [f32; MAX_GRID_FEATURES],
) {
    let (nl, nc) = kernel_dims(layout);
    if layout.kind == GridKind::Dense {
        return grid_forward(layout, params, p, out);
    }
    let (xn, _) = normalize_with_mask(&layout.aabb, p);
    *out = [0.0; MAX_GRID_FEATURES];
    if nc < NARROW_CHANNELS && nl * nc <= LANES {
        if !narrow_forward(layout, params, xn, out) {
            grid_forward(layout, params, p, out);
        }
        return;
    }
    let mut l = 0;
    while l < nl {
        let lv = &layout.level[l];
        let cell = locate(xn, lv.res);
        let Some(r) = vm_rows(params, &vm_corners(lv, nc, &cell), nc) else {
            return grid_forward(layout, params, p, out);
        };
        for (c, o) in out[l * nc..(l + 1) * nc].iter_mut().enumerate() {
            let (line, plane) = vm_interp_rows(&r, c, cell.f);
            *o = line[0] * plane[2] + line[1] * plane[1] + line[2] * plane[0];
        }
        l += 1;
    }
}

/// Lanes of the narrow-grid forms: every (level, channel) feature of a grid with at most this
/// many features is one lane.
const LANES: usize = 16;

/// Grids with fewer channels per level than this (the geometry grid's 2) take the narrow
/// forms: a level's channels alone fill too few SIMD lanes, all levels together fill them.
const NARROW_CHANNELS: usize = 8;

/// The 18 corner values (planes xy, xz, yz as in [`VmValues`], then lines x, y, z) and the
/// 3 cell fractions of every (level, channel) lane of a narrow grid.
struct NarrowLanes {
    v: [[f32; LANES]; 18],
    f: [[f32; LANES]; 3],
}

impl NarrowLanes {
    /// Gathers the lanes at the normalized position `xn`; `None` for a corrupted layout.
    #[inline(always)]
    fn gather(layout: &GridLayout, params: &[f32], xn: [f32; 3]) -> Option<Self> {
        let (nl, nc) = kernel_dims(layout);
        if nc == 2 {
            return Self::gather_fixed::<2>(layout, params, xn);
        }
        let mut g = NarrowLanes {
            v: [[0.0; LANES]; 18],
            f: [[0.0; LANES]; 3],
        };
        for l in 0..nl {
            let lv = &layout.level[l];
            let cell = locate(xn, lv.res);
            let r = vm_rows(params, &vm_corners(lv, nc, &cell), nc)?;
            for c in 0..nc {
                let lane = l * nc + c;
                for (j, row) in r.iter().enumerate() {
                    g.v[j][lane] = row[c];
                }
                for a in 0..3 {
                    g.f[a][lane] = cell.f[a];
                }
            }
        }
        Some(g)
    }

    /// [`Self::gather`] for `NC` channels per level (a row's channels move as one block).
    #[inline(always)]
    fn gather_fixed<const NC: usize>(
        layout: &GridLayout,
        params: &[f32],
        xn: [f32; 3],
    ) -> Option<Self> {
        let (nl, _) = kernel_dims(layout);
        let mut g = NarrowLanes {
            v: [[0.0; LANES]; 18],
            f: [[0.0; LANES]; 3],
        };
        for l in 0..nl.min(LANES / NC) {
            let lv = &layout.level[l];
            let cell = locate(xn, lv.res);
            let r = vm_rows(params, &vm_corners(lv, NC, &cell), NC)?;
            for (v, row) in g.v.iter_mut().zip(r.iter()) {
                let dst: &mut [f32; NC] = v[l * NC..].first_chunk_mut()?;
                *dst = *row.first_chunk::<NC>()?;
            }
            for (f, x) in g.f.iter_mut().zip(cell.f) {
                *f[l * NC..].first_chunk_mut::<NC>()? = [x; NC];
            }
        }
        Some(g)
    }

    /// [`vm_interp`] of lane `i`: the same operations.
    #[inline(always)]
    fn interp(&self, i: usize) -> ([f32; 3], [f32; 3]) {
        let vals = VmValues::from_rows(|j| self.v[j][i]);
        vm_interp(&vals, [self.f[0][i], self.f[1][i], self.f[2][i]])
    }
}

/// [`grid_forward_rows`] of a narrow grid: all features in lanes (each lane the operations of
/// [`grid_forward`]'s channel, unused lanes compute on zeros). False for a corrupted layout.
#[inline(always)]
fn narrow_forward(
    layout: &GridLayout,
    params: &[f32],
    xn: [f32; 3],
    out: &mut [f32; MAX_GRID_FEATURES],
) -> bool {
    let (nl, nc) = kernel_dims(layout);
    let Some(g) = NarrowLanes::gather(layout, params, xn) else {
        return false;
    };
    let mut o = [0.0f32; LANES];
    for (i, o) in o.iter_mut().enumerate() {
        let (line, plane) = g.interp(i);
        *o = line[0] * plane[2] + line[1] * plane[1] + line[2] * plane[0];
    }
    out[..nl * nc].copy_from_slice(&o[..nl * nc]);
    true
}

/// Length of the record [`grid_forward_rows_keep`] fills for `layout`: the six term factors
/// of every feature (0 for a dense grid, whose backward does not use them).
pub fn kept_len(layout: &GridLayout) -> usize {
    let (nl, nc) = kernel_dims(layout);
    if layout.kind == GridKind::Dense || nc > crate::field::mlp::MAX_WIDTH {
        0
    } else {
        6 * nl * nc
    }
}

/// [`grid_forward_rows`] (the same features, the same bits) that also keeps, for the
/// backward, each feature's term factors: the other factor of each of its six products (planes
/// yz, xz, xy, then lines z, y, x: [`term_factors`]' order), `kept[j * nf + i]` for feature `i`
/// of `nf = levels * channels`. The backward multiplies them by the cotangent instead of
/// reading the 18 rows and interpolating again ([`grid_backward_rows_kept`]). False when
/// nothing was kept (a dense grid, a corrupted layout, `kept` shorter than [`kept_len`]);
/// the features are right either way. Host-side.
#[inline]
pub fn grid_forward_rows_keep(
    layout: &GridLayout,
    params: &[f32],
    p: [f32; 3],
    out: &mut [f32; MAX_GRID_FEATURES],
    kept: &mut [f32],
) -> bool {
    let (nl, nc) = kernel_dims(layout);
    let nf = nl * nc;
    let len = kept_len(layout);
    if len == 0 || kept.len() < len {
        grid_forward_rows(layout, params, p, out);
        return false;
    }
    let (xn, _) = normalize_with_mask(&layout.aabb, p);
    *out = [0.0; MAX_GRID_FEATURES];
    if nc < NARROW_CHANNELS && nf <= LANES {
        let Some(g) = NarrowLanes::gather(layout, params, xn) else {
            grid_forward(layout, params, p, out);
            return false;
        };
        let mut o = [0.0f32; LANES];
        let mut t = [[0.0f32; LANES]; 6];
        for (i, o) in o.iter_mut().enumerate() {
            let (line, plane) = g.interp(i);
            *o = line[0] * plane[2] + line[1] * plane[1] + line[2] * plane[0];
            for (t, v) in t.iter_mut().zip(factor_terms(line, plane)) {
                t[i] = v;
            }
        }
        out[..nf].copy_from_slice(&o[..nf]);
        for (dst, t) in kept.chunks_exact_mut(nf).zip(&t) {
            dst.copy_from_slice(&t[..nf]);
        }
        return true;
    }
    let mut l = 0;
    while l < nl {
        let lv = &layout.level[l];
        let cell = locate(xn, lv.res);
        let Some(r) = vm_rows(params, &vm_corners(lv, nc, &cell), nc) else {
            grid_forward(layout, params, p, out);
            return false;
        };
        let (k0, rest) = kept.split_at_mut(nf);
        let (k1, rest) = rest.split_at_mut(nf);
        let (k2, rest) = rest.split_at_mut(nf);
        let (k3, rest) = rest.split_at_mut(nf);
        let (k4, k5) = rest.split_at_mut(nf);
        let at = l * nc..(l + 1) * nc;
        let ks = [
            &mut k0[at.clone()],
            &mut k1[at.clone()],
            &mut k2[at.clone()],
            &mut k3[at.clone()],
            &mut k4[at.clone()],
            &mut k5[at.clone()],
        ];
        let [k0, k1, k2, k3, k4, k5] = ks;
        for (c, o) in out[at].iter_mut().enumerate() {
            let (line, plane) = vm_interp_rows(&r, c, cell.f);
            *o = line[0] * plane[2] + line[1] * plane[1] + line[2] * plane[0];
            let f = factor_terms(line, plane);
            k0[c] = f[0];
            k1[c] = f[1];
            k2[c] = f[2];
            k3[c] = f[3];
            k4[c] = f[4];
            k5[c] = f[5];
        }
        l += 1;
    }
    true
}

/// The other factor of each of a feature's six terms, in [`term_factors`]' order.
#[inline(always)]
fn factor_terms(line: [f32; 3], plane: [f32; 3]) -> [f32; 6] {
    [plane[2], plane[1], plane[0], line[2], line[1], line[0]]
}

/// [`grid_backward_rows_with`] from the factors [`grid_forward_rows_keep`] kept at the same
/// `p` (it returned true): each row value is the cotangent times the kept factor, the product
/// [`term_factors`] forms from the interpolation it repeats (the same f32 either way round),
/// and the same row calls follow, so the same integer sums (tested).
#[inline]
pub fn grid_backward_rows_kept<S: GradSink>(
    layout: &GridLayout,
    p: [f32; 3],
    d_feat: &[f32; MAX_GRID_FEATURES],
    kept: &[f32],
    sink: &mut S,
    gl: &mut [[f32; crate::field::mlp::MAX_WIDTH]; 6],
) {
    let (nl, nc) = kernel_dims(layout);
    let nf = nl * nc;
    let (xn, _) = normalize_with_mask(&layout.aabb, p);
    let mut l = 0;
    while l < nl {
        let lv = &layout.level[l];
        let cell = locate(xn, lv.res);
        let k = vm_corners(lv, nc, &cell);
        let at = l * nc..(l + 1) * nc;
        let d = &d_feat[at.clone()];
        for (j, row) in gl.iter_mut().enumerate() {
            let src = &kept[j * nf..(j + 1) * nf][at.clone()];
            for ((r, &g), &f) in row[..nc].iter_mut().zip(d).zip(src) {
                *r = g * f;
            }
        }
        level_rows_backward(sink, &k, cell.f, gl, nc);
        l += 1;
    }
}

/// Calls `f` with the first index of each of the 12 plane rows (`nc` channels each) that
/// [`grid_forward_rows`] reads and [`grid_backward_rows`] writes at `p` on level `l` of a
/// factorized grid (nothing for dense grids or a level past the last). The CPU's cache hints
/// use it for the finest levels, whose planes are the tensors too large for the caches; it
/// computes no feature.
#[inline(always)]
pub fn for_each_plane_row(layout: &GridLayout, l: usize, p: [f32; 3], mut f: impl FnMut(usize)) {
    let (nl, nc) = kernel_dims(layout);
    if layout.kind == GridKind::Dense || l >= nl {
        return;
    }
    let (xn, _) = normalize_with_mask(&layout.aabb, p);
    let lv = &layout.level[l];
    let k = vm_corners(lv, nc, &locate(xn, lv.res));
    for o in k.xy.into_iter().chain(k.xz).chain(k.yz) {
        f(o);
    }
}

/// The parameter contributions of [`grid_backward`] (not dL/dp), row by row: for each of a
/// level's 18 corners one [`GradSink::add_scaled`] over the channels, each contribution the
/// same product as in [`grid_backward`] (a product of two factors either way round is the same
/// f32), so the integer sums are the same (tested). Dense grids and corrupted layouts take
/// [`grid_backward`]. Host-side; the GPU runs [`grid_backward`].
#[inline]
pub fn grid_backward_rows<S: GradSink>(
    layout: &GridLayout,
    params: &[f32],
    p: [f32; 3],
    d_feat: &[f32; MAX_GRID_FEATURES],
    sink: &mut S,
) {
    let mut gl = [[0.0f32; crate::field::mlp::MAX_WIDTH]; 6];
    grid_backward_rows_with(layout, params, p, d_feat, sink, &mut gl);
}

/// [`grid_backward_rows`] with the caller's factor rows `gl` (any contents: each level writes
/// the channels `..nc` of every row before the sink reads them, and nothing reads past `nc`),
/// so that a caller running it per sample does not clear 3 KB each time. Same calls, same
/// values.
#[inline]
pub fn grid_backward_rows_with<S: GradSink>(
    layout: &GridLayout,
    params: &[f32],
    p: [f32; 3],
    d_feat: &[f32; MAX_GRID_FEATURES],
    sink: &mut S,
    gl: &mut [[f32; crate::field::mlp::MAX_WIDTH]; 6],
) {
    let (nl, nc) = kernel_dims(layout);
    if layout.kind == GridKind::Dense || nc > crate::field::mlp::MAX_WIDTH {
        grid_backward(layout, params, p, d_feat, sink);
        return;
    }
    let (xn, _) = normalize_with_mask(&layout.aabb, p);
    if nc < NARROW_CHANNELS && nl * nc <= LANES {
        if !narrow_backward(layout, params, xn, d_feat, sink, gl) {
            grid_backward(layout, params, p, d_feat, sink);
        }
        return;
    }
    // Per channel: g * (the other factor) of every term: lines x, y, z; planes xy, xz, yz
    // (entries [..nc] are rewritten at every level).
    let mut l = 0;
    while l < nl {
        let lv = &layout.level[l];
        let cell = locate(xn, lv.res);
        let k = vm_corners(lv, nc, &cell);
        let Some(r) = vm_rows(params, &k, nc) else {
            grid_backward(layout, params, p, d_feat, sink);
            return;
        };
        let d = &d_feat[l * nc..(l + 1) * nc];
        for (c, &g) in d.iter().enumerate() {
            let f = term_factors(g, vm_interp_rows(&r, c, cell.f));
            for (row, f) in gl.iter_mut().zip(f) {
                row[c] = f;
            }
        }
        level_rows_backward(sink, &k, cell.f, gl, nc);
        l += 1;
    }
}

/// [`grid_backward_rows`] of a narrow grid: the factors of every (level, channel) in lanes
/// (the operations of [`grid_backward_rows`]' channel loop), then the same row calls in the
/// same order. False (before any call) for a corrupted layout.
#[inline(always)]
fn narrow_backward<S: GradSink>(
    layout: &GridLayout,
    params: &[f32],
    xn: [f32; 3],
    d_feat: &[f32; MAX_GRID_FEATURES],
    sink: &mut S,
    gl: &mut [[f32; crate::field::mlp::MAX_WIDTH]; 6],
) -> bool {
    let (nl, nc) = kernel_dims(layout);
    let Some(g) = NarrowLanes::gather(layout, params, xn) else {
        return false;
    };
    let mut lanes = [[0.0f32; LANES]; 6];
    for i in 0..LANES {
        let d = if i < nl * nc { d_feat[i] } else { 0.0 };
        for (lane, f) in lanes.iter_mut().zip(term_factors(d, g.interp(i))) {
            lane[i] = f;
        }
    }
    for l in 0..nl {
        let lv = &layout.level[l];
        let cell = locate(xn, lv.res);
        let k = vm_corners(lv, nc, &cell);
        for (row, lane) in gl.iter_mut().zip(&lanes) {
            row[..nc].copy_from_slice(&lane[l * nc..(l + 1) * nc]);
        }
        level_rows_backward(sink, &k, cell.f, gl, nc);
    }
    true
}

/// The cotangent `g` of a feature times the other factor of each of its terms, in the
/// order of [`level_rows_backward`]'s rows: lines x, y, z (times the planes yz, xz, xy),
/// then planes xy, xz, yz (times the lines z, y, x).
#[inline(always)]
fn term_factors(g: f32, (line, plane): ([f32; 3], [f32; 3])) -> [f32; 6] {
    [
        g * plane[2],
        g * plane[1],
        g * plane[0],
        g * line[2],
        g * line[1],
        g * line[0],
    ]
}

/// The 18 row contributions of one factorized level at cell fractions `f`: each line's two
/// ends and each plane's four corners, channels `..nc` of the factor rows `gl`
/// ([`term_factors`]' order).
#[inline(always)]
fn level_rows_backward<S: GradSink>(
    sink: &mut S,
    k: &VmCorners,
    f: [f32; 3],
    gl: &[[f32; crate::field::mlp::MAX_WIDTH]; 6],
    nc: usize,
) {
    let [fx, fy, fz] = f;
    sink.add_scaled_rows(k.x, [1.0 - fx, fx], &gl[0], nc);
    sink.add_scaled_rows(k.y, [1.0 - fy, fy], &gl[1], nc);
    sink.add_scaled_rows(k.z, [1.0 - fz, fz], &gl[2], nc);
    plane_rows_backward(sink, k.xy, &gl[3], nc, fx, fy);
    plane_rows_backward(sink, k.xz, &gl[4], nc, fx, fz);
    plane_rows_backward(sink, k.yz, &gl[5], nc, fy, fz);
}

/// [`plane_backward`] for all channels of a corner set at once.
#[inline(always)]
fn plane_rows_backward<S: GradSink>(
    sink: &mut S,
    p: [usize; 4],
    gm: &[f32; crate::field::mlp::MAX_WIDTH],
    nc: usize,
    fa: f32,
    fb: f32,
) {
    let (ua, ub) = (1.0 - fa, 1.0 - fb);
    sink.add_scaled_rows(p, [ua * ub, fa * ub, ua * fb, fa * fb], gm, nc);
}

/// Adds the four bilinear-corner contributions of `gm` = dL/d(plane value) for channel `c`.
#[inline(always)]
fn plane_backward<S: GradSink>(sink: &mut S, p: [usize; 4], c: usize, gm: f32, fa: f32, fb: f32) {
    let (ua, ub) = (1.0 - fa, 1.0 - fb);
    sink.add(p[0] + c, gm * (ua * ub));
    sink.add(p[1] + c, gm * (fa * ub));
    sink.add(p[2] + c, gm * (ua * fb));
    sink.add(p[3] + c, gm * (fa * fb));
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::{F32Sink, NullSink};

    /// Box 2 x 1 x 1 m at the origin; levels of 0.5 m and 1 m cells, 2 channels.
    fn small_cfg(kind: GridKind) -> GridConfig {
        GridConfig {
            kind,
            levels: 2,
            channels: 2,
            cell_sizes: [0.5, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
        }
    }

    /// Records the first index of every row `grid_backward_rows` adds.
    struct RowStarts(std::vec::Vec<usize>);

    impl GradSink for RowStarts {
        fn add(&mut self, _i: usize, _g: f32) {
            panic!("rows only");
        }
        fn add_scaled(
            &mut self,
            offset: usize,
            _g: f32,
            _xs: &[f32; crate::field::mlp::MAX_WIDTH],
            _n: usize,
        ) {
            self.0.push(offset);
        }
    }

    /// Calls `f` with the first index of every row of channels that [`grid_forward_rows`] reads
    /// and [`grid_backward_rows`] writes at `p` (18 corners per factorized level; nothing for
    /// dense grids): the reference the plane rows are tested against.
    fn for_each_row(layout: &GridLayout, p: [f32; 3], mut f: impl FnMut(usize)) {
        if layout.kind == GridKind::Dense {
            return;
        }
        let (nl, nc) = kernel_dims(layout);
        let (xn, _) = normalize_with_mask(&layout.aabb, p);
        let mut l = 0;
        while l < nl {
            let lv = &layout.level[l];
            let k = vm_corners(lv, nc, &locate(xn, lv.res));
            for o in k.xy.into_iter().chain(k.xz).chain(k.yz) {
                f(o);
            }
            for o in k.x.into_iter().chain(k.y).chain(k.z) {
                f(o);
            }
            l += 1;
        }
    }

    /// The rows named per level are exactly the rows the row-wise backward writes, and the
    /// cache hints' plane rows are each level's first 12 of them, at every level,
    /// for points inside, on the faces of and outside the box.
    #[test]
    fn for_each_row_names_the_backward_rows() {
        let aabb = Aabb::new([-1.0, -0.5, -2.0], [3.0, 1.5, 2.0]);
        for cfg in [
            GridConfig::hi_map_geometry(),
            GridConfig::hi_map_appearance(),
        ] {
            let g = GridLayout::new(&cfg, aabb).unwrap();
            let params = std::vec![0.25f32; g.param_count as usize];
            let d_feat = [1.0f32; MAX_GRID_FEATURES];
            for p in [
                [0.3, 0.2, -0.7],
                [-1.0, 1.5, 2.0],
                [7.0, -3.0, 0.1],
                [2.99, 0.0, 1.99],
            ] {
                let mut written = RowStarts(std::vec::Vec::new());
                grid_backward_rows(&g, &params, p, &d_feat, &mut written);
                let mut named = std::vec::Vec::new();
                for_each_row(&g, p, |o| named.push(o));
                // Each level's plane rows: the first 12 of its 18, in the same order.
                for l in 0..g.levels as usize {
                    let mut planes = std::vec::Vec::new();
                    for_each_plane_row(&g, l, p, |o| planes.push(o));
                    assert_eq!(planes[..], named[18 * l..18 * l + 12], "{p:?} level {l}");
                }
                let mut none = 0;
                for_each_plane_row(&g, g.levels as usize, p, |_| none += 1);
                assert_eq!(none, 0);
                written.0.sort_unstable();
                named.sort_unstable();
                assert_eq!(named.len(), 18 * g.levels as usize);
                assert_eq!(named, written.0, "{p:?}");
            }
        }
    }

    fn small_box() -> Aabb {
        Aabb::new([0.0, 0.0, 0.0], [2.0, 1.0, 1.0])
    }

    fn small(kind: GridKind) -> GridLayout {
        GridLayout::new(&small_cfg(kind), small_box()).unwrap()
    }

    fn one_level(kind: GridKind, channels: u32) -> GridLayout {
        let cfg = GridConfig {
            kind,
            levels: 1,
            channels,
            cell_sizes: [0.5, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
        };
        GridLayout::new(&cfg, small_box()).unwrap()
    }

    /// A factorized grid of `n` levels (0.25 m, 0.35 m, ...) with `channels` each.
    fn levels(n: usize, channels: u32) -> GridLayout {
        let mut cell_sizes = [0.0f32; MAX_LEVELS];
        for (l, c) in cell_sizes.iter_mut().take(n).enumerate() {
            *c = 0.25 + 0.1 * l as f32;
        }
        let cfg = GridConfig {
            kind: GridKind::Factorized,
            levels: n as u32,
            channels,
            cell_sizes,
        };
        GridLayout::new(&cfg, small_box()).unwrap()
    }

    fn forward(layout: &GridLayout, params: &[f32], p: [f32; 3]) -> [f32; MAX_GRID_FEATURES] {
        let mut out = [f32::NAN; MAX_GRID_FEATURES];
        grid_forward(layout, params, p, &mut out);
        out
    }

    fn random_params(layout: &GridLayout, seed: u32) -> Vec<f32> {
        let mut params = vec![0.0f32; layout.param_count as usize];
        grid_init(layout, &mut params, seed, 1.0).unwrap();
        params
    }

    // ---------------------------------------------------------------- offset tables

    #[test]
    fn small_box_offsets_factorized() {
        let g = small(GridKind::Factorized);
        // Level 0, 0.5 m: x 2/0.5 = 4 cells -> 5 vertices; y, z 1/0.5 = 2 -> 3.
        // Planes xy 5*3 = 15, xz 5*3 = 15, yz 3*3 = 9; lines 5, 3, 3; times C = 2:
        // xy [0, 30), xz [30, 60), yz [60, 78), x [78, 88), y [88, 94), z [94, 100).
        assert_eq!(
            g.level[0],
            LevelLayout {
                res: [5, 3, 3],
                offset: 0,
                plane_offsets: [0, 30, 60],
                line_offsets: [78, 88, 94],
                count: 100,
            }
        );
        // Level 1, 1 m: 3 x 2 x 2 vertices. xy 6, xz 6, yz 4, lines 3, 2, 2 -> 23 * 2 = 46.
        assert_eq!(
            g.level[1],
            LevelLayout {
                res: [3, 2, 2],
                offset: 100,
                plane_offsets: [100, 112, 124],
                line_offsets: [132, 138, 142],
                count: 46,
            }
        );
        assert_eq!(g.param_count, 146);
        assert_eq!(g.feature_dim(), 4);
        for l in 2..MAX_LEVELS {
            assert_eq!(g.level[l], LevelLayout::UNUSED);
        }
    }

    #[test]
    fn small_box_offsets_dense() {
        let g = small(GridKind::Dense);
        // 5*3*3*2 = 90, then 3*2*2*2 = 24.
        assert_eq!(
            g.level[0],
            LevelLayout {
                res: [5, 3, 3],
                offset: 0,
                plane_offsets: [0; 3],
                line_offsets: [0; 3],
                count: 90,
            }
        );
        assert_eq!(g.level[1].res, [3, 2, 2]);
        assert_eq!(g.level[1].offset, 90);
        assert_eq!(g.level[1].count, 24);
        assert_eq!(g.param_count, 114);
    }

    /// Hi-Map configs on a 4 x 3 x 2.5 m box. Vertices: ceil(extent / cell) + 1.
    #[test]
    fn hi_map_offsets_4x3x2_5() {
        let aabb = Aabb::new([-2.0, -1.0, 0.0], [2.0, 2.0, 2.5]);
        let g = GridLayout::new(&GridConfig::hi_map_geometry(), aabb).unwrap();
        // (res, offset, planes, lines, count), C = 2; count = 2 * (xy + xz + yz + x + y + z).
        // (res, offset, plane offsets, line offsets, count)
        type Row = ([u32; 3], u32, [u32; 3], [u32; 3], u32);
        let expected: [Row; 6] = [
            // 64 cm: 6.25 -> 7 -> 8, 4.6875 -> 5 -> 6, 3.90625 -> 4 -> 5.
            // 2 * (48 + 40 + 30 + 19) = 274.
            ([8, 6, 5], 0, [0, 96, 176], [236, 252, 264], 274),
            // 32 cm: 12.5 -> 14, 9.375 -> 11, 7.8125 -> 9. 2 * (154 + 126 + 99 + 34) = 826.
            ([14, 11, 9], 274, [274, 582, 834], [1032, 1060, 1082], 826),
            // 16 cm: 25 -> 26, 18.75 -> 20, 15.625 -> 17. 2 * (520 + 442 + 340 + 63) = 2730.
            (
                [26, 20, 17],
                1100,
                [1100, 2140, 3024],
                [3704, 3756, 3796],
                2730,
            ),
            // 8 cm: 50 -> 51, 37.5 -> 39, 31.25 -> 33. 2 * (1989 + 1683 + 1287 + 123) = 10164.
            (
                [51, 39, 33],
                3830,
                [3830, 7808, 11174],
                [13748, 13850, 13928],
                10164,
            ),
            // 4 cm: 100 -> 101, 75 -> 76, 62.5 -> 64. 2 * (7676 + 6464 + 4864 + 241) = 38490.
            (
                [101, 76, 64],
                13994,
                [13994, 29346, 42274],
                [52002, 52204, 52356],
                38490,
            ),
            // 2 cm: 200 -> 201, 150 -> 151, 125 -> 126.
            // 2 * (30351 + 25326 + 19026 + 478) = 150362.
            (
                [201, 151, 126],
                52484,
                [52484, 113186, 163838],
                [201890, 202292, 202594],
                150362,
            ),
        ];
        for (l, (res, offset, planes, lines, count)) in expected.iter().enumerate() {
            assert_eq!(
                g.level[l],
                LevelLayout {
                    res: *res,
                    offset: *offset,
                    plane_offsets: *planes,
                    line_offsets: *lines,
                    count: *count,
                },
                "level {l}"
            );
        }
        // 52484 + 150362.
        assert_eq!(g.param_count, 202_846);
        assert_eq!(g.feature_dim(), 12);

        let a = GridLayout::new(&GridConfig::hi_map_appearance(), aabb).unwrap();
        // 24 cm: 16.67 -> 17 -> 18, 12.5 -> 14, 10.42 -> 12. 32 * (252 + 216 + 168 + 44) = 21760.
        assert_eq!(
            a.level[0],
            LevelLayout {
                res: [18, 14, 12],
                offset: 0,
                plane_offsets: [0, 8064, 14976],
                line_offsets: [20352, 20928, 21376],
                count: 21760,
            }
        );
        // 2 cm: as above with C = 32: 32 * 75181 = 2405792.
        assert_eq!(
            a.level[1],
            LevelLayout {
                res: [201, 151, 126],
                offset: 21760,
                plane_offsets: [21760, 992992, 1803424],
                line_offsets: [2412256, 2418688, 2423520],
                count: 2405792,
            }
        );
        assert_eq!(a.param_count, 2_427_552);
        assert_eq!(a.feature_dim(), 64);

        // Dense ablation of the geometry grid: 2 * 8*6*5 = 480 at 64 cm, ..., the sum of
        // 2 * rx*ry*rz over the levels above.
        let d = GridLayout::new(
            &GridConfig::hi_map_geometry().with_kind(GridKind::Dense),
            aabb,
        )
        .unwrap();
        let dense: u32 = expected.iter().map(|e| 2 * e.0[0] * e.0[1] * e.0[2]).sum();
        assert_eq!(d.level[0].count, 480);
        assert_eq!(d.param_count, dense);
    }

    /// The parameter counts on a 6 x 6 x 3 m box (reported to the lead).
    #[test]
    fn hi_map_param_counts_6x6x3() {
        let aabb = Aabb::new([0.0; 3], [6.0, 6.0, 3.0]);
        let g = GridLayout::new(&GridConfig::hi_map_geometry(), aabb).unwrap();
        let a = GridLayout::new(&GridConfig::hi_map_appearance(), aabb).unwrap();
        // 2 cm level: 301 x 301 x 151 vertices;
        // 2 * (90601 + 45451 + 45451 + 753) = 364512 geometry, times 16 = 5832192 appearance.
        assert_eq!(g.level[5].res, [301, 301, 151]);
        assert_eq!(g.level[5].count, 364_512);
        assert_eq!(a.level[1].count, 5_832_192);
        assert_eq!(g.param_count, 489_266);
        assert_eq!(a.param_count, 5_879_232);
    }

    #[test]
    fn vertex_count_rounding() {
        // 0.3 / 0.01 is 30.0000019 in f32: the tolerance keeps it at 30 cells, 31 vertices.
        assert_eq!(vertices_per_axis(0.3, 0.01), Ok(31));
        // A genuine partial cell still rounds up: 0.301 / 0.01 = 30.1 -> 31 cells.
        assert_eq!(vertices_per_axis(0.301, 0.01), Ok(32));
        // Extent smaller than a cell: one cell, two vertices.
        assert_eq!(vertices_per_axis(0.3, 1.0), Ok(2));
        assert_eq!(vertices_per_axis(1.0, 1.0), Ok(2));
        assert!(matches!(
            vertices_per_axis(1.0, 1e-30),
            Err(Error::Capacity { .. })
        ));
    }

    // ---------------------------------------------------------------- errors

    #[test]
    fn errors() {
        let aabb = small_box();
        let mut cfg = GridConfig::hi_map_appearance();
        cfg.levels = 5; // 5 * 32 = 160 > 128
        assert_eq!(
            GridLayout::new(&cfg, aabb),
            Err(Error::Capacity {
                what: "grid features (levels * channels)",
                needed: 160,
                capacity: 128
            })
        );
        let mut cfg = small_cfg(GridKind::Factorized);
        cfg.levels = 0;
        assert!(matches!(
            GridLayout::new(&cfg, aabb),
            Err(Error::InvalidConfig(_))
        ));
        cfg.levels = 9;
        assert!(matches!(
            GridLayout::new(&cfg, aabb),
            Err(Error::Capacity { needed: 9, .. })
        ));
        let mut cfg = small_cfg(GridKind::Factorized);
        cfg.channels = 0;
        assert!(matches!(
            GridLayout::new(&cfg, aabb),
            Err(Error::InvalidConfig(_))
        ));
        // Channel count that would overflow a u32 product.
        cfg.channels = u32::MAX;
        assert!(matches!(
            GridLayout::new(&cfg, aabb),
            Err(Error::Capacity { .. })
        ));
        let cfg = small_cfg(GridKind::Factorized);
        for bad in [
            Aabb::new([0.0; 3], [1.0, 0.0, 1.0]),
            Aabb::new([0.0; 3], [1.0, -1.0, 1.0]),
            Aabb::new([0.0; 3], [f32::NAN, 1.0, 1.0]),
            Aabb::new([f32::NEG_INFINITY, 0.0, 0.0], [1.0; 3]),
        ] {
            assert!(
                matches!(GridLayout::new(&cfg, bad), Err(Error::InvalidConfig(_))),
                "{bad:?}"
            );
        }
        for bad_cell in [0.0, -0.5, f32::NAN, f32::INFINITY] {
            let mut cfg = small_cfg(GridKind::Factorized);
            cfg.cell_sizes[1] = bad_cell;
            assert!(matches!(
                GridLayout::new(&cfg, aabb),
                Err(Error::InvalidConfig(_))
            ));
        }
        // Unused entries are ignored.
        let mut cfg = small_cfg(GridKind::Factorized);
        cfg.cell_sizes[2] = f32::NAN;
        assert!(GridLayout::new(&cfg, aabb).is_ok());
        // Too many parameters for u32: a dense 2 cm grid over 40 x 40 x 40 m (2001^3 * 2).
        let big = Aabb::new([0.0; 3], [40.0; 3]);
        let mut cfg = GridConfig::hi_map_geometry().with_kind(GridKind::Dense);
        cfg.levels = 6;
        assert!(matches!(
            GridLayout::new(&cfg, big),
            Err(Error::Capacity {
                what: "grid parameters",
                ..
            })
        ));
        // Same box factorized fits.
        assert!(GridLayout::new(&GridConfig::hi_map_geometry(), big).is_ok());
        // A box whose extent overflows f32.
        let huge = Aabb::new([-3e38; 3], [3e38; 3]);
        assert!(matches!(
            GridLayout::new(&cfg, huge),
            Err(Error::Capacity { .. })
        ));
    }

    #[test]
    fn init_checks_length_and_draws_normals() {
        let g = small(GridKind::Factorized);
        let mut short = vec![0.0f32; 145];
        assert_eq!(
            grid_init(&g, &mut short, 1, 0.01),
            Err(Error::Shape {
                what: "grid parameters",
                expected: 146,
                got: 145
            })
        );
        let mut long = vec![0.0f32; 147];
        assert!(matches!(
            grid_init(&g, &mut long, 1, 0.01),
            Err(Error::Shape { .. })
        ));
        let mut p = vec![0.0f32; 146];
        assert!(matches!(
            grid_init(&g, &mut p, 1, f32::NAN),
            Err(Error::InvalidConfig(_))
        ));
        grid_init(&g, &mut p, 7, 0.01).unwrap();
        for (i, v) in p.iter().enumerate() {
            assert_eq!(
                v.to_bits(),
                (0.01 * crate::rng::normal(7, 0, i as u32)).to_bits()
            );
        }
        // Statistics on a larger grid: std 0.01.
        let big = GridLayout::new(&GridConfig::hi_map_geometry(), small_box()).unwrap();
        let mut q = vec![0.0f32; big.param_count as usize];
        grid_init(&big, &mut q, 3, 0.01).unwrap();
        let n = q.len() as f64;
        let mean = q.iter().map(|&v| v as f64).sum::<f64>() / n;
        let var = q.iter().map(|&v| (v as f64 - mean).powi(2)).sum::<f64>() / n;
        assert!(n > 10_000.0);
        assert!(mean.abs() < 3e-4, "mean {mean}");
        assert!((var.sqrt() - 0.01).abs() < 3e-4, "std {}", var.sqrt());
    }

    // ---------------------------------------------------------------- golden values

    #[test]
    fn normalize_matches_aabb() {
        let aabb = Aabb::new([-1.3, 0.2, -0.7], [2.9, 1.1, 0.45]);
        for i in 0..2000u32 {
            let p = [
                crate::rng::uniform(1, i, 0) * 6.0 - 2.5,
                crate::rng::uniform(1, i, 1) * 2.0 - 0.3,
                crate::rng::uniform(1, i, 2) * 2.0 - 1.2,
            ];
            let (xn, inside) = normalize_with_mask(&aabb, p);
            let want = aabb.normalize(p);
            for a in 0..3 {
                assert_eq!(xn[a].to_bits(), want[a].to_bits());
                let raw = (p[a] - aabb.min[a]) / (aabb.max[a] - aabb.min[a]) * 2.0 - 1.0;
                assert_eq!(inside[a], (-1.0..=1.0).contains(&raw));
            }
        }
    }

    /// One level, box 2 x 1 x 1, 0.5 m cells: res (5, 3, 3), continuous index u = p / 0.5.
    /// Point p = (0.625, 0.25, 0.875) -> u = (1.25, 0.5, 1.75) (all exact in f32).
    const P_GOLD: [f32; 3] = [0.625, 0.25, 0.875];

    #[test]
    fn golden_factorized_lines() {
        let g = one_level(GridKind::Factorized, 2);
        let lv = g.level[0];
        let c_n = 2usize;
        let mut params = vec![0.0f32; g.param_count as usize];
        // All planes 1; line x = i + 100 c, line y = 2 i, line z = 3 i.
        for v in &mut params[..lv.line_offsets[0] as usize] {
            *v = 1.0;
        }
        for c in 0..c_n {
            for i in 0..5 {
                params[lv.line_offsets[0] as usize + i * c_n + c] = i as f32 + 100.0 * c as f32;
            }
            for i in 0..3 {
                params[lv.line_offsets[1] as usize + i * c_n + c] = 2.0 * i as f32;
                params[lv.line_offsets[2] as usize + i * c_n + c] = 3.0 * i as f32;
            }
        }
        // F_c = (u_x + 100 c) + 2 u_y + 3 u_z = 1.25 + 1.0 + 5.25 + 100 c = 7.5 + 100 c.
        let out = forward(&g, &params, P_GOLD);
        assert_eq!(out[0], 7.5);
        assert_eq!(out[1], 107.5);
        assert!(out[2..].iter().all(|&v| v == 0.0));
    }

    #[test]
    fn golden_factorized_planes() {
        let g = one_level(GridKind::Factorized, 1);
        let lv = g.level[0];
        let (rx, ry, rz) = (5usize, 3usize, 3usize);
        let mut params = vec![0.0f32; g.param_count as usize];
        // Lines all 1; plane xy = ix + 10 iy, xz = ix + 10 iz, yz = iy + 10 iz (checks the
        // row-major (b, a) orientation: bilinear interpolation of a linear function is exact).
        for v in &mut params[lv.line_offsets[0] as usize..] {
            *v = 1.0;
        }
        for iy in 0..ry {
            for ix in 0..rx {
                params[lv.plane_offsets[0] as usize + iy * rx + ix] = (ix + 10 * iy) as f32;
            }
        }
        for iz in 0..rz {
            for ix in 0..rx {
                params[lv.plane_offsets[1] as usize + iz * rx + ix] = (ix + 10 * iz) as f32;
            }
            for iy in 0..ry {
                params[lv.plane_offsets[2] as usize + iz * ry + iy] = (iy + 10 * iz) as f32;
            }
        }
        // F = Myz + Mxz + Mxy = (u_y + 10 u_z) + (u_x + 10 u_z) + (u_x + 10 u_y)
        //   = 2 u_x + 11 u_y + 20 u_z = 2.5 + 5.5 + 35 = 43.
        let out = forward(&g, &params, P_GOLD);
        assert_eq!(out[0], 43.0);

        // A true product: line x = i + 1, plane yz = iy * iz, everything else 0:
        // F = (u_x + 1) * u_y * u_z = 2.25 * 0.5 * 1.75 = 1.96875.
        let mut params = vec![0.0f32; g.param_count as usize];
        for i in 0..rx {
            params[lv.line_offsets[0] as usize + i] = (i + 1) as f32;
        }
        for iz in 0..rz {
            for iy in 0..ry {
                params[lv.plane_offsets[2] as usize + iz * ry + iy] = (iy * iz) as f32;
            }
        }
        let out = forward(&g, &params, P_GOLD);
        assert_eq!(out[0], 1.96875);
    }

    #[test]
    fn golden_dense() {
        let g = one_level(GridKind::Dense, 2);
        let (rx, ry, rz) = (5usize, 3usize, 3usize);
        let mut params = vec![0.0f32; g.param_count as usize];
        // Value = ix + 10 iy + 100 iz + 1000 c -> trilinear gives u_x + 10 u_y + 100 u_z + 1000 c
        // = 1.25 + 5 + 175 + 1000 c = 181.25 + 1000 c.
        for iz in 0..rz {
            for iy in 0..ry {
                for ix in 0..rx {
                    for c in 0..2 {
                        params[((iz * ry + iy) * rx + ix) * 2 + c] =
                            (ix + 10 * iy + 100 * iz + 1000 * c) as f32;
                    }
                }
            }
        }
        let out = forward(&g, &params, P_GOLD);
        assert_eq!(out[0], 181.25);
        assert_eq!(out[1], 1181.25);
        assert!(out[2..].iter().all(|&v| v == 0.0));
        // Product ix * iy * iz: trilinear reproduces u_x u_y u_z = 1.25 * 0.5 * 1.75 = 1.09375.
        for iz in 0..rz {
            for iy in 0..ry {
                for ix in 0..rx {
                    params[((iz * ry + iy) * rx + ix) * 2] = (ix * iy * iz) as f32;
                }
            }
        }
        assert_eq!(forward(&g, &params, P_GOLD)[0], 1.09375);
    }

    /// At a vertex, a factorized feature is exactly vx[i] Myz[j,k] + vy[j] Mxz[i,k] + vz[k] Mxy[i,j]
    /// (computed here with f32 in the same order), a dense one the vertex value; both levels, and
    /// the last vertex (fraction 1) included.
    #[test]
    fn vertices_return_vertex_values() {
        for kind in [GridKind::Factorized, GridKind::Dense] {
            let g = small(kind);
            let params = random_params(&g, 11);
            let c_n = 2usize;
            // Level 1 vertices (1 m) are also level 0 vertices (0.5 m).
            for (ix, iy, iz) in [(0, 0, 0), (1, 1, 0), (2, 1, 1), (2, 0, 1), (1, 0, 1)] {
                let p = [ix as f32, iy as f32, iz as f32];
                let out = forward(&g, &params, p);
                for l in 0..2 {
                    let lv = g.level[l];
                    let s = [2, 1][l]; // vertex index per metre: 0.5 m and 1 m cells
                    let (i, j, k) = (ix * s, iy * s, iz * s);
                    let (rx, ry) = (lv.res[0] as usize, lv.res[1] as usize);
                    for c in 0..c_n {
                        let want = match kind {
                            GridKind::Factorized => {
                                let at = |o: u32, idx: usize| params[o as usize + idx * c_n + c];
                                let vx = at(lv.line_offsets[0], i);
                                let vy = at(lv.line_offsets[1], j);
                                let vz = at(lv.line_offsets[2], k);
                                let mxy = at(lv.plane_offsets[0], j * rx + i);
                                let mxz = at(lv.plane_offsets[1], k * rx + i);
                                let myz = at(lv.plane_offsets[2], k * ry + j);
                                vx * myz + vy * mxz + vz * mxy
                            }
                            GridKind::Dense => {
                                params[lv.offset as usize + ((k * ry + j) * rx + i) * c_n + c]
                            }
                        };
                        assert_eq!(
                            out[l * c_n + c].to_bits(),
                            want.to_bits(),
                            "{kind:?} l{l} c{c} vertex {:?}",
                            (ix, iy, iz)
                        );
                    }
                }
            }
        }
    }

    /// Independent f64 reference of the interpolation (index formulas from the module docs).
    fn reference(g: &GridLayout, params: &[f32], p: [f32; 3]) -> Vec<f64> {
        let c_n = g.channels as usize;
        let mut out = vec![0.0f64; g.feature_dim()];
        for l in 0..g.levels as usize {
            let lv = g.level[l];
            let r = lv.res.map(|v| v as usize);
            let mut i = [0usize; 3];
            let mut f = [0.0f64; 3];
            for a in 0..3 {
                let x = ((p[a] - g.aabb.min[a]) as f64 / (g.aabb.max[a] - g.aabb.min[a]) as f64)
                    .clamp(0.0, 1.0);
                let u = x * (r[a] - 1) as f64;
                i[a] = (u.floor() as usize).min(r[a] - 2);
                f[a] = u - i[a] as f64;
            }
            let w = |a: usize, d: usize| if d == 0 { 1.0 - f[a] } else { f[a] };
            for c in 0..c_n {
                let mut v = 0.0;
                match g.kind {
                    GridKind::Dense => {
                        for dz in 0..2 {
                            for dy in 0..2 {
                                for dx in 0..2 {
                                    let idx = lv.offset as usize
                                        + (((i[2] + dz) * r[1] + i[1] + dy) * r[0] + i[0] + dx)
                                            * c_n
                                        + c;
                                    v += params[idx] as f64 * w(0, dx) * w(1, dy) * w(2, dz);
                                }
                            }
                        }
                    }
                    GridKind::Factorized => {
                        let line = |a: usize| {
                            let o = lv.line_offsets[a] as usize;
                            (0..2)
                                .map(|d| params[o + (i[a] + d) * c_n + c] as f64 * w(a, d))
                                .sum::<f64>()
                        };
                        // plane over axes (a, b), index ((ib * r_a + ia) * C + c)
                        let plane = |k: usize, a: usize, b: usize| {
                            let o = lv.plane_offsets[k] as usize;
                            let mut s = 0.0;
                            for db in 0..2 {
                                for da in 0..2 {
                                    let idx = o + ((i[b] + db) * r[a] + i[a] + da) * c_n + c;
                                    s += params[idx] as f64 * w(a, da) * w(b, db);
                                }
                            }
                            s
                        };
                        v = line(0) * plane(2, 1, 2)
                            + line(1) * plane(1, 0, 2)
                            + line(2) * plane(0, 0, 1);
                    }
                }
                out[l * c_n + c] = v;
            }
        }
        out
    }

    #[test]
    fn forward_matches_f64_reference() {
        let aabb = Aabb::new([-0.3, 0.1, -0.2], [0.5, 0.6, 0.2]);
        for kind in [GridKind::Factorized, GridKind::Dense] {
            let g = GridLayout::new(&GridConfig::hi_map_geometry().with_kind(kind), aabb).unwrap();
            let params = random_params(&g, 5);
            for s in 0..300u32 {
                // Includes points outside the box (clamped) on every side.
                let p = [
                    crate::rng::uniform(9, s, 0) * 1.2 - 0.5,
                    crate::rng::uniform(9, s, 1) * 0.8 - 0.05,
                    crate::rng::uniform(9, s, 2) * 0.6 - 0.3,
                ];
                let out = forward(&g, &params, p);
                let want = reference(&g, &params, p);
                for (k, w) in want.iter().enumerate() {
                    let got = out[k] as f64;
                    assert!(
                        (got - w).abs() <= 1e-5 + 1e-5 * w.abs(),
                        "{kind:?} p {p:?} feature {k}: {got} vs {w}"
                    );
                }
                assert!(out[want.len()..].iter().all(|&v| v == 0.0));
            }
        }
    }

    #[test]
    fn outside_points_clamp_to_border() {
        for kind in [GridKind::Factorized, GridKind::Dense] {
            let g = small(kind);
            let params = random_params(&g, 2);
            let a = forward(&g, &params, [-3.0, 0.3, 7.0]);
            let b = forward(&g, &params, [0.0, 0.3, 1.0]);
            assert_eq!(a, b);
            // NaN positions do not panic and give finite features.
            let n = forward(&g, &params, [f32::NAN, 0.3, 0.2]);
            assert!(n.iter().all(|v| v.is_finite()));
            let mut d = [0.0f32; MAX_GRID_FEATURES];
            d[0] = 1.0;
            let gp = grid_backward(&g, &params[..], [f32::NAN, 0.3, 0.2], &d, &mut NullSink);
            assert_eq!(gp[0], 0.0);
        }
    }

    // ---------------------------------------------------------------- backward

    /// Counts `add` calls and records the largest index.
    struct CountSink {
        calls: usize,
        max_index: usize,
    }

    impl GradSink for CountSink {
        fn add(&mut self, i: usize, _g: f32) {
            self.calls += 1;
            self.max_index = self.max_index.max(i);
        }
    }

    /// Records every contribution as (index, f32 bits), to compare multisets.
    struct RecordSink {
        adds: Vec<(usize, u32)>,
    }
    impl GradSink for RecordSink {
        fn add(&mut self, i: usize, g: f32) {
            self.adds.push((i, g.to_bits()));
        }
    }

    /// The row forms give the per-channel kernels' bits: the features, and the same multiset
    /// of (parameter, contribution) pairs, at random points (inside, on the border, outside)
    /// for both box shapes and random parameters.
    #[test]
    fn row_kernels_equal_the_channel_kernels() {
        let mut rng = crate::rng::SplitMix::new(21);
        for (layout, seed) in [
            (small(GridKind::Factorized), 1),
            (levels(5, 2), 5),
            (levels(8, 2), 6),
            (levels(3, 4), 7),
            (levels(2, 7), 8),
            (levels(3, 7), 9),
            (one_level(GridKind::Factorized, 7), 2),
            (one_level(GridKind::Factorized, 16), 3),
            (one_level(GridKind::Factorized, 32), 4),
            // two levels of the appearance grids' widths
            (levels(2, 16), 10),
            (levels(2, 32), 11),
        ] {
            let params = random_params(&layout, seed);
            for trial in 0..400 {
                let p = [
                    (rng.unit() * 3.0 - 0.5) * 2.0,
                    (rng.unit() * 3.0 - 0.5),
                    (rng.unit() * 3.0 - 0.5),
                ];
                let p = if trial == 0 { [2.0, 1.0, 1.0] } else { p };
                let a = forward(&layout, &params, p);
                let mut b = [1.0f32; MAX_GRID_FEATURES];
                grid_forward_rows(&layout, &params, p, &mut b);
                assert_eq!(a.map(f32::to_bits), b.map(f32::to_bits), "{p:?}");
                let mut d = [0.0f32; MAX_GRID_FEATURES];
                for v in d.iter_mut().take(layout.feature_dim()) {
                    *v = rng.unit() - 0.5;
                }
                let mut s1 = RecordSink { adds: Vec::new() };
                let mut s2 = RecordSink { adds: Vec::new() };
                grid_backward(&layout, &params[..], p, &d, &mut s1);
                grid_backward_rows(&layout, &params, p, &d, &mut s2);
                // The same calls with reused factor rows whatever they held before.
                let mut s3 = RecordSink { adds: Vec::new() };
                let fill = [f32::NAN, 1e30, -7.0][trial % 3];
                let mut gl = [[fill; crate::field::mlp::MAX_WIDTH]; 6];
                grid_backward_rows_with(&layout, &params, p, &d, &mut s3, &mut gl);
                assert_eq!(s2.adds, s3.adds, "{p:?}");
                // The features with the term factors kept, and the backward from them: the
                // same features and the same calls (a kept buffer of stale contents).
                let mut kept = vec![fill; kept_len(&layout) + 3];
                let mut c = [1.0f32; MAX_GRID_FEATURES];
                assert!(grid_forward_rows_keep(
                    &layout, &params, p, &mut c, &mut kept
                ));
                assert_eq!(a.map(f32::to_bits), c.map(f32::to_bits), "{p:?}");
                let mut s4 = RecordSink { adds: Vec::new() };
                grid_backward_rows_kept(&layout, p, &d, &kept, &mut s4, &mut gl);
                assert_eq!(s2.adds, s4.adds, "{p:?}");
                // Too short a buffer keeps nothing and still gives the features.
                let short = kept_len(&layout) - 1;
                assert!(!grid_forward_rows_keep(
                    &layout,
                    &params,
                    p,
                    &mut c,
                    &mut kept[..short]
                ));
                assert_eq!(a.map(f32::to_bits), c.map(f32::to_bits), "{p:?}");
                s1.adds.sort_unstable();
                s2.adds.sort_unstable();
                assert_eq!(s1.adds, s2.adds, "{p:?}");
            }
        }
    }

    #[test]
    fn dense_grids_keep_nothing() {
        let g = small(GridKind::Dense);
        let params = random_params(&g, 4);
        assert_eq!(kept_len(&g), 0);
        let mut kept = vec![0.0f32; 64];
        let mut out = [0.0f32; MAX_GRID_FEATURES];
        let p = [0.3, 0.7, 0.2];
        assert!(!grid_forward_rows_keep(&g, &params, p, &mut out, &mut kept));
        assert_eq!(
            out.map(f32::to_bits),
            forward(&g, &params, p).map(f32::to_bits)
        );
    }

    #[test]
    fn one_add_per_parameter_contribution() {
        for (kind, per_channel) in [(GridKind::Factorized, 18), (GridKind::Dense, 8)] {
            let g = small(kind);
            let params = random_params(&g, 4);
            let d = [1.0f32; MAX_GRID_FEATURES];
            // Last vertex corner (fraction 1) and an interior point.
            for p in [[2.0, 1.0, 1.0], [0.3, 0.7, 0.2]] {
                let mut s = CountSink {
                    calls: 0,
                    max_index: 0,
                };
                grid_backward(&g, &params[..], p, &d, &mut s);
                // 2 levels x 2 channels x (4 x 3 plane corners + 2 x 3 line ends | 8 corners).
                assert_eq!(s.calls, 2 * 2 * per_channel, "{kind:?}");
                assert!(s.max_index < g.param_count as usize);
            }
        }
    }

    /// Loss = sum_k w_k F_k(p) (f64 sum of the f32 features).
    fn loss(g: &GridLayout, params: &[f32], p: [f32; 3], w: &[f32; MAX_GRID_FEATURES]) -> f64 {
        let out = forward(g, params, p);
        (0..g.feature_dim())
            .map(|k| w[k] as f64 * out[k] as f64)
            .sum()
    }

    fn weights(g: &GridLayout, seed: u32) -> [f32; MAX_GRID_FEATURES] {
        let mut w = [0.0f32; MAX_GRID_FEATURES];
        for (k, v) in w.iter_mut().enumerate().take(g.feature_dim()) {
            *v = crate::rng::normal(seed, 1, k as u32);
        }
        w
    }

    fn close(got: f64, want: f64, rel: f64, abs: f64) -> bool {
        (got - want).abs() <= abs + rel * want.abs()
    }

    /// Central differences on every parameter of the small grids at several points, step 1e-2.
    /// Each feature is linear in any single parameter, so the difference is exact up to f32
    /// rounding of the features (~1e-7 * |F| / 2h ~ 1e-5): tolerance abs 1e-4 + rel 1e-3.
    #[test]
    fn fd_params() {
        let h = 1e-2f32;
        for kind in [GridKind::Factorized, GridKind::Dense] {
            let g = small(kind);
            let mut params = random_params(&g, 21);
            let w = weights(&g, 3);
            for (s, p) in [
                [0.3f32, 0.7, 0.2],
                [1.9, 0.05, 0.55],
                [2.0, 1.0, 1.0],
                [-1.0, 0.4, 1.5],
            ]
            .into_iter()
            .enumerate()
            {
                let mut grad = vec![0.0f32; g.param_count as usize];
                grid_backward(&g, &params[..], p, &w, &mut F32Sink { acc: &mut grad });
                let mut nonzero = 0;
                for i in 0..params.len() {
                    let v = params[i];
                    params[i] = v + h;
                    let lp = loss(&g, &params, p, &w);
                    params[i] = v - h;
                    let lm = loss(&g, &params, p, &w);
                    params[i] = v;
                    let fd = (lp - lm) / (2.0 * h as f64);
                    assert!(
                        close(grad[i] as f64, fd, 1e-3, 1e-4),
                        "{kind:?} point {s} param {i}: {} vs fd {fd}",
                        grad[i]
                    );
                    nonzero += (grad[i] != 0.0) as usize;
                }
                // At least one parameter per feature (a dense vertex has a single one).
                assert!(nonzero >= 4, "{kind:?} point {s}: {nonzero} nonzero grads");
            }
        }
    }

    /// Random interior points whose fraction is in [margin, 1 - margin] on every axis of every
    /// level (away from cell boundaries, where the interpolation is not differentiable).
    fn interior_points(g: &GridLayout, seed: u32, n: usize, margin: f32) -> Vec<[f32; 3]> {
        let mut pts = Vec::new();
        let mut k = 0u32;
        while pts.len() < n {
            k += 1;
            assert!(k < 1_000_000);
            let p: [f32; 3] = core::array::from_fn(|a| {
                let u = crate::rng::uniform(seed, k, a as u32);
                g.aabb.min[a] + u * (g.aabb.max[a] - g.aabb.min[a])
            });
            let xn = g.aabb.normalize(p);
            let ok = (0..g.levels as usize).all(|l| {
                let c = locate(xn, g.level[l].res);
                c.f.iter().all(|&f| f >= margin && f <= 1.0 - margin)
            });
            if ok {
                pts.push(p);
            }
        }
        pts
    }

    /// dL/dp against central differences in world units. Inside one cell every feature is
    /// linear along each axis, so the difference is exact up to f32 rounding of p and of the
    /// features. The step h is below margin * finest cell, so +-h stays in the same cell.
    fn fd_position(g: &GridLayout, h: f32, margin: f32, n: usize, rel: f64, abs: f64) {
        let params = random_params(g, 8);
        let w = weights(g, 4);
        for p in interior_points(g, 17, n, margin) {
            let gp = grid_backward(g, &params[..], p, &w, &mut NullSink);
            for a in 0..3 {
                let (mut pp, mut pm) = (p, p);
                pp[a] += h;
                pm[a] -= h;
                // The step actually taken in f32.
                let step = (pp[a] as f64) - (pm[a] as f64);
                let fd = (loss(g, &params, pp, &w) - loss(g, &params, pm, &w)) / step;
                assert!(
                    close(gp[a] as f64, fd, rel, abs),
                    "{:?} p {p:?} axis {a}: {} vs fd {fd}",
                    g.kind,
                    gp[a]
                );
            }
        }
    }

    /// Small grids: finest cell 0.5 m, margin 0.05 (2.5 cm) > h = 5 mm.
    /// Tolerance rel 1e-3 + abs 1e-4 (gradients are O(1..10)).
    #[test]
    fn fd_position_small() {
        for kind in [GridKind::Factorized, GridKind::Dense] {
            fd_position(&small(kind), 5e-3, 0.05, 50, 1e-3, 1e-4);
        }
    }

    /// Hi-Map geometry grid (both kinds) on a 0.5 x 0.4 x 0.3 m box: finest cell 2 cm, margin
    /// 0.1 (2 mm) > h = 0.5 mm. Gradients reach ~100 / m; the f32 rounding of the loss
    /// (~1e-6) over 2h gives ~1e-3 absolute: tolerance rel 2e-3 + abs 5e-3.
    #[test]
    fn fd_position_hi_map_geometry() {
        let aabb = Aabb::new([1.0, -0.2, 0.1], [1.5, 0.2, 0.4]);
        for kind in [GridKind::Factorized, GridKind::Dense] {
            let g = GridLayout::new(&GridConfig::hi_map_geometry().with_kind(kind), aabb).unwrap();
            fd_position(&g, 5e-4, 0.1, 40, 2e-3, 5e-3);
        }
    }

    /// Outside the box on one axis: that axis's gradient is 0 (the feature is constant along it,
    /// as a one-sided difference confirms), the others still match central differences.
    #[test]
    fn clamped_axis_has_zero_gradient() {
        for kind in [GridKind::Factorized, GridKind::Dense] {
            let g = small(kind);
            let params = random_params(&g, 30);
            let w = weights(&g, 5);
            // x beyond max, y and z interior away from cell boundaries (fractions 0.6, 0.3).
            let p = [2.5f32, 0.3, 0.65];
            let gp = grid_backward(&g, &params[..], p, &w, &mut NullSink);
            assert_eq!(gp[0], 0.0);
            let l0 = loss(&g, &params, p, &w);
            assert_eq!(l0, loss(&g, &params, [2.4, 0.3, 0.65], &w));
            let h = 5e-3f32;
            for a in 1..3 {
                let (mut pp, mut pm) = (p, p);
                pp[a] += h;
                pm[a] -= h;
                let step = (pp[a] as f64) - (pm[a] as f64);
                let fd = (loss(&g, &params, pp, &w) - loss(&g, &params, pm, &w)) / step;
                assert!(gp[a] != 0.0);
                assert!(
                    close(gp[a] as f64, fd, 1e-3, 1e-4),
                    "{a}: {} vs {fd}",
                    gp[a]
                );
            }
            // Parameter gradients equal those at the clamped point on the border.
            let mut g_out = vec![0.0f32; g.param_count as usize];
            let mut g_in = vec![0.0f32; g.param_count as usize];
            grid_backward(&g, &params[..], p, &w, &mut F32Sink { acc: &mut g_out });
            let gb = grid_backward(
                &g,
                &params[..],
                [2.0, 0.3, 0.65],
                &w,
                &mut F32Sink { acc: &mut g_in },
            );
            assert_eq!(g_out, g_in);
            // On the border itself the (one-sided) x gradient is kept.
            assert!(gb[0] != 0.0);
        }
    }
}
