//! Backend selection for the command line (`--backend cpu|vulkan|auto`) and the few
//! operations the CLI needs beyond the core's [`Backend`]: batched SDF/colour queries (mesh
//! extraction) and exporting the trained map.
//!
//! `auto` takes a Vulkan GPU (discrete, integrated or virtual; `HIMAP_VULKAN_DEVICE` forces a
//! device) when one is usable and the multi-threaded CPU backend otherwise. The software
//! driver (llvmpipe) alone does not count for `auto`: it runs the same kernels several times
//! slower than the CPU backend, so it is used only with `--backend vulkan`. The choice and its
//! reason are printed by the CLI and recorded in `summary.json`.

use std::str::FromStr;

use himap_core::field::model::{Group, PerGroup};
use himap_core::train::adam::AdamConfig;
use himap_core::train::backend::{Backend, ImageStore};
use himap_vulkan::{DeviceKind, VulkanBackend, VulkanError};

use crate::backend::{ModelData, ParallelCpuBackend};

/// What `--backend` asked for.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum BackendChoice {
    Cpu,
    Vulkan,
    Auto,
}

impl FromStr for BackendChoice {
    type Err = anyhow::Error;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s {
            "cpu" => Ok(Self::Cpu),
            "vulkan" | "gpu" => Ok(Self::Vulkan),
            "auto" => Ok(Self::Auto),
            _ => anyhow::bail!("unknown backend {s:?}: expected cpu, vulkan or auto"),
        }
    }
}

/// The backend a run will use and why.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Decision {
    pub vulkan: bool,
    pub reason: String,
}

/// Resolves `auto` by looking at the Vulkan devices (see the module docs).
pub fn decide(choice: BackendChoice) -> Decision {
    match choice {
        BackendChoice::Cpu => Decision {
            vulkan: false,
            reason: "cpu backend requested".into(),
        },
        BackendChoice::Vulkan => Decision {
            vulkan: true,
            reason: "vulkan backend requested".into(),
        },
        BackendChoice::Auto => {
            let forced = std::env::var(himap_vulkan::DEVICE_ENV).is_ok();
            match himap_vulkan::list_devices() {
                Err(e) => Decision {
                    vulkan: false,
                    reason: format!("auto: no Vulkan ({e}); using the CPU"),
                },
                Ok(devs) => {
                    let usable: Vec<_> = devs.iter().filter(|d| d.usable()).collect();
                    if let Some(d) = usable.iter().find(|d| d.kind != DeviceKind::Cpu) {
                        Decision {
                            vulkan: true,
                            reason: format!("auto: Vulkan GPU {} ({})", d.name, d.kind.as_str()),
                        }
                    } else if forced && !usable.is_empty() {
                        Decision {
                            vulkan: true,
                            reason: format!(
                                "auto: {} is set; using the Vulkan device it selects",
                                himap_vulkan::DEVICE_ENV
                            ),
                        }
                    } else if let Some(d) = usable.first() {
                        Decision {
                            vulkan: false,
                            reason: format!(
                                "auto: only the software Vulkan driver ({}) is present, slower \
                                 than the CPU backend; using the CPU (--backend vulkan forces it)",
                                d.name
                            ),
                        }
                    } else {
                        Decision {
                            vulkan: false,
                            reason: "auto: no usable Vulkan device; using the CPU".into(),
                        }
                    }
                }
            }
        }
    }
}

/// What the CLI needs from a backend beyond [`Backend`].
pub trait MapBackend: Backend {
    /// Signed distances at world points.
    fn query_sdf(&mut self, points: &[[f32; 3]], out: &mut [f32]) -> anyhow::Result<()>;
    /// Colours at world points.
    fn query_color(&mut self, points: &[[f32; 3]], out: &mut [[f32; 3]]) -> anyhow::Result<()>;
    /// The trained map (parameters, Adam moments and step) as host data.
    fn export(&mut self) -> anyhow::Result<ModelData>;
    /// Replaces the map (parameters, Adam moments and step) by `data` of the same layout
    /// (a resumed run).
    fn import(&mut self, data: &ModelData) -> anyhow::Result<()>;
    /// Replaces the map by `data` over another scene box (a grown box, [`crate::grow`]);
    /// `Ok(false)` when the backend cannot change its map's size (the run then keeps its box
    /// and says so).
    fn regrow(&mut self, data: ModelData) -> anyhow::Result<bool>;
    /// CPU worker threads (0 for a GPU backend).
    fn threads(&self) -> usize;
    /// The per-pass table of the passes timed so far over `steps` steps taking `seconds`
    /// (`himap map --profile`); `None` for a backend without pass timings.
    fn profile_table(&self, _steps: usize, _seconds: f64) -> Option<String> {
        None
    }
}

impl MapBackend for ParallelCpuBackend {
    fn query_sdf(&mut self, points: &[[f32; 3]], out: &mut [f32]) -> anyhow::Result<()> {
        self.sdf(points, out);
        Ok(())
    }

    fn query_color(&mut self, points: &[[f32; 3]], out: &mut [[f32; 3]]) -> anyhow::Result<()> {
        self.color(points, out);
        Ok(())
    }

    fn export(&mut self) -> anyhow::Result<ModelData> {
        Ok(self.data().clone())
    }

    fn import(&mut self, data: &ModelData) -> anyhow::Result<()> {
        anyhow::ensure!(
            data.layout == *self.layout(),
            "the saved map's model differs from this configuration's"
        );
        *self.data_mut() = data.clone();
        Ok(())
    }

    fn regrow(&mut self, data: ModelData) -> anyhow::Result<bool> {
        ParallelCpuBackend::regrow(self, data)?;
        Ok(true)
    }

    fn threads(&self) -> usize {
        ParallelCpuBackend::threads(self)
    }

    fn profile_table(&self, _steps: usize, seconds: f64) -> Option<String> {
        Some(format_cpu_profile(
            &self.pass_times(),
            seconds,
            self.layout().param_count(),
        ))
    }
}

/// `himap map --profile`'s table for the CPU backend: each pass's milliseconds per step and
/// share of the mapping time (`seconds`, which holds the steps and the host's work between
/// them), the renders outside the steps, and how many of the map's `params` Adam visited.
pub fn format_cpu_profile(t: &crate::backend::CpuPassTimes, seconds: f64, params: usize) -> String {
    let steps = t.steps.max(1) as f64;
    let wall_ms = (seconds * 1e3).max(1e-9);
    let per_step = wall_ms / steps;
    let ms = |d: std::time::Duration| d.as_secs_f64() * 1e3;
    let mut s = format!(
        "  per pass (wall time; {per_step:.1} ms per step over {} steps):\n",
        t.steps
    );
    let mut covered = 0.0;
    for (name, d) in [
        ("rays: forward, losses, backward", t.rays),
        ("gradient sum and finiteness check", t.reduce),
        ("Adam", t.adam),
    ] {
        covered += ms(d);
        s += &format!(
            "    {name:<40} {:>10.3} ms {:>6.1} %\n",
            ms(d) / steps,
            100.0 * ms(d) / wall_ms
        );
    }
    let rest = (wall_ms - covered).max(0.0);
    s += &format!(
        "    {:<40} {:>10.3} ms {:>6.1} %\n",
        "other (batches, keyframes, host)",
        rest / steps,
        100.0 * rest / wall_ms
    );
    s += &format!(
        "  renders outside the steps (evaluation, previews, mostly outside the mapping time): \
         {:.1} s\n",
        ms(t.renders) / 1e3
    );
    s += &format!(
        "  Adam visited {:.2} M parameters per step on average, of the map's {:.2} M (every \
         block rays have ever reached)\n",
        t.adam_params as f64 / steps / 1e6,
        params as f64 / 1e6
    );
    s += &negligible_line(t);
    s
}

/// The profile's line on the backward's skipped sample branches (their contributions all
/// round to 0 quanta: the same sums).
pub fn negligible_line(t: &crate::backend::CpuPassTimes) -> String {
    format!(
        "  sample branches skipped as negligible (every contribution below half a quantum): \
         {:.1} % of {}\n",
        100.0 * t.branches_skipped as f64 / t.branches_checked.max(1) as f64,
        t.branches_checked
    )
}

impl MapBackend for VulkanBackend {
    fn profile_table(&self, steps: usize, seconds: f64) -> Option<String> {
        let passes = self.profile();
        // the per-update evaluation renders run passes outside the mapping time: the shares
        // are of whichever is larger
        let timed: f64 = passes.iter().map(|p| p.total_ms).sum();
        Some(crate::bench::format_profile(
            &passes,
            (seconds * 1e3).max(timed),
            steps,
        ))
    }

    fn query_sdf(&mut self, points: &[[f32; 3]], out: &mut [f32]) -> anyhow::Result<()> {
        Ok(self.sdf(points, out)?)
    }

    fn query_color(&mut self, points: &[[f32; 3]], out: &mut [[f32; 3]]) -> anyhow::Result<()> {
        Ok(self.color(points, out)?)
    }

    fn export(&mut self) -> anyhow::Result<ModelData> {
        let layout = *self.layout();
        let mut data = ModelData::new(layout, 0).map_err(|e| anyhow::anyhow!("{e}"))?;
        for g in Group::ALL {
            let i = g as usize;
            self.read_params(g, &mut data.params[i])?;
            let (m, v) = (&mut data.m[i], &mut data.v[i]);
            self.read_adam(g, m, v)?;
        }
        data.t = self.steps();
        Ok(data)
    }

    fn import(&mut self, data: &ModelData) -> anyhow::Result<()> {
        anyhow::ensure!(
            data.layout == *self.layout(),
            "the saved map's model differs from this configuration's"
        );
        for g in Group::ALL {
            let i = g as usize;
            self.write_params(g, &data.params[i], false)?;
            self.write_adam(g, &data.m[i], &data.v[i])?;
        }
        self.set_steps(data.t)?;
        Ok(())
    }

    fn regrow(&mut self, data: ModelData) -> anyhow::Result<bool> {
        // the device's buffers are sized at construction: a new backend on the same device
        let mut new = self.regrown(data.layout, data.param_slices())?;
        MapBackend::import(&mut new, &data)?;
        *self = new;
        Ok(true)
    }

    fn threads(&self) -> usize {
        0
    }
}

/// The Vulkan backend over `data` (parameters; Adam moments start at zero unless `data`
/// carries them, see [`VulkanBackend::new`]) with `store` image slots.
pub fn vulkan_backend(
    data: &ModelData,
    adam: PerGroup<AdamConfig>,
    store: ImageStore,
) -> Result<VulkanBackend, VulkanError> {
    VulkanBackend::new(data.layout, data.param_slices(), adam)?.with_images(store)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn choices_parse_and_explicit_choices_are_kept() {
        assert_eq!("cpu".parse::<BackendChoice>().unwrap(), BackendChoice::Cpu);
        assert_eq!(
            "vulkan".parse::<BackendChoice>().unwrap(),
            BackendChoice::Vulkan
        );
        assert_eq!(
            "auto".parse::<BackendChoice>().unwrap(),
            BackendChoice::Auto
        );
        assert!("cuda".parse::<BackendChoice>().is_err());
        assert!(!decide(BackendChoice::Cpu).vulkan);
        assert!(decide(BackendChoice::Vulkan).vulkan);
        // auto always decides and says why
        let d = decide(BackendChoice::Auto);
        assert!(d.reason.starts_with("auto: "), "{}", d.reason);
    }
}
