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
    /// Read the gas charge of runs driven on a road with the road observer
    /// (calibrated by `python -m train.road_observer fit`); prints each run's
    /// estimate, 95 % interval and health, optionally every block (CSV/JSONL).
    Road(RoadArgs),
    /// Turn tabular dyno exports (CSV) into run logs (SPEC §2), one MCAP per
    /// file: columns mapped by flags or a TOML file, units and sign
    /// conventions converted, resampled (anti-aliased) to the nominal rates.
    Import(Box<ImportArgs>),
    /// Run the fleet-gateway daemon (MCAP over TCP and an inbox in, HTTP API
    /// and recorded estimates out); flags override the file and environment.
    Serve(ServeArgs),
    /// Send runs to a NATS `JetStream` worker group as vehicles would
    /// (SPEC §10; see docs/nats.md).
    Publish(PublishArgs),
}

/// `shocktwin road`.
#[derive(Debug, Args)]
pub struct RoadArgs {
    /// The road calibration (`python -m train.road_observer fit --out`).
    #[arg(long, value_name = "ROAD.json")]
    pub calibration: PathBuf,
    /// Run logs driven on a road.
    #[arg(required = true)]
    pub files: Vec<PathBuf>,
    /// A drive of the same unit at a known charge (after a service), read
    /// first: `RUN.mcap@BAR`.
    #[arg(long, value_name = "RUN.mcap@BAR")]
    pub baseline: Option<String>,
    /// Every block read: `.csv` or `.jsonl`.
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Worker threads (default: one per core).
    #[arg(long)]
    pub jobs: Option<usize>,
}

/// `shocktwin publish`.
#[derive(Debug, Args)]
pub struct PublishArgs {
    /// NATS server URL (`nats://127.0.0.1:4222`).
    #[arg(long)]
    pub nats: String,
    /// Run logs to send, all at once (one task per file).
    #[arg(required = true)]
    pub files: Vec<PathBuf>,
    /// Pace each run at real time (as a vehicle would send it).
    #[arg(long)]
    pub realtime: bool,
    /// Pace each run at this many times real time (tests: a vehicle's
    /// stream, faster).
    #[arg(long, conflicts_with = "realtime")]
    pub speed: Option<f64>,
    /// Samples per message, in milliseconds of the run.
    #[arg(long, default_value_t = 100)]
    pub batch_ms: u32,
    /// Send file i as asset `<PREFIX><i>` (load and failover tests: many
    /// assets from few runs).
    #[arg(long)]
    pub rename_assets: Option<String>,
    /// CA of the server certificate (PEM): connect with TLS.
    #[arg(long)]
    pub nats_ca: Option<PathBuf>,
    /// Client certificate (PEM), for a server that verifies clients (with
    /// `--nats-key`; as `[nats] cert_file`).
    #[arg(long, requires = "nats_key")]
    pub nats_cert: Option<PathBuf>,
    /// Its private key (PEM; as `[nats] key_file`).
    #[arg(long, requires = "nats_cert")]
    pub nats_key: Option<PathBuf>,
    /// File whose first line is the server's token (as `[nats] token_file`;
    /// a file, not an argument, so that it is not in the process list).
    #[arg(long)]
    pub nats_token_file: Option<PathBuf>,
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
    /// Random seed (the campaign is deterministic for a seed). The default,
    /// 1, makes the runs of `make demo`'s and `make study`'s campaigns again,
    /// byte for byte, the runs their bundles were trained on: give another
    /// seed (or `--unit`) for held-out runs.
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
    /// What to write: shocktwin run logs, or a crank dyno's CSV export of
    /// each run (for trying `shocktwin import`; see dt-sim's `export`).
    #[arg(long, value_enum, default_value_t = SimFormat::Mcap, conflicts_with = "days")]
    pub format: SimFormat,
    /// With `--format dyno-csv`: the export's sample rate, Hz.
    #[arg(long, default_value_t = 300.0)]
    pub csv_rate_hz: f64,
    /// Rate of the logged `/truth/velocity` (the plant's stroke velocity, a
    /// label the twin never reads), Hz: a divisor of 1000. 1000 logs it at
    /// the accelerometers' rate, for studying the stroke velocity estimate's
    /// error; nothing else in the run changes.
    #[arg(long, default_value_t = dt_sim::run::DEFAULT_TRUTH_VELOCITY_HZ, conflicts_with = "days")]
    pub truth_velocity_hz: u32,
    /// With --road: the drive file's own seed, apart from --seed (which keeps
    /// drawing the rig's sensor errors, the room and the noise): another road
    /// on the same vehicle and sensors. Run ids get `-d<seed>`.
    #[arg(long, requires = "road", conflicts_with = "days")]
    pub drive_seed: Option<u64>,
    /// The rig's own seed: the sensors' errors (accelerometer offsets and
    /// gains, thermocouple offsets) drawn from it, apart from --seed (which
    /// keeps drawing the room and the noise): the same runs read by another
    /// set of sensors. Run ids get `-g<seed>`.
    #[arg(long, conflicts_with = "days")]
    pub rig_seed: Option<u64>,
    /// Play a road drive file instead of the sines: the suspension stroke of
    /// a car at this speed (km/h) over an ISO 8608 road (--road-class),
    /// through a linear quarter-car, 0.5-20 Hz; one run per pressure, every
    /// run the same drive file (from --seed); --frequencies is not used.
    /// With --days: a vehicle on roads, each day's drive its own drive file.
    #[arg(long)]
    pub road: Option<f64>,
    /// With --road: the ISO 8608 road class, A (very good) to E (very poor).
    #[arg(long, default_value = "C", requires = "road", value_parser = parse_road_class)]
    pub road_class: dt_sim::RoadClass,
}

fn parse_road_class(s: &str) -> Result<dt_sim::RoadClass, String> {
    let mut chars = s.chars();
    match (
        chars.next().and_then(dt_sim::RoadClass::from_letter),
        chars.next(),
    ) {
        (Some(c), None) => Ok(c),
        _ => Err(format!(
            "`{s}` is not an ISO 8608 road class (A, B, C, D or E)"
        )),
    }
}

/// Output of `shocktwin simulate`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum SimFormat {
    /// One shocktwin log (MCAP, SPEC §2) per run.
    Mcap,
    /// One crank-dyno CSV export per run (simulated; no accelerometers or ambient).
    DynoCsv,
}

/// `shocktwin import` (column flags override `--map`; see
/// `docs/import.example.toml` for every key).
#[derive(Debug, Args)]
pub struct ImportArgs {
    /// Output directory for the run logs (`<run_id>.mcap`).
    #[arg(long)]
    pub out: PathBuf,
    /// TOML column mapping.
    #[arg(long)]
    pub map: Option<PathBuf>,
    /// The exports to import.
    #[arg(required = true)]
    pub files: Vec<PathBuf>,
    /// Leave out bad rows (unparseable, empty, time not increasing), counted
    /// and reported by reason, instead of failing the file.
    #[arg(long)]
    pub skip_bad_rows: bool,
    /// Replace a log already in `--out` under the same run id that was
    /// imported from other data (without it such a file is an error; a log
    /// imported from the same bytes is replaced either way).
    #[arg(long)]
    pub overwrite: bool,
    /// 1-based line of the header row (default: the first row naming every mapped column).
    #[arg(long)]
    pub header_line: Option<usize>,
    /// Field delimiter: one character (default `,`), or `tab`.
    #[arg(long)]
    pub delimiter: Option<String>,
    /// Decimal separator of the numbers: `.` (default) or `,` (exports
    /// written `1,5`; then another delimiter, e.g. `--delimiter ';'`).
    #[arg(long)]
    pub decimal: Option<char>,
    /// The files' text encoding, a WHATWG label such as `windows-1252`
    /// (Excel's CSV on Western-European Windows), `iso-8859-15` or
    /// `utf-16le` (default: UTF-8, or what a byte-order mark says).
    #[arg(long)]
    pub encoding: Option<String>,
    /// Time column.
    #[arg(long)]
    pub time: Option<String>,
    /// Time format: iso8601 (`Z` or no zone: UTC; a `±HH:MM` offset is converted), `epoch_s`, `epoch_ms`, `elapsed_s`, `elapsed_ms`, auto (by the first cell that reads; `[ms]` in the header: milliseconds), or the file's own layout in the `time` crate's syntax, e.g. `'[day].[month].[year] [hour]:[minute]:[second],[subsecond]'` (no offset: UTC; a time of day alone: since midnight).
    #[arg(long)]
    pub time_format: Option<String>,
    /// Position / displacement column.
    #[arg(long)]
    pub position: Option<String>,
    /// Position unit: mm, cm, m, µm, in.
    #[arg(long)]
    pub position_unit: Option<String>,
    /// Which way the position column counts positive: extension (SPEC) or compression.
    #[arg(long)]
    pub position_positive: Option<String>,
    /// The position column's reading at mid-stroke, in its unit.
    #[arg(long, allow_hyphen_values = true)]
    pub mid_stroke: Option<f64>,
    /// Force column.
    #[arg(long)]
    pub force: Option<String>,
    /// Force unit: N, daN, kN, lbf, kgf.
    #[arg(long)]
    pub force_unit: Option<String>,
    /// Which way the force column counts positive: tension (SPEC) or compression.
    #[arg(long)]
    pub force_positive: Option<String>,
    /// Shock-body temperature column.
    #[arg(long)]
    pub temp_shock: Option<String>,
    /// Ambient temperature column.
    #[arg(long)]
    pub temp_ambient: Option<String>,
    /// Temperature unit: C, F, K.
    #[arg(long)]
    pub temp_unit: Option<String>,
    /// Rod-end accelerometer column.
    #[arg(long)]
    pub a1: Option<String>,
    /// Body-end accelerometer column.
    #[arg(long)]
    pub a2: Option<String>,
    /// Acceleration unit: g, m/s2.
    #[arg(long)]
    pub accel_unit: Option<String>,
    /// Asset id of the runs.
    #[arg(long)]
    pub asset_id: Option<String>,
    /// Run id (one file only; default: the file's stem).
    #[arg(long)]
    pub run_id: Option<String>,
    /// Charge label, e.g. "150 psi" or "10.3 bar" (psia/bara absolute, else gauge),
    /// or "from-name" to read it from each file's name.
    #[arg(long)]
    pub charge: Option<String>,
    /// Dyno excitation frequency, Hz (metadata).
    #[arg(long)]
    pub frequency_hz: Option<f64>,
    /// Dyno stroke peak to peak, mm (metadata; the positions' range is checked against it).
    #[arg(long)]
    pub stroke_pp_mm: Option<f64>,
    /// Extra run metadata, KEY=VALUE (repeatable), e.g. `simulated=true`
    /// for exports of a simulated dyno.
    #[arg(long = "meta", value_name = "KEY=VALUE")]
    pub meta: Vec<String>,
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
    #[arg(long, value_parser = crate::server::config::socket_addr)]
    pub listen: Option<std::net::SocketAddr>,
    /// HTTP API address (default 127.0.0.1:7411).
    #[arg(long, value_parser = crate::server::config::socket_addr)]
    pub http: Option<std::net::SocketAddr>,
    /// Model bundle directory (twin.json + mlp.onnx).
    #[arg(long)]
    pub model: Option<PathBuf>,
    /// Road calibration (`python -m train.road_observer fit`): assets with
    /// `road = true` ([defaults] or [assets.<id>]) are read by the road
    /// observer.
    #[arg(long, value_name = "ROAD.json")]
    pub road: Option<PathBuf>,
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
    /// Start even when a listener off loopback lacks TLS and authentication
    /// (`[tls]`, `[auth]`): anyone who reaches it can read or feed the fleet.
    #[arg(long)]
    pub insecure: bool,
    /// Join the NATS `JetStream` worker group at this URL (`[nats]` in the
    /// file for TLS and credentials; see docs/nats.md).
    #[arg(long)]
    pub nats: Option<String>,
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
    /// The unit's charge-observer baseline: a JSON file with `charge_bar`,
    /// `read_bar`, `read_sd_bar` (as `python -m train.observer baseline`
    /// writes, under `observer_baseline`; with `other_excitations`, one
    /// reading per excitation, each run is corrected by the nearest); every
    /// file replayed is taken to be that unit.
    #[arg(long, value_name = "FILE.json")]
    pub observer_baseline: Option<PathBuf>,
    /// Read every file with the road observer (its calibration, `python -m
    /// train.road_observer fit`): the estimates' pressure, interval and
    /// health are then the road observer's.
    #[arg(long, value_name = "ROAD.json")]
    pub road: Option<PathBuf>,
    /// With `--road`: a drive of the same unit at a known charge (after a
    /// service), read first: `RUN.mcap@BAR`.
    #[arg(long, value_name = "RUN.mcap@BAR")]
    pub road_baseline: Option<String>,
}
