//! Storage buffers, each with its own memory allocation (host-visible or device-local).

use crate::error::VulkanError;
use ash::vk;
use std::sync::Arc;

use super::Device;

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
    pub(super) device: Arc<Device>,
    pub(super) buffer: vk::Buffer,
    pub(super) memory: vk::DeviceMemory,
    pub(super) size: u64,
    /// Host address of the whole allocation when mapped, as an address (not a pointer) so the
    /// type stays `Send`.
    pub(super) mapped: Option<usize>,
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
                what: String::new(),
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
        // A submission queued by `Gpu::submit_on` may still use the buffer: wait for the
        // device first (buffers are freed rarely: a resize, the backend's end).
        self.device.wait_idle();
        // SAFETY: the device runs nothing, so it no longer uses the buffer; unmapping happens
        // implicitly with `vkFreeMemory`.
        unsafe {
            self.device.device.destroy_buffer(self.buffer, None);
            self.device.device.free_memory(self.memory, None);
        }
    }
}
