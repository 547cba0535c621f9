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

/// Command recording and submission state: one command buffer, a fence and a descriptor pool
/// that is reset at the start of every submission.
pub(crate) struct Gpu {
    pub(super) device: Arc<Device>,
    pub(super) pool: vk::CommandPool,
    pub(super) cmd: vk::CommandBuffer,
    pub(super) fence: vk::Fence,
    pub(super) descriptors: vk::DescriptorPool,
    pub(crate) timer: Option<Timer>,
}

impl Gpu {
    /// Starts timing the passes [`Recorder::mark`] names (a query pool of [`MAX_MARKS`]
    /// timestamps). Returns false, and times nothing, when the compute queue has no
    /// timestamps.
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
            cmd: vk::CommandBuffer::null(),
            fence: vk::Fence::null(),
            descriptors: vk::DescriptorPool::null(),
            timer: None,
        };
        let ai = vk::CommandBufferAllocateInfo::default()
            .command_pool(pool)
            .level(vk::CommandBufferLevel::PRIMARY)
            .command_buffer_count(1);
        // SAFETY: `pool` is live.
        gpu.cmd = unsafe { d.allocate_command_buffers(&ai) }.map_err(|r| {
            VulkanError::from_vk("vkAllocateCommandBuffers", r, "command buffer", 0)
        })?[0];
        // SAFETY: valid (default) create info.
        gpu.fence = unsafe { d.create_fence(&vk::FenceCreateInfo::default(), None) }
            .map_err(|r| VulkanError::from_vk("vkCreateFence", r, "fence", 0))?;
        let sizes = [vk::DescriptorPoolSize {
            ty: vk::DescriptorType::STORAGE_BUFFER,
            descriptor_count: MAX_SETS * 16,
        }];
        let dci = vk::DescriptorPoolCreateInfo::default()
            .max_sets(MAX_SETS)
            .pool_sizes(&sizes);
        // SAFETY: valid create info.
        gpu.descriptors = unsafe { d.create_descriptor_pool(&dci, None) }
            .map_err(|r| VulkanError::from_vk("vkCreateDescriptorPool", r, "descriptor pool", 0))?;
        Ok(gpu)
    }

    pub fn device(&self) -> &Arc<Device> {
        &self.device
    }

    /// Records commands with `f`, submits them and waits for completion. A final barrier
    /// makes every device write visible to the host.
    pub fn submit<'a, F>(&mut self, f: F) -> Result<(), VulkanError>
    where
        F: FnOnce(&mut Recorder<'a>) -> Result<(), VulkanError>,
    {
        #[cfg(feature = "fault-injection")]
        crate::fault::submit()?;
        let d = &self.device.device;
        // SAFETY: the previous submission was waited for, so neither the command buffer nor
        // any descriptor set of the pool is in use.
        unsafe {
            d.reset_descriptor_pool(self.descriptors, vk::DescriptorPoolResetFlags::empty())
                .map_err(|r| VulkanError::from_vk("vkResetDescriptorPool", r, "", 0))?;
            d.reset_command_buffer(self.cmd, vk::CommandBufferResetFlags::empty())
                .map_err(|r| VulkanError::from_vk("vkResetCommandBuffer", r, "", 0))?;
            d.begin_command_buffer(
                self.cmd,
                &vk::CommandBufferBeginInfo::default()
                    .flags(vk::CommandBufferUsageFlags::ONE_TIME_SUBMIT),
            )
            .map_err(|r| VulkanError::from_vk("vkBeginCommandBuffer", r, "", 0))?;
        }
        let mut rec = Recorder {
            device: self.device.clone(),
            _borrow: std::marker::PhantomData,
            cmd: self.cmd,
            descriptors: self.descriptors,
            sets: 0,
            timestamps: self
                .timer
                .as_ref()
                .map_or(vk::QueryPool::null(), |t| t.pool),
            marks: Vec::new(),
        };
        if let Some(t) = &self.timer {
            // SAFETY: recording state; the pool has MAX_MARKS queries and is not in use (the
            // previous submission was waited for).
            unsafe {
                d.cmd_reset_query_pool(self.cmd, t.pool, 0, MAX_MARKS);
                d.cmd_write_timestamp(self.cmd, vk::PipelineStageFlags::TOP_OF_PIPE, t.pool, 0);
            }
        }
        let recorded = f(&mut rec);
        let marks = std::mem::take(&mut rec.marks);
        rec.barrier_to_host();
        // SAFETY: the command buffer is in the recording state.
        let ended = unsafe { d.end_command_buffer(self.cmd) }
            .map_err(|r| VulkanError::from_vk("vkEndCommandBuffer", r, "", 0));
        recorded?;
        ended?;
        let cmds = [self.cmd];
        let si = [vk::SubmitInfo::default().command_buffers(&cmds)];
        // SAFETY: the command buffer is executable, the fence unsignalled; every buffer and
        // pipeline it references is borrowed for `'a`, which spans this whole call.
        unsafe { d.queue_submit(self.device.queue, &si, self.fence) }
            .map_err(|r| VulkanError::from_vk("vkQueueSubmit", r, "a submission", 0))?;
        // SAFETY: the fence belongs to this device.
        let waited = unsafe { d.wait_for_fences(&[self.fence], true, TIMEOUT_S * 1_000_000_000) };
        match waited {
            Ok(()) => {}
            Err(vk::Result::TIMEOUT) => {
                // Leave the fence alone: the work may still complete; the next submit would
                // reset a pending fence, so wait for the device instead.
                // SAFETY: waiting is always allowed.
                let _ = unsafe { d.device_wait_idle() };
                let _ = unsafe { d.reset_fences(&[self.fence]) };
                return Err(VulkanError::Timeout { seconds: TIMEOUT_S });
            }
            Err(r) => return Err(VulkanError::from_vk("vkWaitForFences", r, "", 0)),
        }
        // SAFETY: the fence is signalled and no longer used by any pending submission.
        unsafe { d.reset_fences(&[self.fence]) }
            .map_err(|r| VulkanError::from_vk("vkResetFences", r, "", 0))?;
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
        // SAFETY: no submission is pending (each is waited for; waiting for idle once more
        // covers a timed-out one); null handles are valid no-ops for the destroy calls.
        unsafe {
            let _ = d.device_wait_idle();
            if let Some(t) = &self.timer {
                d.destroy_query_pool(t.pool, None);
            }
            d.destroy_descriptor_pool(self.descriptors, None);
            d.destroy_fence(self.fence, None);
            d.destroy_command_pool(self.pool, None);
        }
    }
}

/// Records into the command buffer of one [`Gpu::submit`].
pub(crate) struct Recorder<'a> {
    pub(super) device: Arc<Device>,
    pub(super) _borrow: std::marker::PhantomData<&'a ()>,
    pub(super) cmd: vk::CommandBuffer,
    pub(super) descriptors: vk::DescriptorPool,
    pub(super) sets: u32,
    /// The timer's query pool (null: not timing) and the labels marked so far.
    pub(super) timestamps: vk::QueryPool,
    pub(super) marks: Vec<&'static str>,
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

    /// Fills a buffer with zeros.
    pub fn zero(&mut self, buffer: &'a Buffer) {
        // SAFETY: recording state; the buffer has TRANSFER_DST usage and lives for `'a`.
        unsafe {
            self.device
                .device
                .cmd_fill_buffer(self.cmd, buffer.buffer, 0, vk::WHOLE_SIZE, 0)
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
            });
        }
        if self.sets >= MAX_SETS {
            return Err(VulkanError::Vk {
                call: "allocating a descriptor set (too many in one submission)",
                result: vk::Result::ERROR_OUT_OF_POOL_MEMORY,
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
