//! Vulkan backend for himap: [`VulkanBackend`] implements `himap_core::train::backend::Backend` with
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
mod buffers;
pub mod device;
mod error;
mod passes;
mod raw;

pub use backend::{PassTime, VulkanBackend, VulkanOptions};
pub use device::{
    check_division, check_pipelines, describe_devices, divide_on_device, division_pairs,
    list_devices, DeviceInfo, DeviceKind, DEVICE_ENV,
};
pub use error::VulkanError;
pub use passes::BackwardPass;

/// The post-processed SPIR-V module with every entry point (little-endian words; use
/// `ash::util::read_spv` to get aligned `u32`s). Committed: `himap-shader-build` writes it
/// from `shaders/` and `himap-core` (see the README's "Rebuilding the shaders").
pub const SHADERS_SPV: &[u8] = include_bytes!("../spirv/himap_shaders.spv");

mod shader_info {
    include!("../spirv/shader_info.rs");
}
pub use shader_info::{ENTRY_POINTS, NO_CONTRACTION_DECORATIONS};

/// The CPU/GPU interface (entry points with their bindings and push-constant sizes, record
/// sizes, push-constant blocks, layouts as words), defined once in `himap-core`.
pub use himap_core::gpu_abi::{entry, words, EntryPoint, WORKGROUP_SIZE};

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

/// Environment variable naming another SPIR-V module for the backend to run instead of the
/// built-in one (diagnosis of a driver: variants of the shaders without rebuilding `himap`).
/// The file must declare every entry point with the built-in layouts.
pub const SPIRV_ENV: &str = "HIMAP_SPIRV";

/// The module the backend runs: the file named by [`SPIRV_ENV`] when it is set (an error
/// when it cannot be read or is not SPIR-V), else the built-in [`shader_words`].
pub fn runtime_shader_words() -> Result<Vec<u32>, VulkanError> {
    match std::env::var(SPIRV_ENV) {
        Ok(path) => read_spirv(std::path::Path::new(&path))
            .map_err(|why| VulkanError::Module(format!("{SPIRV_ENV}={path}: {why}"))),
        Err(_) => Ok(shader_words()),
    }
}

/// A SPIR-V module file as `u32` words (little-endian); the error says why it is not one.
pub fn read_spirv(path: &std::path::Path) -> Result<Vec<u32>, String> {
    let b = std::fs::read(path).map_err(|e| format!("reading {}: {e}", path.display()))?;
    if b.len() % 4 != 0 || b.len() < 20 || b[..4] != [0x03, 0x02, 0x23, 0x07] {
        return Err(format!("{} is not a SPIR-V module", path.display()));
    }
    Ok(b.chunks_exact(4)
        .map(|w| u32::from_le_bytes([w[0], w[1], w[2], w[3]]))
        .collect())
}

/// The built-in module as `u32` words.
pub fn shader_words() -> Vec<u32> {
    let (words, rest) = SHADERS_SPV.as_chunks::<4>();
    debug_assert!(rest.is_empty());
    words.iter().map(|w| u32::from_le_bytes(*w)).collect()
}

#[cfg(test)]
mod tests {
    use super::*;
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
        // The module's entry points are exactly the ABI's table.
        let table: BTreeSet<&str> = entry::ALL.iter().map(|e| e.name).collect();
        assert_eq!(listed, table);
        for e in entry::ALL {
            assert!(ENTRY_POINTS.contains(&e.name));
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
    /// declared count (`himap_core::gpu_abi::entry`, which the host's pipelines are built
    /// with). Caught a renumbering
    /// slip that gave `pixel_train_cs` two parameters at binding 8 and one at 9: lavapipe ran
    /// it without complaint, reading garbage.
    #[test]
    fn entry_point_bindings_are_distinct_and_in_range() {
        let declared: BTreeMap<&str, u32> =
            entry::ALL.iter().map(|e| (e.name, e.bindings)).collect();
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
            // The table's count is the module's: its last binding is used.
            assert_eq!(
                used.last().map(|b| b + 1),
                Some(count),
                "{name}: declared {count} bindings, the module uses {used:?}"
            );
        }
    }

    /// Bytes of a type of the module (scalars, vectors, arrays with a constant length,
    /// structs laid out by their `Offset` decorations).
    fn type_size(m: &Module, id: u32) -> u32 {
        let t = m
            .types_global_values
            .iter()
            .find(|i| i.result_id == Some(id))
            .expect("type defined");
        let id_at = |k: usize| match t.operands[k] {
            Operand::IdRef(x) => x,
            ref o => panic!("{o:?}"),
        };
        match t.class.opcode {
            Op::TypeInt | Op::TypeFloat => match t.operands[0] {
                Operand::LiteralBit32(w) => w / 8,
                ref o => panic!("{o:?}"),
            },
            Op::TypeVector => match t.operands[1] {
                Operand::LiteralBit32(n) => n * type_size(m, id_at(0)),
                ref o => panic!("{o:?}"),
            },
            Op::TypeArray => {
                let len = m
                    .types_global_values
                    .iter()
                    .find(|i| i.result_id == Some(id_at(1)))
                    .and_then(|c| match c.operands.first() {
                        Some(Operand::LiteralBit32(n)) => Some(*n),
                        _ => None,
                    })
                    .expect("array length is a constant");
                len * type_size(m, id_at(0))
            }
            Op::TypeStruct => (0..t.operands.len())
                .map(|k| {
                    let offset = m
                        .annotations
                        .iter()
                        .find_map(|a| match a.operands.as_slice() {
                            [Operand::IdRef(s), Operand::LiteralBit32(i), Operand::Decoration(Decoration::Offset), Operand::LiteralBit32(o)]
                                if *s == id && *i as usize == k =>
                            {
                                Some(*o)
                            }
                            _ => None,
                        })
                        .expect("struct member has an Offset");
                    offset + type_size(m, id_at(k))
                })
                .max()
                .unwrap_or(0),
            other => panic!("unexpected push-constant member type {other:?}"),
        }
    }

    /// Each entry point's push-constant block has the size the ABI's table says (the
    /// `#[repr(C)]` struct the host fills).
    #[test]
    fn entry_point_push_constants_have_the_table_size() {
        let declared: BTreeMap<&str, u32> =
            entry::ALL.iter().map(|e| (e.name, e.push_size)).collect();
        let m = module();
        // Push-constant variables and the struct each points to.
        let mut push_vars = BTreeMap::new();
        for v in &m.types_global_values {
            if v.class.opcode != Op::Variable
                || v.operands.first()
                    != Some(&Operand::StorageClass(
                        rspirv::spirv::StorageClass::PushConstant,
                    ))
            {
                continue;
            }
            let ptr = m
                .types_global_values
                .iter()
                .find(|t| t.result_id == v.result_type)
                .expect("pointer type");
            let pointee = match ptr.operands[1] {
                Operand::IdRef(x) => x,
                ref o => panic!("{o:?}"),
            };
            push_vars.insert(v.result_id.unwrap(), type_size(&m, pointee));
        }
        for e in &m.entry_points {
            let name = match &e.operands[2] {
                Operand::LiteralString(s) => s.clone(),
                _ => unreachable!(),
            };
            let sizes: Vec<u32> = e.operands[3..]
                .iter()
                .filter_map(|o| match o {
                    Operand::IdRef(id) => push_vars.get(id).copied(),
                    _ => None,
                })
                .collect();
            assert_eq!(
                sizes,
                vec![declared[name.as_str()]],
                "{name}: push-constant block size"
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
}
