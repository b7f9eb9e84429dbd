//! Run-log format "shocktwin log v1" (SPEC §2): one MCAP file per run of one
//! asset, JSON messages, a `shocktwin.run` metadata record.
//!
//! Types shared by the writer, the whole-file reader and the incremental
//! (sans-io) reader live here.

use std::collections::BTreeMap;

/// Topic names of SPEC §2.
pub mod topic {
    /// Potentiometer, field `position_m`, 100 Hz.
    pub const POSITION: &str = "/position";
    /// Accelerometer pair, fields `a1_mps2`, `a2_mps2`, 1000 Hz.
    pub const ACCELERATION: &str = "/acceleration";
    /// Loadcell, field `force_n`, 50 Hz.
    pub const FORCE: &str = "/force";
    /// Shock-body thermocouple, field `temperature_c`, 1 Hz.
    pub const TEMP_SHOCK: &str = "/temperature/shock";
    /// Ambient thermocouple, field `temperature_c`, 1 Hz.
    pub const TEMP_AMBIENT: &str = "/temperature/ambient";
    /// Simulator truth, field `static_bar`.
    pub const TRUTH_PRESSURE: &str = "/truth/gas_pressure";
    /// Estimator output.
    pub const ESTIMATE: &str = "/estimate";
}

/// Name of the MCAP metadata record that describes a run.
pub const RUN_METADATA_NAME: &str = "shocktwin.run";

/// The `shocktwin.run` metadata of a run (SPEC §2).
#[derive(Debug, Clone, PartialEq, Default, serde::Serialize, serde::Deserialize)]
pub struct RunMetadata {
    /// Unit identifier, `[A-Za-z0-9._-]{1,64}`.
    pub asset_id: String,
    /// Run identifier, same charset.
    pub run_id: String,
    /// Label: true charge pressure, bar gauge at 20 °C (training/evaluation only).
    pub charge_pressure_bar: Option<f64>,
    /// Free text, e.g. `sine 2 Hz 80 mm p-p`.
    pub excitation: Option<String>,
    /// Dyno excitation frequency, when known.
    pub frequency_hz: Option<f64>,
    /// Dyno stroke, peak to peak, metres, when known.
    pub stroke_pp_m: Option<f64>,
    /// Any other keys of the record, kept verbatim.
    pub extra: BTreeMap<String, String>,
}

/// One sensor sample of a shocktwin log; `t_ns` is the MCAP `log_time`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Sample {
    /// `/position`.
    Position { t_ns: i64, position_m: f64 },
    /// `/acceleration`; `a1` on the rod end, `a2` on the body end.
    Acceleration { t_ns: i64, a1_mps2: f64, a2_mps2: f64 },
    /// `/force`, positive in tension.
    Force { t_ns: i64, force_n: f64 },
    /// `/temperature/shock`.
    TempShock { t_ns: i64, temperature_c: f64 },
    /// `/temperature/ambient`.
    TempAmbient { t_ns: i64, temperature_c: f64 },
    /// `/truth/gas_pressure`: instantaneous static gas pressure, bar gauge.
    TruthPressure { t_ns: i64, static_bar: f64 },
}

impl Sample {
    /// The sample's time stamp in nanoseconds.
    #[must_use]
    pub fn t_ns(&self) -> i64 {
        match *self {
            Sample::Position { t_ns, .. }
            | Sample::Acceleration { t_ns, .. }
            | Sample::Force { t_ns, .. }
            | Sample::TempShock { t_ns, .. }
            | Sample::TempAmbient { t_ns, .. }
            | Sample::TruthPressure { t_ns, .. } => t_ns,
        }
    }

    /// The SPEC §2 topic this sample belongs to.
    #[must_use]
    pub fn topic(&self) -> &'static str {
        match self {
            Sample::Position { .. } => topic::POSITION,
            Sample::Acceleration { .. } => topic::ACCELERATION,
            Sample::Force { .. } => topic::FORCE,
            Sample::TempShock { .. } => topic::TEMP_SHOCK,
            Sample::TempAmbient { .. } => topic::TEMP_AMBIENT,
            Sample::TruthPressure { .. } => topic::TRUTH_PRESSURE,
        }
    }
}

/// Column store of one run (what the whole-file reader returns).
/// Each stream keeps its samples in file order with their `t_ns`.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct RunLog {
    /// The run's metadata (`shocktwin.run`).
    pub metadata: RunMetadata,
    /// `/position`: (t_ns, position_m).
    pub position: Vec<(i64, f64)>,
    /// `/acceleration`: (t_ns, a1_mps2, a2_mps2).
    pub acceleration: Vec<(i64, f64, f64)>,
    /// `/force`: (t_ns, force_n).
    pub force: Vec<(i64, f64)>,
    /// `/temperature/shock`: (t_ns, temperature_c).
    pub temp_shock: Vec<(i64, f64)>,
    /// `/temperature/ambient`: (t_ns, temperature_c).
    pub temp_ambient: Vec<(i64, f64)>,
    /// `/truth/gas_pressure`: (t_ns, static_bar).
    pub truth_pressure: Vec<(i64, f64)>,
    /// Messages on topics this format does not know, by topic (counted, not kept).
    pub unknown_topics: BTreeMap<String, u64>,
}
