//! The host's multi-threaded CPU backend. Rays are split into chunks that run on a rayon pool;
//! every gradient contribution is converted to fixed point on its own and added with integer
//! atomics (grids) or into a per-chunk integer buffer flushed with integer atomics (the small
//! decoder and beta groups, which every sample touches). Integer sums do not depend on order,
//! so the parameters and gradients are bit-identical to the core's single-threaded
//! [`himap_core::step::CpuBackend`] for any thread count.

use std::sync::atomic::{AtomicI64, Ordering};

use himap_core::adam::{self, AdamConfig, AdamStep};
use himap_core::fixed;
use himap_core::mapping::{pixel_train, PixelResult, WindowImages, WindowView};
use himap_core::model::{
    color_at, ray_forward, ray_train, sdf_at, Group, LossConfig, ModelGradSink, ModelLayout,
    Params, Ray, RayCache, RayResult, SampleScratch, NUM_GROUPS,
};
use himap_core::step::{
    summarize, summarize_pixels, window_slots, Backend, ImageStore, MapBatch, StepStats,
};
use rayon::prelude::*;

/// Rays per parallel work item.
const CHUNK: usize = 32;

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
    pub params: [Vec<f32>; NUM_GROUPS],
    pub m: [Vec<f32>; NUM_GROUPS],
    pub v: [Vec<f32>; NUM_GROUPS],
    /// Adam steps taken.
    pub t: u32,
}

impl ModelData {
    /// Each group's parameters, in [`himap_core::model::Group::ALL`] order (what
    /// `VulkanBackend::new` takes).
    pub fn param_slices(&self) -> [&[f32]; NUM_GROUPS] {
        core::array::from_fn(|g| &self.params[g][..])
    }

    /// A freshly initialised model (deterministic for `seed`).
    pub fn new(layout: ModelLayout, seed: u32) -> Result<Self, himap_core::Error> {
        let lens = layout.group_lens();
        let mut params: [Vec<f32>; NUM_GROUPS] = Default::default();
        for (g, p) in params.iter_mut().enumerate() {
            *p = vec![0.0; lens[g]];
            layout.init_group(Group::ALL[g], p, seed)?;
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
            geometry_grid: &self.params[0],
            appearance_grid: &self.params[1],
            geometry_mlp: &self.params[2],
            appearance_mlp: &self.params[3],
            beta: self.params[4][0],
        }
    }

    /// Bytes held by parameters and Adam moments.
    pub fn bytes(&self) -> usize {
        self.layout.param_count() * 3 * 4
    }
}

/// The multi-threaded CPU backend.
pub struct ParallelCpuBackend {
    data: ModelData,
    grads: [Vec<AtomicI64>; NUM_GROUPS],
    adam: [AdamConfig; NUM_GROUPS],
    pool: rayon::ThreadPool,
    name: String,
    store: ImageStore,
    images: Vec<u32>,
}

struct ParSink<'a> {
    shared: &'a [Vec<AtomicI64>; NUM_GROUPS],
    local: &'a mut [Vec<i64>; 3],
}

impl ModelGradSink for ParSink<'_> {
    #[inline(always)]
    fn add(&mut self, group: Group, i: usize, g: f32) {
        let q = fixed::to_fixed(g);
        if q == 0 {
            return;
        }
        match group {
            Group::GeometryGrid | Group::AppearanceGrid => {
                if let Some(a) = self.shared[group as usize].get(i) {
                    a.fetch_add(q, Ordering::Relaxed);
                }
            }
            Group::GeometryMlp | Group::AppearanceMlp | Group::Beta => {
                if let Some(x) = self.local[group as usize - 2].get_mut(i) {
                    *x = x.wrapping_add(q);
                }
            }
        }
    }
}

impl ParallelCpuBackend {
    /// A backend over `data` with `threads` worker threads (0 = all cores).
    pub fn new(
        data: ModelData,
        adam: [AdamConfig; NUM_GROUPS],
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
        Ok(Self {
            grads: lens.map(|n| (0..n).map(|_| AtomicI64::new(0)).collect()),
            data,
            adam,
            pool,
            name: format!("cpu ({n} threads)"),
            store: ImageStore::default(),
            images: Vec::new(),
        })
    }

    /// Adds image slot storage of the given size (zero-filled).
    pub fn with_images(mut self, store: ImageStore) -> Self {
        self.images = vec![0; store.total_len()];
        self.store = store;
        self
    }

    /// Mutable access to the model data (loading a saved map; the gradients are untouched).
    pub fn data_mut(&mut self) -> &mut ModelData {
        &mut self.data
    }

    /// The Adam settings per group.
    pub fn adam(&self) -> &[AdamConfig; NUM_GROUPS] {
        &self.adam
    }

    /// Forward, losses and backward of a mapping batch into the (not zeroed) gradient
    /// buffers, with the chunking and integer accumulation of [`Self::accumulate`].
    pub fn accumulate_pixels(
        &mut self,
        batch: &MapBatch<'_>,
        results: &mut [PixelResult],
    ) -> Result<StepStats, CpuError> {
        himap_core::error::check_len("results", results.len(), batch.pixels.len())?;
        let slots = window_slots(batch, &self.store)?;
        let layout = self.data.layout;
        let params = self.data.view();
        let shared = &self.grads;
        let lens = layout.group_lens();
        let images = WindowImages {
            width: self.store.width,
            height: self.store.height,
            slots,
            pixels: &self.images[..],
        };
        let window = WindowView {
            k: batch.k,
            poses: batch.poses,
            images: &images,
        };
        let window = &window;
        self.pool.install(|| {
            batch
                .pixels
                .par_chunks(CHUNK)
                .zip(results.par_chunks_mut(CHUNK))
                .enumerate()
                .for_each(|(c, (pixels, results))| {
                    let mut local = [
                        vec![0i64; lens[2]],
                        vec![0i64; lens[3]],
                        vec![0i64; lens[4]],
                    ];
                    let mut cache = Box::new(RayCache::new());
                    let mut scratch = Box::new(SampleScratch::new());
                    {
                        let mut sink = ParSink {
                            shared,
                            local: &mut local,
                        };
                        for (k, (px, res)) in pixels.iter().zip(results.iter_mut()).enumerate() {
                            *res = pixel_train(
                                &layout,
                                &params,
                                window,
                                *px,
                                (c * CHUNK + k) as u32,
                                &batch.loss,
                                &mut cache,
                                &mut scratch,
                                &mut sink,
                            );
                        }
                    }
                    for (j, buf) in local.iter().enumerate() {
                        let dst = &shared[j + 2];
                        for (i, &q) in buf.iter().enumerate() {
                            if q != 0 {
                                dst[i].fetch_add(q, Ordering::Relaxed);
                            }
                        }
                    }
                });
        });
        Ok(summarize_pixels(results, self.data.t))
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

    fn zero_grads(&mut self) {
        for g in self.grads.iter_mut() {
            g.par_iter_mut().for_each(|a| *a.get_mut() = 0);
        }
    }

    /// Forward, loss and backward into the (not zeroed) gradient buffers.
    pub fn accumulate(
        &mut self,
        rays: &[Ray],
        loss: &LossConfig,
        results: &mut [RayResult],
    ) -> Result<StepStats, CpuError> {
        himap_core::error::check_len("results", results.len(), rays.len())?;
        let layout = self.data.layout;
        let params = self.data.view();
        let shared = &self.grads;
        let lens = layout.group_lens();
        self.pool.install(|| {
            rays.par_chunks(CHUNK)
                .zip(results.par_chunks_mut(CHUNK))
                .enumerate()
                .for_each(|(c, (rays, results))| {
                    let mut local = [
                        vec![0i64; lens[2]],
                        vec![0i64; lens[3]],
                        vec![0i64; lens[4]],
                    ];
                    let mut cache = Box::new(RayCache::new());
                    let mut scratch = Box::new(SampleScratch::new());
                    {
                        let mut sink = ParSink {
                            shared,
                            local: &mut local,
                        };
                        for (k, (ray, res)) in rays.iter().zip(results.iter_mut()).enumerate() {
                            *res = ray_train(
                                &layout,
                                &params,
                                ray,
                                (c * CHUNK + k) as u32,
                                loss,
                                &mut cache,
                                &mut scratch,
                                &mut sink,
                            );
                        }
                    }
                    for (j, buf) in local.iter().enumerate() {
                        let dst = &shared[j + 2];
                        for (i, &q) in buf.iter().enumerate() {
                            if q != 0 {
                                dst[i].fetch_add(q, Ordering::Relaxed);
                            }
                        }
                    }
                });
        });
        Ok(summarize(results, self.data.t))
    }

    /// Adam on every group from the accumulated gradients (element-wise, in parallel).
    pub fn apply_adam(&mut self) {
        self.data.t += 1;
        let t = self.data.t;
        let ModelData { params, m, v, .. } = &mut self.data;
        let grads = &self.grads;
        let adam_cfg = &self.adam;
        self.pool.install(|| {
            for g in 0..NUM_GROUPS {
                let s = AdamStep::new(&adam_cfg[g], t);
                params[g]
                    .par_chunks_mut(4096)
                    .zip(m[g].par_chunks_mut(4096))
                    .zip(v[g].par_chunks_mut(4096))
                    .zip(grads[g].par_chunks(4096))
                    .for_each(|(((p, m), v), gr)| {
                        for i in 0..p.len() {
                            let q = gr[i].load(Ordering::Relaxed);
                            adam::adam_update(
                                &s,
                                &mut p[i],
                                &mut m[i],
                                &mut v[i],
                                fixed::from_fixed(q),
                            );
                        }
                    });
            }
        });
    }

    /// Signed distances at world points.
    pub fn sdf(&self, points: &[[f32; 3]], out: &mut [f32]) {
        let layout = self.data.layout;
        let params = self.data.view();
        self.pool.install(|| {
            points
                .par_chunks(256)
                .zip(out.par_chunks_mut(256))
                .for_each(|(p, o)| {
                    let mut s = Box::new(SampleScratch::new());
                    for (p, o) in p.iter().zip(o.iter_mut()) {
                        *o = sdf_at(&layout, &params, *p, &mut s);
                    }
                });
        });
    }

    /// Colours at world points.
    pub fn color(&self, points: &[[f32; 3]], out: &mut [[f32; 3]]) {
        let layout = self.data.layout;
        let params = self.data.view();
        self.pool.install(|| {
            points
                .par_chunks(256)
                .zip(out.par_chunks_mut(256))
                .for_each(|(p, o)| {
                    let mut s = Box::new(SampleScratch::new());
                    for (p, o) in p.iter().zip(o.iter_mut()) {
                        *o = color_at(&layout, &params, *p, &mut s);
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
        self.zero_grads();
        let mut stats = self.accumulate(rays, loss, results)?;
        self.apply_adam();
        stats.t = self.data.t;
        Ok(stats)
    }

    fn render(&mut self, rays: &[Ray], results: &mut [RayResult]) -> Result<(), CpuError> {
        himap_core::error::check_len("results", results.len(), rays.len())?;
        let layout = self.data.layout;
        let params = self.data.view();
        self.pool.install(|| {
            rays.par_chunks(CHUNK)
                .zip(results.par_chunks_mut(CHUNK))
                .enumerate()
                .for_each(|(c, (rays, results))| {
                    let mut cache = Box::new(RayCache::new());
                    let mut scratch = Box::new(SampleScratch::new());
                    for (k, (ray, res)) in rays.iter().zip(results.iter_mut()).enumerate() {
                        let id = (c * CHUNK + k) as u32;
                        ray_forward(
                            &layout,
                            &params,
                            ray,
                            id,
                            0,
                            false,
                            &mut cache,
                            &mut scratch,
                        );
                        *res = RayResult {
                            color: cache.out.color,
                            depth: cache.out.depth,
                            opacity: cache.out.opacity,
                            loss: 0.0,
                        };
                    }
                });
        });
        Ok(())
    }

    fn read_params(&mut self, group: Group, out: &mut [f32]) -> Result<(), CpuError> {
        let src = &self.data.params[group as usize];
        himap_core::error::check_len(group.name(), out.len(), src.len())?;
        out.copy_from_slice(src);
        Ok(())
    }

    fn read_grads(&mut self, group: Group, out: &mut [i64]) -> Result<(), CpuError> {
        let src = &self.grads[group as usize];
        himap_core::error::check_len(group.name(), out.len(), src.len())?;
        for (o, a) in out.iter_mut().zip(src.iter()) {
            *o = a.load(Ordering::Relaxed);
        }
        Ok(())
    }

    fn write_params(
        &mut self,
        group: Group,
        data: &[f32],
        reset_adam: bool,
    ) -> Result<(), CpuError> {
        let g = group as usize;
        himap_core::error::check_len(group.name(), data.len(), self.data.params[g].len())?;
        self.data.params[g].copy_from_slice(data);
        if reset_adam {
            self.data.m[g].fill(0.0);
            self.data.v[g].fill(0.0);
        }
        Ok(())
    }

    fn image_store(&self) -> ImageStore {
        self.store
    }

    fn upload_frame(&mut self, slot: u32, rgba: &[u32]) -> Result<(), CpuError> {
        let n = self.store.slot_len();
        himap_core::error::check_len("frame pixels", rgba.len(), n)?;
        if slot >= self.store.slots {
            return Err(himap_core::Error::Capacity {
                what: "image slot index",
                needed: slot as u64 + 1,
                capacity: self.store.slots as u64,
            }
            .into());
        }
        let o = slot as usize * n;
        self.images[o..o + n].copy_from_slice(rgba);
        Ok(())
    }

    fn map_step(
        &mut self,
        batch: &MapBatch<'_>,
        results: &mut [PixelResult],
    ) -> Result<StepStats, CpuError> {
        self.zero_grads();
        let mut stats = self.accumulate_pixels(batch, results)?;
        self.apply_adam();
        stats.t = self.data.t;
        Ok(stats)
    }

    fn set_adam_lr(&mut self, group: Group, lr: f32) -> Result<(), CpuError> {
        if !(lr.is_finite() && lr >= 0.0) {
            return Err(
                himap_core::Error::InvalidConfig("learning rate must be finite and >= 0").into(),
            );
        }
        self.adam[group as usize].lr = lr;
        Ok(())
    }
}
