//! Compiles the shader crate (`shaders/`) to the SPIR-V module the Vulkan backend embeds
//! (`vulkan/spirv/himap_shaders.spv`, with `vulkan/spirv/shader_info.rs`), then hardens it for
//! bit-exactness. The module is committed, so everything else builds on stable Rust; this tool
//! needs rust-gpu's pinned nightly (`shaders/rust-toolchain.toml` selects it in `shaders/`):
//!
//! ```sh
//! cd shaders && cargo run --release -p himap-shader-build            # rewrite the module
//! cd shaders && cargo run --release -p himap-shader-build -- --check # fail if it is stale
//! ```
//!
//! 1. `spirv-builder` (target `spirv-unknown-vulkan1.2`, capabilities `Int64` + `Int64Atomics`)
//!    builds the shader crate without rust-gpu's own spirv-opt run.
//! 2. A post-pass with `rspirv` rejects instructions whose GPU result is not bit-identical to
//!    the CPU's (GLSL.std.450 `Fma`, the approximate built-ins `Exp`, `Log`, `Sqrt`, `Pow`,
//!    `Sin`, ... that rust-gpu substitutes for `libm` calls, and `OpFRem`/`OpFMod`), then
//!    decorates the result of every float arithmetic instruction `NoContraction`, so neither
//!    spirv-opt nor a driver may fuse `a * b + c` into an FMA (the CPU never does).
//! 3. `spirv-opt -O` (the installed SPIRV-Tools), the same check again, no `OpFunctionCall`
//!    left (NVIDIA's driver hangs running kernels that call functions), NoContraction on any
//!    new float instruction, and `spirv-val --target-env vulkan1.2`.
//!
//! Why the order matters: SPIRV-Tools 2023.1 (Debian 12's `spirv-tools`) folds every
//! undecorated `a * b + c` into GLSL.std.450 `Fma`; lavapipe happens to lower `Fma` unfused,
//! real GPUs do not. With the decorations in place before spirv-opt it fuses nothing.
//!
//! CI runs `--check`: a kernel change (in `shaders/` or `himap-core`) cannot land with a stale
//! module. The output is deterministic for a given toolchain and SPIRV-Tools version.

use rspirv::binary::Assemble;
use rspirv::dr::{Instruction, Module, Operand};
use rspirv::spirv::{Decoration, Op};
use spirv_builder::{Capability, SpirvBuilder};
use std::collections::BTreeSet;
use std::env;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::process::{Command, ExitCode};

/// The nightly rust-gpu 0.11 needs (must match `shaders/rust-toolchain.toml`).
const TOOLCHAIN: &str = "nightly-2026-08-15";
const TARGET: &str = "spirv-unknown-vulkan1.2";
/// Where the module lives, relative to the repository root.
const SPV: &str = "vulkan/spirv/himap_shaders.spv";
const INFO: &str = "vulkan/spirv/shader_info.rs";

type BoxError = Box<dyn std::error::Error>;

fn main() -> ExitCode {
    let mut check = false;
    for a in env::args().skip(1) {
        match a.as_str() {
            "--check" => check = true,
            "-h" | "--help" => {
                println!(
                    "usage: cd shaders && cargo run --release -p himap-shader-build [-- --check]\n\
                     Writes {SPV} and {INFO}; with --check, compares them with a fresh build \
                     instead and fails when they differ."
                );
                return ExitCode::SUCCESS;
            }
            other => {
                eprintln!("error: unknown argument `{other}` (try --help)");
                return ExitCode::from(2);
            }
        }
    }
    match run(check) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("\nerror: himap-shader-build: {e}\n");
            ExitCode::FAILURE
        }
    }
}

fn run(check: bool) -> Result<(), BoxError> {
    check_toolchain()?;
    check_tool("spirv-opt")?;
    check_tool("spirv-val")?;

    let root = repository_root()?;
    let shader_crate = root.join("shaders");
    let builder = SpirvBuilder::new(&shader_crate, TARGET)
        .capability(Capability::Int64)
        .capability(Capability::Int64Atomics)
        // rust-gpu would run spirv-opt on the undecorated module, and SPIRV-Tools 2023.1
        // (Debian 12's) folds `a * b + c` into GLSL.std.450 `Fma` there. We run spirv-opt
        // ourselves after the NoContraction pass, which stops that fusion.
        .extra_arg("--no-spirv-opt");
    let result = builder.build().map_err(|e| {
        format!(
            "compiling the shaders (`{}`) with rust-gpu failed: {e}\n\
             (rust-gpu diagnostics are above; a Rust construct rust-gpu rejects in himap-core \
             shows up there with its source location)",
            shader_crate.display()
        )
    })?;
    let raw_path = result.module.unwrap_single();
    let raw = std::fs::read(raw_path)
        .map_err(|e| format!("reading the compiled module {}: {e}", raw_path.display()))?;
    let work = raw_path
        .parent()
        .ok_or("the compiled module has no folder")?
        .to_path_buf();

    // 1. Source-level checks and NoContraction on the unoptimized module.
    let mut module = rspirv::dr::load_bytes(&raw)
        .map_err(|e| format!("parsing {} with rspirv: {e}", raw_path.display()))?;
    check_forbidden(&module, FROM_SOURCE)?;
    let added_before = decorate_no_contraction(&mut module);
    let unopt_path = work.join("himap_shaders.unopt.spv");
    std::fs::write(&unopt_path, to_bytes(&module))?;

    // 2. Optimize (rust-gpu's own choice of passes), then check and decorate again: the
    //    optimizer may create new float instructions (they get decorated too) and must not
    //    have fused anything.
    let opt_path = work.join("himap_shaders.opt.spv");
    optimize(&unopt_path, &opt_path)?;
    let mut module = rspirv::dr::load_bytes(std::fs::read(&opt_path)?)
        .map_err(|e| format!("parsing {} with rspirv: {e}", opt_path.display()))?;
    check_forbidden(&module, FROM_OPTIMIZER)?;
    check_no_calls(&module)?;
    let added_after = decorate_no_contraction(&mut module);
    let entry_points = entry_point_names(&module);
    for name in &result.entry_points {
        if !entry_points.contains(name) {
            return Err(format!("entry point `{name}` missing from the module").into());
        }
    }
    let bytes = to_bytes(&module);
    std::fs::write(&opt_path, &bytes)?;
    validate(&opt_path)?;
    let decorations = count_no_contraction(&module);

    let mut info = String::new();
    writeln!(
        info,
        "// Written by himap-shader-build with the module beside it; do not edit.\n\
         /// Entry points of the module, in module order.\n\
         pub const ENTRY_POINTS: &[&str] = &{entry_points:?};\n\
         /// `NoContraction` decorations in the module.\n\
         pub const NO_CONTRACTION_DECORATIONS: usize = {decorations};"
    )?;
    println!(
        "shaders: {} entry points ({}); NoContraction: {added_before} added before spirv-opt, \
         {added_after} after, {decorations} in the module; {} bytes",
        entry_points.len(),
        entry_points.join(", "),
        bytes.len(),
    );
    let (spv, info_path) = (root.join(SPV), root.join(INFO));
    if check {
        let same_spv = std::fs::read(&spv).is_ok_and(|b| b == bytes);
        let same_info = std::fs::read_to_string(&info_path).is_ok_and(|s| s == info);
        if !(same_spv && same_info) {
            return Err(format!(
                "the committed module ({SPV}, {INFO}) differs from the shader sources' \
                 build{}: rebuild it with `cd shaders && cargo run --release -p \
                 himap-shader-build` and commit it",
                if same_spv {
                    " (only its info file)"
                } else {
                    ""
                }
            )
            .into());
        }
        println!("{SPV} and {INFO} match the sources");
    } else {
        std::fs::create_dir_all(spv.parent().ok_or("no folder")?)?;
        std::fs::write(&spv, &bytes)?;
        std::fs::write(&info_path, &info)?;
        println!("wrote {} and {}", spv.display(), info_path.display());
    }
    Ok(())
}

/// The checkout this tool runs for: `cargo run` gives the package's folder at run time (not
/// `env!`: cargo shares one binary between checkouts with the same layout through a common
/// target folder, and a path baked in at compile time would name another checkout); else
/// the first folder up from the current one with `shaders/builder/Cargo.toml`.
fn repository_root() -> Result<PathBuf, BoxError> {
    if let Some(dir) = env::var_os("CARGO_MANIFEST_DIR") {
        let root = PathBuf::from(dir).join("../..");
        if root.join("shaders/builder/Cargo.toml").is_file() {
            return Ok(root.canonicalize()?);
        }
    }
    let mut dir = env::current_dir()?;
    loop {
        if dir.join("shaders/builder/Cargo.toml").is_file() {
            return Ok(dir);
        }
        if !dir.pop() {
            return Err(
                "run this tool with `cargo run` in the repository's shaders/ folder".into(),
            );
        }
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
         -c rust-src,rustc-dev,llvm-tools` and run this tool from `shaders/`, where \
         rust-toolchain.toml selects it"
    );
    // the rustc the shader build will run (rustup picks shaders/rust-toolchain.toml there)
    let dir = repository_root()?.join("shaders");
    let rustc = "rustc".to_string();
    let out = Command::new(&rustc)
        .current_dir(&dir)
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
    let sysroot = Command::new(&rustc)
        .current_dir(&dir)
        .args(["--print", "sysroot"])
        .output()?;
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

/// Rejects a module whose kernels call functions (`OpFunctionCall`): NVIDIA's driver
/// (580.159 on an H200) built such kernels but hung running them, even a one-line kernel
/// calling a `#[inline(never)]` division (2026-12-04). Everything the kernels call must be
/// inlined.
fn check_no_calls(module: &Module) -> Result<(), BoxError> {
    let names: std::collections::BTreeMap<u32, String> = module
        .debug_names
        .iter()
        .filter(|i| i.class.opcode == Op::Name)
        .filter_map(|i| match (i.operands.first(), i.operands.get(1)) {
            (Some(Operand::IdRef(id)), Some(Operand::LiteralString(n))) => Some((*id, n.clone())),
            _ => None,
        })
        .collect();
    let mut called = BTreeSet::new();
    for f in &module.functions {
        for b in &f.blocks {
            for inst in &b.instructions {
                if inst.class.opcode == Op::FunctionCall {
                    if let Some(Operand::IdRef(id)) = inst.operands.first() {
                        called.insert(names.get(id).cloned().unwrap_or(format!("%{id}")));
                    }
                }
            }
        }
    }
    if called.is_empty() {
        return Ok(());
    }
    Err(format!(
        "the shader module calls functions ({}): NVIDIA's driver hangs running kernels that \
         call functions; mark them #[inline(always)]",
        called.into_iter().collect::<Vec<_>>().join(", ")
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
