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
    /// Run logs through the streaming estimator and write the `/estimate`
    /// stream (MCAP, JSON lines or CSV); prints per-run RMSE for labelled logs.
    Replay(ReplayArgs),
    /// Run the fleet-gateway daemon (MCAP over TCP and an inbox in, HTTP API
    /// and recorded estimates out); flags override the file and environment.
    Serve(ServeArgs),
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
    /// Repeat take: every run again on the same rig and unit, with
    /// independent noise and room (0 = the first take; run ids get `-r<k>`).
    #[arg(long, default_value_t = 0)]
    pub repeat: u32,
    /// A unit in service losing gas: one run a day for this many days
    /// (at the first of --frequencies), instead of a campaign.
    #[arg(long, requires = "leak_rate")]
    pub days: Option<u32>,
    /// With --days: charge lost per day, bar.
    #[arg(long, requires = "days")]
    pub leak_rate: Option<f64>,
    /// With --days: the charge on day 0, bar gauge.
    #[arg(long, default_value_t = 12.0, requires = "days")]
    pub start_bar: f64,
    /// With --days: the asset id in the runs' metadata (default: the unit's).
    #[arg(long, requires = "days")]
    pub asset_id: Option<String>,
}

/// `shocktwin inspect`.
#[derive(Debug, Args)]
pub struct InspectArgs {
    /// The MCAP file to inspect.
    pub file: PathBuf,
    /// Print the report as one JSON object instead of text.
    #[arg(long)]
    pub json: bool,
}

/// `shocktwin serve`.
#[derive(Debug, Args)]
pub struct ServeArgs {
    /// TOML configuration file (see crates/dt-server/shocktwin.example.toml).
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Address accepting MCAP streams (default 127.0.0.1:7410).
    #[arg(long)]
    pub listen: Option<std::net::SocketAddr>,
    /// HTTP API address (default 127.0.0.1:7411).
    #[arg(long)]
    pub http: Option<std::net::SocketAddr>,
    /// Model bundle directory (twin.json + mlp.onnx).
    #[arg(long)]
    pub model: Option<PathBuf>,
    /// Watched inbox directory of MCAP files.
    #[arg(long)]
    pub inbox: Option<PathBuf>,
    /// Directory for the recorded /estimate MCAP files.
    #[arg(long)]
    pub record_dir: Option<PathBuf>,
    /// The fleet store (`SQLite` file: history, runs, trends). Default:
    /// `$SHOCKTWIN_STATE_DIR`, else systemd's `$STATE_DIRECTORY`, else
    /// `$XDG_STATE_HOME/shocktwin`, else
    /// `~/.local/state/shocktwin`, then `/fleet.sqlite`.
    #[arg(long, conflicts_with = "no_db")]
    pub db: Option<PathBuf>,
    /// Keep no fleet store (history only in memory).
    #[arg(long)]
    pub no_db: bool,
    /// Log format (also `SHOCKTWIN_LOG_FORMAT=json`).
    #[arg(long, value_enum)]
    pub log_format: Option<LogFormat>,
}

/// Format of the log lines on stderr.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum LogFormat {
    /// Human-readable lines.
    Text,
    /// One JSON object per line (structured logs for a log collector).
    Json,
}

/// `shocktwin replay`.
#[derive(Debug, Args)]
pub struct ReplayArgs {
    /// Model bundle directory (`twin.json` + `mlp.onnx`).
    #[arg(long)]
    pub model: PathBuf,
    /// Run logs to replay.
    #[arg(required = true)]
    pub files: Vec<PathBuf>,
    /// Output: `.mcap` (inputs + `/estimate`), `.jsonl` or `.csv`.
    #[arg(long)]
    pub out: PathBuf,
    /// Worker threads (default: one per core).
    #[arg(long)]
    pub jobs: Option<usize>,
}
