//! The conformance suite ([`himap_tests::conformance`]) against every backend: the host's
//! parallel CPU backend with 1, 2 and 8 threads and the Vulkan backend (skipped, with the
//! reason, where this machine has no Vulkan device; a failure with `HIMAP_REQUIRE_VULKAN=1`).

use himap::backend::{ModelData, ParallelCpuBackend};
use himap::dump::small_config;
use himap_core::field::model::PerGroup;
use himap_core::field::render::RenderMode;
use himap_core::train::adam::AdamConfig;
use himap_core::train::backend::ImageStore;
use himap_tests::conformance::{self, Candidate};
use himap_vulkan::VulkanBackend;

/// The host's parallel CPU backend with this many threads.
struct Cpu(usize);

impl Candidate for Cpu {
    type B = ParallelCpuBackend;

    fn build(
        &self,
        data: &ModelData,
        adam: PerGroup<AdamConfig>,
        store: ImageStore,
    ) -> Option<ParallelCpuBackend> {
        let b = ParallelCpuBackend::new(data.clone(), adam, self.0).expect("thread pool");
        Some(b.with_images(store))
    }
}

/// The Vulkan backend on this machine's first suitable device.
struct Vulkan;

impl Candidate for Vulkan {
    type B = VulkanBackend;

    fn build(
        &self,
        data: &ModelData,
        adam: PerGroup<AdamConfig>,
        store: ImageStore,
    ) -> Option<VulkanBackend> {
        let b = himap_tests::vulkan_or_skip(data, adam)?;
        Some(if store.slots > 0 {
            b.with_images(store).expect("image slots")
        } else {
            b
        })
    }
}

/// Every check of the suite as a test, in one module per backend.
macro_rules! conformance_suite {
    ($($name:ident: $candidate:expr;)*) => {$(
        mod $name {
            use super::*;

            #[test]
            fn forward_rendering() {
                conformance::forward_rendering(&$candidate);
            }

            #[test]
            fn one_step_sdf_density() {
                conformance::one_step(&$candidate, &small_config(RenderMode::SdfDensity));
            }

            #[test]
            fn one_step_occupancy() {
                conformance::one_step(&$candidate, &small_config(RenderMode::Occupancy));
            }

            #[test]
            fn one_step_with_early_termination() {
                conformance::one_step_with_early_termination(&$candidate);
            }

            #[test]
            fn one_step_with_far_samples() {
                conformance::one_step_with_far_samples(&$candidate);
            }

            #[test]
            fn termination_threshold_between_steps() {
                conformance::termination_threshold_between_steps(&$candidate);
            }

            #[test]
            fn nonfinite_steps_are_rejected() {
                conformance::nonfinite_steps_are_rejected(&$candidate);
            }

            #[test]
            fn fifty_training_steps() {
                conformance::fifty_training_steps(&$candidate);
            }

            #[test]
            fn mapping_steps() {
                conformance::mapping_steps(&$candidate);
            }

            #[test]
            fn full_image_render() {
                conformance::full_image_render(&$candidate);
            }

            #[test]
            fn contract_errors() {
                conformance::contract_errors(&$candidate);
            }
        }
    )*};
}

conformance_suite! {
    cpu_1_thread: Cpu(1);
    cpu_2_threads: Cpu(2);
    cpu_8_threads: Cpu(8);
    vulkan: Vulkan;
}
