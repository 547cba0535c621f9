//! The device buffers of [`crate::VulkanBackend`] and their transfers: each parameter
//! group's parts (parameters, Adam moments, fixed-point gradient), the binding tables the
//! field-reading entry points take, growable host-visible or device-local buffers, and
//! uploads and downloads (through a staging buffer when the destination is not mapped).

use std::sync::Arc;

use crate::error::VulkanError;
use crate::raw::{Buffer, Device, Gpu, Memory};
use himap_core::field::model::{Group, PerGroup};
use himap_core::gpu_abi::PARAM_BINDINGS;

/// One part of a group: parameters `start..start + len` with their Adam moments and
/// fixed-point gradient.
pub(crate) struct Part {
    pub(crate) params: Buffer,
    pub(crate) m: Buffer,
    pub(crate) v: Buffer,
    pub(crate) grad: Buffer,
    pub(crate) start: usize,
    pub(crate) len: usize,
}

/// Per-group device state: one part, or two for a grid larger than one storage-buffer binding
/// allows (the shaders read such a group through `SplitParams`).
pub(crate) struct GroupBuffers {
    pub(crate) parts: Vec<Part>,
    pub(crate) len: usize,
}

impl GroupBuffers {
    /// Device buffers of a group in parts of `part_lens` (summing to `params.len()`): the
    /// parameters uploaded, moments and gradient allocated (zeroed by the caller).
    pub(crate) fn upload(
        device: &Arc<Device>,
        gpu: &mut Gpu,
        staging: &mut Option<Buffer>,
        name: &str,
        part_lens: &[usize],
        params: &[f32],
    ) -> Result<Self, VulkanError> {
        let mut parts = Vec::with_capacity(part_lens.len());
        let mut start = 0;
        for &len in part_lens {
            let n = len as u64;
            let buffer = |bytes: u64, what: &str| {
                Buffer::new(device, bytes, Memory::Device, &format!("{name} {what}"))
            };
            let mut p = buffer(n * 4, "parameters")?;
            upload(
                gpu,
                staging,
                &mut p,
                &f32_bytes(&params[start..start + len]),
            )?;
            parts.push(Part {
                params: p,
                m: buffer(n * 4, "Adam m")?,
                v: buffer(n * 4, "Adam v")?,
                grad: buffer(n * 8, "gradient")?,
                start,
                len,
            });
            start += len;
        }
        Ok(Self {
            parts,
            len: params.len(),
        })
    }

    pub(crate) fn lo(&self) -> &Part {
        &self.parts[0]
    }

    /// The second part, or the first again when the group is whole.
    pub(crate) fn hi(&self) -> &Part {
        &self.parts[self.parts.len() - 1]
    }
}

/// The bindings of the field-reading entry points ([`PARAM_BINDINGS`] of them): geometry grid
/// (low, high part), appearance grid (low, high part), geometry MLP, appearance MLP, beta;
/// `buffer` picks each part's parameters or gradients.
pub(crate) fn field_bindings(
    groups: &PerGroup<GroupBuffers>,
    buffer: fn(&Part) -> &Buffer,
) -> [&Buffer; PARAM_BINDINGS] {
    use Group::*;
    [
        buffer(groups[GeometryGrid].lo()),
        buffer(groups[GeometryGrid].hi()),
        buffer(groups[AppearanceGrid].lo()),
        buffer(groups[AppearanceGrid].hi()),
        buffer(groups[GeometryMlp].lo()),
        buffer(groups[AppearanceMlp].lo()),
        buffer(groups[Beta].lo()),
    ]
}

/// The parameter bindings of the field-reading entry points.
pub(crate) fn param_bindings(groups: &PerGroup<GroupBuffers>) -> [&Buffer; PARAM_BINDINGS] {
    field_bindings(groups, |p| &p.params)
}

/// The gradient bindings of `sample_backward_cs`, in the order of [`param_bindings`].
pub(crate) fn grad_bindings(groups: &PerGroup<GroupBuffers>) -> [&Buffer; PARAM_BINDINGS] {
    field_bindings(groups, |p| &p.grad)
}

pub(crate) fn f32_bytes(v: &[f32]) -> Vec<u8> {
    v.iter().flat_map(|x| x.to_le_bytes()).collect()
}

pub(crate) fn u32_bytes(v: &[u32]) -> Vec<u8> {
    v.iter().flat_map(|x| x.to_le_bytes()).collect()
}

/// Makes sure `slot` holds a host-visible buffer of at least `bytes`.
pub(crate) fn ensure<'b>(
    gpu: &Gpu,
    slot: &'b mut Option<Buffer>,
    bytes: u64,
    what: &str,
) -> Result<&'b mut Buffer, VulkanError> {
    ensure_in(gpu, slot, bytes, Memory::Host, what)
}

/// Makes sure `slot` holds a buffer of at least `bytes` in `memory`.
pub(crate) fn ensure_in<'b>(
    gpu: &Gpu,
    slot: &'b mut Option<Buffer>,
    bytes: u64,
    memory: Memory,
    what: &str,
) -> Result<&'b mut Buffer, VulkanError> {
    let grow = match slot {
        Some(b) => b.size() < bytes,
        None => true,
    };
    if grow {
        *slot = None;
        *slot = Some(Buffer::new(
            gpu.device(),
            bytes.next_power_of_two(),
            memory,
            what,
        )?);
    }
    slot.as_mut()
        .ok_or(VulkanError::Unsupported("buffer allocation"))
}

/// Writes `data` at the start of `dst` (through `staging` when `dst` is not mapped).
pub(crate) fn upload(
    gpu: &mut Gpu,
    staging: &mut Option<Buffer>,
    dst: &mut Buffer,
    data: &[u8],
) -> Result<(), VulkanError> {
    upload_at(gpu, staging, dst, 0, data)
}

/// Writes `data` at byte `offset` of `dst` (through `staging` when `dst` is not mapped).
pub(crate) fn upload_at(
    gpu: &mut Gpu,
    staging: &mut Option<Buffer>,
    dst: &mut Buffer,
    offset: u64,
    data: &[u8],
) -> Result<(), VulkanError> {
    if dst.write_mapped(offset, data) {
        return Ok(());
    }
    let st = ensure(gpu, staging, data.len() as u64, "a staging buffer")?;
    st.write_mapped(0, data);
    let (st, dst): (&Buffer, &Buffer) = (st, dst);
    let n = data.len() as u64;
    gpu.submit(|r| {
        r.copy(st, 0, dst, offset, n);
        Ok(())
    })
}

/// Reads `out.len()` floats from the start of `src`.
pub(crate) fn download_f32(
    gpu: &mut Gpu,
    staging: &mut Option<Buffer>,
    src: &Buffer,
    out: &mut [f32],
) -> Result<(), VulkanError> {
    let mut bytes = vec![0u8; out.len() * 4];
    download(gpu, staging, src, &mut bytes)?;
    for (x, b) in out.iter_mut().zip(bytes.as_chunks::<4>().0) {
        *x = f32::from_le_bytes(*b);
    }
    Ok(())
}

/// Reads `out.len()` bytes from the start of `src`.
pub(crate) fn download(
    gpu: &mut Gpu,
    staging: &mut Option<Buffer>,
    src: &Buffer,
    out: &mut [u8],
) -> Result<(), VulkanError> {
    if src.read_mapped(0, out) {
        return Ok(());
    }
    let n = out.len() as u64;
    let st = ensure(gpu, staging, n, "a staging buffer")?;
    {
        let st: &Buffer = st;
        gpu.submit(|r| {
            r.copy(src, 0, st, 0, n);
            Ok(())
        })?;
    }
    st.read_mapped(0, out);
    Ok(())
}
