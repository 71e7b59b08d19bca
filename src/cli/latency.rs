//! `celld latency`: the drivers' latencies on this machine, against an in-process twin-server
//! on loopback (docs/integration.md, "Latency budget").

use anyhow::{Context, Result, bail};
use assembly_cell::config::cell::CellConfig;
use assembly_cell::drivers::latency;
use clap::Args;
use std::path::PathBuf;

#[derive(Args)]
pub struct LatencyArgs {
    /// Cell file (default: the bundled reference cell, cells/phi170.toml).
    #[arg(long)]
    cell: Option<PathBuf>,
    /// Moves and ingested messages to time (the e-stop is timed a tenth as often, a lost
    /// controller's latch a hundredth, 10 to 50 times).
    #[arg(long, default_value_t = 5000)]
    samples: usize,
}

pub fn run(args: LatencyArgs) -> Result<()> {
    if args.samples < 10 {
        bail!("--samples must be at least 10, got {}", args.samples);
    }
    let cell = match &args.cell {
        Some(path) => {
            CellConfig::load(path).with_context(|| format!("--cell {}", path.display()))?
        }
        None => CellConfig::reference(),
    };
    let mut measured = latency::measure(&cell, args.samples)?;
    // A lost controller to the cell's latch: a sample takes about a tenth of a second.
    let latches = (args.samples / 100).clamp(10, 50);
    measured.extend(assembly_cell::cell::latch_latency::measure(&cell, latches)?);
    println!(
        "{:<48} {:>7} {:>9} {:>9} {:>9}",
        "latency", "samples", "p50 µs", "p99 µs", "max µs"
    );
    for samples in &measured {
        println!(
            "{:<48} {:>7} {:>9.1} {:>9.1} {:>9.1}",
            samples.name,
            samples.micros.len(),
            samples.quantile(0.5),
            samples.quantile(0.99),
            samples.quantile(1.0)
        );
    }
    Ok(())
}
