//! CPU throughput at the small and paper configurations (until `himap bench` wires it):
//! `cargo run --release -p himap --example bench_cpu`.
use himap::bench::{bench_cpu, configs, print_header, print_row};

fn main() -> anyhow::Result<()> {
    print_header();
    for (name, cfg) in configs() {
        for threads in [1, 0] {
            let r = bench_cpu(name, &cfg, threads, 2048, 3)?;
            print_row(&r);
        }
    }
    Ok(())
}
