//! The host's multi-threaded CPU backend. Rays are split into chunks that run on a rayon pool;
//! every gradient contribution is converted to fixed point on its own and added into the
//! integer buffers of the thread that runs the chunk (no atomics, no shared cache lines);
//! before Adam the per-thread buffers are summed. Integer sums do not depend on order, so the
//! parameters and gradients are bit-identical to the core's single-threaded
//! [`himap_core::train::reference::CpuBackend`] for any thread count. A ray's forward keeps both decoders'
//! activations of every sample ([`StoredTape`]) so the backward does not evaluate the field
//! again.

use std::sync::{Mutex, MutexGuard};
use std::time::{Duration, Instant};

use himap_core::field::mlp::{MlpLanes, MlpLayout, MlpScratch, LANES, MAX_OUT, MAX_WIDTH};
use himap_core::field::model::{
    color_at_transposed, grid_tape_len, sdf_at_transposed, Group, LossConfig, ModelGradSink,
    ModelLayout, Params, PerGroup, Ray, RayCache, RayResult, RowHint, SampleScratch, StoredTape,
    NUM_GROUPS,
};
use himap_core::field::render::MAX_SAMPLES;
use himap_core::train::adam::{AdamConfig, AdamStep};
use himap_core::train::backend::{
    copy_group, write_group, Backend, ImageStore, MapBatch, StepStats,
};
use himap_core::train::batch::{
    run_items, BatchJob, ItemRunner, MapPixels, RayJob, Rays, TripletMemo,
};
use himap_core::train::fixed;

use crate::layers::{Dest, LayerBatches};
use himap_core::field::negligible::{
    appearance_output_finite, max_abs, DecoderBounds, LayerBounds,
};
use himap_core::train::pixel::{PixelResult, SlotPixels};
use rayon::prelude::*;

/// Rays per parallel work item.
const CHUNK: usize = 32;

/// An output slice cut into chunks of [`CHUNK`] that parallel work items fill by index.
struct ChunkedOut<'a, T> {
    chunks: Vec<Mutex<&'a mut [T]>>,
}

impl<'a, T> ChunkedOut<'a, T> {
    fn new(out: &'a mut [T]) -> Self {
        Self {
            chunks: out.chunks_mut(CHUNK).map(Mutex::new).collect(),
        }
    }

    fn chunks(&self) -> usize {
        self.chunks.len()
    }

    fn chunk(&self, c: usize) -> MutexGuard<'_, &'a mut [T]> {
        self.chunks[c].lock().unwrap_or_else(|e| e.into_inner())
    }
}

/// [`himap_core::train::adam::adam_update`] with the step's constants hoisted and the CPU's square
/// root instruction for `sqrt(v)`: the same operations in the same order, and IEEE square
/// roots are correctly rounded like [`himap_core::math::sqrt`] (tested over 2^25 inputs), so the
/// bits are the same.
#[derive(Clone, Copy, Debug)]
pub struct AdamHw {
    beta1: f32,
    one_minus_beta1: f32,
    beta2: f32,
    one_minus_beta2: f32,
    sqrt_bc2: f32,
    eps: f32,
    step_size: f32,
}

impl AdamHw {
    pub fn new(s: &AdamStep) -> Self {
        Self {
            beta1: s.beta1,
            one_minus_beta1: 1.0 - s.beta1,
            beta2: s.beta2,
            one_minus_beta2: 1.0 - s.beta2,
            sqrt_bc2: himap_core::math::sqrt(s.bias_correction2),
            eps: s.eps,
            step_size: s.lr / s.bias_correction1,
        }
    }

    /// One parameter's update (see [`himap_core::train::adam::adam_update`]).
    #[inline(always)]
    pub fn update(&self, param: &mut f32, m: &mut f32, v: &mut f32, grad: f32) {
        let m_new = self.beta1 * *m + self.one_minus_beta1 * grad;
        let v_new = self.beta2 * *v + self.one_minus_beta2 * grad * grad;
        let denom = v_new.sqrt() / self.sqrt_bc2 + self.eps;
        *param -= self.step_size * m_new / denom;
        *m = m_new;
        *v = v_new;
    }

    /// Whether [`Self::update`] would leave the parameter and both moments finite.
    #[inline(always)]
    pub fn update_is_finite(&self, param: f32, m: f32, v: f32, grad: f32) -> bool {
        let (mut p, mut m, mut v) = (param, m, v);
        self.update(&mut p, &mut m, &mut v, grad);
        himap_core::train::adam::is_finite(p)
            & himap_core::train::adam::is_finite(m)
            & himap_core::train::adam::is_finite(v)
    }

    /// Whether this step's constants allow [`Self::within_bound`] to stand in for
    /// [`Self::update_is_finite`]: decays in [0, 1], `eps > 0`, a bias correction that is not
    /// tiny, and a step so small (against `eps`, and in itself) that no parameter within the
    /// bound can leave the finite range (see [`Self::within_bound`]).
    pub fn bound_applies(&self) -> bool {
        let unit = |x: f32| (0.0..=1.0).contains(&x);
        let ratio = self.step_size.abs() as f64 * 2.0 * BOUND_M as f64 / self.eps as f64;
        unit(self.beta1)
            && unit(self.beta2)
            && unit(self.one_minus_beta1)
            && unit(self.one_minus_beta2)
            && self.eps > 0.0
            && self.eps.is_finite()
            && self.sqrt_bc2 >= 1e-10
            && self.sqrt_bc2.is_finite()
            && ((BOUND_P as f64 + ratio) * 1.01) < 1e38
            && self.step_size.abs() as f64 * 2.0 * BOUND_M as f64 * 1.01 < 1e37
    }

    /// A sufficient condition for [`Self::update_is_finite`] when [`Self::bound_applies`]:
    /// `|param| < 1e30`, `|m| < 1e15`, `0 <= v < 1e30`, `|grad| < 1e15` (false for NaN).
    /// Then `|m'| <= |m| + |grad| < 2e15`, `v' <= v + grad^2 < 2e30`, the denominator is at
    /// least `eps` and at most `sqrt(2e30) / 1e-10`, `step * m'` stays below 1e38, and the
    /// parameter moves by at most `step * 2e15 / eps`, which `bound_applies` keeps (with a
    /// margin for rounding) below `1e38 - 1e30`. Comparisons only: the check pass costs a
    /// fraction of the update's square root and division, and the exact check runs only
    /// where the bound does not hold, so the decision is the exact check's.
    #[inline(always)]
    pub fn within_bound(param: f32, m: f32, v: f32, grad: f32) -> bool {
        Self::state_within_bound(param, m, v) & Self::grad_within_bound(grad)
    }

    /// Whether this step's constants let [`adam_tiny`] stand in for [`Self::update`] where
    /// [`adam_tiny_allowed`] holds: finite decays with `1 - beta1 >= 0` (so that the product
    /// of `1 - beta1` and a zero gradient is `+0`) and `beta2 >= 0`, `eps > 0` and finite, a
    /// positive bias correction and a finite step size.
    #[inline(always)]
    pub fn tiny_applies(&self) -> bool {
        self.beta1.is_finite()
            && self.one_minus_beta1 >= 0.0
            && self.one_minus_beta1.is_finite()
            && self.beta2 >= 0.0
            && self.beta2.is_finite()
            && self.one_minus_beta2.is_finite()
            && self.eps > 0.0
            && self.eps.is_finite()
            && self.sqrt_bc2 > 0.0
            && self.sqrt_bc2.is_finite()
            && self.step_size.is_finite()
    }

    /// The parameter and moment part of [`Self::within_bound`].
    #[inline(always)]
    pub fn state_within_bound(param: f32, m: f32, v: f32) -> bool {
        (param.abs() < BOUND_P) & (m.abs() < BOUND_M) & (0.0..BOUND_P).contains(&v)
    }

    /// The gradient part of [`Self::within_bound`].
    #[inline(always)]
    pub fn grad_within_bound(grad: f32) -> bool {
        grad.abs() < BOUND_M
    }
}

/// Magnitude bounds of [`AdamHw::within_bound`] (parameters and second moments; first moments
/// and gradients).
const BOUND_P: f32 = 1e30;
const BOUND_M: f32 = 1e15;

/// The largest magnitude [`fixed::from_fixed`] returns (an `i64` of quanta of `2^-40`):
/// every summed gradient satisfies [`AdamHw::grad_within_bound`].
const FIXED_SUM_BOUND: f32 = (1u64 << (63 - fixed::FRAC_BITS)) as f32;
const _: () = assert!(FIXED_SUM_BOUND < BOUND_M);

/// Per [`BLOCK`] of each group, whether any Adam moment in it is non-zero.
fn live_blocks(data: &ModelData) -> [Vec<bool>; NUM_GROUPS] {
    std::array::from_fn(|g| {
        data.m[g]
            .chunks(BLOCK)
            .zip(data.v[g].chunks(BLOCK))
            .map(|(m, v)| m.iter().chain(v).any(|&x| x != 0.0))
            .collect()
    })
}

/// Errors of the host CPU backend.
#[derive(Debug, thiserror::Error)]
pub enum CpuError {
    #[error(transparent)]
    Core(#[from] himap_core::Error),
    #[error("could not build a thread pool with {threads} threads: {msg}")]
    Pool { threads: usize, msg: String },
}

/// Parameters, Adam state and gradients of a model, owned on the host.
#[derive(Clone, Debug)]
pub struct ModelData {
    pub layout: ModelLayout,
    pub params: PerGroup<Vec<f32>>,
    pub m: PerGroup<Vec<f32>>,
    pub v: PerGroup<Vec<f32>>,
    /// Adam steps taken.
    pub t: u32,
}

/// Parameter buffers at least this large ask for 2 MB pages ([`huge_params`]).
const HUGE_PARAMS_BYTES: usize = 4 << 20;

/// A zeroed parameter buffer of `n` values. A large one (the grids' planes) asks Linux for
/// transparent 2 MB pages before its first write (`madvise(MADV_HUGEPAGE)`; the allocation is
/// fresh, untouched memory): the forward's rows are spread over a plane of many megabytes,
/// where 4 KB pages make most row reads a TLB miss too. A hint: where the kernel gives none
/// (THP `never`, other systems) the buffer is the same. The parameters are written in full
/// at initialisation, so 2 MB pages hold no more memory than 4 KB ones would. (Sparsely
/// touched buffers, the gradients and Adam's moments, keep 4 KB pages: ARCHITECTURE.md.)
fn huge_params(n: usize) -> Vec<f32> {
    let v = vec![0.0f32; n];
    #[cfg(target_os = "linux")]
    if std::mem::size_of_val(&v[..]) >= HUGE_PARAMS_BYTES {
        const PAGE: usize = 4096;
        let start = v.as_ptr() as usize;
        let end = start + std::mem::size_of_val(&v[..]);
        let first = start.div_ceil(PAGE) * PAGE;
        // SAFETY: madvise on whole pages inside `v`'s allocation changes how the kernel backs
        // them, not their contents (still zero, not yet touched); failure is harmless.
        unsafe {
            libc::madvise(first as *mut libc::c_void, end - first, libc::MADV_HUGEPAGE);
        }
    }
    v
}

impl ModelData {
    /// Each group's parameters, in [`himap_core::field::model::Group::ALL`] order (what
    /// `VulkanBackend::new` takes).
    pub fn param_slices(&self) -> [&[f32]; NUM_GROUPS] {
        core::array::from_fn(|g| &self.params[g][..])
    }

    /// A freshly initialised model (deterministic for `seed`). The grids, whose values depend
    /// on the parameter index alone, are filled in parts on rayon's threads (a 24 m box holds
    /// 34 M normal draws of the core's software `log`, `sqrt` and `cos`); the bits are those of
    /// [`ModelLayout::init_group`] (tested).
    pub fn new(layout: ModelLayout, seed: u32) -> Result<Self, himap_core::Error> {
        const PART: usize = 1 << 16;
        let lens = PerGroup(layout.group_lens());
        let mut params = lens.map(huge_params);
        for g in Group::ALL {
            if ModelLayout::is_grid(g) {
                params[g]
                    .par_chunks_mut(PART)
                    .enumerate()
                    .try_for_each(|(c, part)| layout.init_grid_part(g, part, c * PART, seed))?;
            } else {
                layout.init_group(g, &mut params[g], seed)?;
            }
        }
        Ok(Self {
            layout,
            m: lens.map(|n| vec![0.0; n]),
            v: lens.map(|n| vec![0.0; n]),
            params,
            t: 0,
        })
    }

    /// Borrowed read view for the core's kernels.
    pub fn view(&self) -> Params<'_, [f32]> {
        Params {
            geometry_grid: &self.params[Group::GeometryGrid],
            appearance_grid: &self.params[Group::AppearanceGrid],
            geometry_mlp: &self.params[Group::GeometryMlp],
            appearance_mlp: &self.params[Group::AppearanceMlp],
            beta: self.params[Group::Beta][0],
        }
    }

    /// Both decoders' parameters with transposed weight matrices
    /// ([`himap_core::field::mlp::transpose_weights`]), for the CPU's forward.
    pub fn transposed_mlps(&self) -> [Vec<f32>; 2] {
        let l = &self.layout;
        let (geometry, appearance) = (
            &self.params[Group::GeometryMlp],
            &self.params[Group::AppearanceMlp],
        );
        let mut out = [vec![0.0; geometry.len()], vec![0.0; appearance.len()]];
        // The lengths match the layout by construction (`new`, `write_params` check them).
        himap_core::field::mlp::transpose_weights(&l.geometry_mlp, geometry, &mut out[0])
            .expect("geometry decoder parameters match the layout");
        himap_core::field::mlp::transpose_weights(&l.appearance_mlp, appearance, &mut out[1])
            .expect("appearance decoder parameters match the layout");
        out
    }

    /// Bytes held by parameters and Adam moments.
    pub fn bytes(&self) -> usize {
        self.layout.param_count() * 3 * 4
    }
}

/// The multi-threaded CPU backend.
pub struct ParallelCpuBackend {
    data: ModelData,
    /// One accumulator per pool thread (`rayon::current_thread_index`), reused across steps.
    workers: Vec<Mutex<Worker>>,
    /// The summed fixed-point gradient of the last step (what `read_grads` returns).
    grads: [Vec<i64>; NUM_GROUPS],
    adam: PerGroup<AdamConfig>,
    pool: rayon::ThreadPool,
    name: String,
    store: ImageStore,
    images: Vec<u32>,
    /// Per-pixel depth priors of the image slots ([`Backend::set_depth_prior`]), parallel to
    /// `images`; empty until a prior is first set.
    depth_priors: Vec<f32>,
    /// Per [`BLOCK`] of each group: whether its Adam moments may be non-zero. A block whose
    /// moments are all zero and which no worker touched this step has a zero gradient, and
    /// Adam leaves it exactly as it is (`m = v = 0`, the parameter minus `0 / eps`), so the
    /// sum and Adam pass skips it: same bits as the dense pass, at the cost of the blocks a
    /// step reaches (a large scene box is mostly never seen).
    live: [Vec<bool>; NUM_GROUPS],
    /// `live` must be recomputed from the moments (after [`Self::data_mut`]).
    live_stale: bool,
    /// The blocks the current step's Adam visits (`live` or touched by a worker).
    run: [Vec<bool>; NUM_GROUPS],
    /// The blocks some worker touched this step: only their worker buffers can hold a
    /// contribution (the others were zeroed when last summed), so only they are summed.
    fresh: [Vec<bool>; NUM_GROUPS],
    /// Per block of `grads`: whether its sum may be non-zero (a block summed since it was
    /// last cleared). An untouched block's sum is zero: cleared once, not rewritten each step.
    sum_dirty: [Vec<bool>; NUM_GROUPS],
    /// Per block: every parameter and moment in it is known to satisfy
    /// [`AdamHw::state_within_bound`] (checked as the last Adam pass wrote them), so the next
    /// step's check need not read the block (the gradient part of the bound always holds:
    /// [`FIXED_SUM_BOUND`]). False where unknown (a fresh backend, after [`Self::data_mut`] or
    /// a write): the check then reads the block.
    bounded: [Vec<bool>; NUM_GROUPS],
    /// Wall time of the passes so far (`himap map --profile`).
    times: CpuPassTimes,
    /// The largest magnitude of the appearance grid's parameters (+inf when one is not
    /// finite), computed for a render when unknown and forgotten whenever parameters change.
    appearance_max: Option<f64>,
    /// Whether the current job may render colours lazily ([`SampleTape::lazy_color`]): set
    /// by [`Backend::render`] for its job only.
    lazy_color: bool,
}

/// Wall time of the CPU backend's passes, totals since the backend was built (kept over a
/// [`ParallelCpuBackend::regrow`]): what `himap map --profile` prints for the CPU.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct CpuPassTimes {
    /// Training and mapping steps' rays: forward, losses and backward into the workers'
    /// gradient buffers.
    pub rays: Duration,
    /// Summing the workers' gradients and checking that Adam leaves every value finite.
    pub reduce: Duration,
    /// Adam over the blocks it visits.
    pub adam: Duration,
    /// Renders outside the training steps (evaluation, previews, the mesh's views).
    pub renders: Duration,
    /// Training and mapping steps timed.
    pub steps: u64,
    /// Parameters in the blocks Adam visited, summed over the steps (a block that was ever
    /// reached is visited on every later step: the pass grows with the area mapped).
    pub adam_params: u64,
    /// Sample branches (a decoder and its grid) of the training backward with a non-zero
    /// cotangent, all of which the negligible check saw ([`himap_core::field::negligible`]).
    pub branches_checked: u64,
    /// Of those, the branches skipped: every contribution provably rounds to 0 quanta.
    pub branches_skipped: u64,
}

/// Parameters per block of the sum and Adam pass (and of the touched / live flags).
const BLOCK: usize = 1024;
const BLOCK_SHIFT: u32 = BLOCK.trailing_zeros();

/// The summed gradient of a block no worker touched this step: Adam and its check read this
/// (cached) block instead of the block's own sum, which was cleared and is not read again.
static ZERO_BLOCK: [i64; BLOCK] = [0; BLOCK];

/// A pool thread's private state: its own fixed-point gradient buffers for every group (plain
/// integer adds, no atomics; summed over the workers before Adam, which gives the same integers
/// in any order), the ray cache, scratch and the stored decoder activations of a ray.
struct Worker {
    grads: [Vec<i64>; NUM_GROUPS],
    /// Per [`BLOCK`] of `grads`: whether this step added anything to it.
    touched: [Vec<bool>; NUM_GROUPS],
    cache: Box<RayCache>,
    scratch: Box<SampleScratch>,
    tape_geometry: Vec<MlpScratch>,
    tape_appearance: Vec<MlpScratch>,
    /// The decoders' lanes ([`StoredTape::lanes`]): a ray's samples go through them 8 at a time.
    lanes: Box<[MlpLanes; 2]>,
    /// The grids' backward factor rows, reused from sample to sample.
    grid_rows: Box<std::cell::RefCell<[[f32; MAX_WIDTH]; 6]>>,
    /// The grids' term factors of every sample of a ray ([`StoredTape::grid_kept`]).
    grid_kept: Vec<f32>,
    /// Cache lines of one `i64` gradient row of the geometry and the appearance grid (one for
    /// the geometry's 2 channels, else at least 2: a row may straddle two), which the
    /// backward's cache hint names: the paper's 32 appearance channels span 4.
    grad_row_lines: [usize; 2],
    /// The decoder layers' contributions waiting to be added ([`crate::layers`]): flushed
    /// at the end of every [`Self::run`], before any sum is read.
    layers: LayerBatches,
    /// Sample branches that met the negligible check and those it skipped, since the backend
    /// was built ([`CpuPassTimes::branches_checked`]).
    negligible: (u64, u64),
}

impl Worker {
    fn new(lens: [usize; NUM_GROUPS], kept_per_sample: usize, layout: &ModelLayout) -> Self {
        // A row of 2 channels (16 bytes, 16-byte aligned) lies in one line.
        let lines = |channels: u32| match channels {
            0..=2 => 1,
            c => (c as usize * 8).div_ceil(64).clamp(2, 8),
        };
        Self {
            grads: lens.map(|n| vec![0; n]),
            touched: lens.map(|n| vec![false; n.div_ceil(BLOCK)]),
            cache: Box::new(RayCache::new()),
            scratch: Box::new(SampleScratch::new()),
            tape_geometry: vec![MlpScratch::new(); MAX_SAMPLES],
            tape_appearance: vec![MlpScratch::new(); MAX_SAMPLES],
            lanes: Box::new([MlpLanes::new(), MlpLanes::new()]),
            grid_rows: Box::new(std::cell::RefCell::new([[0.0; MAX_WIDTH]; 6])),
            grid_kept: vec![0.0; MAX_SAMPLES * kept_per_sample],
            grad_row_lines: [
                lines(layout.geometry_grid.channels),
                lines(layout.appearance_grid.channels),
            ],
            layers: LayerBatches::default(),
            negligible: (0, 0),
        }
    }

    /// Runs `f` with the ray cache, scratch, tape (over the decoders' transposed weights `wt`)
    /// and a sink into this worker's buffers.
    fn run<R>(
        &mut self,
        wt: &[Vec<f32>; 2],
        bounds: &DecoderBounds,
        lazy_color: bool,
        f: impl FnOnce(
            &mut RayCache,
            &mut SampleScratch,
            &mut StoredTape<'_, HostRows>,
            &mut WorkerSink<'_>,
        ) -> R,
    ) -> R {
        let mut tape = StoredTape {
            geometry: &mut self.tape_geometry,
            appearance: &mut self.tape_appearance,
            geometry_wt: &wt[0],
            appearance_wt: &wt[1],
            grid_rows: &self.grid_rows,
            grid_kept: &mut self.grid_kept,
            hint: std::marker::PhantomData,
            lanes: Some(&mut self.lanes),
            bounds: Some(*bounds),
            negligible_counts: Default::default(),
            lazy_color,
        };
        let mut sink = WorkerSink {
            grads: &mut self.grads,
            touched: &mut self.touched,
            row_lines: self.grad_row_lines,
            layers: &mut self.layers,
        };
        let r = f(&mut self.cache, &mut self.scratch, &mut tape, &mut sink);
        let (seen, skipped) = tape.negligible_counts.get();
        self.negligible.0 += seen;
        self.negligible.1 += skipped;
        self.layers.flush(&mut Dest {
            grads: &mut self.grads,
            touched: &mut self.touched,
            block_shift: BLOCK_SHIFT,
        });
        r
    }
}

/// Adds each contribution, converted on its own with [`fixed::to_fixed`], into a worker's
/// buffers.
struct WorkerSink<'a> {
    grads: &'a mut [Vec<i64>; NUM_GROUPS],
    touched: &'a mut [Vec<bool>; NUM_GROUPS],
    /// Cache lines of one gradient row of each grid ([`Worker::grad_row_lines`]).
    row_lines: [usize; 2],
    /// The decoder layers' contributions, added in batches of samples ([`crate::layers`]).
    layers: &'a mut LayerBatches,
}

impl ModelGradSink for WorkerSink<'_> {
    const PREFETCH: bool = true;
    const LAYERS: bool = true;

    #[inline(always)]
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
        let mut dest = Dest {
            grads: &mut self.grads[..],
            touched: &mut self.touched[..],
            block_shift: BLOCK_SHIFT,
        };
        self.layers.push(
            &mut dest,
            group as usize,
            w_off,
            b_off,
            gs,
            fan_out,
            xs,
            fan_in,
        );
    }

    #[inline(always)]
    fn prefetch(&mut self, group: Group, offset: usize) {
        let lines = match group {
            Group::GeometryGrid => self.row_lines[0],
            Group::AppearanceGrid => self.row_lines[1],
            _ => 2,
        };
        if let Some(row) = self.grads[group as usize].get(offset..) {
            prefetch_lines(row, lines);
        }
    }

    #[inline(always)]
    fn add(&mut self, group: Group, i: usize, g: f32) {
        let gi = group as usize;
        if let Some(x) = self.grads[gi].get_mut(i) {
            *x = x.wrapping_add(to_fixed_host(g));
            self.touched[gi][i >> BLOCK_SHIFT] = true;
        }
    }

    #[inline(always)]
    fn add_scaled(&mut self, group: Group, offset: usize, g: f32, xs: &[f32; MAX_WIDTH], n: usize) {
        let n = n.min(MAX_WIDTH);
        let gi = group as usize;
        match self.grads[gi].get_mut(offset..offset + n) {
            Some(dst) if n > 0 => {
                if n <= SHORT_ROW {
                    // A few channels (the geometry grid's 2): inline, without the dispatch
                    // and lane setup of a row.
                    for (d, &x) in dst.iter_mut().zip(&xs[..n]) {
                        *d = d.wrapping_add(to_fixed_host(g * x));
                    }
                } else {
                    add_scaled_row(dst, g, &xs[..n]);
                }
                let t = &mut self.touched[gi];
                t[offset >> BLOCK_SHIFT] = true;
                t[(offset + n - 1) >> BLOCK_SHIFT] = true;
            }
            Some(_) => {}
            None => {
                for (i, &x) in xs[..n].iter().enumerate() {
                    self.add(group, offset + i, g * x);
                }
            }
        }
    }

    #[inline(always)]
    fn add_scaled_rows<const R: usize>(
        &mut self,
        group: Group,
        offsets: [usize; R],
        gs: [f32; R],
        xs: &[f32; MAX_WIDTH],
        n: usize,
    ) {
        let gi = group as usize;
        if n == 2 && add_pair_rows(&mut self.grads[gi], &offsets, &gs, [xs[0], xs[1]]) {
            let t = &mut self.touched[gi];
            for pair in offsets.chunks_exact(2) {
                t[pair[0] >> BLOCK_SHIFT] = true;
                t[(pair[0] + 3) >> BLOCK_SHIFT] = true;
            }
            return;
        }
        for (&o, &g) in offsets.iter().zip(&gs) {
            self.add_scaled(group, o, g, xs, n);
        }
    }
}

/// The rows of a 2-channel grid's interpolated read (`R` of 2 or 4 corners) when they come
/// in neighbouring pairs (`offsets[2j + 1] == offsets[2j] + 2`, true of every line and plane
/// read of a narrow grid): each pair is 4 contiguous sums, `dst[o..o + 4] += [to_fixed(g0 *
/// x0), to_fixed(g0 * x1), to_fixed(g1 * x0), to_fixed(g1 * x1)]`, the same products and
/// conversions as one row at a time (in AVX2 lanes when the CPU has them). False, having
/// added nothing, when the rows are not such pairs or do not fit in `dst`.
#[inline(always)]
fn add_pair_rows<const R: usize>(
    dst: &mut [i64],
    offsets: &[usize; R],
    gs: &[f32; R],
    xs: [f32; 2],
) -> bool {
    if R == 0 || !R.is_multiple_of(2) {
        return false;
    }
    for pair in offsets.chunks_exact(2) {
        let fits = pair[0].checked_add(4).is_some_and(|end| end <= dst.len());
        if !fits || pair[1] != pair[0] + 2 {
            return false;
        }
    }
    for (pair, g) in offsets.chunks_exact(2).zip(gs.chunks_exact(2)) {
        let [g0, g1] = [g[0], g[1]];
        let products = [g0 * xs[0], g0 * xs[1], g1 * xs[0], g1 * xs[1]];
        let run = &mut dst[pair[0]..pair[0] + 4];
        #[cfg(target_arch = "x86_64")]
        if std::arch::is_x86_feature_detected!("avx2") {
            // SAFETY: the CPU supports AVX2 (checked above).
            unsafe { add_four_avx2(run, products) };
            continue;
        }
        for (d, &p) in run.iter_mut().zip(&products) {
            *d = d.wrapping_add(to_fixed_host(p));
        }
    }
    true
}

/// `dst[i] += to_fixed(products[i])` for 4 contiguous sums: the magic-number conversion in
/// AVX2 lanes when all 4 are below [`SMALL`] in magnitude (NaN is not), else
/// [`to_fixed_host`] one at a time.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
fn add_four_avx2(dst: &mut [i64], products: [f32; 4]) {
    use std::arch::x86_64::*;
    let Some(dst) = dst.get_mut(..4) else {
        return;
    };
    // SAFETY: `products` holds 4 f32 and `dst` 4 i64 (checked above): the unaligned loads and
    // the store stay within them.
    unsafe {
        let p = _mm_loadu_ps(products.as_ptr());
        let abs = _mm_castsi128_ps(_mm_set1_epi32(i32::MAX));
        let ok = _mm_cmplt_ps(_mm_and_ps(p, abs), _mm_set1_ps(SMALL));
        if _mm_movemask_ps(ok) == 0xf {
            add_fixed_small4(dst.as_mut_ptr(), p);
            return;
        }
    }
    for (d, &p) in dst.iter_mut().zip(&products) {
        *d = d.wrapping_add(to_fixed_host(p));
    }
}

/// The window's RGBA8 slot images with the CPU's cache hint: the warping loss names the
/// rows of the next view's patch while it computes the current one (values as `[u32]`'s).
struct HostPixels<'a>(&'a [u32], &'a [f32]);

impl SlotPixels for HostPixels<'_> {
    const CPU: bool = true;

    #[inline(always)]
    fn pixel(&self, i: usize) -> u32 {
        self.0.pixel(i)
    }

    #[inline(always)]
    fn prefetch(&self, i: usize) {
        if let Some(row) = self.0.get(i..) {
            prefetch_line(row);
        }
    }

    #[inline(always)]
    fn depth_prior(&self, i: usize) -> f32 {
        match self.1.get(i) {
            Some(p) => *p,
            None => 0.0,
        }
    }
}

/// The CPU's [`RowHint`]: the rows the next samples' forward reads (two cache lines each,
/// [`prefetch_rows`]; which rows: [`StoredTape`]), and the decoders' lanes in AVX
/// ([`crate::lanes`]). Side by side on the paper step (`scripts/ab_bench.sh`, one thread
/// each), the hint alone gave the forward about 10 % more samples per second (ARCHITECTURE.md).
pub(crate) struct HostRows;

impl RowHint for HostRows {
    const ACTIVE: bool = true;

    #[inline(always)]
    fn prefetch(row: &[f32]) {
        prefetch_rows(row);
    }

    #[inline(always)]
    fn lanes_pay() -> bool {
        crate::lanes::fast()
    }

    #[inline(always)]
    fn mlp_forward_lanes(
        layout: &MlpLayout,
        wt: &[f32],
        lanes: &mut MlpLanes,
        out: &mut [[f32; LANES]; MAX_OUT],
    ) {
        crate::lanes::mlp_forward_lanes(layout, wt, lanes, out);
    }
}

/// Asks the CPU to bring the cache line of `row[0]` towards its L1 cache (a hint: no effect
/// on any value, nothing on other architectures).
#[inline(always)]
fn prefetch_line<T>(row: &[T]) {
    prefetch_lines(row, 1);
}

/// Asks the CPU to bring a grid row (`row`: its channels) towards its L1 cache: one cache
/// line for a row of 1 or 2 channels (8-byte aligned, the geometry grid's: it never straddles
/// a line), else the first two (a row of up to 16 channels, which may straddle two lines, or
/// the first half of 32). Naming the second line of the geometry's rows too stalled on the
/// full miss buffers: the paper step 207.4 -> 202.4 ms without it (one thread, side by side).
#[inline(always)]
fn prefetch_rows(row: &[f32]) {
    prefetch_lines(row, if row.len() <= 2 { 1 } else { 2 });
}

/// Prefetches `lines` consecutive 64-byte cache lines from `row`'s start (a hint that never
/// faults and changes no value; nothing on other architectures).
#[inline(always)]
fn prefetch_lines<T>(row: &[T], lines: usize) {
    #[cfg(target_arch = "x86_64")]
    {
        use std::arch::x86_64::{_mm_prefetch, _MM_HINT_T0};
        let p = row.as_ptr().cast::<i8>();
        for l in 0..lines {
            // SAFETY: prefetching is a hint that never faults; the addresses are computed with
            // wrapping arithmetic and stay within or just past `row`'s allocation.
            unsafe { _mm_prefetch::<_MM_HINT_T0>(p.wrapping_add(64 * l)) };
        }
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = (row, lines);
}

/// Rows of at most this many contributions are converted inline, one at a time.
const SHORT_ROW: usize = 4;

/// Contributions below this magnitude take [`to_fixed_small`].
pub(crate) const SMALL: f32 = 2048.0;
/// 1.5 * 2^12, whose f64 binade [2^12, 2^13) has a unit in the last place of exactly 2^-40,
/// the fixed-point quantum: adding an f64 below 2^11 in magnitude to it rounds that value to a
/// whole number of quanta, half to even (1.5 * 2^52 quanta, an even number, plus the rounded
/// count), and the sum's bits minus this constant's bits are that count.
pub(crate) const MAGIC: f64 = 6144.0;

/// [`fixed::to_fixed`] for a finite `g` with `|g| < 2048`, branch-free (SIMD-friendly): `g`
/// is exact in f64, and the magic-number addition rounds it to whole quanta half to even,
/// exactly as `to_fixed` rounds `g * 2^40` (no scaling multiply). Tested against `to_fixed`
/// over every 5th f32 below 2048.
#[inline(always)]
pub fn to_fixed_small(g: f32) -> i64 {
    ((g as f64 + MAGIC).to_bits() as i64).wrapping_sub(MAGIC.to_bits() as i64)
}

/// [`fixed::to_fixed`], taking [`to_fixed_small`] for the usual small finite contributions.
#[inline(always)]
pub fn to_fixed_host(g: f32) -> i64 {
    if g.abs() < SMALL {
        to_fixed_small(g)
    } else {
        fixed::to_fixed(g)
    }
}

/// `dst[i] += to_fixed(g * xs[i])` for every i (a decoder weight row or a grid corner's
/// channels): one branch-free pass when every contribution is small and finite (the norm),
/// [`fixed::to_fixed`] otherwise; in AVX2 lanes where the CPU has them. AVX-512's own
/// float-to-int64 conversion (`vcvtps2qq`) gives the same bits but made the paper step 15 %
/// slower on an Intel Xeon with AVX-512 (ARCHITECTURE.md), so the rows stay in AVX2 lanes.
#[inline(always)]
fn add_scaled_row(dst: &mut [i64], g: f32, xs: &[f32]) {
    #[cfg(target_arch = "x86_64")]
    {
        if std::arch::is_x86_feature_detected!("avx2") {
            // SAFETY: the CPU supports AVX2 (checked above); the function is plain safe Rust.
            return unsafe { add_scaled_row_avx2(dst, g, xs) };
        }
    }
    add_scaled_row_generic(dst, g, xs)
}

/// Adam on one block from its summed fixed-point gradients; returns whether every parameter
/// and moment is within [`AdamHw::state_within_bound`] afterwards. With AVX-512 (DQ + VL) the
/// same loop compiled for it ([`adam_block_avx512`]): the compiler converts 8 or 16 sums to
/// f32 at once (`vcvtqq2ps`, round to nearest like `as f32`) and takes the square roots and
/// quotients in lanes, each lane the scalar operations (no FMA: Rust never contracts), so the
/// same bits (tested); x86-64-v3 has no vector int64-to-float conversion and runs it mostly
/// scalar. Adam over every block rays have reached is most of a long walk's step
/// (ARCHITECTURE.md).
#[inline(always)]
fn adam_block(hw: &AdamHw, p: &mut [f32], m: &mut [f32], v: &mut [f32], sum: &[i64]) -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        if has_avx512_dq_vl() {
            // SAFETY: the CPU supports AVX-512 F, DQ and VL (checked above); the function is
            // plain safe Rust.
            return unsafe { adam_block_avx512(hw, p, m, v, sum) };
        }
    }
    adam_block_generic(hw, p, m, v, sum)
}

/// [`adam_block`]'s loop, in runs of 16 parameters: a run whose first moments are all zero
/// or at least [`TINY_M`] in magnitude takes [`AdamHw::update`] (in lanes); a run holding a
/// tiny one takes [`adam_tiny_run`] (in lanes). Same bits either way.
#[inline(always)]
fn adam_block_generic(
    hw: &AdamHw,
    p: &mut [f32],
    m: &mut [f32],
    v: &mut [f32],
    sum: &[i64],
) -> bool {
    let n = p.len().min(m.len()).min(v.len()).min(sum.len());
    let steady = hw.tiny_applies();
    let mut ok = true;
    let mut i = 0;
    while i < n {
        let e = (i + ADAM_RUN).min(n);
        let (p, m, v, sum) = (&mut p[i..e], &mut m[i..e], &mut v[i..e], &sum[i..e]);
        let tiny = steady
            && m.iter()
                .fold(false, |t, &x| t | (x.abs() < TINY_M && x != 0.0));
        if !tiny {
            for (((p, m), v), &q) in p.iter_mut().zip(m.iter_mut()).zip(v.iter_mut()).zip(sum) {
                hw.update(p, m, v, fixed::from_fixed(q));
                ok &= AdamHw::state_within_bound(*p, *m, *v);
            }
        } else {
            ok &= adam_tiny_run(hw, p, m, v, sum);
        }
        i = e;
    }
    ok
}

/// First moments below this magnitude (2^-100, and not zero) make a run of [`adam_block`]
/// try [`adam_tiny`]: with them the f32 update may pass through subnormal numbers, which
/// x86 CPUs handle in microcode at 20-25 times the cost (a block the camera has left decays
/// `m` by 0.9 per step through the subnormal range for ~160 steps before it reaches zero;
/// ARCHITECTURE.md).
const TINY_M: f32 = f32::from_bits((127 - 100) << 23);

/// Parameters per run of [`adam_block_generic`] (16 f32 lanes of AVX-512).
const ADAM_RUN: usize = 16;

/// A run of [`adam_block_generic`] (at most 16 parameters) holding a tiny first moment:
/// where [`adam_tiny_allowed`] holds, [`adam_tiny`]'s moments and the parameter as it was;
/// elsewhere [`AdamHw::update`]. The update runs in lanes over the whole run on stand-in values
/// (`p = 1`, `m = 0`, `v = 1`, no gradient) where the tiny form applies, passed through
/// [`std::hint::black_box`]: with the actual values in reach the compiler computes the update
/// on them too and selects afterwards, and a subnormal moment costs it microcode assists
/// (the whole point of the tiny form). The bits of [`AdamHw::update`] on every parameter.
#[inline(always)]
fn adam_tiny_run(hw: &AdamHw, p: &mut [f32], m: &mut [f32], v: &mut [f32], sum: &[i64]) -> bool {
    const R: usize = ADAM_RUN;
    let n = p.len().min(m.len()).min(v.len()).min(sum.len()).min(R);
    let mut allowed = [false; R];
    let (mut mt, mut vt) = ([0.0f32; R], [0.0f32; R]);
    let (mut pu, mut mu, mut vu, mut qu) = ([1.0f32; R], [0.0f32; R], [1.0f32; R], [0i64; R]);
    for l in 0..n {
        let mf = f32_as_f64_exact(m[l]);
        let a = adam_tiny_allowed(hw, p[l], m[l], mf, v[l], sum[l]);
        allowed[l] = a;
        (mt[l], vt[l]) = adam_tiny(hw, mf, v[l]);
        if !a {
            pu[l] = p[l];
            mu[l] = m[l];
            vu[l] = v[l];
            qu[l] = sum[l];
        }
    }
    let (mut pu, mut mu, mut vu, qu) = std::hint::black_box((pu, mu, vu, qu));
    for l in 0..R {
        hw.update(&mut pu[l], &mut mu[l], &mut vu[l], fixed::from_fixed(qu[l]));
    }
    let mut ok = true;
    for l in 0..n {
        if !allowed[l] {
            p[l] = pu[l];
        }
        m[l] = if allowed[l] { mt[l] } else { mu[l] };
        v[l] = if allowed[l] { vt[l] } else { vu[l] };
        ok &= AdamHw::state_within_bound(p[l], m[l], v[l]);
    }
    ok
}

/// Whether [`adam_tiny`] gives [`AdamHw::update`]'s bits for this parameter (the step
/// constants checked by [`AdamHw::tiny_applies`]): no gradient (`q == 0`), a finite first
/// moment, a normal finite second moment (`2^-100 <= v < inf`) and a finite parameter that
/// the update cannot move: `|step * m' / denom|` is at most `|step| |m| / eps` (`|m'| <= |m|`,
/// `denom >= eps`) plus the subnormal rounding of the two operations (2^-149 each, the second
/// divided by at least `eps`), and where twice that is below `|p| 2^-26`, a quarter of the
/// parameter's unit in the last place or less, the f32 subtraction rounds back to `p`. Float
/// operations on normal f64 numbers only (`mf` is `m` widened from its bits by
/// [`f32_as_f64_exact`], as is `p`).
#[inline(always)]
fn adam_tiny_allowed(hw: &AdamHw, p: f32, m: f32, mf: f64, v: f32, q: i64) -> bool {
    let exp = |x: f32| (x.to_bits() >> 23) & 0xff;
    let eps = hw.eps as f64;
    let bound =
        2.0 * ((hw.step_size as f64).abs() * mf.abs() / eps + TWO_POW_M149 / eps) + TWO_POW_M149;
    (q == 0)
        & (exp(m) != 0xff)
        & (exp(p) != 0xff)
        & (v.to_bits() >= MIN_V_BITS)
        & (v.to_bits() < f32::INFINITY.to_bits())
        & (bound < f32_as_f64_exact(p).abs() * TWO_POW_M26)
}

/// `v >= 2^-100` for a non-negative f32, as bits (sign clear, at least those of 2^-100).
const MIN_V_BITS: u32 = (127 - 100) << 23;

/// The moments of [`AdamHw::update`] with a zero gradient where [`adam_tiny_allowed`] holds
/// (the parameter stays): `m' = beta1 * m + (1 - beta1) * 0`, the product rounded to f32 from
/// its exact f64 value without a subnormal float operation ([`round_f64_to_f32`]), and the
/// `+ (+0)` turning a `-0` product into `+0`; `v' = beta2 * v + (1 - beta2) * 0 * 0` as the
/// same f32 expression (normal numbers). `mf` is `m` widened by [`f32_as_f64_exact`]; returns
/// `(m', v')`. Branch-free, for lanes.
#[inline(always)]
fn adam_tiny(hw: &AdamHw, mf: f64, v: f32) -> (f32, f32) {
    let r = round_f64_to_f32(hw.beta1 as f64 * mf);
    let g = fixed::from_fixed(0);
    // `r + (+0)`: `r`, or `+0` for either zero (a bit mask, not an addition).
    let zero = (r.to_bits() << 1) == 0;
    let m_new = f32::from_bits(r.to_bits() & if zero { 0 } else { u32::MAX });
    (m_new, hw.beta2 * v + hw.one_minus_beta2 * g * g)
}

/// 2^-149 (the f32 subnormal quantum), 2^-26 and 2^149 (exact, from their bits).
const TWO_POW_M149: f64 = f64::from_bits((1023 - 149) << 52);
const TWO_POW_M26: f64 = f64::from_bits((1023 - 26) << 52);
const TWO_POW_149: f64 = f64::from_bits((1023 + 149) << 52);

/// `x` as f64 from its bits, exact for every finite `x` (a subnormal one through integer
/// arithmetic, not through a float conversion of a subnormal input); infinities and NaN give
/// some finite value. Branch-free.
#[inline(always)]
fn f32_as_f64_exact(x: f32) -> f64 {
    let bits = x.to_bits();
    let exp = (bits >> 23) & 0xff;
    let mant = (bits & 0x7f_ffff) as u64;
    // Subnormal: mant * 2^-149; normal: (2^23 + mant) * 2^(exp - 150).
    let (whole, e) = if exp == 0 {
        (mant, 1)
    } else {
        (mant | 0x80_0000, exp)
    };
    let scale = f64::from_bits(((1023 + e as u64) - 150) << 52);
    let magnitude = whole as f64 * scale;
    f64::from_bits(magnitude.to_bits() | ((bits as u64 >> 31) << 63))
}

/// The f32 nearest to a finite `y` (ties to even), as IEEE rounds an exact result: a normal
/// result through the conversion, a subnormal one by rounding `|y| 2^149` to a whole number
/// (exact in f64), so that no float operation produces a subnormal. Branch-free.
#[inline(always)]
fn round_f64_to_f32(y: f64) -> f32 {
    let a = y.abs();
    let normal = a >= f32::MIN_POSITIVE as f64;
    // The conversion only sees a normal result (1.0 stands in for the others).
    let wide = (if normal { y } else { 1.0 }) as f32;
    let k = ((if normal { 0.0 } else { a }) * TWO_POW_149).round_ties_even() as u32;
    let narrow = f32::from_bits(k | ((y.to_bits() >> 63) as u32) << 31);
    if normal {
        wide
    } else {
        narrow
    }
}

/// [`adam_block_generic`] compiled for AVX-512 F, DQ and VL.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512dq,avx512vl")]
fn adam_block_avx512(
    hw: &AdamHw,
    p: &mut [f32],
    m: &mut [f32],
    v: &mut [f32],
    sum: &[i64],
) -> bool {
    adam_block_generic(hw, p, m, v, sum)
}

/// Whether this CPU runs [`adam_block_avx512`] (AVX-512 F, DQ and VL; DQ implies F).
#[cfg(target_arch = "x86_64")]
#[inline(always)]
fn has_avx512_dq_vl() -> bool {
    std::arch::is_x86_feature_detected!("avx512dq")
        && std::arch::is_x86_feature_detected!("avx512vl")
}

/// `dst[k] += to_fixed_small(h[k])` for 4 contributions below [`SMALL`] in magnitude (the
/// caller checked): widened to f64 and rounded to whole quanta by [`to_fixed_small`]'s
/// magic-number addition, in one read-modify-write of 4 sums. The AVX2 rows' and the narrow
/// grids' corner pairs' conversion.
///
/// # Safety
/// `dst` points at 4 readable and writable `i64`.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
#[inline]
unsafe fn add_fixed_small4(dst: *mut i64, h: std::arch::x86_64::__m128) {
    use std::arch::x86_64::*;
    let y = _mm256_add_pd(_mm256_cvtps_pd(h), _mm256_set1_pd(MAGIC));
    let q = _mm256_sub_epi64(
        _mm256_castpd_si256(y),
        _mm256_set1_epi64x(MAGIC.to_bits() as i64),
    );
    let d = dst.cast::<__m256i>();
    // SAFETY: the caller's contract: 4 i64 at `dst`.
    unsafe { _mm256_storeu_si256(d, _mm256_add_epi64(_mm256_loadu_si256(d), q)) };
}

/// [`add_scaled_row`] in AVX2 lanes, one pass: 8 products `g * x` (the same f32 products),
/// and when all 8 are below [`SMALL`] in magnitude (NaN is not) the two halves widened to f64
/// and rounded by [`to_fixed_small`]'s magic-number addition; a group of 8 holding a large or
/// non-finite product, and the tail of a row, take [`to_fixed_host`] one at a time. Tested
/// equal to `to_fixed` on random, tie, huge, subnormal and non-finite contributions.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
fn add_scaled_row_avx2(dst: &mut [i64], g: f32, xs: &[f32]) {
    use std::arch::x86_64::*;
    let n = dst.len().min(xs.len());
    let (dst, xs) = (&mut dst[..n], &xs[..n]);
    let gv = _mm256_set1_ps(g);
    let abs = _mm256_castsi256_ps(_mm256_set1_epi32(i32::MAX));
    let small = _mm256_set1_ps(SMALL);
    let mut i = 0;
    while i + 8 <= n {
        // SAFETY: i + 8 <= n, the length of both slices: the unaligned loads and stores stay
        // within them.
        unsafe {
            let p = _mm256_mul_ps(gv, _mm256_loadu_ps(xs.as_ptr().add(i)));
            let ok = _mm256_cmp_ps::<_CMP_LT_OQ>(_mm256_and_ps(p, abs), small);
            let d = dst.as_mut_ptr().add(i);
            if _mm256_movemask_ps(ok) == 0xff {
                add_fixed_small4(d, _mm256_castps256_ps128(p));
                add_fixed_small4(d.add(4), _mm256_extractf128_ps::<1>(p));
            } else {
                for k in i..i + 8 {
                    dst[k] = dst[k].wrapping_add(fixed::to_fixed(g * xs[k]));
                }
            }
        }
        i += 8;
    }
    for k in i..n {
        dst[k] = dst[k].wrapping_add(to_fixed_host(g * xs[k]));
    }
}

#[inline(always)]
fn add_scaled_row_generic(dst: &mut [i64], g: f32, xs: &[f32]) {
    let mut small = true;
    for &x in xs {
        small &= (g * x).abs() < SMALL;
    }
    if small {
        for (d, &x) in dst.iter_mut().zip(xs) {
            *d = d.wrapping_add(to_fixed_small(g * x));
        }
    } else {
        for (d, &x) in dst.iter_mut().zip(xs) {
            *d = d.wrapping_add(fixed::to_fixed(g * x));
        }
    }
}

impl ParallelCpuBackend {
    /// A backend over `data` with `threads` worker threads (0 = all cores).
    pub fn new(
        data: ModelData,
        adam: PerGroup<AdamConfig>,
        threads: usize,
    ) -> Result<Self, CpuError> {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .map_err(|e| CpuError::Pool {
                threads,
                msg: e.to_string(),
            })?;
        let n = pool.current_num_threads();
        let lens = data.layout.group_lens();
        let live = live_blocks(&data);
        Ok(Self {
            run: live.clone(),
            fresh: live.clone().map(|b| vec![false; b.len()]),
            sum_dirty: live.clone().map(|b| vec![false; b.len()]),
            bounded: live.clone().map(|b| vec![false; b.len()]),
            live,
            live_stale: false,
            workers: (0..n)
                .map(|_| Mutex::new(Worker::new(lens, grid_tape_len(&data.layout), &data.layout)))
                .collect(),
            grads: lens.map(|n| vec![0; n]),
            data,
            adam,
            pool,
            name: format!("cpu ({n} threads)"),
            store: ImageStore::default(),
            images: Vec::new(),
            depth_priors: Vec::new(),
            times: CpuPassTimes::default(),
            appearance_max: None,
            lazy_color: false,
        })
    }

    /// Whether the appearance decoder's output is finite for every sample of the current
    /// parameters ([`appearance_output_finite`]), so that a render may skip the colours of
    /// samples with a zero weight. The appearance grid's largest magnitude is scanned on the
    /// pool once per parameter change.
    fn colors_finite(&mut self) -> bool {
        let grid = &self.data.params[Group::AppearanceGrid as usize];
        let max = *self.appearance_max.get_or_insert_with(|| {
            self.pool.install(|| {
                grid.par_chunks(1 << 16)
                    .map(|c| max_abs(c).unwrap_or(f64::INFINITY))
                    .reduce(|| 0.0, f64::max)
            })
        });
        let layout = &self.data.layout;
        appearance_output_finite(
            &layout.appearance_mlp,
            &self.data.params[Group::AppearanceMlp as usize][..],
            max,
        )
    }

    /// The passes' wall time so far.
    pub fn pass_times(&self) -> CpuPassTimes {
        let mut t = self.times;
        for w in &self.workers {
            let w = w.lock().unwrap_or_else(|e| e.into_inner());
            t.branches_checked += w.negligible.0;
            t.branches_skipped += w.negligible.1;
        }
        t
    }

    /// Adds image slot storage of the given size (zero-filled).
    pub fn with_images(mut self, store: ImageStore) -> Self {
        self.images = vec![0; store.total_len()];
        self.store = store;
        self
    }

    /// Replaces the map by `data` over another layout (a grown scene box,
    /// [`crate::grow`]): new gradient buffers and worker state for its size; the image slots,
    /// the thread count and the learning rates stay.
    pub fn regrow(&mut self, data: ModelData) -> Result<(), CpuError> {
        let mut new = ParallelCpuBackend::new(data, self.adam, self.threads())?;
        new.store = self.store;
        new.images = std::mem::take(&mut self.images);
        new.depth_priors = std::mem::take(&mut self.depth_priors);
        new.name = std::mem::take(&mut self.name);
        new.times = self.times;
        *self = new;
        Ok(())
    }

    /// Mutable access to the model data (loading a saved map; the gradients are untouched).
    pub fn data_mut(&mut self) -> &mut ModelData {
        self.live_stale = true;
        self.appearance_max = None;
        &mut self.data
    }

    /// The Adam settings per group.
    pub fn adam(&self) -> &PerGroup<AdamConfig> {
        &self.adam
    }

    /// Bytes of the backend's own buffers: per-thread and summed gradients, ray tapes.
    pub fn work_bytes(&self) -> usize {
        let lens = self.data.layout.group_lens();
        let grad: usize = lens.iter().sum::<usize>() * 8;
        let tape = 2 * MAX_SAMPLES * std::mem::size_of::<MlpScratch>()
            + MAX_SAMPLES * grid_tape_len(&self.data.layout) * 4;
        grad * (self.workers.len() + 1) + tape * self.workers.len()
    }

    /// Runs `item(k, worker)` for every chunk index `k < chunks` on the pool, each on the
    /// worker state of the thread it runs on.
    fn for_each_chunk(&self, chunks: usize, item: impl Fn(usize, &mut Worker) + Sync) {
        let workers = &self.workers;
        self.pool.install(|| {
            (0..chunks).into_par_iter().for_each(|k| {
                let w = rayon::current_thread_index().unwrap_or(0) % workers.len();
                let mut guard = workers[w].lock().unwrap_or_else(|e| e.into_inner());
                item(k, &mut guard);
            });
        });
    }

    /// Runs a batch on the pool: its items cut into chunks of [`CHUNK`] that run on whichever
    /// thread is free, each on that thread's tape and into its gradient buffers; item `i`
    /// keeps its index as its id ([`himap_core::train::batch`]), so the contributions do not depend
    /// on the schedule. Returns the batch's statistics (before Adam).
    fn run_job<J>(&self, job: &J, results: &mut [J::Output]) -> Result<StepStats, CpuError>
    where
        J: BatchJob + Sync,
        J::Output: Send,
    {
        himap_core::error::check_len("results", results.len(), job.len())?;
        let layout = self.data.layout;
        let params = self.data.view();
        let wt = self.data.transposed_mlps();
        let bounds = DecoderBounds {
            geometry: LayerBounds::of(&layout.geometry_mlp, params.geometry_mlp),
            appearance: LayerBounds::of(&layout.appearance_mlp, params.appearance_mlp),
        };
        let out = ChunkedOut::new(results);
        self.for_each_chunk(out.chunks(), |c, w| {
            let mut results = out.chunk(c);
            w.run(
                &wt,
                &bounds,
                self.lazy_color,
                |cache, scratch, tape, sink| {
                    let mut runner = ItemRunner {
                        layout: &layout,
                        params: &params,
                        cache,
                        scratch,
                        tape,
                        sink,
                        memo: TripletMemo::EMPTY,
                    };
                    run_items(job, &mut runner, c * CHUNK, &mut results);
                },
            );
        });
        drop(out);
        Ok(J::summarize(results, self.data.t))
    }

    /// A mapping batch as a [`MapPixels`] job over the backend's image slots.
    fn accumulate_pixels(
        &self,
        batch: &MapBatch<'_>,
        results: &mut [PixelResult],
    ) -> Result<StepStats, CpuError> {
        let pixels = HostPixels(&self.images[..], &self.depth_priors[..]);
        let images = batch.window_images(&self.store, &pixels)?;
        let job = MapPixels::of(batch, &images);
        self.run_job(&job, results)
    }

    /// The model data (parameters and Adam state).
    pub fn data(&self) -> &ModelData {
        &self.data
    }

    /// Consumes the backend, returning the model data.
    pub fn into_data(self) -> ModelData {
        self.data
    }

    /// Threads in the pool.
    pub fn threads(&self) -> usize {
        self.pool.current_num_threads()
    }

    /// Sums the workers' gradients into `grads` (zeroing the workers' buffers for the next
    /// step), then runs Adam on every group, element-wise in parallel ([`AdamHw`]), unless
    /// `reject` or the update would not be finite: then nothing but the gradient sums
    /// changes, and `stats.rejected` says so (see [`StepStats::rejected`]). Sets `stats.t`.
    fn finish_step(&mut self, stats: &mut StepStats) {
        let t = self.data.t + 1;
        let t0 = Instant::now();
        let finite = self.reduce_grads(t);
        let t1 = Instant::now();
        self.times.reduce += t1 - t0;
        if !stats.rejected && finite {
            self.apply_adam(t);
            self.times.adam += t1.elapsed();
        } else {
            stats.rejected = true;
        }
        self.times.steps += 1;
        stats.t = self.data.t;
    }

    /// Marks the blocks Adam visits at step `t` (live or touched by a worker), sums the
    /// workers' gradients of those blocks into `grads` and zeroes the workers' buffers.
    /// Returns whether Adam at step `t` would leave every parameter and moment finite.
    fn reduce_grads(&mut self, t: u32) -> bool {
        if self.live_stale {
            self.live = live_blocks(&self.data);
            self.live_stale = false;
            // a block that leaves `live` must not keep an old sum
            for g in self.grads.iter_mut() {
                g.fill(0);
            }
            for d in self.sum_dirty.iter_mut() {
                d.fill(false);
            }
            for b in self.bounded.iter_mut() {
                b.fill(false);
            }
        }
        let ModelData { params, m, v, .. } = &self.data;
        let mut workers: Vec<_> = self
            .workers
            .iter_mut()
            .map(|w| w.get_mut().unwrap_or_else(|e| e.into_inner()))
            .collect();
        let mut finite = true;
        for g in 0..NUM_GROUPS {
            let hw = AdamHw::new(&AdamStep::new(&self.adam[g], t));
            let bound = hw.bound_applies();
            let run = &mut self.run[g];
            let fresh = &mut self.fresh[g];
            fresh.fill(false);
            for w in workers.iter_mut() {
                for (f, t) in fresh.iter_mut().zip(w.touched[g].iter_mut()) {
                    *f |= std::mem::take(t);
                }
            }
            for ((r, &l), &f) in run.iter_mut().zip(&self.live[g]).zip(fresh.iter()) {
                *r = l | f;
            }
            let dirty = &mut self.sum_dirty[g];
            let mut parts: Vec<std::slice::ChunksMut<'_, i64>> = workers
                .iter_mut()
                .map(|w| w.grads[g].chunks_mut(BLOCK))
                .collect();
            let mut items = Vec::with_capacity(params[g].len().div_ceil(BLOCK));
            for (b, (((p, m), v), sum)) in params[g]
                .chunks(BLOCK)
                .zip(m[g].chunks(BLOCK))
                .zip(v[g].chunks(BLOCK))
                .zip(self.grads[g].chunks_mut(BLOCK))
                .enumerate()
            {
                // Only a block some worker touched has worker slices to add (every other
                // worker block is zero): the rest are stepped past, not gathered.
                let blocks: Vec<&mut [i64]> = if fresh[b] {
                    parts.iter_mut().filter_map(|it| it.next()).collect()
                } else {
                    parts.iter_mut().for_each(|it| _ = it.next());
                    Vec::new()
                };
                if !run[b] {
                    continue;
                }
                // its sum is written now, so Adam visits it from now on (where it is the
                // identity while its moments and sum are zero)
                self.live[g][b] = true;
                // Untouched: the sum is zero once cleared.
                let clear = fresh[b] || dirty[b];
                dirty[b] = fresh[b];
                self.times.adam_params += p.len() as u64;
                items.push((p, m, v, sum, clear, fresh[b], self.bounded[g][b], blocks));
            }
            finite &= self.pool.install(|| {
                items
                    .into_par_iter()
                    .map(|(p, m, v, sum, clear, fresh, state_bounded, blocks)| {
                        // Worker by worker over the whole block, then the check: loops the
                        // compiler vectorises (integer sums: the same in any order).
                        let mut blocks = blocks.into_iter();
                        if clear {
                            // The first worker's block becomes the sum (`0 + x` is `x`): one
                            // pass over the block instead of a clear and an add.
                            match blocks.next() {
                                Some(b) => {
                                    for (s, x) in sum.iter_mut().zip(b.iter_mut()) {
                                        *s = std::mem::take(x);
                                    }
                                }
                                None => sum.fill(0),
                            }
                        }
                        for b in blocks {
                            for (s, x) in sum.iter_mut().zip(b.iter_mut()) {
                                *s = s.wrapping_add(*x);
                                *x = 0;
                            }
                        }
                        // An untouched block's gradient is zero: read from the cached
                        // zero block rather than from its (cleared) sum.
                        let sum: &[i64] = if fresh { sum } else { &ZERO_BLOCK[..p.len()] };
                        // The bound (comparisons) first; the exact check (Adam's own
                        // operations) only where it does not settle it: the same decision.
                        // A fixed-point sum is below 2^23 in magnitude (FIXED_SUM_BOUND),
                        // so the gradient part of the bound always holds: where the last
                        // Adam pass found the block's state within it, the whole bound holds
                        // without reading the block.
                        let bounded = bound
                            && (state_bounded
                                || p.iter().zip(m).zip(v).zip(sum.iter()).fold(
                                    true,
                                    |ok, (((&p, &m), &v), &q)| {
                                        ok & AdamHw::within_bound(p, m, v, fixed::from_fixed(q))
                                    },
                                ));
                        bounded
                            || p.iter().zip(m).zip(v).zip(sum.iter()).fold(
                                true,
                                |ok, (((&p, &m), &v), &q)| {
                                    ok & hw.update_is_finite(p, m, v, fixed::from_fixed(q))
                                },
                            )
                    })
                    .reduce(|| true, |a, b| a & b)
            });
        }
        finite
    }

    /// Adam step `t` on the blocks [`Self::reduce_grads`] marked, from the summed gradients.
    fn apply_adam(&mut self, t: u32) {
        self.data.t = t;
        self.appearance_max = None;
        let ModelData { params, m, v, .. } = &mut self.data;
        for g in 0..NUM_GROUPS {
            let hw = AdamHw::new(&AdamStep::new(&self.adam[g], t));
            // One work item per block that may change: its parameters, moments and summed
            // gradient. Skipped blocks have zero moments and a zero sum, where Adam is the
            // identity.
            let (run, fresh) = (&self.run[g], &self.fresh[g]);
            let items: Vec<_> = params[g]
                .chunks_mut(BLOCK)
                .zip(m[g].chunks_mut(BLOCK))
                .zip(v[g].chunks_mut(BLOCK))
                .zip(self.grads[g].chunks(BLOCK))
                .zip(self.bounded[g].iter_mut())
                .enumerate()
                .filter(|(b, _)| run[*b])
                .map(|(b, x)| (fresh[b], x))
                .collect();
            self.pool.install(|| {
                items
                    .into_par_iter()
                    .for_each(|(fresh, ((((p, m), v), sum), bounded))| {
                        // An untouched block's gradient is zero: the cached zero block.
                        let sum: &[i64] = if fresh { sum } else { &ZERO_BLOCK[..p.len()] };
                        *bounded = adam_block(&hw, p, m, v, sum);
                    });
            });
        }
    }

    /// Blocks of Adam's pass that were processed at least once (or loaded with moments).
    pub fn live_blocks(&self) -> (usize, usize) {
        let n = self.live.iter().map(|l| l.len()).sum();
        let k = self.live.iter().flatten().filter(|&&x| x).count();
        (k, n)
    }

    /// Signed distances at world points ([`himap_core::field::model::sdf_at`]'s bits, in the fast forms).
    pub fn sdf(&self, points: &[[f32; 3]], out: &mut [f32]) {
        let wt = self.data.transposed_mlps();
        self.query(points, out, |l, p, x, s, a| {
            sdf_at_transposed(l, p, &wt[0], x, s, a)
        });
    }

    /// Colours at world points ([`himap_core::field::model::color_at`]'s bits, in the fast forms).
    pub fn color(&self, points: &[[f32; 3]], out: &mut [[f32; 3]]) {
        let wt = self.data.transposed_mlps();
        self.query(points, out, |l, p, x, s, a| {
            color_at_transposed(l, p, &wt[1], x, s, a)
        });
    }

    /// `out[i] = f(points[i])` for a field query `f`, in parallel.
    fn query<T: Send>(
        &self,
        points: &[[f32; 3]],
        out: &mut [T],
        f: impl Fn(&ModelLayout, &Params<'_, [f32]>, [f32; 3], &mut SampleScratch, &mut MlpScratch) -> T
            + Sync,
    ) {
        let layout = self.data.layout;
        let params = self.data.view();
        self.pool.install(|| {
            points
                .par_chunks(256)
                .zip(out.par_chunks_mut(256))
                .for_each(|(p, o)| {
                    let mut s = Box::new(SampleScratch::new());
                    let mut act = Box::new(MlpScratch::new());
                    for (p, o) in p.iter().zip(o.iter_mut()) {
                        *o = f(&layout, &params, *p, &mut s, &mut act);
                    }
                });
        });
    }
}

impl Backend for ParallelCpuBackend {
    type Error = CpuError;

    fn layout(&self) -> &ModelLayout {
        &self.data.layout
    }

    fn name(&self) -> &str {
        &self.name
    }

    fn train_step(
        &mut self,
        rays: &[Ray],
        loss: &LossConfig,
        results: &mut [RayResult],
    ) -> Result<StepStats, CpuError> {
        let t0 = Instant::now();
        let mut stats = self.run_job(
            &Rays {
                rays,
                job: RayJob::Train(loss),
            },
            results,
        )?;
        self.times.rays += t0.elapsed();
        self.finish_step(&mut stats);
        Ok(stats)
    }

    fn render(&mut self, rays: &[Ray], results: &mut [RayResult]) -> Result<(), CpuError> {
        let t0 = Instant::now();
        self.lazy_color = self.colors_finite();
        let r = self.run_job(
            &Rays {
                rays,
                job: RayJob::Render,
            },
            results,
        );
        self.lazy_color = false;
        r?;
        self.times.renders += t0.elapsed();
        Ok(())
    }

    fn render_depth(&mut self, rays: &[Ray], results: &mut [RayResult]) -> Result<(), CpuError> {
        let t0 = Instant::now();
        self.run_job(
            &Rays {
                rays,
                job: RayJob::RenderDepth,
            },
            results,
        )?;
        self.times.renders += t0.elapsed();
        Ok(())
    }

    fn read_params(&mut self, group: Group, out: &mut [f32]) -> Result<(), CpuError> {
        Ok(copy_group(group, out, &self.data.params[group as usize])?)
    }

    fn read_grads(&mut self, group: Group, out: &mut [i64]) -> Result<(), CpuError> {
        Ok(copy_group(group, out, &self.grads[group as usize])?)
    }

    fn read_adam(&mut self, group: Group, m: &mut [f32], v: &mut [f32]) -> Result<(), CpuError> {
        let g = group as usize;
        copy_group(group, m, &self.data.m[g])?;
        Ok(copy_group(group, v, &self.data.v[g])?)
    }

    fn write_params(
        &mut self,
        group: Group,
        data: &[f32],
        reset_adam: bool,
    ) -> Result<(), CpuError> {
        let g = group as usize;
        self.bounded[g].fill(false);
        self.appearance_max = None;
        let ModelData { params, m, v, .. } = &mut self.data;
        Ok(write_group(
            group,
            data,
            &mut params[g],
            &mut m[g],
            &mut v[g],
            reset_adam,
        )?)
    }

    fn image_store(&self) -> ImageStore {
        self.store
    }

    fn upload_frame(&mut self, slot: u32, rgba: &[u32]) -> Result<(), CpuError> {
        let r = self.store.slot_range(slot, rgba.len())?;
        if !self.depth_priors.is_empty() {
            self.depth_priors[r.clone()].fill(0.0);
        }
        self.images[r].copy_from_slice(rgba);
        Ok(())
    }

    fn set_depth_prior(&mut self, slot: u32, prior: &[f32]) -> Result<bool, CpuError> {
        let r = self.store.slot_range(slot, prior.len())?;
        if self.depth_priors.is_empty() {
            self.depth_priors = vec![0.0; self.store.total_len()];
        }
        self.depth_priors[r].copy_from_slice(prior);
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
    ) -> Result<StepStats, CpuError> {
        let adam = batch.adam(&self.adam)?;
        let t0 = Instant::now();
        let mut stats = self.accumulate_pixels(batch, results)?;
        self.times.rays += t0.elapsed();
        let saved = std::mem::replace(&mut self.adam, adam);
        self.finish_step(&mut stats);
        self.adam = saved;
        Ok(stats)
    }

    fn set_adam_lr(&mut self, group: Group, lr: f32) -> Result<(), CpuError> {
        Ok(self.adam[group].set_lr(lr)?)
    }

    fn adam_lr(&self, group: Group) -> f32 {
        self.adam[group].lr
    }

    fn set_min_transmittance(&mut self, t: f32) -> Result<(), CpuError> {
        Ok(self.data.layout.set_min_transmittance(t)?)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use himap_core::train::adam::{adam_update, AdamConfig};

    /// The paper's model over a 2 m cube on 2 threads, Adam at 1e-3 on every group.
    fn paper_backend_2m() -> ParallelCpuBackend {
        let config = himap_core::field::model::ModelConfig::paper(himap_core::Aabb {
            min: [-1.0, -1.0, -1.0],
            max: [1.0, 1.0, 1.0],
        });
        let layout = ModelLayout::new(&config).unwrap();
        let adam = PerGroup::from_fn(|_| AdamConfig::new(1e-3));
        ParallelCpuBackend::new(ModelData::new(layout, 1).unwrap(), adam, 2).unwrap()
    }

    /// The blocks Adam found within the bound skip the next step's check; a write of the
    /// parameters (`write_params`) or of the whole state (`data_mut`) makes the check read
    /// them again: a NaN second moment written after accepted steps (which the forward does
    /// not read, so the loss stays finite) rejects the next step and changes nothing, and
    /// once undone the steps are accepted again.
    #[test]
    fn written_state_is_checked_again() {
        use himap_core::train::backend::Backend;
        let mut be = paper_backend_2m();
        let rays: Vec<Ray> = (0..64)
            .map(|i| {
                let a = i as f32 * 0.1;
                Ray {
                    origin: [0.0, 0.0, -0.9],
                    dir: [0.3 * a.cos(), 0.3 * a.sin(), 1.0],
                    target: [0.2, 0.5, 0.8],
                    target_depth: 1.0,
                }
            })
            .collect();
        let loss = LossConfig {
            lambda_color: 1.0,
            lambda_depth: 1.0,
            ray_scale: 1.0 / 64.0,
            color_to_geometry: true,
            seed: 0,
        };
        let mut res = vec![RayResult::default(); rays.len()];
        let mut step =
            |be: &mut ParallelCpuBackend| be.train_step(&rays, &loss, &mut res).unwrap().rejected;
        for _ in 0..3 {
            assert!(!step(&mut be));
        }
        let g = Group::GeometryMlp;
        assert!(be.bounded[g as usize].iter().all(|&b| b));
        // a write leaves the group's blocks unchecked until Adam visits them again
        let p = be.data().params[g].clone();
        be.write_params(g, &p, false).unwrap();
        assert!(be.bounded[g as usize].iter().all(|&b| !b));
        assert!(!step(&mut be));
        assert!(be.bounded[g as usize].iter().all(|&b| b));
        // a NaN moment: rejected, nothing changes
        let keep = be.data().v[g][0];
        be.data_mut().v[g][0] = f32::NAN;
        let before = be.data().params.clone();
        assert!(step(&mut be), "a NaN moment must reject the step");
        for gr in Group::ALL {
            let same = before[gr]
                .iter()
                .zip(&be.data().params[gr])
                .all(|(a, b)| a.to_bits() == b.to_bits());
            assert!(same, "{gr:?} changed by a rejected step");
        }
        assert!(be.data().v[g][0].is_nan());
        be.data_mut().v[g][0] = keep;
        assert!(!step(&mut be));
    }

    /// The pass times count the steps (rejected ones too), the parameters Adam visits (the
    /// blocks rays reached, not the whole map) and the renders apart from the steps; the
    /// profile table prints them.
    #[test]
    fn pass_times_count_steps_and_visited_parameters() {
        use himap_core::train::backend::Backend;
        let mut be = paper_backend_2m();
        assert_eq!(be.pass_times(), CpuPassTimes::default());
        // a thin bundle near one corner reaches a small part of the box
        let rays: Vec<Ray> = (0..16)
            .map(|i| Ray {
                origin: [-0.95, -0.95, -0.95],
                dir: [1.0, 0.01 * i as f32, 0.01],
                target: [0.2, 0.5, 0.8],
                target_depth: 1.0,
            })
            .collect();
        let loss = LossConfig {
            lambda_color: 1.0,
            lambda_depth: 0.0,
            ray_scale: 1.0 / 16.0,
            color_to_geometry: true,
            seed: 0,
        };
        let mut res = vec![RayResult::default(); rays.len()];
        for _ in 0..2 {
            be.train_step(&rays, &loss, &mut res).unwrap();
        }
        let t = be.pass_times();
        assert_eq!(t.steps, 2);
        assert_eq!(t.renders, Duration::ZERO);
        let layout = *be.layout();
        let total = layout.param_count() as u64;
        assert!(
            t.adam_params > 0 && t.adam_params < total,
            "{} of {total}",
            t.adam_params
        );
        be.render(&rays, &mut res).unwrap();
        assert!(be.pass_times().renders > Duration::ZERO);
        assert_eq!(be.pass_times().steps, 2);
        let table = crate::select::format_cpu_profile(&be.pass_times(), 1.0, layout.param_count());
        for line in ["rays: forward", "Adam", "other", "renders outside"] {
            assert!(table.contains(line), "{line} missing from\n{table}");
        }
    }

    /// The branch-free conversion equals the core's for every 5th f32 bit pattern below 2048
    /// in magnitude (both signs; about 430 million values, ties and subnormals included).
    #[test]
    fn small_conversion_equals_to_fixed() {
        let limit = SMALL.to_bits();
        let bad = (0..limit / 5)
            .into_par_iter()
            .map(|i| i * 5)
            .filter(|&b| {
                let g = f32::from_bits(b);
                to_fixed_small(g) != fixed::to_fixed(g) || to_fixed_small(-g) != fixed::to_fixed(-g)
            })
            .count();
        assert_eq!(bad, 0);
        // Exact ties at the quantum: half to even, like the core.
        for k in 0..64 {
            let g = (k as f32 + 0.5) * fixed::INV_SCALE;
            assert_eq!(to_fixed_small(g), fixed::to_fixed(g), "{k}");
            assert_eq!(to_fixed_host(-g), fixed::to_fixed(-g), "{k}");
        }
        for g in [f32::NAN, f32::INFINITY, -f32::INFINITY, 2048.0, -3e6, 1e30] {
            assert_eq!(to_fixed_host(g), fixed::to_fixed(g), "{g}");
        }
    }

    /// A narrow grid's corner pairs added together ([`add_pair_rows`]) give the sums of one
    /// row at a time with the core's conversion, for 2 and 4 corners, random, tiny, huge and
    /// non-finite values and weights; rows that are not neighbouring pairs or do not fit are
    /// refused untouched.
    #[test]
    fn pair_rows_add_the_core_conversions() {
        let mut rng = himap_core::rng::SplitMix::new(5);
        let specials = [
            0.0f32,
            -0.0,
            f32::NAN,
            f32::INFINITY,
            -f32::INFINITY,
            2048.0,
            -2047.9,
            1e30,
            0.5 * fixed::INV_SCALE,
            -1.5 * fixed::INV_SCALE,
            f32::MIN_POSITIVE * 0.5,
        ];
        let value = |rng: &mut himap_core::rng::SplitMix| {
            if rng.unit() < 0.15 {
                specials[(rng.unit() * specials.len() as f32) as usize % specials.len()]
            } else {
                (rng.unit() - 0.5) * 2f32.powi((rng.unit() * 50.0) as i32 - 40)
            }
        };
        let reference = |dst: &mut [i64], offsets: &[usize], gs: &[f32], xs: [f32; 2]| {
            for (&o, &g) in offsets.iter().zip(gs) {
                for (c, &x) in xs.iter().enumerate() {
                    dst[o + c] = dst[o + c].wrapping_add(fixed::to_fixed(g * x));
                }
            }
        };
        for trial in 0..3000 {
            let xs = [value(&mut rng), value(&mut rng)];
            let start: Vec<i64> = (0..64).map(|i| (i as i64 - 30) << 40).collect();
            let a = (rng.unit() * 20.0) as usize * 2;
            let b = a + 2 + (rng.unit() * 10.0) as usize * 2;
            let (mut got, mut want) = (start.clone(), start.clone());
            if trial % 2 == 0 {
                let gs = [value(&mut rng), value(&mut rng)];
                assert!(add_pair_rows(&mut got, &[a, a + 2], &gs, xs));
                reference(&mut want, &[a, a + 2], &gs, xs);
            } else {
                let gs = [
                    value(&mut rng),
                    value(&mut rng),
                    value(&mut rng),
                    value(&mut rng),
                ];
                let offsets = [a, a + 2, b, b + 2];
                assert!(add_pair_rows(&mut got, &offsets, &gs, xs));
                reference(&mut want, &offsets, &gs, xs);
            }
            assert_eq!(got, want, "trial {trial}: xs {xs:?}");
        }
        let mut dst = vec![7i64; 8];
        assert!(!add_pair_rows(&mut dst, &[0, 3], &[1.0, 1.0], [1.0, 1.0]));
        assert!(!add_pair_rows(&mut dst, &[6, 8], &[1.0, 1.0], [1.0, 1.0]));
        assert!(!add_pair_rows(&mut dst, &[0, 2, 1], &[1.0; 3], [1.0, 1.0]));
        assert_eq!(dst, vec![7i64; 8]);
    }

    /// The AVX2 row conversion equals the core's (see [`check_row_conversion`]).
    #[test]
    fn avx2_rows_add_the_core_conversions() {
        #[cfg(target_arch = "x86_64")]
        {
            if !std::arch::is_x86_feature_detected!("avx2") {
                eprintln!("skipped: this CPU has no AVX2 (the portable path is tested)");
                return;
            }
            // SAFETY: checked above that the CPU has AVX2.
            check_row_conversion(|d, g, x| unsafe { add_scaled_row_avx2(d, g, x) });
        }
    }

    /// A row conversion equals the core's on every kind of contribution: random magnitudes
    /// over the whole exponent range, exact ties at the quantum, the clamp, subnormals and
    /// non-finite values, with every row length up to 40 (the tails).
    #[cfg(target_arch = "x86_64")]
    fn check_row_conversion(row: impl Fn(&mut [i64], f32, &[f32])) {
        let mut rng = himap_core::rng::SplitMix::new(11);
        let mut specials = vec![
            0.0f32,
            -0.0,
            f32::NAN,
            -f32::NAN,
            f32::INFINITY,
            f32::NEG_INFINITY,
            f32::MIN_POSITIVE * 0.5,
            fixed::MAX_CONTRIBUTION,
            fixed::MAX_CONTRIBUTION * 1.5,
            -fixed::MAX_CONTRIBUTION * 3.0,
            2048.0,
            -2047.9,
            1e30,
        ];
        specials.extend((0..64).map(|k| (k as f32 + 0.5) * fixed::INV_SCALE));
        specials.extend((0..64).map(|k| -(k as f32 + 0.5) * fixed::INV_SCALE));
        for trial in 0..4000 {
            let n = trial % 41;
            let xs: Vec<f32> = (0..n)
                .map(|_| {
                    if rng.unit() < 0.2 {
                        specials[(rng.unit() * specials.len() as f32) as usize % specials.len()]
                    } else {
                        let e = (rng.unit() * 80.0) as i32 - 60;
                        (rng.unit() - 0.5) * 2f32.powi(e)
                    }
                })
                .collect();
            let g = match trial % 5 {
                0 => 1.0,
                1 => (rng.unit() - 0.5) * 2f32.powi((rng.unit() * 40.0) as i32 - 30),
                2 => specials[trial % specials.len()],
                _ => rng.unit() - 0.5,
            };
            let start: Vec<i64> = (0..n).map(|i| (i as i64 - 20) << 41).collect();
            let mut dst = start.clone();
            row(&mut dst, g, &xs);
            for ((d, s), &x) in dst.iter().zip(&start).zip(&xs) {
                assert_eq!(*d, s.wrapping_add(fixed::to_fixed(g * x)), "g {g} x {x}");
            }
        }
    }

    /// Rows with large or non-finite contributions take the exact path, in the dispatched
    /// form (AVX-512 where present) and in the portable one (AVX2 / SSE).
    #[test]
    fn rows_add_the_core_conversions() {
        let xs: Vec<f32> = (0..40).map(|i| (i as f32 - 17.3) * 0.37).collect();
        for g in [1e-7f32, 0.3, -5.0, 300.0, f32::NAN, 1e5] {
            let mut dst = vec![7i64; xs.len()];
            let mut portable = dst.clone();
            add_scaled_row(&mut dst, g, &xs);
            add_scaled_row_generic(&mut portable, g, &xs);
            for ((d, p), &x) in dst.iter().zip(&portable).zip(&xs) {
                assert_eq!(*d, 7 + fixed::to_fixed(g * x), "g {g} x {x}");
                assert_eq!(*p, *d, "g {g} x {x}");
            }
        }
    }

    /// The AVX-512 Adam block gives the scalar loop's bits: random states and sums over the
    /// whole exponent range, zeros, subnormals, non-finite states, huge sums (their int64 to
    /// f32 rounding), every block length up to 40 (the tails) and a full block, over several
    /// steps and learning rates; the bound flag agrees too.
    #[test]
    #[cfg(target_arch = "x86_64")]
    fn adam_block_lanes_give_the_scalar_bits() {
        if !has_avx512_dq_vl() {
            eprintln!("skipped: this CPU has no AVX-512 DQ + VL (the generic loop runs)");
            return;
        }
        let mut rng = himap_core::rng::SplitMix::new(17);
        let specials = [
            0.0f32,
            -0.0,
            f32::MIN_POSITIVE * 0.25,
            f32::NAN,
            f32::INFINITY,
            -f32::INFINITY,
            1e30,
            -3e-20,
        ];
        let mut lens: Vec<usize> = (1..=40).collect();
        lens.push(BLOCK);
        let mut checked = 0;
        for t in [1u32, 3, 1000] {
            for lr in [1e-3f32, 0.1] {
                let hw = AdamHw::new(&AdamStep::new(&AdamConfig::new(lr), t));
                for &n in &lens {
                    let mut f = |k: usize, top: f32| {
                        if rng.unit() < 0.1 {
                            specials[k % specials.len()]
                        } else {
                            (rng.unit() - 0.5) * 2f32.powf(rng.unit() * top - top / 2.0)
                        }
                    };
                    let p: Vec<f32> = (0..n).map(|k| f(k, 40.0)).collect();
                    let m: Vec<f32> = (0..n).map(|k| f(k + 1, 40.0)).collect();
                    let v: Vec<f32> = (0..n).map(|k| f(k + 2, 40.0).abs()).collect();
                    let sum: Vec<i64> = (0..n)
                        .map(|k| match k % 7 {
                            0 => 0,
                            1 => i64::MAX - k as i64,
                            2 => i64::MIN + k as i64,
                            3 => (1i64 << 53) + 1 + k as i64,
                            _ => (rng.unit() as f64 * 2e12 - 1e12) as i64,
                        })
                        .collect();
                    let (mut p1, mut m1, mut v1) = (p.clone(), m.clone(), v.clone());
                    let (mut p2, mut m2, mut v2) = (p, m, v);
                    let ok1 = adam_block_generic(&hw, &mut p1, &mut m1, &mut v1, &sum);
                    // SAFETY: the CPU supports AVX-512 F, DQ and VL (checked above).
                    let ok2 = unsafe { adam_block_avx512(&hw, &mut p2, &mut m2, &mut v2, &sum) };
                    assert_eq!(ok1, ok2, "bound flag, length {n}");
                    for (a, b) in [(&p1, &p2), (&m1, &m2), (&v1, &v2)] {
                        // NaN payloads may differ (a NaN state is rejected before Adam)
                        let same = a
                            .iter()
                            .zip(b)
                            .all(|(x, y)| x.to_bits() == y.to_bits() || x.is_nan() && y.is_nan());
                        assert!(same, "length {n}, t {t}, lr {lr}");
                    }
                    checked += n;
                }
            }
        }
        assert!(checked > 6 * BLOCK);
    }

    /// Runs holding tiny and subnormal first moments (the blocks a walk leaves behind) give
    /// [`AdamHw::update`]'s bits one parameter at a time, in the generic loop and in AVX-512
    /// lanes: moments across the subnormal range and its edges (both signs, zeros), second
    /// moments above and below 2^-100 and subnormal, parameters from huge to zero (where the
    /// update may move them), zero and nonzero gradients, several steps and rates.
    #[test]
    fn adam_tiny_moments_give_the_update_bits() {
        let mut rng = himap_core::rng::SplitMix::new(23);
        let sub = |k: u32| f32::from_bits(k);
        let ms = [
            0.0f32,
            -0.0,
            sub(1),
            sub(2),
            sub(3),
            -sub(5),
            sub(0x7f_ffff),
            f32::MIN_POSITIVE,
            -f32::MIN_POSITIVE * 1.1,
            1e-39,
            -3e-38,
            1e-36,
            2e-32,
            7.8e-31,
            8e-31,
            1e-20,
            1e-8,
            f32::NAN,
            f32::INFINITY,
        ];
        let vs = [
            1e-6f32,
            1e-20,
            7.888_609e-31,
            7.9e-31,
            7.8e-31,
            1e-40,
            0.0,
            1e30,
            f32::NAN,
        ];
        let ps = [
            1e-2f32,
            -0.5,
            1e-12,
            1e-30,
            1e-40,
            0.0,
            -0.0,
            3e38,
            f32::INFINITY,
        ];
        let mut checked = 0;
        for t in [1u32, 7, 2000] {
            for lr in [1e-3f32, 1e-2, 0.3] {
                let hw = AdamHw::new(&AdamStep::new(&AdamConfig::new(lr), t));
                for trial in 0..40 {
                    let n = if trial % 5 == 0 { BLOCK } else { 1 + trial * 7 };
                    let mut pick = |set: &[f32], rest: f32| {
                        if rng.unit() < 0.7 {
                            set[(rng.unit() * set.len() as f32) as usize % set.len()]
                        } else {
                            rest * (rng.unit() - 0.5)
                        }
                    };
                    let m: Vec<f32> = (0..n).map(|_| pick(&ms, 1e-37)).collect();
                    let v: Vec<f32> = (0..n).map(|_| pick(&vs, 1e-4).abs()).collect();
                    let p: Vec<f32> = (0..n).map(|_| pick(&ps, 0.1)).collect();
                    let sum: Vec<i64> = (0..n)
                        .map(|k| {
                            if k % 9 == 4 {
                                (rng.unit() * 4e3) as i64 - 2000
                            } else {
                                0
                            }
                        })
                        .collect();
                    let (mut p0, mut m0, mut v0) = (p.clone(), m.clone(), v.clone());
                    let mut ok0 = true;
                    for k in 0..n {
                        hw.update(
                            &mut p0[k],
                            &mut m0[k],
                            &mut v0[k],
                            fixed::from_fixed(sum[k]),
                        );
                        ok0 &= AdamHw::state_within_bound(p0[k], m0[k], v0[k]);
                    }
                    let same = |a: &[f32], b: &[f32]| {
                        a.iter()
                            .zip(b)
                            .all(|(x, y)| x.to_bits() == y.to_bits() || x.is_nan() && y.is_nan())
                    };
                    let (mut p1, mut m1, mut v1) = (p.clone(), m.clone(), v.clone());
                    let ok1 = adam_block_generic(&hw, &mut p1, &mut m1, &mut v1, &sum);
                    assert_eq!(ok0, ok1, "bound flag, t {t}, lr {lr}, trial {trial}");
                    assert!(
                        same(&p0, &p1) && same(&m0, &m1) && same(&v0, &v1),
                        "t {t} lr {lr} trial {trial}"
                    );
                    if has_avx512_dq_vl() {
                        let (mut p2, mut m2, mut v2) = (p.clone(), m.clone(), v.clone());
                        // SAFETY: the CPU supports AVX-512 F, DQ and VL (checked above).
                        let ok2 =
                            unsafe { adam_block_avx512(&hw, &mut p2, &mut m2, &mut v2, &sum) };
                        assert_eq!(ok0, ok2, "lanes: bound flag, t {t}, lr {lr}, trial {trial}");
                        assert!(
                            same(&p0, &p2) && same(&m0, &m2) && same(&v0, &v2),
                            "lanes: t {t} lr {lr} trial {trial}"
                        );
                    }
                    checked += n;
                }
            }
        }
        assert!(checked > 20 * BLOCK);
    }

    /// The exact widening and rounding under the tiny form: every subnormal f32 and samples of
    /// the normal ones widen to their value, and rounding a product of two f32 (exact in f64)
    /// gives the f32 product's bits, subnormal results and the edge to the normal range included.
    #[test]
    fn tiny_form_widens_and_rounds_exactly() {
        for k in (0u32..0x80_0000)
            .step_by(97)
            .chain([1, 2, 0x7f_ffff, 0x80_0000, 0x80_0001])
        {
            for x in [f32::from_bits(k), -f32::from_bits(k)] {
                assert_eq!(
                    f32_as_f64_exact(x).to_bits(),
                    (x as f64).to_bits(),
                    "{k:#x}"
                );
            }
        }
        let mut rng = himap_core::rng::SplitMix::new(3);
        for _ in 0..200_000 {
            let a = f32::from_bits((rng.unit() * 0x0100_0000 as f32) as u32 + 0x0080_0000);
            let b = 0.5 + rng.unit() * 0.5;
            let a = if rng.unit() < 0.5 { -a } else { a };
            let want = b * a;
            let got = round_f64_to_f32(b as f64 * f32_as_f64_exact(a));
            assert_eq!(got.to_bits(), want.to_bits(), "{a:e} * {b}");
        }
    }

    /// Wherever the cheap bound settles the finiteness check, the exact check agrees: random
    /// values and the bound's corners (just inside every limit, both signs), over learning
    /// rates, `eps` and steps that let the bound apply; an overflowing learning rate does not.
    #[test]
    fn adam_bound_implies_the_exact_check() {
        let below = |x: f32| f32::from_bits(x.to_bits() - 1);
        let mut rng = himap_core::rng::SplitMix::new(5);
        let mut applied = 0;
        for t in [1u32, 2, 10, 5000] {
            for lr in [1e-3f32, 0.1, 10.0, 1e6, 1e24, 1e38] {
                for eps in [1e-8f32, 1e-15, 1e-30, 1e5] {
                    let cfg = AdamConfig {
                        eps,
                        ..AdamConfig::new(lr)
                    };
                    let hw = AdamHw::new(&AdamStep::new(&cfg, t));
                    if !hw.bound_applies() {
                        continue;
                    }
                    applied += 1;
                    let (bp, bm) = (below(BOUND_P), below(BOUND_M));
                    let mut cases = vec![];
                    for sp in [1.0f32, -1.0] {
                        for sm in [1.0f32, -1.0] {
                            for sg in [1.0f32, -1.0] {
                                cases.push((sp * bp, sm * bm, below(BOUND_P), sg * bm));
                                cases.push((sp * bp, sm * bm, 0.0, sg * bm));
                                cases.push((sp * bp, 0.0, 0.0, sg * 1e-30));
                            }
                        }
                    }
                    for _ in 0..2000 {
                        let e = |r: &mut himap_core::rng::SplitMix, top: f32| {
                            (r.unit() - 0.5) * 2f32.powf(r.unit() * top.log2())
                        };
                        cases.push((
                            e(&mut rng, BOUND_P),
                            e(&mut rng, BOUND_M),
                            e(&mut rng, BOUND_P).abs(),
                            e(&mut rng, BOUND_M),
                        ));
                    }
                    for (p, m, v, g) in cases {
                        if AdamHw::within_bound(p, m, v, g) {
                            assert!(
                                hw.update_is_finite(p, m, v, g),
                                "lr {lr} eps {eps} t {t}: {p} {m} {v} {g}"
                            );
                        }
                    }
                }
            }
        }
        assert!(applied > 10, "the bound applied to {applied} settings only");
        let huge = AdamHw::new(&AdamStep::new(&AdamConfig::new(1e38), 1));
        assert!(!huge.bound_applies());
        assert!(!AdamHw::within_bound(f32::NAN, 0.0, 0.0, 0.0));
        assert!(!AdamHw::within_bound(0.0, 0.0, -1.0, 0.0));
        assert!(!AdamHw::within_bound(0.0, 0.0, 0.0, f32::INFINITY));
    }

    /// The parallel initialisation gives the core's sequential bits, group by group; a bad
    /// initialisation scale is still an error.
    #[test]
    fn parallel_init_equals_the_core_init() {
        let config = himap_core::field::model::ModelConfig::paper(himap_core::Aabb {
            min: [-1.0, -1.0, -0.5],
            max: [1.5, 1.0, 0.5],
        });
        let layout = ModelLayout::new(&config).unwrap();
        assert!(
            layout.group_len(Group::AppearanceGrid) > 3 << 16,
            "several parts"
        );
        for seed in [0u32, 7] {
            let data = ModelData::new(layout, seed).unwrap();
            for g in Group::ALL {
                let mut want = vec![0.0f32; layout.group_len(g)];
                layout.init_group(g, &mut want, seed).unwrap();
                let same = data.params[g]
                    .iter()
                    .zip(&want)
                    .all(|(a, b)| a.to_bits() == b.to_bits());
                assert!(same, "{g:?} seed {seed}");
            }
        }
        let mut bad = config;
        bad.grid_init_std = f32::NAN;
        let layout = ModelLayout::new(&bad).unwrap();
        assert!(ModelData::new(layout, 0).is_err());
    }

    /// The CPU's square root equals the core's bit-by-bit one on 2^25 inputs spread over
    /// every exponent (non-negative: Adam only takes roots of second moments), and one Adam
    /// update gives the core's bits.
    #[test]
    fn hardware_adam_equals_core_adam() {
        let bad = (0..0x7f80_0000u32 / 61)
            .into_par_iter()
            .map(|i| i * 61)
            .filter(|&b| {
                let x = f32::from_bits(b);
                x.sqrt().to_bits() != himap_core::math::sqrt(x).to_bits()
            })
            .count();
        assert_eq!(bad, 0);
        let mut rng = himap_core::rng::SplitMix::new(3);
        for t in [1u32, 2, 17, 1000] {
            for lr in [0.01f32, 1e-5, 0.1] {
                let s = AdamStep::new(&AdamConfig::new(lr), t);
                let hw = AdamHw::new(&s);
                for _ in 0..2000 {
                    let grad = (rng.unit() - 0.5) * 10f32.powi((rng.unit() * 12.0) as i32 - 8);
                    let (p, m, v) = (
                        rng.unit() - 0.5,
                        (rng.unit() - 0.5) * 1e-2,
                        rng.unit() * 1e-4,
                    );
                    let (mut p1, mut m1, mut v1) = (p, m, v);
                    let (mut p2, mut m2, mut v2) = (p, m, v);
                    adam_update(&s, &mut p1, &mut m1, &mut v1, grad);
                    hw.update(&mut p2, &mut m2, &mut v2, grad);
                    assert_eq!(
                        [p1.to_bits(), m1.to_bits(), v1.to_bits()],
                        [p2.to_bits(), m2.to_bits(), v2.to_bits()]
                    );
                }
            }
        }
    }
}
