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
//!
//! Files: `instance` (the loader, instance, physical-device queries and the logical device),
//! `buffer` (storage buffers and their memory), `pipeline` (the shader module and compute
//! pipelines), `gpu` (command recording, submission and descriptor sets).

mod buffer;
mod gpu;
mod instance;
mod pipeline;

pub(crate) use buffer::{Buffer, Memory};
pub(crate) use gpu::{Gpu, Recorder, Set};
pub(crate) use instance::{version_string, Device, Instance, PhysicalInfo};
pub(crate) use pipeline::{Pipeline, ShaderModule};
