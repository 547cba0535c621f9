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
//! `pixel_depth_cs` (partner depths, with the planarity prior), `pixel_loss_cs` (colour, warping,
//! depth-prior and planarity losses) and `pixel_backward_cs` as pass 2. A render is passes 1
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
use crate::passes::{
    batch_push, dispatch_items, push_bytes, range_push, BackwardPass, Passes, Pipelines,
};
use crate::raw::{Buffer, Gpu, Memory, PhysicalInfo, ShaderModule, FRAMES};
use crate::words;
use himap_core::error::check_len;
use himap_core::field::model::{
    Group, LossConfig, ModelLayout, PerGroup, Ray, RayResult, NUM_GROUPS,
};
use himap_core::gpu_abi::{
    pixel_result_from_record, ray_result_from_record, TrainPush, PIXEL_AUX_FLOATS,
    PIXEL_RESULT_FLOATS, PIXEL_RESULT_LOSSES, RAY_FLOATS, RESULT_FLOATS, RESULT_LOSS,
    SAMPLE_FLOATS, STATUS_REJECTED, STATUS_STEPS, STATUS_WORDS,
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
    /// The backward's structure where the device offers both; `None` (the default) times
    /// both on the first steps and keeps the faster ([`VulkanBackend::backward_pass`]).
    pub backward: Option<BackwardPass>,
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
    /// Per-batch inputs and outputs (host-visible, grown on demand): rays (or query points,
    /// or a mapping step's pixel rays), per-item results of training steps and renders.
    input: Option<Buffer>,
    output: Option<Buffer>,
    /// The host-visible buffers of the mapping steps, one per [`Gpu`] frame, and the frame
    /// of the step queued behind the last one returned ([`Backend::map_step`]'s `next`).
    maps: [MapFrame; FRAMES],
    queued: Option<usize>,
    /// Per-sample records of the current batch (device-local, grown on demand).
    samples: Option<Buffer>,
    /// The image slots (device-local, allocated by [`VulkanBackend::with_images`]).
    images: Buffer,
    /// A host copy of the image slots, for [`Backend::slot_texel`].
    host_images: Vec<u32>,
    /// Where the per-pixel depth-prior targets start in `images` (words; 0 = none yet: the
    /// buffer holds only the slots until [`Backend::set_depth_prior`] is first called), and
    /// their host copy.
    priors_at: u32,
    host_priors: Vec<f32>,
    store: ImageStore,
    /// Staging for device-local buffers that are not host-visible.
    staging: Option<Buffer>,
    /// The status words (`gpu_abi::STATUS_WORDS`; host-visible): the step's count of
    /// non-finite values (`loss_check_cs`, `adam_check_cs`; zeroed at the start of every
    /// step, non-zero rejects it) and the count of steps taken (Adam's `t`).
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
    /// The backward's structure: chosen, or being measured.
    backward: BackwardChoice,
}

/// Measured backward passes kept per structure before the faster is chosen (after one
/// warm-up step of each).
const BACKWARD_TRIALS: u32 = 3;

/// How the steps' backward pass is chosen on this device: fixed where only one structure
/// exists (or the options fix it), otherwise the first steps alternate between the two,
/// their device times taken from the frame's timestamp pair, and the faster one (the least
/// time of [`BACKWARD_TRIALS`] each) is kept. Both give the same bits.
#[derive(Clone, Copy, Debug)]
struct BackwardChoice {
    chosen: Option<BackwardPass>,
    /// Per structure ([`BackwardPass::ALL`] order): steps recorded, least time (ns) of the
    /// timed ones, and how many times were noted (the first is the warm-up).
    recorded: [u32; 2],
    best_ns: [f64; 2],
    noted: [u32; 2],
}

impl BackwardChoice {
    fn new(chosen: Option<BackwardPass>) -> Self {
        Self {
            chosen,
            recorded: [0; 2],
            best_ns: [f64::INFINITY; 2],
            noted: [0; 2],
        }
    }

    /// The structure of the next step recorded.
    fn next(&mut self) -> BackwardPass {
        if let Some(c) = self.chosen {
            return c;
        }
        let i = ((self.recorded[0] + self.recorded[1]) % 2) as usize;
        self.recorded[i] += 1;
        BackwardPass::ALL[i]
    }

    /// A finished step's backward time (`None`: not timed); chooses once both have
    /// [`BACKWARD_TRIALS`] measurements after their warm-up step.
    fn note(&mut self, used: BackwardPass, ns: Option<f64>) {
        if self.chosen.is_some() {
            return;
        }
        let i = used as usize;
        // (a step without a backward, an empty batch, has no time)
        let Some(ns) = ns else {
            return;
        };
        self.noted[i] += 1;
        // the first of each structure warms up (pipeline creation, caches)
        if self.noted[i] > 1 {
            self.best_ns[i] = self.best_ns[i].min(ns);
        }
        if self.noted.iter().all(|&m| m > BACKWARD_TRIALS) {
            let faster = if self.best_ns[1] <= self.best_ns[0] {
                1
            } else {
                0
            };
            self.chosen = Some(BackwardPass::ALL[faster]);
        }
    }
}

/// The host-visible buffers of one mapping step: the window's words, the pixels, the
/// per-pixel results and the status words copied at the step's end; and a hash of the batch
/// it holds (a queued step is checked against the batch the caller then brings).
#[derive(Default)]
struct MapFrame {
    window: Option<Buffer>,
    pixels: Option<Buffer>,
    results: Option<Buffer>,
    /// Between the pixel passes: [`PIXEL_AUX_FLOATS`] per pixel (device memory).
    aux: Option<Buffer>,
    status: Option<Buffer>,
    batch: u64,
    /// The backward structure the step used (its time goes to [`BackwardChoice::note`]).
    backward: Option<BackwardPass>,
}

/// FNV-1a over what decides a mapping step: pixels, poses, slots, loss words, rates.
fn batch_hash(batch: &MapBatch<'_>) -> u64 {
    let mut h = 0xcbf2_9ce4_8422_2325u64;
    let mut add = |w: u32| {
        h ^= u64::from(w);
        h = h.wrapping_mul(0x0000_0100_0000_01b3);
    };
    for p in batch.pixels {
        add(p.frame);
        add(p.u);
        add(p.v);
    }
    for (p, s) in batch.poses.iter().zip(batch.slots) {
        p.m.iter().flatten().for_each(|x| add(x.to_bits()));
        add(*s);
    }
    add(batch.loss.seed);
    add(batch.loss.lambda_color.to_bits());
    add(batch.loss.lambda_warp.to_bits());
    add(batch.loss.color_to_geometry as u32);
    add(batch.loss.lambda_depth_prior.to_bits());
    if let Some(lr) = batch.lr {
        lr.iter().for_each(|x| add(x.to_bits()));
    }
    h
}

/// The first `len` floats of a host-visible buffer.
fn mapped_f32s(buf: &Buffer, len: usize) -> Vec<f32> {
    let mut bytes = vec![0u8; len * 4];
    buf.read_mapped(0, &mut bytes);
    bytes
        .as_chunks::<4>()
        .0
        .iter()
        .map(|b| f32::from_le_bytes(*b))
        .collect()
}

/// The status words of a finished step: whether its checks rejected it, and the device's
/// count of steps taken.
fn read_status(status: &Buffer) -> (bool, u32) {
    let mut b = [0u8; 4 * STATUS_WORDS];
    status.read_mapped(0, &mut b);
    let word = |i: usize| u32::from_le_bytes([b[4 * i], b[4 * i + 1], b[4 * i + 2], b[4 * i + 3]]);
    (word(STATUS_REJECTED) != 0, word(STATUS_STEPS))
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
        let module = ShaderModule::new(&device, &crate::runtime_shader_words()?)?;
        let pipelines = Pipelines::new(&device, &module, !options.global_atomics_only)?;
        let workgroup_sums_available = pipelines.sample_backward_wg.is_some();
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
            maps: Default::default(),
            queued: None,
            samples: None,
            images: Buffer::new(&device, 16, Memory::Device, "the image slots")?,
            host_images: Vec::new(),
            priors_at: 0,
            host_priors: Vec::new(),
            status: {
                let mut b = Buffer::new(&device, 16, Memory::Host, "the step's status words")?;
                b.write_mapped(0, &[0u8; 16]);
                b
            },
            store: ImageStore::default(),
            staging,
            pipelines,
            _module: module,
            gpu,
            host_times: Default::default(),
            profiling: false,
            loop_budget,
            backward: BackwardChoice::new(
                if options.global_atomics_only || !workgroup_sums_available {
                    Some(BackwardPass::GlobalAtomics)
                } else if info.timestamp_valid_bits == 0 || info.timestamp_period <= 0.0 {
                    // nothing to time them with: the structure built for real GPUs
                    Some(options.backward.unwrap_or(BackwardPass::WorkgroupSums))
                } else {
                    options.backward
                },
            ),
        })
    }

    /// Adam steps taken so far.
    pub fn steps(&self) -> u32 {
        self.t
    }

    /// Overwrites a group's Adam moments (a resumed run).
    pub fn write_adam(&mut self, group: Group, m: &[f32], v: &[f32]) -> Result<(), VulkanError> {
        self.settle()?;
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

    /// A backend like this one over another layout (a grown scene box): the same device
    /// (opened again), learning rates, backward structure, profiling, image slots and their
    /// contents, with `params` uploaded and the Adam moments and step at zero (import them
    /// next). Built with the default [`VulkanOptions`] otherwise.
    pub fn regrown(
        &mut self,
        layout: ModelLayout,
        params: [&[f32]; NUM_GROUPS],
    ) -> Result<Self, VulkanError> {
        self.settle()?;
        let options = VulkanOptions {
            backward: self.backward.chosen,
            ..VulkanOptions::default()
        };
        let mut new =
            Self::with_options(layout, params, self.adam, options)?.with_images(self.store)?;
        for slot in 0..self.store.slots {
            let words = self.store.slot_range(slot, self.store.slot_len())?;
            let img = self.host_images[words.clone()].to_vec();
            Backend::upload_frame(&mut new, slot, &img)?;
            if self.priors_at != 0 {
                let prior = self.host_priors[words].to_vec();
                Backend::set_depth_prior(&mut new, slot, &prior)?;
            }
        }
        if self.profiling {
            new.enable_profiling()?;
        }
        Ok(new)
    }

    /// Sets the count of Adam steps taken (a resumed run).
    pub fn set_steps(&mut self, t: u32) -> Result<(), VulkanError> {
        self.settle()?;
        let mut w = [0u8; 4];
        w.copy_from_slice(&t.to_le_bytes());
        self.status.write_mapped((STATUS_STEPS * 4) as u64, &w);
        self.t = t;
        Ok(())
    }

    /// Waits for every submitted step (a queued one's results stay in its frame for the
    /// `map_step` that brings its batch; a step left pending by an error is waited for too),
    /// so that the other calls see the device at rest.
    fn settle(&mut self) -> Result<(), VulkanError> {
        self.gpu.wait_all()
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
        self.settle()?;
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
        self.images = self.zeroed_images(store.total_len() as u64 * 4, "the image slots")?;
        self.store = store;
        self.host_images = vec![0; store.total_len()];
        self.priors_at = 0;
        self.host_priors = Vec::new();
        Ok(self)
    }

    /// A zeroed device-local image buffer of `bytes` (checked against the binding limit).
    fn zeroed_images(&mut self, bytes: u64, what: &str) -> Result<Buffer, VulkanError> {
        self.check_binding(what, bytes)?;
        let img = Buffer::new(self.gpu.device(), bytes, Memory::Device, "the image slots")?;
        {
            let img: &Buffer = &img;
            self.gpu.submit(|r| {
                r.zero(img);
                Ok(())
            })?;
        }
        Ok(img)
    }

    /// Grows the image buffer to hold a depth-prior target per pixel after the slots
    /// (zeroed), the slots copied in from the host copy.
    fn add_priors(&mut self) -> Result<(), VulkanError> {
        self.settle()?;
        let total = self.store.total_len();
        self.images = self.zeroed_images(
            2 * total as u64 * 4,
            "the image slots with their depth priors",
        )?;
        let words = self.host_images.clone();
        upload_at(
            &mut self.gpu,
            &mut self.staging,
            &mut self.images,
            0,
            &u32_bytes(&words),
        )?;
        self.priors_at = u32::try_from(total).map_err(|_| {
            VulkanError::Unsupported("an image store of 2^32 words or more with depth priors")
        })?;
        self.host_priors = vec![0.0; total];
        Ok(())
    }

    /// Samples per ray of the layout (`config.max_ray_samples()`, 1..=MAX_SAMPLES), as the
    /// shaders.
    fn samples_per_ray(&self) -> usize {
        self.layout.config.max_ray_samples()
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

    /// The backward's structure on this device: the one chosen (`None` while the first
    /// steps still time both), and the least device time (ms) measured for each
    /// ([`BackwardPass::ALL`] order; `None` where not measured).
    pub fn backward_pass(&self) -> (Option<BackwardPass>, [Option<f64>; 2]) {
        let b = &self.backward;
        let ms = |i: usize| (b.noted[i] > 1).then(|| b.best_ns[i] * 1e-6);
        (b.chosen, [ms(0), ms(1)])
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
        match &self.output {
            Some(out) => mapped_f32s(out, len),
            None => vec![0.0; len],
        }
    }

    /// Writes a mapping batch's window (intrinsics, poses, slots, loss settings as words) and
    /// pixels into frame `f`'s buffers, and sizes the buffers of its pixel rays and results.
    fn stage_window(
        &mut self,
        f: usize,
        batch: &MapBatch<'_>,
        slots: &[u32],
    ) -> Result<(), VulkanError> {
        let n = batch.pixels.len();
        let frames = batch.poses.len();
        let mut w = vec![0u32; words::WINDOW];
        let size = (self.store.width, self.store.height);
        let (k, poses, loss) = (&batch.k, batch.poses, &batch.loss);
        words::window_to_words(k, size, &slots[..frames], poses, loss, &mut w);
        w[words::WINDOW_PRIORS] = self.priors_at;
        let bytes = (words::WINDOW * 4) as u64;
        let m = &mut self.maps[f];
        ensure(&self.gpu, &mut m.window, bytes, "the mapping window")?
            .write_mapped(0, &u32_bytes(&w));
        self.check_binding("the pixels of a batch", (n * 12) as u64)?;
        let flat: Vec<u32> = batch
            .pixels
            .iter()
            .flat_map(|p| [p.frame, p.u, p.v])
            .collect();
        let m = &mut self.maps[f];
        ensure(&self.gpu, &mut m.pixels, (n * 12) as u64, "pixels")?
            .write_mapped(0, &u32_bytes(&flat));
        let result_bytes = (n * PIXEL_RESULT_FLOATS * 4) as u64;
        self.check_binding("the pixel results of a batch", result_bytes)?;
        let m = &mut self.maps[f];
        ensure(&self.gpu, &mut m.results, result_bytes, "pixel results")?;
        let aux_bytes = (n.max(1) * PIXEL_AUX_FLOATS * 4) as u64;
        self.check_binding("the pixel records between passes", aux_bytes)?;
        let m = &mut self.maps[f];
        ensure_in(
            &self.gpu,
            &mut m.aux,
            aux_bytes,
            Memory::Device,
            "pixel records between passes",
        )?;
        ensure(
            &self.gpu,
            &mut m.status,
            16,
            "a mapping step's status words",
        )?;
        m.batch = batch_hash(batch);
        let ray_bytes = (n * RAY_FLOATS * 4) as u64;
        self.check_binding("the rays of a batch", ray_bytes)?;
        ensure(&self.gpu, &mut self.input, ray_bytes, "pixel rays")?;
        Ok(())
    }

    fn read_results(&self, results: &mut [RayResult]) {
        let f = self.read_floats(results.len() * RESULT_FLOATS);
        for (r, v) in results.iter_mut().zip(f.as_chunks::<RESULT_FLOATS>().0) {
            *r = ray_result_from_record(v);
        }
    }

    /// After a step: its status words (`status`: the step's own copy, or the shared buffer
    /// after a waited-for submission). When its checks counted a non-finite value Adam did
    /// nothing and `stats` says the step was rejected; the step count is the device's.
    fn finish_step(&mut self, mut stats: StepStats, (rejected, t): (bool, u32)) -> StepStats {
        stats.rejected |= rejected;
        self.t = t;
        stats.t = t;
        stats
    }

    /// The Adam scalars of the next step with the rates of `adam` (the shaders take the bias
    /// corrections from the device's step count, which the host's `t` mirrors between steps).
    fn adam_steps(&self, adam: &PerGroup<AdamConfig>) -> [AdamStep; NUM_GROUPS] {
        core::array::from_fn(|g| AdamStep::new(&adam[g], self.t.wrapping_add(1)))
    }
}

impl VulkanBackend {
    /// Stages `batch` in frame `f`'s buffers and submits its mapping step there without
    /// waiting (waited for and timed instead when profiling). Refuses a window the device's
    /// loop budget cannot run.
    fn submit_map(&mut self, f: usize, batch: &MapBatch<'_>) -> Result<(), VulkanError> {
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
        let adam = batch.adam(&self.adam)?;
        let n = batch.pixels.len();
        // the frame's buffers are rewritten: its previous step must be done
        self.gpu.wait(f)?;
        let t0 = std::time::Instant::now();
        self.stage_window(f, batch, &slots)?;
        let records = self.stage_samples(n)?;
        self.host_time("upload (host)", t0);
        let steps = self.adam_steps(&adam);
        let seed = batch.loss.seed;
        let planar = batch.loss.planar.weight != 0.0;
        let timed = self.profiling;
        let backward = self.backward.next();
        self.maps[f].backward = Some(backward);
        let Self {
            gpu,
            groups,
            model_words,
            input,
            samples,
            maps,
            images,
            pipelines,
            max_groups,
            status,
            ..
        } = self;
        let m = &maps[f];
        let (
            Some(input),
            Some(samples),
            Some(pixels),
            Some(window),
            Some(output),
            Some(aux),
            Some(copy),
        ) = (
            input.as_ref(),
            samples.as_ref(),
            m.pixels.as_ref(),
            m.window.as_ref(),
            m.results.as_ref(),
            m.aux.as_ref(),
            m.status.as_ref(),
        )
        else {
            return Err(VulkanError::Unsupported("buffer allocation"));
        };
        let images: &Buffer = images;
        let status: &Buffer = status;
        let passes = Passes {
            pipelines,
            groups,
            model_words,
            rays: input,
            samples,
            status,
            records,
            max_groups: *max_groups,
            backward,
        };
        gpu.submit_on(f, timed, |r| {
            passes.zero_grads(r);
            if n > 0 {
                let pipeline = &pipelines.pixel_rays;
                let set = r.bind(pipeline, &[window, pixels, images, input])?;
                dispatch_items(r, pipeline, &set, n, passes.max_groups, range_push);
                r.barrier();
                r.mark("pixel rays");
                passes.sample_forward(r, seed, true)?;
                // the planarity triplets are cut by the whole batch's size
                let push = |first, count| batch_push(first, count, n as u32);
                let pixel_passes = [
                    (
                        planar,
                        &pipelines.pixel_depth,
                        "composite depth (per pixel)",
                    ),
                    (
                        true,
                        &pipelines.pixel_loss,
                        "composite and pixel losses (per pixel)",
                    ),
                    (
                        true,
                        &pipelines.pixel_backward,
                        "compositing backward (per pixel)",
                    ),
                ];
                for (_, pipeline, mark) in pixel_passes.into_iter().filter(|p| p.0) {
                    let set = passes.bind_composite(
                        r,
                        pipeline,
                        &[window, pixels, images],
                        &[output, aux],
                    )?;
                    dispatch_items(r, pipeline, &set, n, passes.max_groups, push);
                    r.barrier();
                    r.mark(mark);
                }
                passes.sample_backward(r)?;
            }
            passes.checked_adam(
                r,
                &steps,
                output,
                n,
                PIXEL_RESULT_FLOATS,
                PIXEL_RESULT_LOSSES,
            )?;
            // the step's own copy of the status words: the next queued step zeroes them
            r.copy(status, 0, copy, 0, (4 * STATUS_WORDS) as u64);
            Ok(())
        })
    }

    /// Splits `self` for recording a ray batch (train or render): the device, the passes
    /// over the staged rays and sample records, and the results buffer.
    fn ray_passes(
        &mut self,
        records: usize,
        backward: BackwardPass,
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
            backward,
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
        self.settle()?;
        let records = self.stage_rays(rays)?;
        let steps = self.adam_steps(&self.adam);
        let n = rays.len();
        let backward = self.backward.next();
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
        let (gpu, passes, output) = self.ray_passes(records, backward)?;
        let pipelines = passes.pipelines;
        gpu.submit(|r| {
            passes.zero_grads(r);
            if n > 0 {
                passes.sample_forward(r, loss.seed, true)?;
                let pipeline = &pipelines.ray_train;
                let set = passes.bind_composite(r, pipeline, &[], &[output])?;
                dispatch_items(r, pipeline, &set, n, passes.max_groups, train_push);
                r.barrier();
                r.mark("composite and loss (per ray)");
                passes.sample_backward(r)?;
            }
            passes.checked_adam(r, &steps, output, n, RESULT_FLOATS, RESULT_LOSS)
        })?;
        let ns = self.gpu.stamp_ns(0)?;
        self.backward.note(backward, ns);
        self.read_results(results);
        let stats = summarize(results, self.t);
        let status = read_status(&self.status);
        Ok(self.finish_step(stats, status))
    }

    fn render(&mut self, rays: &[Ray], results: &mut [RayResult]) -> Result<(), VulkanError> {
        check_len("results", results.len(), rays.len())?;
        if rays.is_empty() {
            return Ok(());
        }
        self.settle()?;
        let records = self.stage_rays(rays)?;
        let n = rays.len();
        let (gpu, passes, output) = self.ray_passes(records, BackwardPass::GlobalAtomics)?;
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
        self.settle()?;
        let g = &self.groups[group as usize];
        check_len(group.name(), out.len(), g.len)?;
        for p in &g.parts {
            let r = p.start..p.start + p.len;
            download_f32(&mut self.gpu, &mut self.staging, &p.params, &mut out[r])?;
        }
        Ok(())
    }

    fn read_adam(&mut self, group: Group, m: &mut [f32], v: &mut [f32]) -> Result<(), VulkanError> {
        self.settle()?;
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
        self.settle()?;
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
        self.settle()?;
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
        self.settle()?;
        let words = self.store.slot_range(slot, rgba.len())?;
        self.host_images[words.clone()].copy_from_slice(rgba);
        upload_at(
            &mut self.gpu,
            &mut self.staging,
            &mut self.images,
            (words.start * 4) as u64,
            &u32_bytes(rgba),
        )?;
        if self.priors_at != 0 {
            // a new frame in the slot: its old priors go
            self.host_priors[words.clone()].fill(0.0);
            let zeros = vec![0u32; words.len()];
            upload_at(
                &mut self.gpu,
                &mut self.staging,
                &mut self.images,
                ((self.priors_at as usize + words.start) * 4) as u64,
                &u32_bytes(&zeros),
            )?;
        }
        Ok(())
    }

    fn set_depth_prior(&mut self, slot: u32, prior: &[f32]) -> Result<bool, VulkanError> {
        self.settle()?;
        let words = self.store.slot_range(slot, prior.len())?;
        if self.priors_at == 0 {
            self.add_priors()?;
        }
        self.host_priors[words.clone()].copy_from_slice(prior);
        let bits: Vec<u32> = prior.iter().map(|p| p.to_bits()).collect();
        upload_at(
            &mut self.gpu,
            &mut self.staging,
            &mut self.images,
            ((self.priors_at as usize + words.start) * 4) as u64,
            &u32_bytes(&bits),
        )?;
        Ok(true)
    }

    fn slot_texel(&self, slot: u32, u: u32, v: u32) -> u32 {
        match self.store.texel_index(slot, u, v) {
            Some(i) if i < self.host_images.len() => self.host_images[i],
            _ => 0,
        }
    }

    fn map_step(
        &mut self,
        batch: &MapBatch<'_>,
        results: &mut [PixelResult],
        next: Option<&MapBatch<'_>>,
    ) -> Result<StepStats, VulkanError> {
        #[cfg(feature = "fault-injection")]
        crate::fault::map_step()?;
        check_len("results", results.len(), batch.pixels.len())?;
        let f = match self.queued.take() {
            Some(f) => {
                if self.maps[f].batch != batch_hash(batch) {
                    // the queued step has run on the parameters already: nothing to undo
                    self.gpu.wait_all()?;
                    return Err(VulkanError::Unsupported(
                        "map_step: the batch differs from the one the previous call queued as next",
                    ));
                }
                f
            }
            None => {
                let f = (0..FRAMES).find(|&f| !self.gpu.pending(f)).unwrap_or(0);
                self.submit_map(f, batch)?;
                f
            }
        };
        // Queue the next step behind this one (not when timing: timed submissions wait).
        if let Some(nb) = next.filter(|_| !self.profiling) {
            let g = (f + 1) % FRAMES;
            self.submit_map(g, nb)?;
            self.queued = Some(g);
        }
        let t0 = std::time::Instant::now();
        self.gpu.wait(f)?;
        if let Some(used) = self.maps[f].backward {
            let ns = self.gpu.stamp_ns(f)?;
            self.backward.note(used, ns);
        }
        let n = batch.pixels.len();
        let m = &self.maps[f];
        let (Some(out), Some(status)) = (m.results.as_ref(), m.status.as_ref()) else {
            return Err(VulkanError::Unsupported("buffer allocation"));
        };
        let f32s = mapped_f32s(out, n * PIXEL_RESULT_FLOATS);
        let status = read_status(status);
        self.host_time("read back (host)", t0);
        for (r, v) in results
            .iter_mut()
            .zip(f32s.as_chunks::<PIXEL_RESULT_FLOATS>().0)
        {
            *r = pixel_result_from_record(v);
        }
        let stats = summarize_pixels(results, self.t);
        Ok(self.finish_step(stats, status))
    }

    fn set_adam_lr(&mut self, group: Group, lr: f32) -> Result<(), VulkanError> {
        Ok(self.adam[group].set_lr(lr)?)
    }

    fn adam_lr(&self, group: Group) -> f32 {
        self.adam[group].lr
    }

    fn set_min_transmittance(&mut self, t: f32) -> Result<(), VulkanError> {
        self.settle()?;
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
