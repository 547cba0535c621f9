//! [`VulkanError`]: everything that can go wrong in the Vulkan backend, each with what to do.

use ash::vk;
use std::fmt;

/// Errors of the Vulkan backend. Every message names the cause and a remedy; none of them is
/// fatal to the process (the CPU backend keeps working).
#[derive(Debug, Clone, PartialEq)]
pub enum VulkanError {
    /// `libvulkan.so.1` (or the platform's loader) could not be loaded.
    NoLoader(String),
    /// The loader or driver supports only Vulkan 1.0/1.1; the shaders need 1.2.
    ApiTooOld { found: String },
    /// `vkCreateInstance` failed.
    Instance(vk::Result),
    /// The loader found no physical device at all.
    NoDevice,
    /// `HIMAP_VULKAN_DEVICE` names no device.
    DeviceNotFound {
        wanted: String,
        available: Vec<String>,
    },
    /// Devices exist but none has the features the shaders need.
    NoSuitableDevice { devices: Vec<String> },
    /// The chosen device lacks features (or a compute queue) the shaders need.
    MissingFeature {
        device: String,
        missing: Vec<&'static str>,
    },
    /// Device (or host-visible) memory ran out.
    OutOfDeviceMemory { what: String, bytes: u64 },
    /// Host memory ran out inside the driver.
    OutOfHostMemory,
    /// The device was lost (driver crash, reset, timeout).
    DeviceLost,
    /// A submission did not finish within the timeout.
    Timeout { seconds: u64 },
    /// A tensor is larger than one storage-buffer binding (`maxStorageBufferRange`) or one
    /// allocation (`maxMemoryAllocationSize`) allows.
    TensorTooLarge {
        what: String,
        bytes: u64,
        limit: u64,
        limit_name: &'static str,
    },
    /// A pass would run more loop iterations in one invocation than this device completes
    /// (measured at start by the loop canary: llvmpipe cuts every loop after 65535).
    LoopBudget {
        what: String,
        needed: u32,
        budget: u32,
    },
    /// The shader module named by `HIMAP_SPIRV` cannot be used.
    Module(String),
    /// An operation the Vulkan backend does not implement yet.
    Unsupported(&'static str),
    /// Invalid input (shapes, sizes): the core's error.
    Core(himap_core::Error),
    /// Any other Vulkan call failure.
    Vk {
        call: &'static str,
        result: vk::Result,
        /// What the call was for (a shader entry point, a buffer); empty when nothing more is
        /// known.
        what: String,
    },
}

impl VulkanError {
    /// Maps a `vk::Result` of `call` to the specific variants where one exists.
    pub(crate) fn from_vk(call: &'static str, result: vk::Result, what: &str, bytes: u64) -> Self {
        match result {
            vk::Result::ERROR_OUT_OF_DEVICE_MEMORY => Self::OutOfDeviceMemory {
                what: what.to_string(),
                bytes,
            },
            vk::Result::ERROR_OUT_OF_HOST_MEMORY => Self::OutOfHostMemory,
            vk::Result::ERROR_DEVICE_LOST => Self::DeviceLost,
            _ => Self::Vk {
                call,
                result,
                what: what.to_string(),
            },
        }
    }
}

impl From<himap_core::Error> for VulkanError {
    fn from(e: himap_core::Error) -> Self {
        Self::Core(e)
    }
}

const USE_CPU: &str = "or run with `--backend cpu`";

impl fmt::Display for VulkanError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::NoLoader(e) => write!(
                f,
                "the Vulkan loader could not be loaded ({e}); install it (Debian/Ubuntu: \
                 `apt-get install libvulkan1 mesa-vulkan-drivers`, the latter adds the lavapipe \
                 CPU driver) {USE_CPU}"
            ),
            Self::ApiTooOld { found } => write!(
                f,
                "the Vulkan loader/driver offers API {found}, the shaders need Vulkan 1.2; \
                 update the Vulkan loader and driver {USE_CPU}"
            ),
            Self::Instance(r) => write!(
                f,
                "creating a Vulkan instance failed ({r}); check the driver installation \
                 (`vulkaninfo --summary`) {USE_CPU}"
            ),
            Self::NoDevice => write!(
                f,
                "no Vulkan device found; install a driver (`apt-get install \
                 mesa-vulkan-drivers` gives the lavapipe CPU driver) {USE_CPU}"
            ),
            Self::DeviceNotFound { wanted, available } => write!(
                f,
                "HIMAP_VULKAN_DEVICE={wanted:?} matches no device (by index or name \
                 substring); available: {}; unset it or pick one of those",
                list(available)
            ),
            Self::NoSuitableDevice { devices } => write!(
                f,
                "no Vulkan device has the features himap's shaders need (Vulkan 1.2, \
                 shaderInt64, shaderBufferInt64Atomics, vulkanMemoryModel, a compute queue); \
                 found: {}; see `himap devices`; update the driver {USE_CPU}",
                list(devices)
            ),
            Self::MissingFeature { device, missing } => write!(
                f,
                "Vulkan device {device:?} lacks {} which the shaders need; pick another device \
                 with HIMAP_VULKAN_DEVICE (see `himap devices`), update the driver, {USE_CPU}",
                missing.join(", ")
            ),
            Self::OutOfDeviceMemory { what, bytes } => write!(
                f,
                "out of device memory allocating {what} ({bytes} bytes); use a smaller \
                 configuration (fewer grid levels, coarser cells, fewer rays per batch), free \
                 GPU memory, {USE_CPU}"
            ),
            Self::OutOfHostMemory => write!(
                f,
                "the Vulkan driver ran out of host memory; free memory or use a smaller \
                 configuration"
            ),
            Self::DeviceLost => write!(
                f,
                "the Vulkan device was lost (driver crash or GPU reset; on some systems a \
                 watchdog kills long dispatches); retry with fewer rays per batch, update the \
                 driver, {USE_CPU}"
            ),
            Self::Timeout { seconds } => write!(
                f,
                "a Vulkan submission did not finish within {seconds} s; use fewer rays per \
                 batch {USE_CPU}"
            ),
            Self::TensorTooLarge {
                what,
                bytes,
                limit,
                limit_name,
            } => write!(
                f,
                "{what} needs {bytes} bytes, more than this device's {limit_name} ({limit} \
                 bytes); splitting tensors across bindings is not implemented yet: use a \
                 coarser or factorized grid, {USE_CPU}"
            ),
            Self::LoopBudget {
                what,
                needed,
                budget,
            } => write!(
                f,
                "{what} needs up to {needed} loop iterations per invocation, and this device \
                 cuts loops after {budget} (measured at start; llvmpipe's limit), which would \
                 silently change the results; use a smaller mapping window \
                 (mapper.local_frames + mapper.window_keyframes + mapper.global_keyframes), a \
                 GPU, {USE_CPU}"
            ),
            Self::Module(why) => write!(f, "{why} (unset HIMAP_SPIRV to run the built-in shaders)"),
            Self::Unsupported(what) => write!(
                f,
                "the Vulkan backend does not implement {what} yet; {USE_CPU}"
            ),
            Self::Core(e) => write!(f, "{e}"),
            Self::Vk { call, result, what } => {
                let what = if what.is_empty() {
                    String::new()
                } else {
                    format!(" ({what})")
                };
                write!(
                    f,
                    "{call} failed{what}: {result}; check the driver (`vulkaninfo --summary`), \
                     {USE_CPU}"
                )
            }
        }
    }
}

impl std::error::Error for VulkanError {}

fn list(v: &[String]) -> String {
    if v.is_empty() {
        "none".to_string()
    } else {
        v.iter()
            .enumerate()
            .map(|(i, s)| format!("[{i}] {s}"))
            .collect::<Vec<_>>()
            .join(", ")
    }
}
