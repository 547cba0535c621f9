//! The compute passes of one submission: the pipelines of the entry points, push-constant
//! bytes, dispatches cut to the device's workgroup-count limit, and [`Passes`], which records
//! the per-sample forward and backward and the checked Adam update of a step (see the order
//! of the passes in [`crate::VulkanBackend`]'s module documentation).

use std::sync::Arc;

use crate::buffers::{grad_bindings, param_bindings, GroupBuffers};
use crate::error::VulkanError;
use crate::raw::{Buffer, Device, Pipeline, Recorder, Set, ShaderModule};
use crate::{entry, WORKGROUP_SIZE};
use himap_core::field::model::{Group, PerGroup, NUM_GROUPS};
use himap_core::gpu_abi::{
    AdamPush, LossCheckPush, PushWords, RangePush, SamplePush, STATUS_REJECTED,
};
use himap_core::train::adam::AdamStep;

pub(crate) struct Pipelines {
    pub(crate) loop_canary: Pipeline,
    pub(crate) sample_forward: Pipeline,
    pub(crate) ray_train: Pipeline,
    pub(crate) sample_backward: Pipeline,
    /// `sample_backward_wg_cs`, on devices with `shaderSharedInt64Atomics` unless the
    /// options ask for the global-atomics pass.
    pub(crate) sample_backward_wg: Option<Pipeline>,
    pub(crate) ray_render: Pipeline,
    pub(crate) pixel_rays: Pipeline,
    pub(crate) pixel_depth: Pipeline,
    pub(crate) pixel_loss: Pipeline,
    pub(crate) pixel_backward: Pipeline,
    pub(crate) adam: Pipeline,
    pub(crate) loss_check: Pipeline,
    pub(crate) adam_check: Pipeline,
    pub(crate) step_count: Pipeline,
    pub(crate) sdf: Pipeline,
    pub(crate) color: Pipeline,
}

impl Pipelines {
    /// Every pipeline of the backend's passes, from the module's entry points.
    pub(crate) fn new(
        device: &Arc<Device>,
        module: &ShaderModule,
        workgroup_sums: bool,
    ) -> Result<Self, VulkanError> {
        let p = |e| Pipeline::new(device, module, e);
        let wg = workgroup_sums && device.info.shader_shared_int64_atomics;
        Ok(Self {
            loop_canary: p(&entry::LOOP_CANARY)?,
            sample_forward: p(&entry::SAMPLE_FORWARD)?,
            ray_train: p(&entry::RAY_TRAIN)?,
            sample_backward: p(&entry::SAMPLE_BACKWARD)?,
            sample_backward_wg: if wg {
                Some(p(&entry::SAMPLE_BACKWARD_WG)?)
            } else {
                None
            },
            ray_render: p(&entry::RAY_RENDER)?,
            pixel_rays: p(&entry::PIXEL_RAYS)?,
            pixel_depth: p(&entry::PIXEL_DEPTH)?,
            pixel_loss: p(&entry::PIXEL_LOSS)?,
            pixel_backward: p(&entry::PIXEL_BACKWARD)?,
            adam: p(&entry::ADAM)?,
            loss_check: p(&entry::LOSS_CHECK)?,
            adam_check: p(&entry::ADAM_CHECK)?,
            step_count: p(&entry::STEP_COUNT)?,
            sdf: p(&entry::SDF_QUERY)?,
            color: p(&entry::COLOR_QUERY)?,
        })
    }
}

pub(crate) fn push_bytes(p: impl PushWords) -> [u8; 32] {
    let words = p.words();
    let mut b = [0u8; 32];
    for (i, w) in words.iter().enumerate() {
        b[4 * i..4 * i + 4].copy_from_slice(&w.to_le_bytes());
    }
    b
}

/// Items per dispatch and the dispatches covering `n` items: `(first, count, groups)`.
pub(crate) fn chunks(n: usize, max_groups: u32) -> Vec<(u32, u32, u32)> {
    let per = max_groups as usize * WORKGROUP_SIZE as usize;
    let mut out = Vec::new();
    let mut first = 0;
    while first < n {
        let count = (n - first).min(per);
        out.push((
            first as u32,
            count as u32,
            count.div_ceil(WORKGROUP_SIZE as usize) as u32,
        ));
        first += count;
    }
    out
}

/// Dispatches `pipeline` over `n` items, one per invocation, in chunks within the
/// workgroup-count limit; `push(first, count)` gives a chunk's push constants (the first
/// `pipeline.push_size()` bytes are used).
pub(crate) fn dispatch_items<'a>(
    r: &mut Recorder<'a>,
    pipeline: &'a Pipeline,
    set: &Set<'a>,
    n: usize,
    max_groups: u32,
    push: impl Fn(u32, u32) -> [u8; 32],
) {
    for (first, count, wg) in chunks(n, max_groups) {
        let p = push(first, count);
        r.dispatch(pipeline, set, &p[..pipeline.push_size()], wg);
    }
}

/// Push constants of the entry points that take only the item range.
pub(crate) fn range_push(first: u32, count: u32) -> [u8; 32] {
    push_bytes(RangePush {
        n: count,
        first,
        ..Default::default()
    })
}

/// Push constants of a per-item entry point that also needs the whole batch's size.
pub(crate) fn batch_push(first: u32, count: u32, total: u32) -> [u8; 32] {
    push_bytes(RangePush {
        n: count,
        first,
        total,
        ..Default::default()
    })
}

/// What the passes of one submission share: pipelines, model buffers, and the batch's rays
/// and sample records.
/// The per-sample backward's structure (the same bits either way, tested): one global `i64`
/// atomic per gradient contribution, or the decoders' weight contributions summed in
/// workgroup memory first (`sample_backward_wg_cs`, devices with `shaderSharedInt64Atomics`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum BackwardPass {
    /// `sample_backward_cs`.
    GlobalAtomics,
    /// `sample_backward_wg_cs`.
    WorkgroupSums,
}

impl BackwardPass {
    /// Both, in index order.
    pub const ALL: [BackwardPass; 2] = [BackwardPass::GlobalAtomics, BackwardPass::WorkgroupSums];

    /// Short name for reports.
    pub fn name(self) -> &'static str {
        match self {
            BackwardPass::GlobalAtomics => "global atomics",
            BackwardPass::WorkgroupSums => "workgroup sums",
        }
    }
}

pub(crate) struct Passes<'a> {
    pub(crate) pipelines: &'a Pipelines,
    pub(crate) groups: &'a PerGroup<GroupBuffers>,
    pub(crate) model_words: &'a Buffer,
    pub(crate) rays: &'a Buffer,
    pub(crate) samples: &'a Buffer,
    /// The step's non-finite count.
    pub(crate) status: &'a Buffer,
    /// Sample records of the batch (rays x samples per ray).
    pub(crate) records: usize,
    pub(crate) max_groups: u32,
    /// The backward's structure (`WorkgroupSums` falls back to global atomics where the
    /// device has no workgroup-sum pipeline).
    pub(crate) backward: BackwardPass,
}

impl<'a> Passes<'a> {
    /// Binds a compositing pass (`ray_train_cs`; a mapping step's `pixel_depth_cs`,
    /// `pixel_loss_cs`, `pixel_backward_cs`): the model words and beta's parameter and
    /// gradient, then `inputs` (the window's, for a mapping step), then the rays, the samples
    /// and `outputs` (the results; for the pixel passes also their per-pixel records).
    pub(crate) fn bind_composite(
        &self,
        r: &mut Recorder<'a>,
        pipeline: &Pipeline,
        inputs: &[&'a Buffer],
        outputs: &[&'a Buffer],
    ) -> Result<Set<'a>, VulkanError> {
        let beta = self.groups[Group::Beta].lo();
        let mut b = vec![self.model_words, &beta.params, &beta.grad];
        b.extend_from_slice(inputs);
        b.extend_from_slice(&[self.rays, self.samples]);
        b.extend_from_slice(outputs);
        r.bind(pipeline, &b)
    }

    /// Zeroes every gradient buffer and the step's non-finite count.
    pub(crate) fn zero_grads(&self, r: &mut Recorder<'a>) {
        for p in self.groups.iter().flat_map(|g| g.parts.iter()) {
            r.zero(&p.grad);
        }
        // the rejection count only: the step count lives on (`gpu_abi::STATUS_WORDS`)
        r.zero_range(self.status, (STATUS_REJECTED * 4) as u64, 4);
        r.barrier();
        r.mark("zero gradients");
    }

    /// Pass 1: `sample_forward_cs` over every sample record.
    pub(crate) fn sample_forward(
        &self,
        r: &mut Recorder<'a>,
        seed: u32,
        jitter: bool,
    ) -> Result<(), VulkanError> {
        let pipeline = &self.pipelines.sample_forward;
        let set = r.bind(
            pipeline,
            &[
                &[self.model_words][..],
                &param_bindings(self.groups),
                &[self.rays, self.samples],
            ]
            .concat(),
        )?;
        dispatch_items(
            r,
            pipeline,
            &set,
            self.records,
            self.max_groups,
            |first, count| {
                push_bytes(SamplePush {
                    n: count,
                    first,
                    seed,
                    jitter: jitter as u32,
                })
            },
        );
        r.barrier();
        r.mark("forward (per sample)");
        Ok(())
    }

    /// Pass 3: `sample_backward_cs` over every sample record.
    pub(crate) fn sample_backward(&self, r: &mut Recorder<'a>) -> Result<(), VulkanError> {
        let pipeline = match (self.backward, &self.pipelines.sample_backward_wg) {
            (BackwardPass::WorkgroupSums, Some(p)) => p,
            _ => &self.pipelines.sample_backward,
        };
        let set = r.bind(
            pipeline,
            &[
                &[self.model_words][..],
                &param_bindings(self.groups),
                &grad_bindings(self.groups),
                &[self.rays, self.samples],
            ]
            .concat(),
        )?;
        // the frame's timestamp pair times this pass (the backend's choice of structure)
        r.stamp();
        dispatch_items(r, pipeline, &set, self.records, self.max_groups, range_push);
        r.barrier();
        r.stamp();
        r.mark("backward (per sample)");
        Ok(())
    }

    /// The step's checks and update: `loss_check_cs` over the `n` result records of
    /// `stride` floats (loss fields at `losses`), then `adam_check_cs` and `adam_cs` over
    /// every part of every group (`adam_cs` does nothing when a check counted anything).
    pub(crate) fn checked_adam(
        &self,
        r: &mut Recorder<'a>,
        steps: &[AdamStep; NUM_GROUPS],
        results: &'a Buffer,
        n: usize,
        stride: usize,
        losses: (usize, usize),
    ) -> Result<(), VulkanError> {
        let pipeline = &self.pipelines.loss_check;
        let set = r.bind(pipeline, &[results, self.status])?;
        dispatch_items(r, pipeline, &set, n, self.max_groups, |first, count| {
            push_bytes(LossCheckPush {
                n: count,
                first,
                stride: stride as u32,
                loss_a: losses.0 as u32,
                loss_b: losses.1 as u32,
                ..Default::default()
            })
        });
        r.barrier();
        self.adam(r, steps, &self.pipelines.adam_check)?;
        r.barrier();
        r.mark("finiteness checks");
        self.adam(r, steps, &self.pipelines.adam)?;
        r.barrier();
        let pipeline = &self.pipelines.step_count;
        let set = r.bind(pipeline, &[self.status])?;
        dispatch_items(r, pipeline, &set, 1, self.max_groups, range_push);
        r.barrier();
        r.mark("Adam");
        Ok(())
    }

    /// `pipeline` (`adam_cs` or `adam_check_cs`) over every part of every group.
    pub(crate) fn adam(
        &self,
        r: &mut Recorder<'a>,
        steps: &[AdamStep; NUM_GROUPS],
        pipeline: &'a Pipeline,
    ) -> Result<(), VulkanError> {
        for (g, s) in self.groups.iter().zip(steps.iter()) {
            for part in &g.parts {
                let set = r.bind(
                    pipeline,
                    &[&part.params, &part.m, &part.v, &part.grad, self.status],
                )?;
                dispatch_items(
                    r,
                    pipeline,
                    &set,
                    part.len,
                    self.max_groups,
                    |first, count| {
                        push_bytes(AdamPush {
                            n: count,
                            first,
                            step: *s,
                        })
                    },
                );
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn chunks_cover_every_item_once() {
        assert!(chunks(0, 10).is_empty());
        assert_eq!(chunks(1, 10), vec![(0, 1, 1)]);
        assert_eq!(chunks(64 * 10, 10), vec![(0, 640, 10)]);
        assert_eq!(chunks(641, 10), vec![(0, 640, 10), (640, 1, 1)]);
        assert_eq!(chunks(130, 1), vec![(0, 64, 1), (64, 64, 1), (128, 2, 1)]);
    }

    #[test]
    fn push_bytes_are_little_endian_words() {
        let b = push_bytes(AdamPush {
            n: 1,
            first: 0x0403_0201,
            step: AdamStep {
                bias_correction2: 1.0,
                ..Default::default()
            },
        });
        assert_eq!(&b[..8], &[1, 0, 0, 0, 1, 2, 3, 4]);
        assert_eq!(&b[28..], &1.0f32.to_le_bytes());
        // Blocks shorter than 8 words leave the rest zero (only their size is pushed).
        let r = push_bytes(RangePush {
            n: 7,
            first: 9,
            ..Default::default()
        });
        assert_eq!(&r[..8], &[7, 0, 0, 0, 9, 0, 0, 0]);
        assert!(r[8..].iter().all(|&x| x == 0));
        // every field of a block is pushed (a field left out reads 0 in the shader)
        let t = batch_push(9, 7, 300); // first 9, count 7
        assert_eq!(&t[..12], &[7, 0, 0, 0, 9, 0, 0, 0, 44, 1, 0, 0]);
    }
}
