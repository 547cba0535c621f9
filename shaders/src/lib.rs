//! rust-gpu compute entry points (under construction).
#![cfg_attr(target_arch = "spirv", no_std)]
