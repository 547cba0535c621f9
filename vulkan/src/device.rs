//! Device discovery and selection: discrete GPU first, then integrated, virtual, CPU (lavapipe),
//! other; `HIMAP_VULKAN_DEVICE` picks one by index (as listed by [`list_devices`]) or by a
//! case-insensitive name substring.

use crate::error::VulkanError;
use crate::raw::{self, Instance, PhysicalInfo};
use ash::vk;
use std::fmt::Write as _;
use std::sync::Arc;

/// Environment variable that picks a device by index or name substring.
pub const DEVICE_ENV: &str = "HIMAP_VULKAN_DEVICE";

/// Kind of a physical device.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord)]
pub enum DeviceKind {
    Discrete,
    Integrated,
    Virtual,
    Cpu,
    Other,
}

impl DeviceKind {
    fn from_vk(t: vk::PhysicalDeviceType) -> Self {
        match t {
            vk::PhysicalDeviceType::DISCRETE_GPU => Self::Discrete,
            vk::PhysicalDeviceType::INTEGRATED_GPU => Self::Integrated,
            vk::PhysicalDeviceType::VIRTUAL_GPU => Self::Virtual,
            vk::PhysicalDeviceType::CPU => Self::Cpu,
            _ => Self::Other,
        }
    }

    pub fn as_str(self) -> &'static str {
        match self {
            Self::Discrete => "discrete GPU",
            Self::Integrated => "integrated GPU",
            Self::Virtual => "virtual GPU",
            Self::Cpu => "CPU (software)",
            Self::Other => "other",
        }
    }
}

/// One Vulkan device as `himap devices` shows it.
#[derive(Clone, Debug, PartialEq)]
pub struct DeviceInfo {
    /// Position in the loader's enumeration (what `HIMAP_VULKAN_DEVICE=<index>` selects).
    pub index: usize,
    pub name: String,
    pub kind: DeviceKind,
    /// `major.minor.patch`.
    pub api_version: String,
    /// Largest storage-buffer binding in bytes (the largest tensor one binding can hold).
    pub max_storage_buffer_range: u64,
    /// Largest single allocation in bytes.
    pub max_memory_allocation_size: u64,
    /// Size of the largest device-local heap in bytes.
    pub device_local_bytes: u64,
    pub shader_int64: bool,
    pub shader_buffer_int64_atomics: bool,
    pub vulkan_memory_model: bool,
    /// Required features this device lacks (empty: the backend can use it).
    pub missing: Vec<&'static str>,
    /// Timestamps on the compute queue (`himap bench --profile`): ns per tick, 0 when none.
    pub timestamp_period_ns: f32,
    /// Optional features faster gradient sums could use: 64-bit atomics on workgroup memory,
    /// workgroup memory (bytes), subgroup size, subgroup arithmetic, 64-bit subgroup types.
    pub shader_shared_int64_atomics: bool,
    pub max_compute_shared_memory_size: u32,
    pub subgroup_size: u32,
    pub subgroup_arithmetic: bool,
    pub shader_subgroup_extended_types: bool,
    /// 32-bit float controls: subnormals preserved, flushed to zero, signed zero/inf/NaN
    /// preserved, round to nearest even (each on request in a shader; Vulkan 1.2).
    pub float_controls_32: [bool; 4],
}

impl DeviceInfo {
    fn from_raw(index: usize, p: &PhysicalInfo) -> Self {
        Self {
            index,
            name: p.name.clone(),
            kind: DeviceKind::from_vk(p.device_type),
            api_version: raw::version_string(p.api_version),
            max_storage_buffer_range: p.max_storage_buffer_range as u64,
            max_memory_allocation_size: p.max_memory_allocation_size,
            device_local_bytes: p.device_local_bytes,
            shader_int64: p.shader_int64,
            shader_buffer_int64_atomics: p.shader_buffer_int64_atomics,
            vulkan_memory_model: p.vulkan_memory_model,
            missing: p.missing(),
            timestamp_period_ns: if p.timestamp_valid_bits > 0 {
                p.timestamp_period
            } else {
                0.0
            },
            shader_shared_int64_atomics: p.shader_shared_int64_atomics,
            max_compute_shared_memory_size: p.max_compute_shared_memory_size,
            subgroup_size: p.subgroup_size,
            subgroup_arithmetic: p.subgroup_arithmetic,
            shader_subgroup_extended_types: p.shader_subgroup_extended_types,
            float_controls_32: p.float_controls_32,
        }
    }

    /// Whether the backend can run on this device.
    pub fn usable(&self) -> bool {
        self.missing.is_empty()
    }
}

/// Every Vulkan device the loader reports, in enumeration order.
pub fn list_devices() -> Result<Vec<DeviceInfo>, VulkanError> {
    let instance = Instance::new()?;
    Ok(instance
        .physical_devices()?
        .iter()
        .enumerate()
        .map(|(i, p)| DeviceInfo::from_raw(i, p))
        .collect())
}

/// The device list as text for `himap devices` (one block per device, the one the backend
/// would choose marked), or the reason there is none.
pub fn describe_devices() -> String {
    let devices = match list_devices() {
        Ok(d) => d,
        Err(e) => return format!("no Vulkan: {e}\n"),
    };
    if devices.is_empty() {
        return format!("no Vulkan: {}\n", VulkanError::NoDevice);
    }
    let wanted = std::env::var(DEVICE_ENV).ok();
    let chosen = choose(&devices, wanted.as_deref());
    let mut s = String::new();
    for d in &devices {
        let mark = match &chosen {
            Ok(i) if *i == d.index => " (selected)",
            _ => "",
        };
        let yn = |b: bool| if b { "yes" } else { "NO" };
        let _ = writeln!(s, "[{}] {}{mark}", d.index, d.name);
        let _ = writeln!(s, "    type: {}, Vulkan {}", d.kind.as_str(), d.api_version);
        let _ = writeln!(
            s,
            "    maxStorageBufferRange: {} MiB, maxMemoryAllocationSize: {} MiB, device-local heap: {} MiB",
            d.max_storage_buffer_range >> 20,
            d.max_memory_allocation_size.min(u64::MAX >> 1) >> 20,
            d.device_local_bytes >> 20
        );
        let _ = writeln!(
            s,
            "    shaderInt64: {}, shaderBufferInt64Atomics: {}, vulkanMemoryModel: {}",
            yn(d.shader_int64),
            yn(d.shader_buffer_int64_atomics),
            yn(d.vulkan_memory_model)
        );
        let _ = writeln!(
            s,
            "    optional: timestamps: {}, shaderSharedInt64Atomics: {}, shared memory: {} KiB, \
             subgroup size: {}, subgroup arithmetic: {}, shaderSubgroupExtendedTypes: {}",
            if d.timestamp_period_ns > 0.0 {
                format!("{} ns per tick", d.timestamp_period_ns)
            } else {
                "none".into()
            },
            yn(d.shader_shared_int64_atomics),
            d.max_compute_shared_memory_size >> 10,
            d.subgroup_size,
            yn(d.subgroup_arithmetic),
            yn(d.shader_subgroup_extended_types)
        );
        let fc = d.float_controls_32;
        let _ = writeln!(
            s,
            "    float controls (f32): DenormPreserve: {}, DenormFlushToZero: {}, \
             SignedZeroInfNanPreserve: {}, RoundingModeRTE: {}",
            yn(fc[0]),
            yn(fc[1]),
            yn(fc[2]),
            yn(fc[3])
        );
        if d.usable() {
            let _ = writeln!(s, "    usable by himap: yes");
        } else {
            let _ = writeln!(
                s,
                "    usable by himap: no (missing {})",
                d.missing.join(", ")
            );
        }
    }
    if let Err(e) = chosen {
        let _ = writeln!(s, "no device selected: {e}");
    }
    s
}

fn rank(kind: DeviceKind) -> u32 {
    match kind {
        DeviceKind::Discrete => 0,
        DeviceKind::Integrated => 1,
        DeviceKind::Virtual => 2,
        DeviceKind::Cpu => 3,
        DeviceKind::Other => 4,
    }
}

/// Index of the device to use: the one `wanted` names (index or name substring), else the
/// best usable one by kind.
pub(crate) fn choose(devices: &[DeviceInfo], wanted: Option<&str>) -> Result<usize, VulkanError> {
    if devices.is_empty() {
        return Err(VulkanError::NoDevice);
    }
    if let Some(w) = wanted.map(str::trim).filter(|w| !w.is_empty()) {
        let hit = match w.parse::<usize>() {
            Ok(i) => devices.iter().find(|d| d.index == i),
            Err(_) => {
                let lw = w.to_lowercase();
                devices.iter().find(|d| d.name.to_lowercase().contains(&lw))
            }
        };
        return match hit {
            Some(d) if d.usable() => Ok(d.index),
            Some(d) => Err(VulkanError::MissingFeature {
                device: d.name.clone(),
                missing: d.missing.clone(),
            }),
            None => Err(VulkanError::DeviceNotFound {
                wanted: w.to_string(),
                available: devices.iter().map(|d| d.name.clone()).collect(),
            }),
        };
    }
    devices
        .iter()
        .filter(|d| d.usable())
        .min_by_key(|d| (rank(d.kind), d.index))
        .map(|d| d.index)
        .ok_or_else(|| VulkanError::NoSuitableDevice {
            devices: devices
                .iter()
                .map(|d| format!("{} (missing {})", d.name, d.missing.join(", ")))
                .collect(),
        })
}

/// What [`divide_on_device`] returns: the kernels' quotients, the device's `OpFDiv`
/// quotients, and the times of three dispatches (dispatch + wait, ms).
pub type Quotients = (Vec<f32>, Vec<f32>, [f64; 3]);

/// Divides `a[i] / b[i]` on the selected device with the kernels' division
/// (`math::div`, `divide_cs`) and with the device's own `OpFDiv`.
pub fn divide_on_device(a: &[f32], b: &[f32]) -> Result<Quotients, VulkanError> {
    let n = a.len().min(b.len()).max(1);
    let device = open()?;
    let module = raw::ShaderModule::new(&device, &crate::runtime_shader_words()?)?;
    let pipeline = raw::Pipeline::new(&device, &module, &himap_core::gpu_abi::entry::DIVIDE)?;
    let bytes = |v: &[f32]| v.iter().flat_map(|x| x.to_le_bytes()).collect::<Vec<u8>>();
    let mut ba = raw::Buffer::new(&device, 4 * n as u64, raw::Memory::Host, "dividends")?;
    let mut bb = raw::Buffer::new(&device, 4 * n as u64, raw::Memory::Host, "divisors")?;
    let out = raw::Buffer::new(&device, 8 * n as u64, raw::Memory::Host, "quotients")?;
    ba.write_mapped(0, &bytes(&a[..n.min(a.len())]));
    bb.write_mapped(0, &bytes(&b[..n.min(b.len())]));
    let mut gpu = raw::Gpu::new(&device)?;
    let push = crate::passes::push_bytes(himap_core::gpu_abi::KernelPush {
        n: a.len().min(b.len()) as u32,
        ..Default::default()
    });
    let groups = n.div_ceil(crate::WORKGROUP_SIZE as usize) as u32;
    let mut times = [0.0; 3];
    for t in times.iter_mut() {
        let t0 = std::time::Instant::now();
        gpu.submit(|r| {
            let set = r.bind(&pipeline, &[&ba, &bb, &out])?;
            r.dispatch(&pipeline, &set, &push[..pipeline.push_size()], groups);
            Ok(())
        })?;
        *t = t0.elapsed().as_secs_f64() * 1e3;
    }
    let mut raw_out = vec![0u8; 8 * n];
    out.read_mapped(0, &mut raw_out);
    let q: Vec<f32> = raw_out
        .chunks_exact(4)
        .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
        .collect();
    let m = a.len().min(b.len());
    Ok((q[..m].to_vec(), q[n..n + m].to_vec(), times))
}

/// `n` pairs for [`check_division`]: half random bit patterns (all exponents, subnormals,
/// specials), half moderate values (`1e-3..1e3`, random signs), as the kernels divide.
pub fn division_pairs(n: usize) -> (Vec<f32>, Vec<f32>) {
    let mut state = 0x9e37_79b9_7f4a_7c15u64;
    let mut next = move || {
        state ^= state << 13;
        state ^= state >> 7;
        state ^= state << 17;
        state
    };
    let (mut a, mut b) = (Vec::with_capacity(n), Vec::with_capacity(n));
    for i in 0..n {
        let r = next();
        if i % 2 == 0 {
            a.push(f32::from_bits(r as u32));
            b.push(f32::from_bits((r >> 32) as u32));
        } else {
            let v = |x: u64, sgn: u64| {
                let m = 1e-3f32 * 1e6f32.powf((x & 0xff_ffff) as f32 / 16_777_216.0);
                if sgn & 1 == 1 {
                    -m
                } else {
                    m
                }
            };
            a.push(v(r, r >> 60));
            b.push(v(r >> 24, r >> 61));
        }
    }
    (a, b)
}

/// `himap devices --divide N`: [`divide_on_device`] over [`division_pairs`], each quotient
/// list against the CPU's correctly rounded quotients: mismatches (NaN equals NaN), the
/// largest difference in ULP, the first few mismatching pairs, and the dispatch times.
pub fn check_division(n: u32) -> String {
    let mut s = String::new();
    let n = n.max(1) as usize;
    let (a, b) = division_pairs(n);
    let (kernels, device_div, times) = match divide_on_device(&a, &b) {
        Ok(r) => r,
        Err(e) => return format!("division: FAILED: {e}\n"),
    };
    let _ = writeln!(s, "division ({n} pairs):");
    let key = |v: f32| {
        let u = v.to_bits();
        if u >> 31 == 1 {
            -((u & 0x7fff_ffff) as i64)
        } else {
            u as i64
        }
    };
    for (label, q) in [
        ("math::div (kernels)", &kernels),
        ("OpFDiv (device)", &device_div),
    ] {
        let (mut bad, mut worst) = (0usize, 0u64);
        let mut lines = String::new();
        for i in 0..n {
            let (cpu, dev) = (a[i] / b[i], q[i]);
            if cpu.to_bits() == dev.to_bits() || (cpu.is_nan() && dev.is_nan()) {
                continue;
            }
            bad += 1;
            if !cpu.is_nan() && !dev.is_nan() {
                worst = worst.max((key(cpu) - key(dev)).unsigned_abs());
            }
            if bad <= 6 {
                let _ = writeln!(
                    lines,
                    "      {:e} ({:#010x}) / {:e} ({:#010x}): CPU {:e} ({:#010x}), device {:e} ({:#010x})",
                    a[i],
                    a[i].to_bits(),
                    b[i],
                    b[i].to_bits(),
                    cpu,
                    cpu.to_bits(),
                    dev,
                    dev.to_bits()
                );
            }
        }
        let _ = writeln!(
            s,
            "  {label:<22} {bad} of {n} differ from the CPU (largest {worst} ULP)"
        );
        s.push_str(&lines);
    }
    let _ = writeln!(
        s,
        "  dispatch + wait: {:.2} / {:.2} / {:.2} ms (3 runs)",
        times[0], times[1], times[2]
    );
    s
}

/// Builds the compute pipeline of every shader entry point on the selected device, one at a
/// time, and reports each one's result and build time (`himap devices --pipelines`): a driver
/// that rejects one entry point is named precisely, where the backend stops at the first.
///
/// `spirv`: another SPIR-V module to build instead of the committed one (words), for
/// narrowing a driver's failure down; `disable_optimization`: build with
/// `VK_PIPELINE_CREATE_DISABLE_OPTIMIZATION_BIT` (does the driver's optimiser fail?).
pub fn check_pipelines(spirv: Option<&[u32]>, disable_optimization: bool) -> String {
    let mut s = String::new();
    let device = match open() {
        Ok(d) => d,
        Err(e) => return format!("no usable Vulkan device: {e}\n"),
    };
    let _ = writeln!(s, "pipelines on {}:", device.info.name);
    let committed = crate::shader_words();
    let module = match raw::ShaderModule::new(&device, spirv.unwrap_or(&committed)) {
        Ok(m) => m,
        Err(e) => {
            let _ = writeln!(s, "  shader module: FAILED: {e}");
            return s;
        }
    };
    let table = himap_core::gpu_abi::entry::ALL;
    // Another module: every entry point it declares, with the table's layout where the name
    // is in the table, else the widest layout (unused bindings are allowed).
    let entries: Vec<himap_core::gpu_abi::EntryPoint> = match spirv {
        None => table.to_vec(),
        Some(words) => module_entry_names(words)
            .into_iter()
            .map(|name| {
                table.iter().copied().find(|e| e.name == name).unwrap_or(
                    himap_core::gpu_abi::EntryPoint {
                        name: Box::leak(name.into_boxed_str()),
                        bindings: table.iter().map(|e| e.bindings).max().unwrap_or(1),
                        push_size: table.iter().map(|e| e.push_size).max().unwrap_or(4),
                    },
                )
            })
            .collect(),
    };
    let mut failed = 0;
    for e in entries.iter() {
        if e.name == himap_core::gpu_abi::entry::SAMPLE_BACKWARD_WG.name
            && !device.info.shader_shared_int64_atomics
        {
            let _ = writeln!(
                s,
                "  {:<24} not built (no shaderSharedInt64Atomics)",
                e.name
            );
            continue;
        }
        let t0 = std::time::Instant::now();
        let flags = if disable_optimization {
            vk::PipelineCreateFlags::DISABLE_OPTIMIZATION
        } else {
            vk::PipelineCreateFlags::empty()
        };
        let r = raw::Pipeline::with_flags(&device, &module, e, flags);
        let ms = t0.elapsed().as_secs_f64() * 1e3;
        match r {
            Ok(_) => {
                let _ = writeln!(s, "  {:<24} ok ({ms:.0} ms)", e.name);
            }
            Err(err) => {
                failed += 1;
                let _ = writeln!(s, "  {:<24} FAILED ({ms:.0} ms): {err}", e.name);
            }
        }
    }
    let _ = writeln!(s, "{failed} of {} entry points failed", entries.len());
    s
}

/// Names of a SPIR-V module's entry points (`OpEntryPoint`, opcode 15: execution model,
/// function id, then the name as a nul-terminated literal).
fn module_entry_names(words: &[u32]) -> Vec<String> {
    let mut names = Vec::new();
    let mut i = 5;
    while i < words.len() {
        let (count, op) = ((words[i] >> 16) as usize, words[i] & 0xffff);
        if count == 0 || i + count > words.len() {
            break;
        }
        if op == 15 && count > 3 {
            let bytes: Vec<u8> = words[i + 3..i + count]
                .iter()
                .flat_map(|w| w.to_le_bytes())
                .take_while(|&b| b != 0)
                .collect();
            names.push(String::from_utf8_lossy(&bytes).into_owned());
        }
        i += count;
    }
    names
}

/// Opens the selected device (see the module documentation).
pub(crate) fn open() -> Result<Arc<raw::Device>, VulkanError> {
    let instance = Instance::new()?;
    let physical = instance.physical_devices()?;
    let infos: Vec<DeviceInfo> = physical
        .iter()
        .enumerate()
        .map(|(i, p)| DeviceInfo::from_raw(i, p))
        .collect();
    let wanted = std::env::var(DEVICE_ENV).ok();
    let i = choose(&infos, wanted.as_deref())?;
    raw::Device::new(instance, physical[i].clone())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_diagnostic_reads_every_entry_point_name_of_the_module() {
        let mut names = module_entry_names(&crate::shader_words());
        names.sort();
        let mut want: Vec<String> = crate::ENTRY_POINTS.iter().map(|s| s.to_string()).collect();
        want.sort();
        assert_eq!(names, want);
        // a truncated module stops cleanly
        assert!(module_entry_names(&crate::shader_words()[..7]).len() <= 1);
    }

    fn dev(index: usize, name: &str, kind: DeviceKind, usable: bool) -> DeviceInfo {
        DeviceInfo {
            index,
            name: name.into(),
            kind,
            api_version: "1.3.0".into(),
            max_storage_buffer_range: 1 << 27,
            max_memory_allocation_size: 1 << 31,
            device_local_bytes: 1 << 30,
            shader_int64: usable,
            shader_buffer_int64_atomics: true,
            vulkan_memory_model: true,
            missing: if usable { vec![] } else { vec!["shaderInt64"] },
            timestamp_period_ns: 1.0,
            shader_shared_int64_atomics: false,
            max_compute_shared_memory_size: 32 << 10,
            subgroup_size: 32,
            subgroup_arithmetic: true,
            shader_subgroup_extended_types: false,
            float_controls_32: [false; 4],
        }
    }

    #[test]
    fn choose_prefers_discrete_then_integrated_then_cpu() {
        let d = [
            dev(0, "llvmpipe", DeviceKind::Cpu, true),
            dev(1, "Intel UHD", DeviceKind::Integrated, true),
            dev(2, "NVIDIA RTX", DeviceKind::Discrete, true),
        ];
        assert_eq!(choose(&d, None).unwrap(), 2);
        assert_eq!(choose(&d[..2], None).unwrap(), 1);
        assert_eq!(choose(&d[..1], None).unwrap(), 0);
        // an unusable discrete GPU is skipped
        let d2 = [
            dev(0, "llvmpipe", DeviceKind::Cpu, true),
            dev(1, "old", DeviceKind::Discrete, false),
        ];
        assert_eq!(choose(&d2, None).unwrap(), 0);
        assert!(matches!(
            choose(&d2[1..], None),
            Err(VulkanError::NoSuitableDevice { .. })
        ));
        assert_eq!(choose(&[], None), Err(VulkanError::NoDevice));
    }

    #[test]
    fn choose_by_env_index_or_name() {
        let d = [
            dev(0, "llvmpipe (LLVM 15)", DeviceKind::Cpu, true),
            dev(1, "NVIDIA RTX", DeviceKind::Discrete, true),
            dev(2, "old", DeviceKind::Discrete, false),
        ];
        assert_eq!(choose(&d, Some("0")).unwrap(), 0);
        assert_eq!(choose(&d, Some("LLVMpipe")).unwrap(), 0);
        assert_eq!(choose(&d, Some(" nvidia ")).unwrap(), 1);
        assert_eq!(choose(&d, Some("")).unwrap(), 1);
        assert!(matches!(
            choose(&d, Some("7")),
            Err(VulkanError::DeviceNotFound { .. })
        ));
        assert!(matches!(
            choose(&d, Some("amd")),
            Err(VulkanError::DeviceNotFound { .. })
        ));
        let e = choose(&d, Some("old")).unwrap_err();
        assert!(matches!(e, VulkanError::MissingFeature { .. }));
        assert!(e.to_string().contains("shaderInt64"), "{e}");
    }
}
