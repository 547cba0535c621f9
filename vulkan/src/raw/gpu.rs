//! Command recording and submission: one command buffer, a fence and a descriptor pool per
//! [`Gpu`]; [`Recorder`] records the passes of one submission.

use crate::error::VulkanError;
use ash::vk;
use std::sync::Arc;

use super::{Buffer, Device, Pipeline};

/// How long [`Gpu::submit`] waits for a submission.
const TIMEOUT_S: u64 = 900;
/// Descriptor sets per submission.
const MAX_SETS: u32 = 64;
/// Timestamps per submission (the start and one after each marked pass).
const MAX_MARKS: u32 = 64;

/// GPU time per named pass, from timestamp queries ([`Gpu::enable_timestamps`]).
pub(crate) struct Timer {
    pool: vk::QueryPool,
    period_ns: f64,
    mask: u64,
    /// Per label: total nanoseconds and how many times it was marked.
    pub(crate) totals: Vec<(&'static str, f64, u64)>,
}

/// One command buffer with its fence and descriptor pool (reset at the start of each of its
/// submissions); `pending` while a submission of it may still run.
pub(super) struct Frame {
    pub(super) cmd: vk::CommandBuffer,
    pub(super) fence: vk::Fence,
    pub(super) descriptors: vk::DescriptorPool,
    pub(super) pending: bool,
    /// Two timestamps around one pass of each submission ([`Recorder::stamp`]; null when
    /// the queue has none), and whether the last recording wrote both.
    pub(super) stamps: vk::QueryPool,
    pub(super) stamped: bool,
}

/// How many submissions may be in flight ([`Gpu::submit_on`]).
pub(crate) const FRAMES: usize = 2;

/// Command recording and submission state: [`FRAMES`] command buffers, each with a fence and
/// a descriptor pool. [`Gpu::submit`] records on frame 0 and waits; [`Gpu::submit_on`]
/// can queue a frame's commands and return, [`Gpu::wait`] waits for them. Every submission
/// starts with a full barrier, so the queue runs submissions one after the other.
pub(crate) struct Gpu {
    pub(super) device: Arc<Device>,
    pub(super) pool: vk::CommandPool,
    pub(super) frames: [Frame; FRAMES],
    pub(crate) timer: Option<Timer>,
}

impl Gpu {
    /// Starts timing the passes [`Recorder::mark`] names (a query pool of [`MAX_MARKS`]
    /// timestamps; only [`Self::submit`] times). Returns false, and times nothing, when the
    /// compute queue has no timestamps.
    pub fn enable_timestamps(&mut self) -> Result<bool, VulkanError> {
        if self.timer.is_some() {
            return Ok(true);
        }
        let info = &self.device.info;
        if info.timestamp_valid_bits == 0 || info.timestamp_period <= 0.0 {
            return Ok(false);
        }
        let ci = vk::QueryPoolCreateInfo::default()
            .query_type(vk::QueryType::TIMESTAMP)
            .query_count(MAX_MARKS);
        // SAFETY: valid create info for this device.
        let pool = unsafe { self.device.device.create_query_pool(&ci, None) }
            .map_err(|r| VulkanError::from_vk("vkCreateQueryPool", r, "timestamps", 0))?;
        let bits = info.timestamp_valid_bits;
        self.timer = Some(Timer {
            pool,
            period_ns: f64::from(info.timestamp_period),
            mask: if bits >= 64 {
                u64::MAX
            } else {
                (1u64 << bits) - 1
            },
            totals: Vec::new(),
        });
        Ok(true)
    }

    pub fn new(device: &Arc<Device>) -> Result<Self, VulkanError> {
        let d = &device.device;
        let ci = vk::CommandPoolCreateInfo::default()
            .queue_family_index(device.queue_family)
            .flags(vk::CommandPoolCreateFlags::RESET_COMMAND_BUFFER);
        // SAFETY: valid create info for this device's queue family.
        let pool = unsafe { d.create_command_pool(&ci, None) }
            .map_err(|r| VulkanError::from_vk("vkCreateCommandPool", r, "command pool", 0))?;
        // From here on `gpu`'s Drop cleans up whatever was created (null handles are skipped).
        let mut gpu = Self {
            device: device.clone(),
            pool,
            frames: core::array::from_fn(|_| Frame {
                cmd: vk::CommandBuffer::null(),
                fence: vk::Fence::null(),
                descriptors: vk::DescriptorPool::null(),
                pending: false,
                stamps: vk::QueryPool::null(),
                stamped: false,
            }),
            timer: None,
        };
        let ai = vk::CommandBufferAllocateInfo::default()
            .command_pool(pool)
            .level(vk::CommandBufferLevel::PRIMARY)
            .command_buffer_count(FRAMES as u32);
        // SAFETY: `pool` is live.
        let cmds = unsafe { d.allocate_command_buffers(&ai) }.map_err(|r| {
            VulkanError::from_vk("vkAllocateCommandBuffers", r, "command buffer", 0)
        })?;
        for (f, cmd) in gpu.frames.iter_mut().zip(cmds) {
            f.cmd = cmd;
            // SAFETY: valid (default) create info.
            f.fence = unsafe { d.create_fence(&vk::FenceCreateInfo::default(), None) }
                .map_err(|r| VulkanError::from_vk("vkCreateFence", r, "fence", 0))?;
            let sizes = [vk::DescriptorPoolSize {
                ty: vk::DescriptorType::STORAGE_BUFFER,
                descriptor_count: MAX_SETS * 16,
            }];
            let dci = vk::DescriptorPoolCreateInfo::default()
                .max_sets(MAX_SETS)
                .pool_sizes(&sizes);
            // SAFETY: valid create info.
            f.descriptors = unsafe { d.create_descriptor_pool(&dci, None) }.map_err(|r| {
                VulkanError::from_vk("vkCreateDescriptorPool", r, "descriptor pool", 0)
            })?;
            if device.info.timestamp_valid_bits > 0 && device.info.timestamp_period > 0.0 {
                let ci = vk::QueryPoolCreateInfo::default()
                    .query_type(vk::QueryType::TIMESTAMP)
                    .query_count(2);
                // SAFETY: valid create info for this device.
                f.stamps = unsafe { d.create_query_pool(&ci, None) }
                    .map_err(|r| VulkanError::from_vk("vkCreateQueryPool", r, "timestamps", 0))?;
            }
        }
        Ok(gpu)
    }

    pub fn device(&self) -> &Arc<Device> {
        &self.device
    }

    /// Records commands with `f`, submits them and waits for completion (after waiting for
    /// every queued frame). A final barrier makes every device write visible to the host.
    pub fn submit<'a, F>(&mut self, f: F) -> Result<(), VulkanError>
    where
        F: FnOnce(&mut Recorder<'a>) -> Result<(), VulkanError>,
    {
        self.submit_on(0, true, f)
    }

    /// Records commands with `f` on frame `frame` and submits them. With `wait`, as
    /// [`Self::submit`] (timed). Without, returns once they are queued (first waiting for the
    /// frame's previous submission; not timed) and [`Self::wait`] waits for them: the
    /// commands may reference only buffers that outlive that wait (a [`super::Buffer`]'s drop
    /// waits for the device, see the module documentation).
    pub fn submit_on<'a, F>(&mut self, frame: usize, wait: bool, f: F) -> Result<(), VulkanError>
    where
        F: FnOnce(&mut Recorder<'a>) -> Result<(), VulkanError>,
    {
        #[cfg(feature = "fault-injection")]
        crate::fault::submit()?;
        if !wait {
            self.wait(frame)?;
            self.record(frame, false, f)?;
            return self.queue(frame);
        }
        self.wait_all()?;
        let marks = self.record(frame, true, f)?;
        self.queue(frame)?;
        self.wait(frame)?;
        self.read_timestamps(&marks)
    }

    /// The device time (ns) between the two [`Recorder::stamp`]s of frame `frame`'s last
    /// submission, once waited for; `None` when it did not write both or the queue has no
    /// timestamps.
    pub fn stamp_ns(&self, frame: usize) -> Result<Option<f64>, VulkanError> {
        let fr = &self.frames[frame];
        if fr.pending || !fr.stamped || fr.stamps == vk::QueryPool::null() {
            return Ok(None);
        }
        let info = &self.device.info;
        let mut ticks = [0u64; 2];
        // SAFETY: both queries were written by the submission that was waited for.
        unsafe {
            self.device.device.get_query_pool_results(
                fr.stamps,
                0,
                &mut ticks,
                vk::QueryResultFlags::TYPE_64 | vk::QueryResultFlags::WAIT,
            )
        }
        .map_err(|r| VulkanError::from_vk("vkGetQueryPoolResults", r, "timestamps", 0))?;
        let mask = match info.timestamp_valid_bits {
            b if b >= 64 => u64::MAX,
            b => (1u64 << b) - 1,
        };
        let dt = (ticks[1] & mask).wrapping_sub(ticks[0] & mask) & mask;
        Ok(Some(dt as f64 * f64::from(info.timestamp_period)))
    }

    /// Whether frame `frame` has a submission that was not waited for.
    pub fn pending(&self, frame: usize) -> bool {
        self.frames[frame].pending
    }

    /// Waits for every pending frame.
    pub fn wait_all(&mut self) -> Result<(), VulkanError> {
        for f in 0..FRAMES {
            self.wait(f)?;
        }
        Ok(())
    }

    /// Resets frame `frame` and records `f` into it (timestamps when `timed` and timing).
    fn record<'a, F>(
        &mut self,
        frame: usize,
        timed: bool,
        f: F,
    ) -> Result<Vec<&'static str>, VulkanError>
    where
        F: FnOnce(&mut Recorder<'a>) -> Result<(), VulkanError>,
    {
        let d = &self.device.device;
        let fr = &self.frames[frame];
        debug_assert!(!fr.pending);
        let stamps = fr.stamps;
        // SAFETY: the frame's previous submission was waited for, so neither its command
        // buffer nor any descriptor set of its pool is in use.
        unsafe {
            d.reset_descriptor_pool(fr.descriptors, vk::DescriptorPoolResetFlags::empty())
                .map_err(|r| VulkanError::from_vk("vkResetDescriptorPool", r, "", 0))?;
            d.reset_command_buffer(fr.cmd, vk::CommandBufferResetFlags::empty())
                .map_err(|r| VulkanError::from_vk("vkResetCommandBuffer", r, "", 0))?;
            d.begin_command_buffer(
                fr.cmd,
                &vk::CommandBufferBeginInfo::default()
                    .flags(vk::CommandBufferUsageFlags::ONE_TIME_SUBMIT),
            )
            .map_err(|r| VulkanError::from_vk("vkBeginCommandBuffer", r, "", 0))?;
        }
        let timer = self.timer.as_ref().filter(|_| timed);
        let mut rec = Recorder {
            device: self.device.clone(),
            _borrow: std::marker::PhantomData,
            cmd: fr.cmd,
            descriptors: fr.descriptors,
            sets: 0,
            timestamps: timer.map_or(vk::QueryPool::null(), |t| t.pool),
            marks: Vec::new(),
            stamps,
            stamps_written: 0,
        };
        // The queue's earlier submissions (and the host's writes before this submission)
        // complete before anything recorded here.
        rec.barrier();
        if stamps != vk::QueryPool::null() {
            // SAFETY: recording state; the frame's pool is not in use (its previous
            // submission was waited for).
            unsafe { d.cmd_reset_query_pool(fr.cmd, stamps, 0, 2) };
        }
        if let Some(t) = timer {
            // SAFETY: recording state; the pool has MAX_MARKS queries and is not in use (only
            // the waited-for `submit` uses it).
            unsafe {
                d.cmd_reset_query_pool(fr.cmd, t.pool, 0, MAX_MARKS);
                d.cmd_write_timestamp(fr.cmd, vk::PipelineStageFlags::TOP_OF_PIPE, t.pool, 0);
            }
        }
        let recorded = f(&mut rec);
        let marks = std::mem::take(&mut rec.marks);
        let stamped = rec.stamps_written == 2;
        rec.barrier_to_host();
        // SAFETY: the command buffer is in the recording state.
        let ended = unsafe { d.end_command_buffer(fr.cmd) }
            .map_err(|r| VulkanError::from_vk("vkEndCommandBuffer", r, "", 0));
        self.frames[frame].stamped = stamped;
        recorded?;
        ended?;
        Ok(marks)
    }

    /// Submits frame `frame`'s recorded commands.
    fn queue(&mut self, frame: usize) -> Result<(), VulkanError> {
        let d = &self.device.device;
        let fr = &mut self.frames[frame];
        let cmds = [fr.cmd];
        let si = [vk::SubmitInfo::default().command_buffers(&cmds)];
        // SAFETY: the command buffer is executable, the fence unsignalled; every buffer and
        // pipeline it references outlives the wait for this frame (see `submit_on`).
        unsafe { d.queue_submit(self.device.queue, &si, fr.fence) }
            .map_err(|r| VulkanError::from_vk("vkQueueSubmit", r, "a submission", 0))?;
        fr.pending = true;
        Ok(())
    }

    /// Waits for frame `frame`'s submission (nothing when none is pending).
    pub fn wait(&mut self, frame: usize) -> Result<(), VulkanError> {
        let d = &self.device.device;
        let fr = &mut self.frames[frame];
        if !fr.pending {
            return Ok(());
        }
        // SAFETY: the fence belongs to this device.
        let waited = unsafe { d.wait_for_fences(&[fr.fence], true, TIMEOUT_S * 1_000_000_000) };
        match waited {
            Ok(()) => {}
            Err(vk::Result::TIMEOUT) => {
                // The work may still complete; wait for the device so that the next submit
                // does not reset a pending fence.
                // SAFETY: waiting is always allowed.
                let _ = unsafe { d.device_wait_idle() };
                let _ = unsafe { d.reset_fences(&[fr.fence]) };
                fr.pending = false;
                return Err(VulkanError::Timeout { seconds: TIMEOUT_S });
            }
            Err(r) => return Err(VulkanError::from_vk("vkWaitForFences", r, "", 0)),
        }
        fr.pending = false;
        // SAFETY: the fence is signalled and no longer used by any pending submission.
        unsafe { d.reset_fences(&[fr.fence]) }
            .map_err(|r| VulkanError::from_vk("vkResetFences", r, "", 0))
    }

    /// Adds the timestamps of the submission just waited for to the timer's totals.
    fn read_timestamps(&mut self, marks: &[&'static str]) -> Result<(), VulkanError> {
        let d = &self.device.device;
        if let (Some(t), false) = (self.timer.as_mut(), marks.is_empty()) {
            let mut ticks = vec![0u64; marks.len() + 1];
            // SAFETY: queries 0..=marks.len() were written in the submission just waited for.
            unsafe {
                d.get_query_pool_results(
                    t.pool,
                    0,
                    &mut ticks,
                    vk::QueryResultFlags::TYPE_64 | vk::QueryResultFlags::WAIT,
                )
            }
            .map_err(|r| VulkanError::from_vk("vkGetQueryPoolResults", r, "timestamps", 0))?;
            for (i, label) in marks.iter().enumerate() {
                let dt = (ticks[i + 1] & t.mask).wrapping_sub(ticks[i] & t.mask) & t.mask;
                let ns = dt as f64 * t.period_ns;
                match t.totals.iter_mut().find(|e| e.0 == *label) {
                    Some(e) => {
                        e.1 += ns;
                        e.2 += 1;
                    }
                    None => t.totals.push((label, ns, 1)),
                }
            }
        }
        Ok(())
    }
}

impl Drop for Gpu {
    fn drop(&mut self) {
        let d = &self.device.device;
        // SAFETY: waiting for idle covers every pending frame; null handles are valid no-ops
        // for the destroy calls.
        unsafe {
            let _ = d.device_wait_idle();
            if let Some(t) = &self.timer {
                d.destroy_query_pool(t.pool, None);
            }
            for f in &self.frames {
                if f.stamps != vk::QueryPool::null() {
                    d.destroy_query_pool(f.stamps, None);
                }
                d.destroy_descriptor_pool(f.descriptors, None);
                d.destroy_fence(f.fence, None);
            }
            d.destroy_command_pool(self.pool, None);
        }
    }
}

/// Records into the command buffer of one [`Gpu::submit`] or [`Gpu::submit_on`].
pub(crate) struct Recorder<'a> {
    pub(super) device: Arc<Device>,
    pub(super) _borrow: std::marker::PhantomData<&'a ()>,
    pub(super) cmd: vk::CommandBuffer,
    pub(super) descriptors: vk::DescriptorPool,
    pub(super) sets: u32,
    /// The timer's query pool (null: not timing) and the labels marked so far.
    pub(super) timestamps: vk::QueryPool,
    pub(super) marks: Vec<&'static str>,
    /// The frame's two-timestamp pool ([`Self::stamp`]) and how many were written.
    pub(super) stamps: vk::QueryPool,
    pub(super) stamps_written: u32,
}

impl<'a> Recorder<'a> {
    /// Ends the pass named `label` for the timer: a timestamp once everything recorded
    /// before has completed (nothing when not timing, or past [`MAX_MARKS`]).
    pub fn mark(&mut self, label: &'static str) {
        if self.timestamps == vk::QueryPool::null() || self.marks.len() + 1 >= MAX_MARKS as usize {
            return;
        }
        self.marks.push(label);
        // SAFETY: recording state; query `marks.len()` of the pool was reset at the start of
        // this submission and is written once.
        unsafe {
            self.device.device.cmd_write_timestamp(
                self.cmd,
                vk::PipelineStageFlags::BOTTOM_OF_PIPE,
                self.timestamps,
                self.marks.len() as u32,
            )
        };
    }

    /// Writes the next timestamp of the frame's pair (the first before a pass, the second
    /// after it and its barrier; [`Gpu::stamp_ns`]); nothing when the queue has no
    /// timestamps or both are written.
    pub fn stamp(&mut self) {
        if self.stamps == vk::QueryPool::null() || self.stamps_written >= 2 {
            return;
        }
        // SAFETY: recording state; the pool's two queries were reset at the start of this
        // recording and each is written once.
        unsafe {
            self.device.device.cmd_write_timestamp(
                self.cmd,
                vk::PipelineStageFlags::BOTTOM_OF_PIPE,
                self.stamps,
                self.stamps_written,
            )
        };
        self.stamps_written += 1;
    }

    /// Fills a buffer with zeros.
    pub fn zero(&mut self, buffer: &'a Buffer) {
        // SAFETY: recording state; the buffer has TRANSFER_DST usage and lives for `'a`.
        unsafe {
            self.device
                .device
                .cmd_fill_buffer(self.cmd, buffer.buffer, 0, vk::WHOLE_SIZE, 0)
        };
    }

    /// Fills `size` bytes of a buffer from `offset` (both multiples of 4) with zeros.
    pub fn zero_range(&mut self, buffer: &'a Buffer, offset: u64, size: u64) {
        // SAFETY: recording state; the buffer has TRANSFER_DST usage and lives for `'a`;
        // callers keep the range inside the buffer.
        unsafe {
            self.device
                .device
                .cmd_fill_buffer(self.cmd, buffer.buffer, offset, size, 0)
        };
    }

    /// Copies `size` bytes between buffers.
    pub fn copy(
        &mut self,
        src: &'a Buffer,
        src_offset: u64,
        dst: &'a Buffer,
        dst_offset: u64,
        size: u64,
    ) {
        let region = [vk::BufferCopy {
            src_offset,
            dst_offset,
            size,
        }];
        // SAFETY: recording state; both buffers have the transfer usages and live for `'a`;
        // callers keep the ranges inside the buffers.
        unsafe {
            self.device
                .device
                .cmd_copy_buffer(self.cmd, src.buffer, dst.buffer, &region)
        };
    }

    /// A full memory barrier between everything before and everything after.
    pub fn barrier(&mut self) {
        let mb = [vk::MemoryBarrier::default()
            .src_access_mask(vk::AccessFlags::MEMORY_WRITE)
            .dst_access_mask(vk::AccessFlags::MEMORY_READ | vk::AccessFlags::MEMORY_WRITE)];
        // SAFETY: recording state; a global memory barrier has no other preconditions.
        unsafe {
            self.device.device.cmd_pipeline_barrier(
                self.cmd,
                vk::PipelineStageFlags::ALL_COMMANDS,
                vk::PipelineStageFlags::ALL_COMMANDS,
                vk::DependencyFlags::empty(),
                &mb,
                &[],
                &[],
            )
        };
    }

    fn barrier_to_host(&mut self) {
        let mb = [vk::MemoryBarrier::default()
            .src_access_mask(vk::AccessFlags::MEMORY_WRITE)
            .dst_access_mask(vk::AccessFlags::HOST_READ)];
        // SAFETY: as in `barrier`.
        unsafe {
            self.device.device.cmd_pipeline_barrier(
                self.cmd,
                vk::PipelineStageFlags::ALL_COMMANDS,
                vk::PipelineStageFlags::HOST,
                vk::DependencyFlags::empty(),
                &mb,
                &[],
                &[],
            )
        };
    }

    /// Allocates and writes a descriptor set binding `buffers[i]` at binding `i`.
    pub fn bind(
        &mut self,
        pipeline: &Pipeline,
        buffers: &[&'a Buffer],
    ) -> Result<Set<'a>, VulkanError> {
        if buffers.len() != pipeline.bindings as usize {
            return Err(VulkanError::Vk {
                call: "binding buffers (wrong count for the pipeline)",
                result: vk::Result::ERROR_UNKNOWN,
                what: String::new(),
            });
        }
        if self.sets >= MAX_SETS {
            return Err(VulkanError::Vk {
                call: "allocating a descriptor set (too many in one submission)",
                result: vk::Result::ERROR_OUT_OF_POOL_MEMORY,
                what: String::new(),
            });
        }
        let d = &self.device.device;
        let layouts = [pipeline.set_layout];
        let ai = vk::DescriptorSetAllocateInfo::default()
            .descriptor_pool(self.descriptors)
            .set_layouts(&layouts);
        // SAFETY: the pool is live and was sized for MAX_SETS sets of up to 16 bindings.
        let set = unsafe { d.allocate_descriptor_sets(&ai) }
            .map_err(|r| VulkanError::from_vk("vkAllocateDescriptorSets", r, "", 0))?[0];
        self.sets += 1;
        let infos: Vec<[vk::DescriptorBufferInfo; 1]> = buffers
            .iter()
            .map(|b| {
                [vk::DescriptorBufferInfo {
                    buffer: b.buffer,
                    offset: 0,
                    range: vk::WHOLE_SIZE,
                }]
            })
            .collect();
        let writes: Vec<_> = infos
            .iter()
            .enumerate()
            .map(|(i, info)| {
                vk::WriteDescriptorSet::default()
                    .dst_set(set)
                    .dst_binding(i as u32)
                    .descriptor_type(vk::DescriptorType::STORAGE_BUFFER)
                    .buffer_info(info)
            })
            .collect();
        // SAFETY: `set` is freshly allocated and not in use; every buffer is a live storage
        // buffer (the backend checks sizes against maxStorageBufferRange before creating them).
        unsafe { d.update_descriptor_sets(&writes, &[]) };
        Ok(Set {
            set,
            _borrow: std::marker::PhantomData,
        })
    }

    /// Binds `pipeline` and `set`, pushes `push` (exactly the pipeline's push size) and
    /// dispatches `groups` workgroups along x.
    pub fn dispatch(&mut self, pipeline: &'a Pipeline, set: &Set<'a>, push: &[u8], groups: u32) {
        if push.len() != pipeline.push_size as usize || groups == 0 {
            return;
        }
        let d = &self.device.device;
        // SAFETY: recording state; the set was allocated for this pipeline's set layout; the
        // push range matches the pipeline layout; `groups` is within the device limit (callers
        // split dispatches by `max_workgroup_count_x`).
        unsafe {
            d.cmd_bind_pipeline(self.cmd, vk::PipelineBindPoint::COMPUTE, pipeline.pipeline);
            d.cmd_bind_descriptor_sets(
                self.cmd,
                vk::PipelineBindPoint::COMPUTE,
                pipeline.layout,
                0,
                &[set.set],
                &[],
            );
            d.cmd_push_constants(
                self.cmd,
                pipeline.layout,
                vk::ShaderStageFlags::COMPUTE,
                0,
                push,
            );
            d.cmd_dispatch(self.cmd, groups, 1, 1);
        }
    }
}

/// A descriptor set valid for one submission.
pub(crate) struct Set<'a> {
    pub(super) set: vk::DescriptorSet,
    pub(super) _borrow: std::marker::PhantomData<&'a ()>,
}
