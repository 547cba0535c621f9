//! Shared pieces of himap's cross-crate tests: the backend conformance suite
//! ([`conformance`]) and the Vulkan backend's constructor for tests ([`vulkan_or_skip`]).

pub mod conformance;

use himap::backend::ModelData;
use himap_core::field::model::PerGroup;
use himap_core::train::adam::AdamConfig;
use himap_vulkan::{VulkanBackend, VulkanError};

/// The Vulkan backend over `data`'s parameters, or `None` (with the reason printed) when this
/// machine has no usable Vulkan device. With `HIMAP_REQUIRE_VULKAN=1` a missing device is a
/// test failure. Errors that are not about device availability always fail.
pub fn vulkan_or_skip(data: &ModelData, adam: PerGroup<AdamConfig>) -> Option<VulkanBackend> {
    vulkan_result_or_skip(VulkanBackend::new(data.layout, data.param_slices(), adam))
}

/// `r`'s value, or `None` (with the reason printed) when its error says this machine has no
/// usable Vulkan device; with `HIMAP_REQUIRE_VULKAN=1` that is a test failure, and any other
/// error always is.
pub fn vulkan_result_or_skip<T>(r: Result<T, VulkanError>) -> Option<T> {
    match r {
        Ok(b) => Some(b),
        Err(
            e @ (VulkanError::NoLoader(_)
            | VulkanError::ApiTooOld { .. }
            | VulkanError::Instance(_)
            | VulkanError::NoDevice
            | VulkanError::NoSuitableDevice { .. }
            | VulkanError::MissingFeature { .. }
            | VulkanError::DeviceNotFound { .. }),
        ) => {
            if std::env::var("HIMAP_REQUIRE_VULKAN").is_ok_and(|v| v == "1") {
                panic!("HIMAP_REQUIRE_VULKAN=1 but no usable Vulkan device: {e}");
            }
            eprintln!("skipping: no usable Vulkan device: {e}");
            None
        }
        Err(e) => panic!("the Vulkan device failed: {e}"),
    }
}
