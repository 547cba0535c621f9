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
