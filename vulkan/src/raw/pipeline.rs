//! The SPIR-V shader module and one compute pipeline per entry point.

use crate::error::VulkanError;
use ash::vk;
use std::ffi::CString;
use std::sync::Arc;

use super::Device;

/// The shader module.
pub(crate) struct ShaderModule {
    pub(super) device: Arc<Device>,
    pub(super) module: vk::ShaderModule,
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
    pub(super) device: Arc<Device>,
    pub(super) set_layout: vk::DescriptorSetLayout,
    pub(super) layout: vk::PipelineLayout,
    pub(super) pipeline: vk::Pipeline,
    pub(super) bindings: u32,
    pub(super) push_size: u32,
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
        Self::with_flags(device, module, entry, vk::PipelineCreateFlags::empty())
    }

    /// [`Pipeline::new`] with creation flags (the driver diagnostic's
    /// `DISABLE_OPTIMIZATION`).
    pub fn with_flags(
        device: &Arc<Device>,
        module: &ShaderModule,
        entry: &himap_core::gpu_abi::EntryPoint,
        flags: vk::PipelineCreateFlags,
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
            .flags(flags)
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
