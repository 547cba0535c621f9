//! Every `unsafe` ash call of the crate, behind safe RAII types. Nothing outside this module
//! uses `unsafe` (the crate root denies it).
//!
//! Ownership: [`Instance`] owns the loader and the `VkInstance`; [`Device`] (always in an
//! `Arc`) owns the `VkDevice` and keeps its instance alive; [`Buffer`], [`Pipeline`] and
//! [`Gpu`] (command pool, command buffer, fence, descriptor pool) each hold an
//! `Arc<Device>`, so the device is destroyed only after every object created from it.
//!
//! Synchronisation: work is recorded into a command buffer by [`Gpu::submit`], submitted and
//! waited for before `submit` returns, so no recorded buffer or descriptor set is in use once
//! it returns. Buffers referenced by a recording borrow for the recorder's lifetime.
//! [`Gpu::submit_on`] (the mapping steps queued one ahead) returns before the device is
//! done; a [`Buffer`]'s drop waits for the device to be idle, so a buffer that a queued
//! submission uses is never freed under it (and the `Gpu`'s drop waits too). The caller
//! waits for a frame ([`Gpu::wait`]) before it reads what the frame wrote.
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
pub(crate) use gpu::{Gpu, Recorder, Set, FRAMES};
pub(crate) use instance::{version_string, Device, Instance, PhysicalInfo};
pub(crate) use pipeline::{Pipeline, ShaderModule};
