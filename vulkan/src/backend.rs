//! [`VulkanBackend`]: the core's [`Backend`] on a Vulkan device, bit-identical to
//! `himap_core::train::reference::CpuBackend`.
//!
//! Parameters, Adam moments and fixed-point gradients of the five groups live in persistent
//! device buffers (uploaded once at construction, read back only on request); so do the image
//! slots of the mapping window (one upload per frame). A training step is one submission of
//! passes over the core's stages of `ray_train`:
//!
//! 1. `sample_forward_cs`: one invocation per (ray, sample): sample depth, SDF, colour;
//! 2. `ray_train_cs`: one per ray: compositing, loss, compositing backward (per-sample
//!    cotangents into the samples buffer, beta gradient with an i64 atomic);
//! 3. `sample_backward_cs`: one per (ray, sample): field backward, gradients added with i64
//!    atomics (order-independent, so the sums equal the CPU's);
//! 4. `adam_cs` per group.
//!
//! A mapping step runs `pixel_rays_cs` (camera ray of every sampled pixel) first and
//! `pixel_train_cs` (colour, warping and depth-prior losses) as pass 2. A render is passes 1
//! and `ray_render_cs`. Splitting per sample keeps every invocation short: real GPUs get
//! more parallelism, and the software driver (llvmpipe) stays under its limit of 65535 loop
//! iterations per invocation, past which it silently cuts loops short (that limit is what
//! made whole-ray kernels disagree with the CPU).
//!
//! Rays, pixels and per-item results travel through host-visible buffers; the host sums the
//! loss in item order, as the CPU does.
//!
//! Tensor size: one storage-buffer binding holds at most `maxStorageBufferRange` bytes (128 MiB
//! on lavapipe). A grid group whose i64 gradient is larger is split into two parts (two
//! buffers each for parameters, moments and gradient); the shaders read it through
//! `SplitParams` and add gradients through `AtomicModelSink` by index, and Adam runs per part.
//! So a grid may have up to `2 * maxStorageBufferRange / 8` parameters (33.5 M on lavapipe);
//! larger groups, and decoders past one binding, are a [`VulkanError::TensorTooLarge`] at
//! construction.

use crate::buffers::{
    download, download_f32, ensure, ensure_in, f32_bytes, param_bindings, u32_bytes, upload,
    upload_at, GroupBuffers,
};
use crate::device;
use crate::error::VulkanError;
use crate::passes::{batch_push, dispatch_items, push_bytes, range_push, Passes, Pipelines};
use crate::raw::{Buffer, Gpu, Memory, PhysicalInfo, ShaderModule};
use crate::words;
use himap_core::error::check_len;
use himap_core::field::model::{
    Group, LossConfig, ModelLayout, PerGroup, Ray, RayResult, NUM_GROUPS,
};
use himap_core::field::render::MAX_SAMPLES;
use himap_core::gpu_abi::{
    pixel_result_from_record, ray_result_from_record, TrainPush, PIXEL_RESULT_FLOATS,
    PIXEL_RESULT_LOSSES, RAY_FLOATS, RESULT_FLOATS, RESULT_LOSS, SAMPLE_FLOATS,
};
use himap_core::train::adam::{AdamConfig, AdamStep};
use himap_core::train::backend::{
    summarize, summarize_pixels, window_slots, Backend, ImageStore, MapBatch, StepStats,
};
use himap_core::train::pixel::PixelResult;

/// Construction options of [`VulkanBackend`].
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct VulkanOptions {
    /// Largest storage-buffer binding to use, in bytes (default: the device's
    /// `maxStorageBufferRange`, at most `maxMemoryAllocationSize`). Lower values force the
    /// grids to be split across two bindings (used by the tests).
    pub max_binding_bytes: Option<u64>,
    /// Add every decoder-weight contribution with a global atomic even where the device
    /// could sum them per workgroup first (`shaderSharedInt64Atomics`); the same bits either
    /// way (tests compare the two).
    pub global_atomics_only: bool,
}

/// The largest storage-buffer binding a group may use, and the name of the limit that sets it
/// (named in the error for a tensor that does not fit).
struct BindingLimit {
    /// The device's: `maxStorageBufferRange`, at most `maxMemoryAllocationSize`.
    device_max: u64,
    /// A group's: the device's, or [`VulkanOptions::max_binding_bytes`] below it.
    group: u64,
    name: &'static str,
}

impl BindingLimit {
    fn new(info: &PhysicalInfo, options: &VulkanOptions) -> Self {
        let range = info.max_storage_buffer_range as u64;
        let device_max = range.min(info.max_memory_allocation_size);
        let device_name = if range <= info.max_memory_allocation_size {
            "maxStorageBufferRange"
        } else {
            "maxMemoryAllocationSize"
        };
        match options.max_binding_bytes {
            Some(b) if b < device_max => Self {
                device_max,
                group: b.max(64),
                name: "VulkanOptions::max_binding_bytes",
            },
            _ => Self {
                device_max,
                group: device_max,
                name: device_name,
            },
        }
    }

    /// The parts of each group: one, or two for a grid whose i64 gradient (the largest buffer
    /// of a group) does not fit one binding; larger groups are an error naming the limit.
    fn split(&self, lens: [usize; NUM_GROUPS]) -> Result<[Vec<usize>; NUM_GROUPS], VulkanError> {
        let part_max = (self.group / 8) as usize;
        let mut part_lens: [Vec<usize>; NUM_GROUPS] = Default::default();
        for (g, &len) in lens.iter().enumerate() {
            let grid = g < 2;
            part_lens[g] = if len <= part_max {
                vec![len]
            } else if grid && len <= 2 * part_max {
                vec![part_max, len - part_max]
            } else {
                let split = if grid {
                    " (even split in two bindings)"
                } else {
                    ""
                };
                return Err(VulkanError::TensorTooLarge {
                    what: format!(
                        "the fixed-point gradient of {}{split}",
                        Group::ALL[g].name()
                    ),
                    bytes: len as u64 * 8,
                    limit: if grid { 2 * self.group } else { self.group },
                    limit_name: self.name,
                });
            };
        }
        Ok(part_lens)
    }
}

/// The Vulkan backend. Construct with [`VulkanBackend::new`].
pub struct VulkanBackend {
    layout: ModelLayout,
    name: String,
    adam: PerGroup<AdamConfig>,
    t: u32,
    max_groups: u32,
    max_binding: u64,
    model_words: Buffer,
    groups: PerGroup<GroupBuffers>,
    /// Per-batch inputs and outputs (host-visible, grown on demand): rays (or query points),
    /// per-item results, sampled pixels, the mapping window's words.
    input: Option<Buffer>,
    output: Option<Buffer>,
    pixels: Option<Buffer>,
    window: Option<Buffer>,
    /// Per-sample records of the current batch (device-local, grown on demand).
    samples: Option<Buffer>,
    /// The image slots (device-local, allocated by [`VulkanBackend::with_images`]).
    images: Buffer,
    store: ImageStore,
    /// Staging for device-local buffers that are not host-visible.
    staging: Option<Buffer>,
    /// The step's count of non-finite values (`loss_check_cs`, `adam_check_cs`; host-visible,
    /// zeroed at the start of every step): non-zero rejects the step.
    status: Buffer,
    pipelines: Pipelines,
    _module: ShaderModule,
    gpu: Gpu,
    /// Host time of the transfers per label ([`VulkanBackend::enable_profiling`]), and
    /// whether they are timed.
    host_times: std::cell::RefCell<Vec<(&'static str, f64, u64)>>,
    profiling: bool,
    /// Loop iterations one invocation completes on this device (`None`: at least
    /// [`CANARY_MAX`]), measured at construction by [`measure_loop_budget`].
    loop_budget: Option<u32>,
}

/// The longest loop the canary tries (a device that completes it has no budget that matters).
pub const CANARY_MAX: u32 = 1 << 22;

/// Whether one canary invocation of `n` steps completes on `gpu` (the state and the step
/// count equal the CPU's).
fn canary_passes(
    gpu: &mut Gpu,
    pipelines: &Pipelines,
    out: &Buffer,
    n: u32,
) -> Result<bool, VulkanError> {
    let seed = 0x9E37_79B9u32 ^ n;
    gpu.submit(|r| {
        r.zero(out);
        r.barrier();
        let pipeline = &pipelines.loop_canary;
        let set = r.bind(pipeline, &[out])?;
        let push = push_bytes(himap_core::gpu_abi::KernelPush {
            n,
            arg: seed,
            ..Default::default()
        });
        r.dispatch(pipeline, &set, &push[..pipeline.push_size()], 1);
        Ok(())
    })?;
    let mut b = [0u8; 8];
    out.read_mapped(0, &mut b);
    let got = [
        u32::from_le_bytes([b[0], b[1], b[2], b[3]]),
        u32::from_le_bytes([b[4], b[5], b[6], b[7]]),
    ];
    Ok(got == himap_core::gpu_abi::loop_canary(n, seed))
}

/// The device's loop budget: `None` when a loop of [`CANARY_MAX`] iterations completes, else
/// the largest count that does (binary search, about 22 tiny submissions).
fn measure_loop_budget(
    device: &std::sync::Arc<crate::raw::Device>,
    gpu: &mut Gpu,
    pipelines: &Pipelines,
) -> Result<Option<u32>, VulkanError> {
    let out = Buffer::new(device, 8, Memory::Host, "the loop canary")?;
    if canary_passes(gpu, pipelines, &out, CANARY_MAX)? {
        return Ok(None);
    }
    // invariant: lo passes (0 always does), hi fails
    let (mut lo, mut hi) = (0u32, CANARY_MAX);
    while hi - lo > 1 {
        let mid = lo + (hi - lo) / 2;
        if canary_passes(gpu, pipelines, &out, mid)? {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    Ok(Some(lo))
}

/// Time spent in one named pass ([`VulkanBackend::profile`]).
#[derive(Clone, Debug, PartialEq)]
pub struct PassTime {
    /// The pass (`"forward (per sample)"`, `"Adam"`, ...); transfers end in `"(host)"`.
    pub name: &'static str,
    /// Whether it was timed on the device (timestamp queries) or on the host (transfers).
    pub device: bool,
    /// Total milliseconds over `count` runs.
    pub total_ms: f64,
    pub count: u64,
}

fn add_time(list: &mut Vec<(&'static str, f64, u64)>, name: &'static str, ns: f64) {
    match list.iter_mut().find(|e| e.0 == name) {
        Some(e) => {
            e.1 += ns;
            e.2 += 1;
        }
        None => list.push((name, ns, 1)),
    }
}

/// The model words the kernels read: the layout, then where each grid's parameters split
/// across two bindings (`u32::MAX`: one binding), from the grids' part lengths.
fn model_words(layout: &ModelLayout, grid_parts: [&[usize]; 2]) -> Vec<u32> {
    let mut w = vec![0u32; words::MODEL_WORDS];
    words::model_layout_to_words(layout, &mut w, 0);
    for (k, parts) in grid_parts.iter().enumerate() {
        w[words::SPLITS + k] = if parts.len() > 1 {
            parts[0] as u32
        } else {
            u32::MAX
        };
    }
    w
}

impl VulkanBackend {
    /// Opens the selected device (see [`crate::list_devices`]; `HIMAP_VULKAN_DEVICE`), builds
    /// the pipelines and uploads `params` (one slice per group, [`Group::ALL`] order); Adam
    /// moments start at zero.
    pub fn new(
        layout: ModelLayout,
        params: [&[f32]; NUM_GROUPS],
        adam: PerGroup<AdamConfig>,
    ) -> Result<Self, VulkanError> {
        Self::with_options(layout, params, adam, VulkanOptions::default())
    }

    /// [`VulkanBackend::new`] with [`VulkanOptions`].
    pub fn with_options(
        layout: ModelLayout,
        params: [&[f32]; NUM_GROUPS],
        adam: PerGroup<AdamConfig>,
        options: VulkanOptions,
    ) -> Result<Self, VulkanError> {
        let lens = layout.group_lens();
        for (g, p) in params.iter().enumerate() {
            check_len(Group::ALL[g].name(), p.len(), lens[g])?;
        }
        let device = device::open()?;
        let info = device.info.clone();
        let limit = BindingLimit::new(&info, &options);
        let part_lens = limit.split(lens)?;
        let mut gpu = Gpu::new(&device)?;
        let module = ShaderModule::new(&device, &crate::shader_words())?;
        let pipelines = Pipelines::new(&device, &module, !options.global_atomics_only)?;
        let loop_budget = measure_loop_budget(&device, &mut gpu, &pipelines)?;
        let w = model_words(&layout, [&part_lens[0], &part_lens[1]]);
        let mut staging = None;
        let mut model_words = Buffer::new(
            &device,
            (w.len() * 4) as u64,
            Memory::Device,
            "the model layout",
        )?;
        upload(&mut gpu, &mut staging, &mut model_words, &u32_bytes(&w))?;
        let mut make = |g: usize| {
            let (name, parts) = (Group::ALL[g].name(), &part_lens[g]);
            GroupBuffers::upload(&device, &mut gpu, &mut staging, name, parts, params[g])
        };
        let groups = PerGroup([make(0)?, make(1)?, make(2)?, make(3)?, make(4)?]);
        {
            let g = &groups;
            gpu.submit(|r| {
                for p in g.iter().flat_map(|b| b.parts.iter()) {
                    r.zero(&p.m);
                    r.zero(&p.v);
                    r.zero(&p.grad);
                }
                Ok(())
            })?;
        }
        Ok(Self {
            layout,
            name: format!("vulkan: {}", info.name),
            adam,
            t: 0,
            max_groups: info.max_workgroup_count_x.clamp(1, 65535),
            max_binding: limit.device_max,
            model_words,
            groups,
            input: None,
            output: None,
            pixels: None,
            window: None,
            samples: None,
            images: Buffer::new(&device, 16, Memory::Device, "the image slots")?,
            status: Buffer::new(&device, 16, Memory::Host, "the step's finiteness status")?,
            store: ImageStore::default(),
            staging,
            pipelines,
            _module: module,
            gpu,
            host_times: Default::default(),
            profiling: false,
            loop_budget,
        })
    }

    /// Adam steps taken so far.
    pub fn steps(&self) -> u32 {
        self.t
    }

    /// Overwrites a group's Adam moments (a resumed run).
    pub fn write_adam(&mut self, group: Group, m: &[f32], v: &[f32]) -> Result<(), VulkanError> {
        let g = &mut self.groups[group as usize];
        check_len(group.name(), m.len(), g.len)?;
        check_len(group.name(), v.len(), g.len)?;
        for p in g.parts.iter_mut() {
            let r = p.start..p.start + p.len;
            upload(
                &mut self.gpu,
                &mut self.staging,
                &mut p.m,
                &f32_bytes(&m[r.clone()]),
            )?;
            upload(
                &mut self.gpu,
                &mut self.staging,
                &mut p.v,
                &f32_bytes(&v[r]),
            )?;
        }
        Ok(())
    }

    /// Sets the count of Adam steps taken (a resumed run).
    pub fn set_steps(&mut self, t: u32) {
        self.t = t;
    }

    /// Signed distances at world points (`sdf_at`, as the CPU backends' `sdf`).
    pub fn sdf(&mut self, points: &[[f32; 3]], out: &mut [f32]) -> Result<(), VulkanError> {
        check_len("sdf output", out.len(), points.len())?;
        let mut res = vec![0.0f32; points.len()];
        self.query(false, points, &mut res)?;
        out.copy_from_slice(&res);
        Ok(())
    }

    /// Colours at world points (`color_at`).
    pub fn color(&mut self, points: &[[f32; 3]], out: &mut [[f32; 3]]) -> Result<(), VulkanError> {
        check_len("color output", out.len(), points.len())?;
        let mut res = vec![0.0f32; points.len() * 3];
        self.query(true, points, &mut res)?;
        for (o, c) in out.iter_mut().zip(res.as_chunks::<3>().0) {
            *o = [c[0], c[1], c[2]];
        }
        Ok(())
    }

    fn check_binding(&self, what: &str, bytes: u64) -> Result<(), VulkanError> {
        if bytes > self.max_binding {
            return Err(VulkanError::TensorTooLarge {
                what: what.to_string(),
                bytes,
                limit: self.max_binding,
                limit_name: "maxStorageBufferRange",
            });
        }
        Ok(())
    }

    fn query(
        &mut self,
        color: bool,
        points: &[[f32; 3]],
        out: &mut [f32],
    ) -> Result<(), VulkanError> {
        let n = points.len();
        if n == 0 {
            return Ok(());
        }
        let per = if color { 3 } else { 1 };
        self.check_binding("the query points", n as u64 * 12)?;
        self.check_binding("the query results", (n * per) as u64 * 4)?;
        let flat: Vec<f32> = points.iter().flatten().copied().collect();
        ensure(&self.gpu, &mut self.input, n as u64 * 12, "query points")?
            .write_mapped(0, &f32_bytes(&flat));
        ensure(
            &self.gpu,
            &mut self.output,
            (n * per) as u64 * 4,
            "query results",
        )?;
        let Self {
            gpu,
            groups,
            model_words,
            input,
            output,
            pipelines,
            max_groups,
            ..
        } = self;
        let (Some(input), Some(output)) = (input.as_ref(), output.as_ref()) else {
            return Err(VulkanError::Unsupported("buffer allocation"));
        };
        let pipeline = if color {
            &pipelines.color
        } else {
            &pipelines.sdf
        };
        gpu.submit(|r| {
            let set = r.bind(
                pipeline,
                &[
                    &[&*model_words][..],
                    &param_bindings(groups),
                    &[input, output],
                ]
                .concat(),
            )?;
            dispatch_items(r, pipeline, &set, n, *max_groups, range_push);
            Ok(())
        })?;
        let mut bytes = vec![0u8; out.len() * 4];
        output.read_mapped(0, &mut bytes);
        for (x, b) in out.iter_mut().zip(bytes.as_chunks::<4>().0) {
            *x = f32::from_le_bytes(*b);
        }
        Ok(())
    }

    /// Allocates `store.slots` image slots of `store.width` x `store.height` RGBA8 pixels for
    /// the mapping window (device-local, zeroed), replacing any previous store.
    pub fn with_images(mut self, store: ImageStore) -> Result<Self, VulkanError> {
        let bytes = store.total_len() as u64 * 4;
        self.check_binding("the image slots", bytes)?;
        self.images = Buffer::new(self.gpu.device(), bytes, Memory::Device, "the image slots")?;
        {
            let img: &Buffer = &self.images;
            self.gpu.submit(|r| {
                r.zero(img);
                Ok(())
            })?;
        }
        self.store = store;
        Ok(self)
    }

    /// Samples per ray of the layout (`config.samples`, 1..=MAX_SAMPLES), as the shaders.
    fn samples_per_ray(&self) -> usize {
        (self.layout.config.samples as usize).clamp(1, MAX_SAMPLES)
    }

    /// Makes room for the sample records of `rays` rays.
    fn stage_samples(&mut self, rays: usize) -> Result<usize, VulkanError> {
        let records = rays * self.samples_per_ray();
        let bytes = (records * SAMPLE_FLOATS * 4) as u64;
        self.check_binding("the sample records of a batch", bytes)?;
        ensure_in(
            &self.gpu,
            &mut self.samples,
            bytes,
            Memory::Device,
            "sample records",
        )?;
        Ok(records)
    }

    /// Whether the per-sample backward sums the decoders' weight gradients per workgroup in
    /// workgroup memory before the global atomics (`sample_backward_wg_cs`).
    pub fn workgroup_sums(&self) -> bool {
        self.pipelines.sample_backward_wg.is_some()
    }

    /// The loop iterations one invocation completes on this device, measured at start by the
    /// loop canary (`loop_canary_cs`): `None` when a loop of [`CANARY_MAX`] completes (a real
    /// GPU), `Some(n)` on a device that cuts loops (llvmpipe: 65535 per invocation). Mapping
    /// steps whose warping pass could need more are refused ([`VulkanError::LoopBudget`])
    /// instead of running silently wrong.
    pub fn loop_budget(&self) -> Option<u32> {
        self.loop_budget
    }

    /// Times every later submission's passes with timestamp queries, and the host's
    /// transfers (uploads of a batch, read-back of its results). Returns false when the device
    /// has no timestamps on its compute queue (then only the transfers are timed).
    pub fn enable_profiling(&mut self) -> Result<bool, VulkanError> {
        self.profiling = true;
        self.gpu.enable_timestamps()
    }

    /// The times measured since profiling was enabled (or [`Self::reset_profile`]): device
    /// passes in the order they first ran, then the host transfers.
    pub fn profile(&self) -> Vec<PassTime> {
        let dev = self.gpu.timer.as_ref().map_or(&[][..], |t| &t.totals[..]);
        let host = self.host_times.borrow();
        dev.iter()
            .map(|e| (e, true))
            .chain(host.iter().map(|e| (e, false)))
            .map(|(&(name, ns, count), device)| PassTime {
                name,
                device,
                total_ms: ns * 1e-6,
                count,
            })
            .collect()
    }

    /// Forgets the times measured so far.
    pub fn reset_profile(&mut self) {
        if let Some(t) = self.gpu.timer.as_mut() {
            t.totals.clear();
        }
        self.host_times.borrow_mut().clear();
    }

    /// Adds the host time since `t0` to `name` when profiling.
    fn host_time(&self, name: &'static str, t0: std::time::Instant) {
        if self.profiling {
            let ns = t0.elapsed().as_secs_f64() * 1e9;
            add_time(&mut self.host_times.borrow_mut(), name, ns);
        }
    }

    /// Uploads rays and makes room for their results and sample records; returns the number of
    /// sample records.
    fn stage_rays(&mut self, rays: &[Ray]) -> Result<usize, VulkanError> {
        let t0 = std::time::Instant::now();
        let r = self.stage_rays_untimed(rays);
        self.host_time("upload (host)", t0);
        r
    }

    fn stage_rays_untimed(&mut self, rays: &[Ray]) -> Result<usize, VulkanError> {
        let n = rays.len();
        self.check_binding("the rays of a batch", (n * RAY_FLOATS * 4) as u64)?;
        let mut flat = Vec::with_capacity(n * RAY_FLOATS);
        for r in rays {
            flat.extend_from_slice(&r.origin);
            flat.extend_from_slice(&r.dir);
            flat.extend_from_slice(&r.target);
            flat.push(r.target_depth);
        }
        ensure(
            &self.gpu,
            &mut self.input,
            (n * RAY_FLOATS * 4) as u64,
            "rays",
        )?
        .write_mapped(0, &f32_bytes(&flat));
        ensure(
            &self.gpu,
            &mut self.output,
            (n * RESULT_FLOATS * 4) as u64,
            "ray results",
        )?;
        self.stage_samples(n)
    }

    fn read_floats(&self, len: usize) -> Vec<f32> {
        let t0 = std::time::Instant::now();
        let f = self.read_floats_untimed(len);
        self.host_time("read back (host)", t0);
        f
    }

    fn read_floats_untimed(&self, len: usize) -> Vec<f32> {
        let Some(out) = &self.output else {
            return vec![0.0; len];
        };
        let mut bytes = vec![0u8; len * 4];
        out.read_mapped(0, &mut bytes);
        bytes
            .as_chunks::<4>()
            .0
            .iter()
            .map(|b| f32::from_le_bytes(*b))
            .collect()
    }

    /// Writes a mapping batch's window (intrinsics, poses, slots, loss settings as words) and
    /// pixels, and sizes the buffers of its pixel rays and results.
    fn stage_window(&mut self, batch: &MapBatch<'_>, slots: &[u32]) -> Result<(), VulkanError> {
        let n = batch.pixels.len();
        let frames = batch.poses.len();
        let mut w = vec![0u32; words::WINDOW];
        let size = (self.store.width, self.store.height);
        let (k, poses, loss) = (&batch.k, batch.poses, &batch.loss);
        words::window_to_words(k, size, &slots[..frames], poses, loss, &mut w);
        let bytes = (words::WINDOW * 4) as u64;
        ensure(&self.gpu, &mut self.window, bytes, "the mapping window")?
            .write_mapped(0, &u32_bytes(&w));
        self.check_binding("the pixels of a batch", (n * 12) as u64)?;
        let flat: Vec<u32> = batch
            .pixels
            .iter()
            .flat_map(|p| [p.frame, p.u, p.v])
            .collect();
        ensure(&self.gpu, &mut self.pixels, (n * 12) as u64, "pixels")?
            .write_mapped(0, &u32_bytes(&flat));
        let ray_bytes = (n * RAY_FLOATS * 4) as u64;
        self.check_binding("the rays of a batch", ray_bytes)?;
        ensure(&self.gpu, &mut self.input, ray_bytes, "pixel rays")?;
        let result_bytes = (n * PIXEL_RESULT_FLOATS * 4) as u64;
        self.check_binding("the pixel results of a batch", result_bytes)?;
        ensure(&self.gpu, &mut self.output, result_bytes, "pixel results")?;
        Ok(())
    }

    fn read_results(&self, results: &mut [RayResult]) {
        let f = self.read_floats(results.len() * RESULT_FLOATS);
        for (r, v) in results.iter_mut().zip(f.as_chunks::<RESULT_FLOATS>().0) {
            *r = ray_result_from_record(v);
        }
    }

    /// After a step's submission: when its checks counted a non-finite value, Adam did
    /// nothing, so the step count goes back and `stats` says the step was rejected.
    fn finish_step(&mut self, mut stats: StepStats) -> StepStats {
        let mut b = [0u8; 4];
        self.status.read_mapped(0, &mut b);
        if u32::from_le_bytes(b) != 0 {
            self.t -= 1;
            stats.rejected = true;
            stats.t = self.t;
        }
        stats
    }

    fn adam_steps(&mut self) -> [AdamStep; NUM_GROUPS] {
        self.t += 1;
        core::array::from_fn(|g| AdamStep::new(&self.adam[g], self.t))
    }
}

impl VulkanBackend {
    /// Splits `self` for recording a ray batch (train or render): the device, the passes
    /// over the staged rays and sample records, and the results buffer.
    fn ray_passes(
        &mut self,
        records: usize,
    ) -> Result<(&mut Gpu, Passes<'_>, &Buffer), VulkanError> {
        let (Some(input), Some(output), Some(samples)) = (
            self.input.as_ref(),
            self.output.as_ref(),
            self.samples.as_ref(),
        ) else {
            return Err(VulkanError::Unsupported("buffer allocation"));
        };
        let passes = Passes {
            pipelines: &self.pipelines,
            groups: &self.groups,
            model_words: &self.model_words,
            rays: input,
            samples,
            status: &self.status,
            records,
            max_groups: self.max_groups,
        };
        Ok((&mut self.gpu, passes, output))
    }
}

impl Backend for VulkanBackend {
    type Error = VulkanError;

    fn layout(&self) -> &ModelLayout {
        &self.layout
    }

    fn name(&self) -> &str {
        &self.name
    }

    fn train_step(
        &mut self,
        rays: &[Ray],
        loss: &LossConfig,
        results: &mut [RayResult],
    ) -> Result<StepStats, VulkanError> {
        check_len("results", results.len(), rays.len())?;
        let records = self.stage_rays(rays)?;
        let steps = self.adam_steps();
        let n = rays.len();
        let train_push = |first: u32, count: u32| {
            push_bytes(TrainPush {
                n: count,
                first,
                seed: loss.seed,
                color_to_geometry: loss.color_to_geometry as u32,
                lambda_color: loss.lambda_color,
                lambda_depth: loss.lambda_depth,
                ray_scale: loss.ray_scale,
                _pad: 0,
            })
        };
        let (gpu, passes, output) = self.ray_passes(records)?;
        let pipelines = passes.pipelines;
        gpu.submit(|r| {
            passes.zero_grads(r);
            if n > 0 {
                passes.sample_forward(r, loss.seed, true)?;
                let pipeline = &pipelines.ray_train;
                let set = passes.bind_composite(r, pipeline, &[], output)?;
                dispatch_items(r, pipeline, &set, n, passes.max_groups, train_push);
                r.barrier();
                r.mark("composite and loss (per ray)");
                passes.sample_backward(r)?;
            }
            passes.checked_adam(r, &steps, output, n, RESULT_FLOATS, RESULT_LOSS)
        })?;
        self.read_results(results);
        let stats = summarize(results, self.t);
        Ok(self.finish_step(stats))
    }

    fn render(&mut self, rays: &[Ray], results: &mut [RayResult]) -> Result<(), VulkanError> {
        check_len("results", results.len(), rays.len())?;
        if rays.is_empty() {
            return Ok(());
        }
        let records = self.stage_rays(rays)?;
        let n = rays.len();
        let (gpu, passes, output) = self.ray_passes(records)?;
        let (pipelines, groups, model_words, input, samples) = (
            passes.pipelines,
            passes.groups,
            passes.model_words,
            passes.rays,
            passes.samples,
        );
        gpu.submit(|r| {
            passes.sample_forward(r, 0, false)?;
            let pipeline = &pipelines.ray_render;
            let set = r.bind(
                pipeline,
                &[
                    model_words,
                    &groups[Group::Beta].lo().params,
                    input,
                    samples,
                    output,
                ],
            )?;
            dispatch_items(r, pipeline, &set, n, passes.max_groups, range_push);
            r.mark("composite (render)");
            Ok(())
        })?;
        self.read_results(results);
        Ok(())
    }

    fn read_params(&mut self, group: Group, out: &mut [f32]) -> Result<(), VulkanError> {
        let g = &self.groups[group as usize];
        check_len(group.name(), out.len(), g.len)?;
        for p in &g.parts {
            let r = p.start..p.start + p.len;
            download_f32(&mut self.gpu, &mut self.staging, &p.params, &mut out[r])?;
        }
        Ok(())
    }

    fn read_adam(&mut self, group: Group, m: &mut [f32], v: &mut [f32]) -> Result<(), VulkanError> {
        let g = &self.groups[group as usize];
        check_len(group.name(), m.len(), g.len)?;
        check_len(group.name(), v.len(), g.len)?;
        for p in &g.parts {
            let r = p.start..p.start + p.len;
            download_f32(&mut self.gpu, &mut self.staging, &p.m, &mut m[r.clone()])?;
            download_f32(&mut self.gpu, &mut self.staging, &p.v, &mut v[r])?;
        }
        Ok(())
    }

    fn read_grads(&mut self, group: Group, out: &mut [i64]) -> Result<(), VulkanError> {
        let g = &self.groups[group as usize];
        check_len(group.name(), out.len(), g.len)?;
        for p in &g.parts {
            let mut bytes = vec![0u8; p.len * 8];
            download(&mut self.gpu, &mut self.staging, &p.grad, &mut bytes)?;
            for (x, b) in out[p.start..p.start + p.len]
                .iter_mut()
                .zip(bytes.as_chunks::<8>().0)
            {
                *x = i64::from_le_bytes(*b);
            }
        }
        Ok(())
    }

    fn write_params(
        &mut self,
        group: Group,
        data: &[f32],
        reset_adam: bool,
    ) -> Result<(), VulkanError> {
        let g = &mut self.groups[group as usize];
        check_len(group.name(), data.len(), g.len)?;
        for p in g.parts.iter_mut() {
            upload(
                &mut self.gpu,
                &mut self.staging,
                &mut p.params,
                &f32_bytes(&data[p.start..p.start + p.len]),
            )?;
        }
        if reset_adam {
            let parts = &g.parts;
            self.gpu.submit(|r| {
                for p in parts {
                    r.zero(&p.m);
                    r.zero(&p.v);
                }
                Ok(())
            })?;
        }
        Ok(())
    }

    fn image_store(&self) -> ImageStore {
        self.store
    }

    fn upload_frame(&mut self, slot: u32, rgba: &[u32]) -> Result<(), VulkanError> {
        let words = self.store.slot_range(slot, rgba.len())?;
        upload_at(
            &mut self.gpu,
            &mut self.staging,
            &mut self.images,
            (words.start * 4) as u64,
            &u32_bytes(rgba),
        )
    }

    fn map_step(
        &mut self,
        batch: &MapBatch<'_>,
        results: &mut [PixelResult],
    ) -> Result<StepStats, VulkanError> {
        #[cfg(feature = "fault-injection")]
        crate::fault::map_step()?;
        check_len("results", results.len(), batch.pixels.len())?;
        if let Some(budget) = self.loop_budget {
            let frames = batch.poses.len() as u32;
            let needed = himap_core::gpu_abi::pixel_train_loop_bound(frames);
            if needed > budget {
                return Err(VulkanError::LoopBudget {
                    what: format!("the warping pass over a {frames}-frame mapping window"),
                    needed,
                    budget,
                });
            }
        }
        let slots = window_slots(batch, &self.store)?;
        let n = batch.pixels.len();
        let t0 = std::time::Instant::now();
        self.stage_window(batch, &slots)?;
        let records = self.stage_samples(n)?;
        self.host_time("upload (host)", t0);
        let steps = self.adam_steps();
        let seed = batch.loss.seed;
        let Self {
            gpu,
            groups,
            model_words,
            input,
            output,
            samples,
            pixels,
            window,
            images,
            pipelines,
            max_groups,
            status,
            ..
        } = self;
        let (Some(input), Some(output), Some(samples), Some(pixels), Some(window)) = (
            input.as_ref(),
            output.as_ref(),
            samples.as_ref(),
            pixels.as_ref(),
            window.as_ref(),
        ) else {
            return Err(VulkanError::Unsupported("buffer allocation"));
        };
        let images: &Buffer = images;
        let passes = Passes {
            pipelines,
            groups,
            model_words,
            rays: input,
            samples,
            status,
            records,
            max_groups: *max_groups,
        };
        gpu.submit(|r| {
            passes.zero_grads(r);
            if n > 0 {
                let pipeline = &pipelines.pixel_rays;
                let set = r.bind(pipeline, &[window, pixels, images, input])?;
                dispatch_items(r, pipeline, &set, n, passes.max_groups, range_push);
                r.barrier();
                r.mark("pixel rays");
                passes.sample_forward(r, seed, true)?;
                let pipeline = &pipelines.pixel_train;
                let set = passes.bind_composite(r, pipeline, &[window, pixels, images], output)?;
                // the planarity triplets are cut by the whole batch's size
                let push = |first, count| batch_push(first, count, n as u32);
                dispatch_items(r, pipeline, &set, n, passes.max_groups, push);
                r.barrier();
                r.mark("composite and pixel losses (per pixel)");
                passes.sample_backward(r)?;
            }
            passes.checked_adam(
                r,
                &steps,
                output,
                n,
                PIXEL_RESULT_FLOATS,
                PIXEL_RESULT_LOSSES,
            )
        })?;
        let f = self.read_floats(n * PIXEL_RESULT_FLOATS);
        for (r, v) in results
            .iter_mut()
            .zip(f.as_chunks::<PIXEL_RESULT_FLOATS>().0)
        {
            *r = pixel_result_from_record(v);
        }
        let stats = summarize_pixels(results, self.t);
        Ok(self.finish_step(stats))
    }

    fn set_adam_lr(&mut self, group: Group, lr: f32) -> Result<(), VulkanError> {
        Ok(self.adam[group].set_lr(lr)?)
    }

    fn adam_lr(&self, group: Group) -> f32 {
        self.adam[group].lr
    }

    fn set_min_transmittance(&mut self, t: f32) -> Result<(), VulkanError> {
        let mut layout = self.layout;
        layout.set_min_transmittance(t)?;
        let parts =
            |g: usize| -> Vec<usize> { self.groups[g].parts.iter().map(|p| p.len).collect() };
        let (p0, p1) = (parts(0), parts(1));
        let w = model_words(&layout, [&p0, &p1]);
        upload(
            &mut self.gpu,
            &mut self.staging,
            &mut self.model_words,
            &u32_bytes(&w),
        )?;
        self.layout = layout;
        Ok(())
    }
}
