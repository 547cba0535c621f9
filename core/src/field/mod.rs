//! The radiance field: what the map is and how a ray is rendered from it, forward and
//! backward.
//!
//! - [`grid`]: the hierarchical factorized feature grids (geometry and appearance), sampled
//!   trilinearly, with their gradients;
//! - [`mlp`]: the two small decoders;
//! - [`render`]: volume rendering of one ray from per-sample SDF values and colours;
//! - [`model`]: the field per sample and per ray (`ray_forward`, `ray_train`,
//!   `ray_backward`), its parameter groups and layouts;
//! - [`negligible`]: which samples' backward provably adds nothing (host-side).

pub mod grid;
pub mod mlp;
pub mod model;
#[cfg(not(target_arch = "spirv"))]
pub mod negligible;
pub mod render;
