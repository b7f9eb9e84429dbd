//! Command-line definition of `shocktwin` (SPEC §7).

use std::path::PathBuf;

use clap::{Args, Parser, Subcommand};

/// shocktwin — digital twin of a shock absorber's gas charge.
#[derive(Debug, Parser)]
#[command(name = "shocktwin", version, about)]
pub struct Cli {
    /// The subcommand to run.
    #[command(subcommand)]
    pub command: Command,
}

/// Subcommands of SPEC §7.
#[derive(Debug, Subcommand)]
pub enum Command {
    /// Simulate a dyno campaign (one MCAP log per run; simulated data).
    Simulate(SimulateArgs),
    /// Print channels, rates, duration, metadata and problems of an MCAP file.
    Inspect(InspectArgs),
}

/// `shocktwin simulate`.
#[derive(Debug, Args)]
pub struct SimulateArgs {
    /// Output directory for the campaign's run files.
    #[arg(long)]
    pub out: PathBuf,
    /// Charge pressures in bar gauge, comma separated.
    #[arg(long, value_delimiter = ',', default_value = "0.5,4,7,10,12")]
    pub pressures: Vec<f64>,
    /// Excitation frequencies in Hz, comma separated.
    #[arg(long, value_delimiter = ',', default_value = "1,2,4")]
    pub frequencies: Vec<f64>,
    /// Random seed (the campaign is deterministic for a seed).
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Shortened runs (for tests and the demo).
    #[arg(long)]
    pub quick: bool,
    /// Simulate a second unit of the same model: parameters scattered by a
    /// few per cent, drawn from this unit seed.
    #[arg(long)]
    pub unit: Option<u64>,
}

/// `shocktwin inspect`.
#[derive(Debug, Args)]
pub struct InspectArgs {
    /// The MCAP file to inspect.
    pub file: PathBuf,
}
