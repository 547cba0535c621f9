//! The Vulkan loader and instance, what a physical device offers, and the logical device.

use crate::error::VulkanError;
use ash::vk;
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
    /// Nanoseconds per timestamp tick (`timestampPeriod`).
    pub timestamp_period: f32,
    /// Valid bits of the compute queue's timestamps (0: no timestamps on that queue).
    pub timestamp_valid_bits: u32,
    /// What faster gradient sums could use (not required): 64-bit atomics on workgroup
    /// memory, the workgroup memory size, the subgroup size and operations.
    pub shader_shared_int64_atomics: bool,
    pub max_compute_shared_memory_size: u32,
    pub subgroup_size: u32,
    pub subgroup_arithmetic: bool,
    pub shader_subgroup_extended_types: bool,
    /// 32-bit float controls the driver offers (Vulkan 1.2; all `false` before): subnormals
    /// preserved / flushed on request, signed zeros, infinities and NaNs preserved, round to
    /// nearest even on request. Reported by `himap devices` (bit-exactness diagnosis).
    pub float_controls_32: [bool; 4],
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
    pub(super) _entry: ash::Entry,
    pub(super) instance: ash::Instance,
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
            let mut subgroup = vk::PhysicalDeviceSubgroupProperties::default();
            let (mut shader_int64, mut atomics64, mut memory_model) = (false, false, false);
            let (mut shared64, mut extended_types) = (false, false);
            let mut float_controls_32 = [false; 4];
            if props.api_version >= vk::API_VERSION_1_1 {
                let mut p2 = vk::PhysicalDeviceProperties2::default()
                    .push_next(&mut maint3)
                    .push_next(&mut subgroup);
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
                shared64 = v12.shader_shared_int64_atomics == vk::TRUE;
                extended_types = v12.shader_subgroup_extended_types == vk::TRUE;
                let mut fc = vk::PhysicalDeviceFloatControlsProperties::default();
                let mut p2 = vk::PhysicalDeviceProperties2::default().push_next(&mut fc);
                // SAFETY: the device supports Vulkan 1.2, whose core includes the float
                // controls properties structure; both live across the call.
                unsafe { self.instance.get_physical_device_properties2(pd, &mut p2) };
                float_controls_32 = [
                    fc.shader_denorm_preserve_float32 == vk::TRUE,
                    fc.shader_denorm_flush_to_zero_float32 == vk::TRUE,
                    fc.shader_signed_zero_inf_nan_preserve_float32 == vk::TRUE,
                    fc.shader_rounding_mode_rte_float32 == vk::TRUE,
                ];
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
            let timestamp_valid_bits =
                compute_queue_family.map_or(0, |q| families[q as usize].timestamp_valid_bits);
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
                timestamp_period: props.limits.timestamp_period,
                timestamp_valid_bits,
                shader_shared_int64_atomics: shared64,
                max_compute_shared_memory_size: props.limits.max_compute_shared_memory_size,
                subgroup_size: subgroup.subgroup_size,
                subgroup_arithmetic: subgroup
                    .supported_operations
                    .contains(vk::SubgroupFeatureFlags::ARITHMETIC),
                shader_subgroup_extended_types: extended_types,
                float_controls_32,
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
    pub(super) instance: Arc<Instance>,
    pub(super) device: ash::Device,
    pub(super) queue: vk::Queue,
    pub(super) queue_family: u32,
    pub(super) memory: vk::PhysicalDeviceMemoryProperties,
    pub info: PhysicalInfo,
}

impl Device {
    /// Waits until the device runs nothing (before a buffer that a queued submission may use
    /// is freed).
    pub fn wait_idle(&self) {
        // SAFETY: waiting is always allowed; errors (a lost device) surface at the next call.
        let _ = unsafe { self.device.device_wait_idle() };
    }

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
            .shader_buffer_int64_atomics(true)
            // optional: the workgroup-summed backward pass (`sample_backward_wg_cs`)
            .shader_shared_int64_atomics(info.shader_shared_int64_atomics);
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
    pub(super) fn memory_type(
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
