//! Vulkan backend for himap: [`VulkanBackend`] implements `himap_core::step::Backend` with
//! rust-gpu compute shaders that give the CPU core's bits.
//!
//! - [`list_devices`] / [`describe_devices`]: the devices, their limits and features
//!   (`himap devices`);
//! - [`VulkanBackend::new`]: opens the device chosen by [`device`]'s rules (discrete, then
//!   integrated, then software; `HIMAP_VULKAN_DEVICE` by index or name substring);
//! - every `unsafe` ash call lives in the private `raw` module, each with a `SAFETY` comment;
//! - errors are [`VulkanError`] values with a remedy in the message; nothing panics.
//!
//! `build.rs` compiles `../shaders` with rust-gpu to one SPIR-V 1.5 module for Vulkan 1.2,
//! decorates every float operation `NoContraction` and validates it. Pipelines built from it
//! need the device features `shaderInt64`, `shaderBufferInt64Atomics` and `vulkanMemoryModel`.

#![deny(unsafe_code)]

mod backend;
pub mod device;
mod error;
mod raw;

pub use backend::{VulkanBackend, VulkanOptions};
pub use device::{describe_devices, list_devices, DeviceInfo, DeviceKind, DEVICE_ENV};
pub use error::VulkanError;

/// The post-processed SPIR-V module with every entry point (little-endian words; use
/// `ash::util::read_spv` to get aligned `u32`s).
pub const SHADERS_SPV: &[u8] = include_bytes!(env!("HIMAP_SHADERS_SPV"));

mod shader_info {
    include!(concat!(env!("OUT_DIR"), "/shader_info.rs"));
}
pub use shader_info::{ENTRY_POINTS, NO_CONTRACTION_DECORATIONS};

/// Entry point names (see `shaders/src/lib.rs` for their bindings).
pub mod entry {
    pub const PROBE: &str = "probe_cs";
    pub const FIXED_ACCUMULATE: &str = "fixed_accumulate_cs";
    pub const MLP_FORWARD: &str = "mlp_forward_cs";
    pub const GRID_FORWARD: &str = "grid_forward_cs";
    pub const SAMPLE_FORWARD: &str = "sample_forward_cs";
    pub const RAY_TRAIN: &str = "ray_train_cs";
    pub const SAMPLE_BACKWARD: &str = "sample_backward_cs";
    pub const RAY_RENDER: &str = "ray_render_cs";
    pub const PIXEL_RAYS: &str = "pixel_rays_cs";
    pub const PIXEL_TRAIN: &str = "pixel_train_cs";
    pub const ADAM: &str = "adam_cs";
    pub const LOSS_CHECK: &str = "loss_check_cs";
    pub const ADAM_CHECK: &str = "adam_check_cs";
    pub const SDF_QUERY: &str = "sdf_query_cs";
    pub const COLOR_QUERY: &str = "color_query_cs";
}

/// Workgroup size (x) of every entry point.
pub const WORKGROUP_SIZE: u32 = 64;

/// Fault injection for the GPU-failure tests (cargo feature `fault-injection`, test builds
/// only): after a given number of further mapping steps, every submission fails as on a lost
/// device. Process-wide, so a test that arms it runs in a test binary of its own.
#[cfg(feature = "fault-injection")]
pub mod fault {
    use std::sync::atomic::{AtomicBool, AtomicI64, Ordering};

    /// Mapping steps left before the device is "lost" (< 0: disarmed), and whether it is.
    static LEFT: AtomicI64 = AtomicI64::new(-1);
    static LOST: AtomicBool = AtomicBool::new(false);

    /// Lets `n` more mapping steps (`map_step`) succeed; the next one and every submission
    /// after it fail with `VulkanError::DeviceLost`, as on a GPU reset.
    pub fn lose_device_after_map_steps(n: u32) {
        LOST.store(false, Ordering::SeqCst);
        LEFT.store(n as i64, Ordering::SeqCst);
    }

    /// Back to normal operation.
    pub fn disarm() {
        LEFT.store(-1, Ordering::SeqCst);
        LOST.store(false, Ordering::SeqCst);
    }

    /// At every mapping step.
    pub(crate) fn map_step() -> Result<(), crate::VulkanError> {
        let left = LEFT.load(Ordering::SeqCst);
        if left == 0 {
            LOST.store(true, Ordering::SeqCst);
        } else if left > 0 {
            LEFT.store(left - 1, Ordering::SeqCst);
        }
        submit()
    }

    /// At every submission.
    pub(crate) fn submit() -> Result<(), crate::VulkanError> {
        if LOST.load(Ordering::SeqCst) {
            return Err(crate::VulkanError::DeviceLost);
        }
        Ok(())
    }
}

/// Layouts and scene constants as `u32` words, the exact encoding the shaders decode (one
/// source file shared with `himap-shaders`).
#[path = "../../shaders/src/words.rs"]
pub mod words;

/// The module as `u32` words.
pub fn shader_words() -> Vec<u32> {
    let (words, rest) = SHADERS_SPV.as_chunks::<4>();
    debug_assert!(rest.is_empty());
    words.iter().map(|w| u32::from_le_bytes(*w)).collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use himap_core::camera::{Intrinsics, Pose};
    use himap_core::grid::{GridConfig, GridKind, GridLayout};
    use himap_core::Aabb;
    use rspirv::dr::{Module, Operand};
    use rspirv::spirv::{Capability, Decoration, ExecutionMode, Op};
    use std::collections::{BTreeMap, BTreeSet};

    fn module() -> Module {
        rspirv::dr::load_words(shader_words()).expect("module parses")
    }

    #[test]
    fn module_has_entry_points_and_capabilities() {
        let m = module();
        let mut names = BTreeMap::new();
        for e in &m.entry_points {
            match (&e.operands[0], &e.operands[1], &e.operands[2]) {
                (
                    Operand::ExecutionModel(rspirv::spirv::ExecutionModel::GLCompute),
                    Operand::IdRef(id),
                    Operand::LiteralString(s),
                ) => {
                    names.insert(*id, s.clone());
                }
                other => panic!("unexpected entry point {other:?}"),
            }
        }
        let listed: BTreeSet<&str> = names.values().map(|s| s.as_str()).collect();
        for want in [
            entry::PROBE,
            entry::FIXED_ACCUMULATE,
            entry::MLP_FORWARD,
            entry::GRID_FORWARD,
            entry::SAMPLE_FORWARD,
            entry::RAY_TRAIN,
            entry::SAMPLE_BACKWARD,
            entry::RAY_RENDER,
            entry::PIXEL_RAYS,
            entry::PIXEL_TRAIN,
            entry::ADAM,
            entry::SDF_QUERY,
            entry::COLOR_QUERY,
        ] {
            assert!(listed.contains(want), "{want} missing from {listed:?}");
            assert!(ENTRY_POINTS.contains(&want));
        }
        assert_eq!(listed.len(), ENTRY_POINTS.len());
        // Every entry point runs 64 x 1 x 1 invocations per workgroup.
        let mut sized = BTreeSet::new();
        for x in &m.execution_modes {
            if let [Operand::IdRef(id), Operand::ExecutionMode(ExecutionMode::LocalSize), Operand::LiteralBit32(a), Operand::LiteralBit32(b), Operand::LiteralBit32(c)] =
                x.operands.as_slice()
            {
                assert_eq!((*a, *b, *c), (WORKGROUP_SIZE, 1, 1), "{}", names[id]);
                sized.insert(*id);
            }
        }
        assert_eq!(sized.len(), names.len());
        let caps: BTreeSet<Capability> = m
            .capabilities
            .iter()
            .filter_map(|c| match c.operands[0] {
                Operand::Capability(c) => Some(c),
                _ => None,
            })
            .collect();
        for c in [
            Capability::Shader,
            Capability::Int64,
            Capability::Int64Atomics,
            Capability::VulkanMemoryModel,
        ] {
            assert!(caps.contains(&c), "{c:?} missing from {caps:?}");
        }
    }

    /// Each entry point uses every storage-buffer binding at most once and none past its
    /// declared count (the counts the host's pipelines are built with). Caught a renumbering
    /// slip that gave `pixel_train_cs` two parameters at binding 8 and one at 9: lavapipe ran
    /// it without complaint, reading garbage.
    #[test]
    fn entry_point_bindings_are_distinct_and_in_range() {
        let declared: BTreeMap<&str, u32> = [
            (entry::PROBE, 2),
            (entry::FIXED_ACCUMULATE, 2),
            (entry::MLP_FORWARD, 4),
            (entry::GRID_FORWARD, 4),
            (entry::SAMPLE_FORWARD, 10),
            (entry::RAY_TRAIN, 6),
            (entry::SAMPLE_BACKWARD, 17),
            (entry::RAY_RENDER, 5),
            (entry::PIXEL_RAYS, 4),
            (entry::PIXEL_TRAIN, 9),
            (entry::ADAM, 5),
            (entry::LOSS_CHECK, 2),
            (entry::ADAM_CHECK, 5),
            (entry::SDF_QUERY, 10),
            (entry::COLOR_QUERY, 10),
        ]
        .into_iter()
        .collect();
        let m = module();
        let mut binding = BTreeMap::new();
        for a in &m.annotations {
            if let [Operand::IdRef(id), Operand::Decoration(Decoration::Binding), Operand::LiteralBit32(b)] =
                a.operands.as_slice()
            {
                binding.insert(*id, *b);
            }
        }
        for e in &m.entry_points {
            let name = match &e.operands[2] {
                Operand::LiteralString(s) => s.clone(),
                _ => unreachable!(),
            };
            let count = declared[name.as_str()];
            let mut used: Vec<u32> = e.operands[3..]
                .iter()
                .filter_map(|o| match o {
                    Operand::IdRef(id) => binding.get(id).copied(),
                    _ => None,
                })
                .collect();
            used.sort_unstable();
            let n = used.len();
            used.dedup();
            assert_eq!(used.len(), n, "{name}: a binding used twice: {used:?}");
            assert!(
                used.iter().all(|&b| b < count),
                "{name}: bindings {used:?} past its {count}"
            );
        }
    }

    #[test]
    fn every_float_op_is_no_contraction_and_no_fma() {
        let m = module();
        let decorated: BTreeSet<u32> = m
            .annotations
            .iter()
            .filter(|a| {
                a.class.opcode == Op::Decorate
                    && a.operands[1] == Operand::Decoration(Decoration::NoContraction)
            })
            .map(|a| match a.operands[0] {
                Operand::IdRef(id) => id,
                _ => unreachable!(),
            })
            .collect();
        let mut float_ops = 0;
        let mut glsl_fma = 0;
        let mut frem = 0;
        for f in &m.functions {
            for b in &f.blocks {
                for i in &b.instructions {
                    match i.class.opcode {
                        Op::FAdd | Op::FSub | Op::FMul | Op::FDiv | Op::FNegate | Op::Dot => {
                            float_ops += 1;
                            let id = i.result_id.unwrap();
                            assert!(decorated.contains(&id), "%{id} {:?} undecorated", i);
                        }
                        // GLSL.std.450 Fma is extended instruction 50.
                        Op::ExtInst
                            if i.operands.get(1) == Some(&Operand::LiteralExtInstInteger(50)) =>
                        {
                            glsl_fma += 1
                        }
                        Op::FRem | Op::FMod => frem += 1,
                        _ => {}
                    }
                }
            }
        }
        assert!(float_ops > 0);
        assert!(decorated.len() >= float_ops);
        assert_eq!(NO_CONTRACTION_DECORATIONS, decorated.len());
        // build.rs rejects these (and the approximate GLSL.std.450 built-ins).
        assert_eq!((glsl_fma, frem), (0, 0));
    }

    /// Gradient atomics add 64-bit fixed-point integers; the only other atomics are the
    /// 32-bit counts of non-finite values (`loss_check_cs`, `adam_check_cs`), which add 1.
    #[test]
    fn fixed_accumulate_uses_64_bit_atomics() {
        let m = module();
        let int_types = |bits: u32| -> BTreeSet<u32> {
            m.types_global_values
                .iter()
                .filter(|t| {
                    t.class.opcode == Op::TypeInt
                        && t.operands.first() == Some(&Operand::LiteralBit32(bits))
                })
                .filter_map(|t| t.result_id)
                .collect()
        };
        let i64_types = int_types(64);
        let counts = int_types(32);
        let atomics: Vec<_> = m
            .functions
            .iter()
            .flat_map(|f| f.blocks.iter())
            .flat_map(|b| b.instructions.iter())
            .filter(|i| i.class.opcode == Op::AtomicIAdd)
            .collect();
        assert!(!atomics.is_empty());
        let wide = atomics
            .iter()
            .filter(|a| i64_types.contains(&a.result_type.unwrap()))
            .count();
        let narrow = atomics
            .iter()
            .filter(|a| counts.contains(&a.result_type.unwrap()))
            .count();
        assert!(wide > 0, "no 64-bit atomics");
        assert_eq!(wide + narrow, atomics.len(), "atomics of another type");
        // one count per check entry point (inlined once each)
        assert!(
            narrow <= 2,
            "{narrow} 32-bit atomics: only the two checks count"
        );
    }

    #[test]
    fn words_round_trip() {
        let aabb = Aabb::new([-1.0, -2.0, 0.5], [3.0, 1.0, 2.75]);
        for kind in [GridKind::Factorized, GridKind::Dense] {
            let g = GridLayout::new(&GridConfig::hi_map_geometry().with_kind(kind), aabb).unwrap();
            let mut w = [0u32; words::GRID_LAYOUT];
            words::grid_layout_to_words(&g, &mut w, 0);
            assert_eq!(words::grid_layout_from_words(&w, 0), g);
            // Words past the end of a short buffer read as zeros instead of panicking.
            let short = words::grid_layout_from_words(&w[..3], 0);
            assert_eq!((short.levels, short.param_count), (g.levels, 0));
            assert_eq!((short.aabb.max, short.level[0].res), ([0.0; 3], [0; 3]));
        }
        let pose = Pose {
            m: [
                [0.0, 0.0, 1.0, 1.5],
                [0.0, 1.0, 0.0, -2.0],
                [-1.0, 0.0, 0.0, 3.25],
            ],
        };
        let k = Intrinsics {
            width: 1200,
            height: 680,
            fx: 600.0,
            fy: 600.5,
            cx: 599.5,
            cy: 339.5,
        };
        let mut w = [0u32; words::AABB + words::POSE + words::INTRINSICS];
        words::aabb_to_words(&aabb, &mut w, 0);
        words::pose_to_words(&pose, &mut w, 6);
        words::intrinsics_to_words(&k, &mut w, 18);
        assert_eq!(words::aabb_from_words(&w, 0), aabb);
        assert_eq!(words::pose_from_words(&w, 6), pose);
        assert_eq!(words::intrinsics_from_words(&w, 18), k);
        assert_eq!(w[0], (-1.0f32).to_bits());
        assert_eq!(w[18], 1200);
        // The whole model layout (what train/render/query shaders decode), every render mode.
        for mode in [
            himap_core::render::RenderMode::SdfDensity,
            himap_core::render::RenderMode::SdfDirect,
            himap_core::render::RenderMode::Occupancy,
        ] {
            let mut cfg = himap_core::model::ModelConfig::paper(aabb);
            cfg.render_mode = mode;
            cfg.dual_path = mode != himap_core::render::RenderMode::SdfDirect;
            cfg.appearance_grid = cfg.appearance_grid.with_kind(GridKind::Dense);
            cfg.appearance_grid.cell_sizes[1] = 0.5;
            let l = himap_core::model::ModelLayout::new(&cfg).unwrap();
            let mut w = vec![0u32; words::MODEL_LAYOUT];
            words::model_layout_to_words(&l, &mut w, 0);
            assert_eq!(words::model_layout_from_words(&w, 0), l);
        }
    }
}
