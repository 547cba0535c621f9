//! Compiles `../shaders` to one SPIR-V module with rust-gpu, then hardens it for bit-exactness:
//!
//! 1. `spirv-builder` (target `spirv-unknown-vulkan1.2`, capabilities `Int64` + `Int64Atomics`)
//!    builds the shader crate with the pinned nightly (see `rust-toolchain.toml`), without
//!    rust-gpu's own spirv-opt run.
//! 2. A post-pass with `rspirv` rejects instructions whose GPU result is not bit-identical to
//!    the CPU's (GLSL.std.450 `Fma`, the approximate built-ins `Exp`, `Log`, `Sqrt`, `Pow`,
//!    `Sin`, ... that rust-gpu substitutes for `libm` calls, and `OpFRem`/`OpFMod`), then
//!    decorates the result of every float arithmetic instruction `NoContraction`, so neither
//!    spirv-opt nor a driver may fuse `a * b + c` into an FMA (the CPU never does).
//! 3. `spirv-opt -O` (the installed SPIRV-Tools), the same check again, NoContraction on any
//!    new float instruction, and `spirv-val --target-env vulkan1.2`.
//!
//! Why the order matters: SPIRV-Tools 2023.1 (Debian 12's `spirv-tools`) folds every
//! undecorated `a * b + c` into GLSL.std.450 `Fma`; lavapipe happens to lower `Fma` unfused,
//! real GPUs do not. With the decorations in place before spirv-opt it fuses nothing.
//!
//! Outputs: `$OUT_DIR/himap_shaders.spv` (exported as `HIMAP_SHADERS_SPV`) and
//! `$OUT_DIR/shader_info.rs` (entry point names, decoration count), both used by `src/lib.rs`.
//! Set `HIMAP_VERBOSE_BUILD=1` to get the post-pass summary as a cargo warning (it is always
//! printed to the build script's stdout, visible with `cargo build -vv`).

// `std::io::set_output_capture` (see `build_filtered`); this build needs the pinned nightly
// anyway (rustc_codegen_spirv).
#![feature(internal_output_capture)]
#![allow(internal_features)]

use rspirv::binary::Assemble;
use rspirv::dr::{Instruction, Module, Operand};
use rspirv::spirv::{Decoration, Op};
use spirv_builder::{Capability, CompileResult, SpirvBuilder};
use std::collections::BTreeSet;
use std::env;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::{Arc, Mutex};

/// The nightly rust-gpu 0.11 needs (must match `rust-toolchain.toml`).
const TOOLCHAIN: &str = "nightly-2026-08-15";
const TARGET: &str = "spirv-unknown-vulkan1.2";

type BoxError = Box<dyn std::error::Error>;

fn main() {
    if let Err(e) = run() {
        // cargo shows the build script's stderr when it fails.
        eprintln!("\nerror: himap-vulkan build script: {e}\n");
        std::process::exit(1);
    }
}

fn run() -> Result<(), BoxError> {
    println!("cargo::rerun-if-env-changed=HIMAP_VERBOSE_BUILD");
    check_toolchain()?;
    check_tool("spirv-opt")?;
    check_tool("spirv-val")?;

    let manifest = PathBuf::from(env::var("CARGO_MANIFEST_DIR")?);
    let root = manifest.join("..");
    let shader_crate = root.join("shaders");
    // spirv-builder reports the shader and himap-core sources; manifests and the toolchain
    // pin matter too.
    for f in [
        "Cargo.toml",
        "Cargo.lock",
        "rust-toolchain.toml",
        "shaders/Cargo.toml",
        "core/Cargo.toml",
    ] {
        println!("cargo::rerun-if-changed={}", root.join(f).display());
    }
    let mut builder = SpirvBuilder::new(&shader_crate, TARGET)
        .capability(Capability::Int64)
        .capability(Capability::Int64Atomics)
        // rust-gpu would run spirv-opt on the undecorated module, and SPIRV-Tools 2023.1
        // (Debian 12's) folds `a * b + c` into GLSL.std.450 `Fma` there. We run spirv-opt
        // ourselves after the NoContraction pass, which stops that fusion.
        .extra_arg("--no-spirv-opt");
    // rerun-if-changed on every shader and himap-core source, forward rustc diagnostics.
    builder.build_script.defaults = true;
    // We export the post-processed module ourselves (HIMAP_SHADERS_SPV); the raw module's
    // `himap_shaders.spv` variable would only invite using the undecorated one.
    builder.build_script.env_shader_spv_path = Some(false);
    let result = build_filtered(&builder).map_err(|e| {
        format!(
            "compiling the shaders (`{}`) with rust-gpu failed: {e}\n\
             (rust-gpu diagnostics are above as warnings; a Rust construct rust-gpu rejects in \
             himap-core shows up there with its source location)",
            shader_crate.display()
        )
    })?;
    let raw_path = result.module.unwrap_single();
    let raw = std::fs::read(raw_path)
        .map_err(|e| format!("reading the compiled module {}: {e}", raw_path.display()))?;

    // 1. Source-level checks and NoContraction on the unoptimized module.
    let mut module = rspirv::dr::load_bytes(&raw)
        .map_err(|e| format!("parsing {} with rspirv: {e}", raw_path.display()))?;
    check_forbidden(&module, FROM_SOURCE)?;
    let added_before = decorate_no_contraction(&mut module);
    let out_dir = PathBuf::from(env::var("OUT_DIR")?);
    let unopt_path = out_dir.join("himap_shaders.unopt.spv");
    std::fs::write(&unopt_path, to_bytes(&module))?;

    // 2. Optimize (rust-gpu's own choice of passes), then check and decorate again: the
    //    optimizer may create new float instructions (they get decorated too) and must not
    //    have fused anything.
    let spv_path = out_dir.join("himap_shaders.spv");
    optimize(&unopt_path, &spv_path)?;
    let mut module = rspirv::dr::load_bytes(std::fs::read(&spv_path)?)
        .map_err(|e| format!("parsing {} with rspirv: {e}", spv_path.display()))?;
    check_forbidden(&module, FROM_OPTIMIZER)?;
    let added_after = decorate_no_contraction(&mut module);
    let entry_points = entry_point_names(&module);
    for name in &result.entry_points {
        if !entry_points.contains(name) {
            return Err(format!("entry point `{name}` missing from the module").into());
        }
    }
    let bytes = to_bytes(&module);
    std::fs::write(&spv_path, &bytes)?;
    validate(&spv_path)?;
    let decorations = count_no_contraction(&module);

    let mut info = String::new();
    writeln!(
        info,
        "/// Entry points of the module, in module order.\n\
         pub const ENTRY_POINTS: &[&str] = &{entry_points:?};\n\
         /// `NoContraction` decorations in the module.\n\
         pub const NO_CONTRACTION_DECORATIONS: usize = {decorations};"
    )?;
    std::fs::write(out_dir.join("shader_info.rs"), info)?;

    let summary = format!(
        "shaders: {} entry points ({}); NoContraction: {added_before} added before spirv-opt, \
         {added_after} after, {decorations} in the module; {} bytes -> {}",
        entry_points.len(),
        entry_points.join(", "),
        bytes.len(),
        spv_path.display()
    );
    println!("{summary}");
    if env::var_os("HIMAP_VERBOSE_BUILD").is_some_and(|v| !v.is_empty() && v != "0") {
        println!("cargo::warning={summary}");
    }
    println!("cargo::rustc-env=HIMAP_SHADERS_SPV={}", spv_path.display());
    Ok(())
}

/// Runs the builder, passing its build-script output (rerun-if-changed lines, forwarded rustc
/// diagnostics) through except rust-gpu's warning that we disabled its spirv-opt run.
fn build_filtered(builder: &SpirvBuilder) -> Result<CompileResult, BoxError> {
    let sink = Arc::new(Mutex::new(Vec::<u8>::new()));
    let previous = std::io::set_output_capture(Some(sink.clone()));
    let result = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| builder.build()));
    std::io::set_output_capture(previous);
    let captured = sink.lock().map(|b| b.clone()).unwrap_or_default();
    let mut skip_blank = false;
    for line in String::from_utf8_lossy(&captured).lines() {
        if line.contains("`spirv-opt` should have ran") {
            skip_blank = true;
            continue;
        }
        if skip_blank && line.trim() == "cargo::warning=" {
            skip_blank = false;
            continue;
        }
        skip_blank = false;
        println!("{line}");
    }
    match result {
        Ok(r) => Ok(r?),
        Err(panic) => std::panic::resume_unwind(panic),
    }
}

fn to_bytes(module: &Module) -> Vec<u8> {
    module
        .assemble()
        .iter()
        .flat_map(|w| w.to_le_bytes())
        .collect()
}

/// `spirv-opt` with the passes rust-gpu uses for an optimized build without debug info.
fn optimize(input: &Path, output: &Path) -> Result<(), BoxError> {
    let out = Command::new("spirv-opt")
        .args([
            "--target-env=vulkan1.2",
            "-O",
            "--eliminate-dead-const",
            "--strip-debug",
        ])
        .arg(input)
        .arg("-o")
        .arg(output)
        .output()
        .map_err(|e| format!("running spirv-opt: {e}"))?;
    if !out.status.success() {
        return Err(format!(
            "spirv-opt failed on {}:\n{}{}",
            input.display(),
            String::from_utf8_lossy(&out.stdout),
            String::from_utf8_lossy(&out.stderr)
        )
        .into());
    }
    Ok(())
}

/// The compiler this build runs with must be the pinned nightly with `rust-src` (for
/// `-Zbuild-std=core`) and `rustc-dev` (rustc_codegen_spirv's own build checks the commit hash
/// and `rustc-dev` before we get here; this repeats it with a himap-specific hint).
fn check_toolchain() -> Result<(), BoxError> {
    let hint = format!(
        "install it with `rustup toolchain install {TOOLCHAIN} --profile minimal \
         -c rust-src,rustc-dev,llvm-tools` and build from the workspace root, where \
         rust-toolchain.toml selects it (himap-core alone also builds on stable: \
         `cargo +stable build -p himap-core`)"
    );
    let rustc = env::var("RUSTC").unwrap_or_else(|_| "rustc".into());
    let out = Command::new(&rustc)
        .args(["-vV"])
        .output()
        .map_err(|e| format!("running `{rustc} -vV`: {e}"))?;
    let version = String::from_utf8_lossy(&out.stdout);
    if !version.contains("nightly") || !version.contains("2026-08-14") {
        return Err(format!(
            "the shaders need the {TOOLCHAIN} toolchain (rustc 1.99.0-nightly 2026-08-14), \
             but this build uses:\n{version}\n{hint}"
        )
        .into());
    }
    let sysroot = Command::new(&rustc).args(["--print", "sysroot"]).output()?;
    let sysroot = PathBuf::from(String::from_utf8_lossy(&sysroot.stdout).trim());
    let rustlib = sysroot.join("lib").join("rustlib");
    for (component, path) in [
        ("rust-src", rustlib.join("src/rust/library/core")),
        (
            "rustc-dev",
            rustlib.join("rustc-src/rust/compiler/rustc_codegen_ssa"),
        ),
    ] {
        if !path.is_dir() {
            return Err(format!(
                "the {TOOLCHAIN} toolchain at {} lacks the `{component}` component; {hint}",
                sysroot.display()
            )
            .into());
        }
    }
    Ok(())
}

/// spirv-builder is built with `use-installed-tools`: it runs SPIRV-Tools' binaries from PATH.
fn check_tool(tool: &str) -> Result<(), BoxError> {
    match Command::new(tool).arg("--version").output() {
        Ok(o) if o.status.success() => Ok(()),
        _ => Err(format!(
            "`{tool}` not found on PATH: the shader build uses the installed SPIRV-Tools \
             (spirv-builder feature `use-installed-tools`); install them with \
             `apt-get install -y spirv-tools`"
        )
        .into()),
    }
}

/// Float instructions whose result a driver could contract with a neighbour (FMA).
fn is_float_arith(op: Op) -> bool {
    matches!(
        op,
        Op::FAdd
            | Op::FSub
            | Op::FMul
            | Op::FDiv
            | Op::FNegate
            | Op::FRem
            | Op::FMod
            | Op::VectorTimesScalar
            | Op::MatrixTimesScalar
            | Op::VectorTimesMatrix
            | Op::MatrixTimesVector
            | Op::MatrixTimesMatrix
            | Op::OuterProduct
            | Op::Dot
    )
}

/// GLSL.std.450 instructions that give the CPU's bits on every Vulkan implementation: integer
/// min/max/clamp and bit scans, `FAbs`, `Floor`, `Ceil`, `Trunc`, `RoundEven`, and the
/// NaN-defined `NMin`/`NMax`/`NClamp`. Everything else is an approximation (Vulkan allows ULP
/// errors; lavapipe's `Exp` flushes subnormals), may be fused (`Fma`, `FMix`, `SmoothStep`),
/// or leaves NaN/halfway cases to the driver (`FMin`/`FMax`/`FClamp` from `f32::min`/`max`/
/// `clamp`, `FSign`, `Round`).
fn glsl_name(n: u32) -> Option<(&'static str, bool)> {
    const NAMES: [&str; 82] = [
        "?",
        "Round",
        "RoundEven",
        "Trunc",
        "FAbs",
        "SAbs",
        "FSign",
        "SSign",
        "Floor",
        "Ceil",
        "Fract",
        "Radians",
        "Degrees",
        "Sin",
        "Cos",
        "Tan",
        "Asin",
        "Acos",
        "Atan",
        "Sinh",
        "Cosh",
        "Tanh",
        "Asinh",
        "Acosh",
        "Atanh",
        "Atan2",
        "Pow",
        "Exp",
        "Log",
        "Exp2",
        "Log2",
        "Sqrt",
        "InverseSqrt",
        "Determinant",
        "MatrixInverse",
        "Modf",
        "ModfStruct",
        "FMin",
        "UMin",
        "SMin",
        "FMax",
        "UMax",
        "SMax",
        "FClamp",
        "UClamp",
        "SClamp",
        "FMix",
        "IMix",
        "Step",
        "SmoothStep",
        "Fma",
        "Frexp",
        "FrexpStruct",
        "Ldexp",
        "PackSnorm4x8",
        "PackUnorm4x8",
        "PackSnorm2x16",
        "PackUnorm2x16",
        "PackHalf2x16",
        "PackDouble2x32",
        "UnpackSnorm2x16",
        "UnpackUnorm2x16",
        "UnpackHalf2x16",
        "UnpackSnorm4x8",
        "UnpackUnorm4x8",
        "UnpackDouble2x32",
        "Length",
        "Distance",
        "Cross",
        "Normalize",
        "FaceForward",
        "Reflect",
        "Refract",
        "FindILsb",
        "FindSMsb",
        "FindUMsb",
        "InterpolateAtCentroid",
        "InterpolateAtSample",
        "InterpolateAtOffset",
        "NMin",
        "NMax",
        "NClamp",
    ];
    const EXACT: [u32; 18] = [
        2, 3, 4, 5, 8, 9, 38, 39, 41, 42, 44, 45, 73, 74, 75, 79, 80, 81,
    ];
    let name = NAMES.get(n as usize)?;
    Some((name, EXACT.contains(&n)))
}

const FROM_SOURCE: &str = "GLSL.std.450 built-ins come from calls into the `libm` crate \
     (rust-gpu replaces e.g. `libm::expf` with `Exp`), from glam/f32 methods that go through \
     libm, from `mul_add` (`Fma`) or from `f32::min`/`max`/`clamp`/`signum`/`round`; \
     OpFRem/OpFMod from `%` on floats. Kernels must use `himap_core::math` (vendored \
     plain-f32 math) instead; see DESIGN.md, \"Kernels that must compile for both CPU and \
     SPIR-V\".";
const FROM_OPTIMIZER: &str = "They were not in rust-gpu's output, so spirv-opt created them \
     (the NoContraction decorations should prevent fusion; check the SPIRV-Tools version).";

/// Rejects instructions whose GPU result differs from the CPU's.
fn check_forbidden(module: &Module, why: &str) -> Result<(), BoxError> {
    let glsl: BTreeSet<u32> = module
        .ext_inst_imports
        .iter()
        .filter(|i| matches!(i.operands.first(), Some(Operand::LiteralString(s)) if s == "GLSL.std.450"))
        .filter_map(|i| i.result_id)
        .collect();
    let mut found = BTreeSet::new();
    for f in &module.functions {
        for b in &f.blocks {
            for inst in &b.instructions {
                match inst.class.opcode {
                    Op::ExtInst => {
                        if let (
                            Some(Operand::IdRef(set)),
                            Some(Operand::LiteralExtInstInteger(n)),
                        ) = (inst.operands.first(), inst.operands.get(1))
                        {
                            if glsl.contains(set) {
                                match glsl_name(*n) {
                                    Some((_, true)) => {}
                                    Some((name, false)) => {
                                        found.insert(format!("GLSL.std.450 {name}"));
                                    }
                                    None => {
                                        found.insert(format!("GLSL.std.450 #{n}"));
                                    }
                                }
                            }
                        }
                    }
                    Op::FRem | Op::FMod => {
                        found.insert(format!("Op{:?}", inst.class.opcode));
                    }
                    _ => {}
                }
            }
        }
    }
    if found.is_empty() {
        return Ok(());
    }
    Err(format!(
        "the shader module contains instructions that are not bit-identical between CPU and \
         GPU: {}.\n{why}",
        found.into_iter().collect::<Vec<_>>().join(", ")
    )
    .into())
}

/// Ids decorated `NoContraction`.
fn no_contraction_ids(module: &Module) -> BTreeSet<u32> {
    module
        .annotations
        .iter()
        .filter(|a| {
            a.class.opcode == Op::Decorate
                && matches!(
                    a.operands.get(1),
                    Some(Operand::Decoration(Decoration::NoContraction))
                )
        })
        .filter_map(|a| match a.operands.first() {
            Some(Operand::IdRef(id)) => Some(*id),
            _ => None,
        })
        .collect()
}

fn count_no_contraction(module: &Module) -> usize {
    no_contraction_ids(module).len()
}

/// Adds `OpDecorate %r NoContraction` for the result of every float arithmetic instruction
/// that does not have it yet; returns how many were added.
fn decorate_no_contraction(module: &mut Module) -> usize {
    let already = no_contraction_ids(module);
    let mut targets = BTreeSet::new();
    for f in &module.functions {
        for b in &f.blocks {
            for inst in &b.instructions {
                if is_float_arith(inst.class.opcode) {
                    if let Some(id) = inst.result_id {
                        if !already.contains(&id) {
                            targets.insert(id);
                        }
                    }
                }
            }
        }
    }
    for &id in &targets {
        module.annotations.push(Instruction::new(
            Op::Decorate,
            None,
            None,
            vec![
                Operand::IdRef(id),
                Operand::Decoration(Decoration::NoContraction),
            ],
        ));
    }
    targets.len()
}

fn entry_point_names(module: &Module) -> Vec<String> {
    module
        .entry_points
        .iter()
        .filter_map(|e| match e.operands.get(2) {
            Some(Operand::LiteralString(s)) => Some(s.clone()),
            _ => None,
        })
        .collect()
}

fn validate(spv: &Path) -> Result<(), BoxError> {
    let out = Command::new("spirv-val")
        .args(["--target-env", "vulkan1.2"])
        .arg(spv)
        .output()
        .map_err(|e| format!("running spirv-val: {e}"))?;
    if !out.status.success() {
        return Err(format!(
            "spirv-val --target-env vulkan1.2 rejects the post-processed module {}:\n{}{}",
            spv.display(),
            String::from_utf8_lossy(&out.stdout),
            String::from_utf8_lossy(&out.stderr)
        )
        .into());
    }
    Ok(())
}
