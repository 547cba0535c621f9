//! The `himap` command line.

use std::path::PathBuf;

use anyhow::Context;
use clap::{Parser, Subcommand};
use himap::dump::{dump_step, DumpOptions};

#[derive(Parser)]
#[command(
    name = "himap",
    version,
    about = "Monocular dense mapping with a hierarchical factorized radiance field (Hi-Map)"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Train a small field on a built-in analytic target and print the loss going down.
    Demo {
        /// Training steps.
        #[arg(long, default_value_t = 300)]
        steps: usize,
        /// Rays per step.
        #[arg(long, default_value_t = 512)]
        rays: usize,
        /// Worker threads (0 = all cores).
        #[arg(long, default_value_t = 0)]
        threads: usize,
        #[arg(long, default_value_t = 0)]
        seed: u64,
    },
    /// Write a synthetic Replica-layout sequence of a procedural room (colour, exact depth,
    /// poses, intrinsics) plus its ground-truth mesh `gt_mesh.ply`.
    Synth {
        #[arg(long)]
        out: PathBuf,
        #[arg(long, default_value_t = 60)]
        frames: usize,
        #[arg(long, default_value_t = 160)]
        width: u32,
        #[arg(long, default_value_t = 120)]
        height: u32,
        #[arg(long, default_value_t = 0)]
        seed: u64,
    },
    /// Mesh metrics as the paper reports them: Accuracy and Completion (cm), Completion ratio
    /// (% of ground-truth points within 5 cm), from area-weighted surface samples.
    Eval {
        /// Reconstructed mesh (PLY).
        #[arg(long)]
        mesh: PathBuf,
        /// Ground truth: a mesh PLY, or a dataset directory (its gt_mesh.ply, else its
        /// back-projected ground-truth depth).
        #[arg(long)]
        gt: PathBuf,
        /// Also write the report as JSON.
        #[arg(long)]
        json: Option<PathBuf>,
        /// Surface samples per mesh.
        #[arg(long, default_value_t = 200_000)]
        samples: usize,
        /// Culling of the reconstruction by the dataset's cameras: none, frustum, occlusion.
        #[arg(long, default_value = "none")]
        cull: String,
    },
    /// Run one training step of a small model on random rays and write every input, output
    /// and gradient to a safetensors file (see the README for the tensor names and formulas).
    DumpStep {
        #[arg(long)]
        out: PathBuf,
        #[arg(long, default_value_t = 0)]
        seed: u64,
        /// Number of rays.
        #[arg(long, default_value_t = 64)]
        rays: usize,
        /// Rendering: sdf-density (Hi-Map), sdf-direct or occupancy.
        #[arg(long, default_value = "sdf-density")]
        render: String,
    },
}

fn parse_render(s: &str) -> anyhow::Result<himap_core::render::RenderMode> {
    use himap_core::render::RenderMode::*;
    Ok(match s {
        "sdf-density" => SdfDensity,
        "sdf-direct" => SdfDirect,
        "occupancy" => Occupancy,
        other => {
            anyhow::bail!("unknown rendering '{other}': use sdf-density, sdf-direct or occupancy")
        }
    })
}

fn main() -> anyhow::Result<()> {
    let cli = Cli::parse();
    match cli.command {
        Command::Demo {
            steps,
            rays,
            threads,
            seed,
        } => {
            let cfg = himap::dump::small_config(himap_core::render::RenderMode::SdfDensity);
            let layout = himap_core::model::ModelLayout::new(&cfg)?;
            println!(
                "training a {}-parameter field on an analytic sphere-in-a-box target: {steps} steps x {rays} rays",
                layout.param_count()
            );
            let start = std::time::Instant::now();
            let (first, last) = himap::train_demo::run(
                layout,
                steps,
                rays,
                threads,
                seed,
                |step, loss, psnr| println!("step {step:5}  loss {loss:.5}  PSNR {psnr:6.2} dB"),
                (steps / 10).max(1),
            )?;
            println!(
                "loss {first:.5} -> {last:.5} in {:.1} s",
                start.elapsed().as_secs_f32()
            );
        }
        Command::Synth {
            out,
            frames,
            width,
            height,
            seed,
        } => {
            let opts = himap::synth::SynthOptions {
                frames,
                width,
                height,
                seed,
            };
            let s = himap::synth::write_synthetic(&out, &opts)
                .with_context(|| format!("writing the synthetic sequence to {}", out.display()))?;
            println!(
                "wrote {} frames of {}x{} to {} ({} ground-truth triangles); scene box {:?} .. {:?}",
                s.frames,
                s.intrinsics.width,
                s.intrinsics.height,
                s.out.display(),
                s.mesh_triangles,
                s.scene_box.min,
                s.scene_box.max
            );
        }
        Command::Eval {
            mesh,
            gt,
            json,
            samples,
            cull,
        } => {
            use himap::eval::{Culling, EvalOptions};
            let culling = match cull.as_str() {
                "none" => Culling::None,
                "frustum" => Culling::Frustum,
                "occlusion" => Culling::FrustumOcclusion,
                other => anyhow::bail!("unknown culling '{other}': use none, frustum or occlusion"),
            };
            let opts = EvalOptions {
                n_samples: samples,
                culling,
                ..EvalOptions::default()
            };
            let report = himap::eval::run_eval_cli(&mesh, &gt, json.as_deref(), &opts)?;
            println!("{report}");
        }
        Command::DumpStep {
            out,
            seed,
            rays,
            render,
        } => {
            let opts = DumpOptions {
                seed,
                rays,
                render_mode: parse_render(&render)?,
            };
            let loss = dump_step(&out, &opts).with_context(|| "dump-step failed")?;
            println!("wrote {} (loss {loss})", out.display());
        }
    }
    Ok(())
}
