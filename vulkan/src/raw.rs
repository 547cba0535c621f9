//! Every `unsafe` ash call of the crate, behind safe RAII types. Nothing outside this module
//! uses `unsafe` (the crate root denies it).
//!
//! Ownership: [`Instance`] owns the loader and the `VkInstance`; [`Device`] (always in an
//! `Arc`) owns the `VkDevice` and keeps its instance alive; [`Buffer`], [`Pipeline`] and
//! [`Gpu`] (command pool, command buffer, fence, descriptor pool) each hold an
//! `Arc<Device>`, so the device is destroyed only after every object created from it.
//!
//! Synchronisation: work is recorded into one command buffer by [`Gpu::submit`], submitted and
//! waited for before `submit` returns, so no recorded buffer or descriptor set is in use once
//! a safe call returns. Buffers referenced by a recording borrow for the recorder's lifetime,
//! which spans the whole submission.
#![allow(unsafe_code)]

use crate::error::VulkanError;
use ash::vk;
use std::ffi::CString;
use std::sync::Arc;

/// What the backend needs from a physical device, and what it has.
#[derive(Clone, Debug, PartialEq)]
pub(crate) struct PhysicalInfo {
    pub handle: vk::PhysicalDevice,
    pub name: String,
    pub device_type: vk::PhysicalDeviceType,
    pub api_version: u32,
    pub driver_version: u32,
    pub max_storage_buffer_range: u32,
    pub max_memory_allocation_size: u64,
    pub max_push_constants_size: u32,
    pub max_per_stage_storage_buffers: u32,
    pub max_workgroup_count_x: u32,
    pub device_local_bytes: u64,
    pub compute_queue_family: Option<u32>,
    pub shader_int64: bool,
    pub shader_buffer_int64_atomics: bool,
    pub vulkan_memory_model: bool,
}

impl PhysicalInfo {
    /// Names of the required features this device lacks (empty: usable).
    pub fn missing(&self) -> Vec<&'static str> {
        let mut m = Vec::new();
        if self.api_version < vk::API_VERSION_1_2 {
            m.push("Vulkan 1.2");
        }
        if !self.shader_int64 {
            m.push("shaderInt64");
        }
        if !self.shader_buffer_int64_atomics {
            m.push("shaderBufferInt64Atomics");
        }
        if !self.vulkan_memory_model {
            m.push("vulkanMemoryModel");
        }
        if self.compute_queue_family.is_none() {
            m.push("a compute queue");
        }
        if self.max_per_stage_storage_buffers < 17 {
            m.push("17 storage buffers per stage");
        }
        if self.max_push_constants_size < 32 {
            m.push("32 bytes of push constants");
        }
        m
    }
}

/// The loader and a Vulkan 1.2 instance.
pub(crate) struct Instance {
    _entry: ash::Entry,
    instance: ash::Instance,
}

impl Instance {
    pub fn new() -> Result<Arc<Self>, VulkanError> {
        // SAFETY: loading the system's Vulkan loader runs its initialisation code; we trust the
        // installed loader (the same assumption every Vulkan program makes). The returned
        // `Entry` keeps the library loaded for as long as it lives, and `Instance` owns it.
        let entry =
            unsafe { ash::Entry::load() }.map_err(|e| VulkanError::NoLoader(e.to_string()))?;
        // SAFETY: `entry` is a loaded loader; the call has no preconditions beyond that.
        let version = match unsafe { entry.try_enumerate_instance_version() } {
            Ok(Some(v)) => v,
            Ok(None) => vk::API_VERSION_1_0,
            Err(r) => return Err(VulkanError::Instance(r)),
        };
        if version < vk::API_VERSION_1_2 {
            return Err(VulkanError::ApiTooOld {
                found: version_string(version),
            });
        }
        let app_name = c"himap";
        let app = vk::ApplicationInfo::default()
            .application_name(app_name)
            .application_version(1)
            .engine_name(app_name)
            .api_version(vk::API_VERSION_1_2);
        let ci = vk::InstanceCreateInfo::default().application_info(&app);
        // SAFETY: `ci` and `app` are valid, fully initialised structures that outlive the call;
        // no extensions or layers are requested.
        let instance =
            unsafe { entry.create_instance(&ci, None) }.map_err(VulkanError::Instance)?;
        Ok(Arc::new(Self {
            _entry: entry,
            instance,
        }))
    }

    /// Every physical device with its properties, limits and the features we need.
    pub fn physical_devices(&self) -> Result<Vec<PhysicalInfo>, VulkanError> {
        // SAFETY: `self.instance` is a live instance.
        let handles = unsafe { self.instance.enumerate_physical_devices() }
            .map_err(|r| VulkanError::from_vk("vkEnumeratePhysicalDevices", r, "", 0))?;
        let mut out = Vec::with_capacity(handles.len());
        for pd in handles {
            // SAFETY: `pd` was just enumerated from this live instance.
            let props = unsafe { self.instance.get_physical_device_properties(pd) };
            let name = props
                .device_name_as_c_str()
                .map(|s| s.to_string_lossy().into_owned())
                .unwrap_or_else(|_| "<unnamed>".to_string());
            let mut maint3 = vk::PhysicalDeviceMaintenance3Properties::default();
            let (mut shader_int64, mut atomics64, mut memory_model) = (false, false, false);
            if props.api_version >= vk::API_VERSION_1_1 {
                let mut p2 = vk::PhysicalDeviceProperties2::default().push_next(&mut maint3);
                // SAFETY: the device supports Vulkan 1.1 (core `vkGetPhysicalDeviceProperties2`)
                // and the instance is 1.2; `p2` chains only structures of Vulkan 1.1 core.
                unsafe { self.instance.get_physical_device_properties2(pd, &mut p2) };
            }
            if props.api_version >= vk::API_VERSION_1_2 {
                let mut v12 = vk::PhysicalDeviceVulkan12Features::default();
                let mut f2 = vk::PhysicalDeviceFeatures2::default().push_next(&mut v12);
                // SAFETY: the device supports Vulkan 1.2, so the 1.2 feature structure is a
                // valid member of the chain; both live across the call.
                unsafe { self.instance.get_physical_device_features2(pd, &mut f2) };
                shader_int64 = f2.features.shader_int64 == vk::TRUE;
                atomics64 = v12.shader_buffer_int64_atomics == vk::TRUE;
                memory_model = v12.vulkan_memory_model == vk::TRUE;
            }
            // SAFETY: `pd` is a valid physical device of this instance.
            let families = unsafe {
                self.instance
                    .get_physical_device_queue_family_properties(pd)
            };
            let compute_queue_family = families
                .iter()
                .position(|f| f.queue_flags.contains(vk::QueueFlags::COMPUTE) && f.queue_count > 0)
                .map(|i| i as u32);
            // SAFETY: as above.
            let mem = unsafe { self.instance.get_physical_device_memory_properties(pd) };
            let device_local_bytes = mem.memory_heaps[..mem.memory_heap_count as usize]
                .iter()
                .filter(|h| h.flags.contains(vk::MemoryHeapFlags::DEVICE_LOCAL))
                .map(|h| h.size)
                .max()
                .unwrap_or(0);
            let max_alloc = if maint3.max_memory_allocation_size > 0 {
                maint3.max_memory_allocation_size
            } else {
                u64::MAX
            };
            out.push(PhysicalInfo {
                handle: pd,
                name,
                device_type: props.device_type,
                api_version: props.api_version,
                driver_version: props.driver_version,
                max_storage_buffer_range: props.limits.max_storage_buffer_range,
                max_memory_allocation_size: max_alloc,
                max_push_constants_size: props.limits.max_push_constants_size,
                max_per_stage_storage_buffers: props
                    .limits
                    .max_per_stage_descriptor_storage_buffers,
                max_workgroup_count_x: props.limits.max_compute_work_group_count[0],
                device_local_bytes,
                compute_queue_family,
                shader_int64,
                shader_buffer_int64_atomics: atomics64,
                vulkan_memory_model: memory_model,
            });
        }
        Ok(out)
    }
}

impl Drop for Instance {
    fn drop(&mut self) {
        // SAFETY: every device created from this instance holds an `Arc<Instance>`, so none is
        // alive any more; the instance is destroyed exactly once.
        unsafe { self.instance.destroy_instance(None) };
    }
}

/// `major.minor.patch` of a packed Vulkan version.
pub(crate) fn version_string(v: u32) -> String {
    format!(
        "{}.{}.{}",
        vk::api_version_major(v),
        vk::api_version_minor(v),
        vk::api_version_patch(v)
    )
}

/// A logical device with one compute queue.
pub(crate) struct Device {
    instance: Arc<Instance>,
    device: ash::Device,
    queue: vk::Queue,
    queue_family: u32,
    memory: vk::PhysicalDeviceMemoryProperties,
    pub info: PhysicalInfo,
}

impl Device {
    /// Creates the device with the features the shaders need (the caller checked
    /// `info.missing()` is empty).
    pub fn new(instance: Arc<Instance>, info: PhysicalInfo) -> Result<Arc<Self>, VulkanError> {
        let missing = info.missing();
        if !missing.is_empty() {
            return Err(VulkanError::MissingFeature {
                device: info.name.clone(),
                missing,
            });
        }
        let queue_family = info.compute_queue_family.unwrap_or(0);
        let priorities = [1.0f32];
        let qci = [vk::DeviceQueueCreateInfo::default()
            .queue_family_index(queue_family)
            .queue_priorities(&priorities)];
        let mut v12 = vk::PhysicalDeviceVulkan12Features::default()
            .vulkan_memory_model(true)
            .shader_buffer_int64_atomics(true);
        let mut f2 = vk::PhysicalDeviceFeatures2::default()
            .features(vk::PhysicalDeviceFeatures::default().shader_int64(true))
            .push_next(&mut v12);
        let ci = vk::DeviceCreateInfo::default()
            .queue_create_infos(&qci)
            .push_next(&mut f2);
        // SAFETY: `info.handle` belongs to `instance` (both come from
        // `Instance::physical_devices`); the requested features were reported as supported;
        // every structure in `ci` lives across the call; `pEnabledFeatures` is null because
        // the features travel in the `PhysicalDeviceFeatures2` chain.
        let device = unsafe { instance.instance.create_device(info.handle, &ci, None) }
            .map_err(|r| VulkanError::from_vk("vkCreateDevice", r, "the logical device", 0))?;
        // SAFETY: queue 0 of `queue_family` was requested in `ci`.
        let queue = unsafe { device.get_device_queue(queue_family, 0) };
        // SAFETY: `info.handle` is a valid physical device of `instance`.
        let memory = unsafe {
            instance
                .instance
                .get_physical_device_memory_properties(info.handle)
        };
        Ok(Arc::new(Self {
            instance,
            device,
            queue,
            queue_family,
            memory,
            info,
        }))
    }

    /// Index of a memory type allowed by `bits` with all of `want`, preferring those that also
    /// have `prefer`.
    fn memory_type(
        &self,
        bits: u32,
        want: vk::MemoryPropertyFlags,
        prefer: vk::MemoryPropertyFlags,
    ) -> Option<(u32, vk::MemoryPropertyFlags)> {
        let n = self.memory.memory_type_count as usize;
        let ok = |i: usize, f: vk::MemoryPropertyFlags| {
            bits & (1 << i) != 0 && self.memory.memory_types[i].property_flags.contains(f)
        };
        (0..n)
            .find(|&i| ok(i, want | prefer))
            .or_else(|| (0..n).find(|&i| ok(i, want)))
            .map(|i| (i as u32, self.memory.memory_types[i].property_flags))
    }
}

impl Drop for Device {
    fn drop(&mut self) {
        // SAFETY: every object created from this device holds an `Arc<Device>`, so all of them
        // are destroyed; waiting first makes sure no queue work is pending.
        unsafe {
            let _ = self.device.device_wait_idle();
            self.device.destroy_device(None);
        }
        let _ = &self.instance;
    }
}

/// Where a buffer's memory lives.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Memory {
    /// Device-local (mapped too when the device-local type is host-visible, as on integrated
    /// and CPU devices).
    Device,
    /// Host-visible and coherent (staging, per-batch inputs and outputs).
    Host,
}

/// A storage buffer with its own memory allocation.
pub(crate) struct Buffer {
    device: Arc<Device>,
    buffer: vk::Buffer,
    memory: vk::DeviceMemory,
    size: u64,
    /// Host address of the whole allocation when mapped, as an address (not a pointer) so the
    /// type stays `Send`.
    mapped: Option<usize>,
}

impl Buffer {
    /// A buffer of `size` bytes (at least 16) usable as storage buffer and copy source/target.
    pub fn new(
        device: &Arc<Device>,
        size: u64,
        memory: Memory,
        what: &str,
    ) -> Result<Self, VulkanError> {
        let size = size.max(16).next_multiple_of(8);
        let d = &device.device;
        let ci = vk::BufferCreateInfo::default()
            .size(size)
            .usage(
                vk::BufferUsageFlags::STORAGE_BUFFER
                    | vk::BufferUsageFlags::TRANSFER_SRC
                    | vk::BufferUsageFlags::TRANSFER_DST,
            )
            .sharing_mode(vk::SharingMode::EXCLUSIVE);
        // SAFETY: `ci` is a valid create info with a non-zero size.
        let buffer = unsafe { d.create_buffer(&ci, None) }
            .map_err(|r| VulkanError::from_vk("vkCreateBuffer", r, what, size))?;
        // SAFETY: `buffer` was just created from `d`.
        let req = unsafe { d.get_buffer_memory_requirements(buffer) };
        let coherent =
            vk::MemoryPropertyFlags::HOST_VISIBLE | vk::MemoryPropertyFlags::HOST_COHERENT;
        let ty = match memory {
            Memory::Device => device.memory_type(
                req.memory_type_bits,
                vk::MemoryPropertyFlags::DEVICE_LOCAL,
                vk::MemoryPropertyFlags::empty(),
            ),
            Memory::Host => device.memory_type(
                req.memory_type_bits,
                coherent,
                vk::MemoryPropertyFlags::HOST_CACHED,
            ),
        }
        .or_else(|| {
            device.memory_type(
                req.memory_type_bits,
                vk::MemoryPropertyFlags::empty(),
                vk::MemoryPropertyFlags::empty(),
            )
        });
        let Some((type_index, flags)) = ty else {
            // SAFETY: `buffer` is unused and owned here.
            unsafe { d.destroy_buffer(buffer, None) };
            return Err(VulkanError::Vk {
                call: "selecting a memory type",
                result: vk::Result::ERROR_FEATURE_NOT_PRESENT,
            });
        };
        let ai = vk::MemoryAllocateInfo::default()
            .allocation_size(req.size)
            .memory_type_index(type_index);
        // SAFETY: `ai` names a memory type of this device allowed for `buffer`.
        let mem = match unsafe { d.allocate_memory(&ai, None) } {
            Ok(m) => m,
            Err(r) => {
                // SAFETY: `buffer` is unused and owned here.
                unsafe { d.destroy_buffer(buffer, None) };
                return Err(VulkanError::from_vk("vkAllocateMemory", r, what, size));
            }
        };
        let free = |r: vk::Result, call| {
            // SAFETY: `buffer` and `mem` are unused and owned here.
            unsafe {
                d.destroy_buffer(buffer, None);
                d.free_memory(mem, None);
            }
            VulkanError::from_vk(call, r, what, size)
        };
        // SAFETY: `mem` is large enough (`req.size`) and of an allowed type; offset 0 meets
        // any alignment.
        if let Err(r) = unsafe { d.bind_buffer_memory(buffer, mem, 0) } {
            return Err(free(r, "vkBindBufferMemory"));
        }
        let mapped = if flags.contains(coherent) {
            // SAFETY: the memory is host-visible and not mapped yet; it stays mapped until
            // `drop` frees it.
            match unsafe { d.map_memory(mem, 0, vk::WHOLE_SIZE, vk::MemoryMapFlags::empty()) } {
                Ok(p) => Some(p as usize),
                Err(r) => return Err(free(r, "vkMapMemory")),
            }
        } else {
            None
        };
        Ok(Self {
            device: device.clone(),
            buffer,
            memory: mem,
            size,
            mapped,
        })
    }

    pub fn size(&self) -> u64 {
        self.size
    }

    /// Copies `data` to byte `offset` of a mapped buffer. Returns false (nothing written) when
    /// the buffer is not mapped or the range does not fit.
    pub fn write_mapped(&mut self, offset: u64, data: &[u8]) -> bool {
        match self.mapped {
            Some(base) if offset + data.len() as u64 <= self.size => {
                // SAFETY: the mapping covers `size` bytes and the range fits; `&mut self`
                // guarantees no other host access, and no device work is pending (every
                // submission is waited for). Coherent memory needs no flush.
                unsafe {
                    std::ptr::copy_nonoverlapping(
                        data.as_ptr(),
                        (base as *mut u8).add(offset as usize),
                        data.len(),
                    )
                };
                true
            }
            _ => false,
        }
    }

    /// Copies bytes from `offset` of a mapped buffer into `out`. Returns false when the buffer
    /// is not mapped or the range does not fit.
    pub fn read_mapped(&self, offset: u64, out: &mut [u8]) -> bool {
        match self.mapped {
            Some(base) if offset + out.len() as u64 <= self.size => {
                // SAFETY: as in `write_mapped`; device writes were made available to the host
                // by the final barrier of the submission that produced them.
                unsafe {
                    std::ptr::copy_nonoverlapping(
                        (base as *const u8).add(offset as usize),
                        out.as_mut_ptr(),
                        out.len(),
                    )
                };
                true
            }
            _ => false,
        }
    }
}

impl Drop for Buffer {
    fn drop(&mut self) {
        // SAFETY: no submission is pending (all are waited for), so the device no longer uses
        // the buffer; unmapping happens implicitly with `vkFreeMemory`.
        unsafe {
            self.device.device.destroy_buffer(self.buffer, None);
            self.device.device.free_memory(self.memory, None);
        }
    }
}

/// The shader module.
pub(crate) struct ShaderModule {
    device: Arc<Device>,
    module: vk::ShaderModule,
}

impl ShaderModule {
    pub fn new(device: &Arc<Device>, words: &[u32]) -> Result<Self, VulkanError> {
        let ci = vk::ShaderModuleCreateInfo::default().code(words);
        // SAFETY: `words` is the SPIR-V module built and validated (`spirv-val`) by build.rs.
        let module = unsafe { device.device.create_shader_module(&ci, None) }
            .map_err(|r| VulkanError::from_vk("vkCreateShaderModule", r, "the shader module", 0))?;
        Ok(Self {
            device: device.clone(),
            module,
        })
    }
}

impl Drop for ShaderModule {
    fn drop(&mut self) {
        // SAFETY: pipelines created from the module do not need it any more.
        unsafe { self.device.device.destroy_shader_module(self.module, None) };
    }
}

/// A compute pipeline of one entry point of the ABI's table: its descriptor set 0 has the
/// entry's storage buffers, plus its push-constant bytes.
pub(crate) struct Pipeline {
    device: Arc<Device>,
    set_layout: vk::DescriptorSetLayout,
    layout: vk::PipelineLayout,
    pipeline: vk::Pipeline,
    bindings: u32,
    push_size: u32,
}

impl Pipeline {
    /// Bytes of push constants the pipeline takes.
    pub fn push_size(&self) -> usize {
        self.push_size as usize
    }

    pub fn new(
        device: &Arc<Device>,
        module: &ShaderModule,
        entry: &himap_core::gpu_abi::EntryPoint,
    ) -> Result<Self, VulkanError> {
        let (bindings, push_size) = (entry.bindings, entry.push_size);
        let entry = entry.name;
        let d = &device.device;
        let b: Vec<_> = (0..bindings)
            .map(|i| {
                vk::DescriptorSetLayoutBinding::default()
                    .binding(i)
                    .descriptor_type(vk::DescriptorType::STORAGE_BUFFER)
                    .descriptor_count(1)
                    .stage_flags(vk::ShaderStageFlags::COMPUTE)
            })
            .collect();
        let ci = vk::DescriptorSetLayoutCreateInfo::default().bindings(&b);
        // SAFETY: `ci` describes `bindings` distinct storage-buffer bindings.
        let set_layout = unsafe { d.create_descriptor_set_layout(&ci, None) }
            .map_err(|r| VulkanError::from_vk("vkCreateDescriptorSetLayout", r, entry, 0))?;
        let ranges = [vk::PushConstantRange {
            stage_flags: vk::ShaderStageFlags::COMPUTE,
            offset: 0,
            size: push_size,
        }];
        let layouts = [set_layout];
        let lci = vk::PipelineLayoutCreateInfo::default()
            .set_layouts(&layouts)
            .push_constant_ranges(&ranges);
        // SAFETY: `set_layout` is live; the push range is within the device limit (checked by
        // `PhysicalInfo::missing`).
        let layout = match unsafe { d.create_pipeline_layout(&lci, None) } {
            Ok(l) => l,
            Err(r) => {
                // SAFETY: unused, owned here.
                unsafe { d.destroy_descriptor_set_layout(set_layout, None) };
                return Err(VulkanError::from_vk("vkCreatePipelineLayout", r, entry, 0));
            }
        };
        let name = CString::new(entry).unwrap_or_default();
        let stage = vk::PipelineShaderStageCreateInfo::default()
            .stage(vk::ShaderStageFlags::COMPUTE)
            .module(module.module)
            .name(&name);
        let pci = [vk::ComputePipelineCreateInfo::default()
            .stage(stage)
            .layout(layout)];
        // SAFETY: the module contains `entry` as a GLCompute entry point whose bindings and
        // push-constant block match `layout` (checked by the crate's tests).
        let res = unsafe { d.create_compute_pipelines(vk::PipelineCache::null(), &pci, None) };
        let pipeline = match res {
            Ok(p) => p[0],
            Err((_, r)) => {
                // SAFETY: unused, owned here.
                unsafe {
                    d.destroy_pipeline_layout(layout, None);
                    d.destroy_descriptor_set_layout(set_layout, None);
                }
                return Err(VulkanError::from_vk(
                    "vkCreateComputePipelines",
                    r,
                    entry,
                    0,
                ));
            }
        };
        Ok(Self {
            device: device.clone(),
            set_layout,
            layout,
            pipeline,
            bindings,
            push_size,
        })
    }
}

impl Drop for Pipeline {
    fn drop(&mut self) {
        // SAFETY: no submission is pending; the objects were created by this device.
        unsafe {
            self.device.device.destroy_pipeline(self.pipeline, None);
            self.device
                .device
                .destroy_pipeline_layout(self.layout, None);
            self.device
                .device
                .destroy_descriptor_set_layout(self.set_layout, None);
        }
    }
}

/// How long [`Gpu::submit`] waits for a submission.
const TIMEOUT_S: u64 = 900;
/// Descriptor sets per submission.
const MAX_SETS: u32 = 64;

/// Command recording and submission state: one command buffer, a fence and a descriptor pool
/// that is reset at the start of every submission.
pub(crate) struct Gpu {
    device: Arc<Device>,
    pool: vk::CommandPool,
    cmd: vk::CommandBuffer,
    fence: vk::Fence,
    descriptors: vk::DescriptorPool,
}

impl Gpu {
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
        };
        let recorded = f(&mut rec);
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
            d.destroy_descriptor_pool(self.descriptors, None);
            d.destroy_fence(self.fence, None);
            d.destroy_command_pool(self.pool, None);
        }
    }
}

/// Records into the command buffer of one [`Gpu::submit`].
pub(crate) struct Recorder<'a> {
    device: Arc<Device>,
    _borrow: std::marker::PhantomData<&'a ()>,
    cmd: vk::CommandBuffer,
    descriptors: vk::DescriptorPool,
    sets: u32,
}

impl<'a> Recorder<'a> {
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
    set: vk::DescriptorSet,
    _borrow: std::marker::PhantomData<&'a ()>,
}
