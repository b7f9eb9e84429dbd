//! Run-log format "shocktwin log v1" (SPEC §2): one MCAP file per run of one
//! asset, JSON messages, a `shocktwin.run` metadata record.
//!
//! - [`LogWriter`]: writes a run (metadata first, one `json` channel with a
//!   `jsonschema` schema per topic, `log_time` = `publish_time` = `t_ns`).
//! - [`read_log`] / [`read_log_bytes`]: whole-file reader into a [`RunLog`].
//! - [`LogDecoder`]: incremental reader fed bytes as they arrive (a socket).
//! - [`inspect()`]: what any MCAP file holds and lacks ([`InspectReport`]).
//! - [`raw`]: the generic MCAP layer underneath (any MCAP, size limits on
//!   untrusted lengths), checked against the official conformance files.
//!
//! Which findings are fatal and which are `problems` is tabled in [`reader`].
//! Types shared by the writer and the readers live here.

use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;

mod decode;
mod error;
pub mod inspect;
pub mod raw;
pub mod reader;
mod writer;

pub use error::LogError;
pub use inspect::{inspect, inspect_bytes, InspectReport};
pub use raw::ReadLimits;
pub use reader::{
    read_log, read_log_bytes, LogDecoder, LogEvent, SampleMessage, SamplesInOrder, Undecoded,
};
pub use writer::{Compression, LogWriter, WriteOptions};

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
    /// Simulator truth, field `velocity_mps`.
    pub const TRUTH_VELOCITY: &str = "/truth/velocity";
    /// Estimator output.
    pub const ESTIMATE: &str = "/estimate";
}

/// Name of the MCAP metadata record that describes a run.
pub const RUN_METADATA_NAME: &str = "shocktwin.run";

/// The problem `read_log` and `inspect` both note for a file whose run
/// metadata follows a message (one text, so the two cannot drift apart).
fn metadata_after_first_message() -> String {
    format!("metadata `{RUN_METADATA_NAME}` comes after the first message (a stream reader would refuse it)")
}

/// The `shocktwin.run` metadata of a run (SPEC §2).
#[derive(Debug, Clone, PartialEq, Default, serde::Serialize, serde::Deserialize)]
pub struct RunMetadata {
    /// Unit identifier, `[A-Za-z0-9._-]{1,64}`, not `.` or `..`.
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
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub enum Sample {
    /// `/position`.
    Position {
        /// MCAP `log_time`, ns.
        t_ns: i64,
        /// Extension relative to mid-stroke, m.
        position_m: f64,
    },
    /// `/acceleration`; `a1` on the rod end, `a2` on the body end.
    Acceleration {
        /// MCAP `log_time`, ns.
        t_ns: i64,
        /// Rod-end acceleration, m/s².
        a1_mps2: f64,
        /// Body-end acceleration, m/s².
        a2_mps2: f64,
    },
    /// `/force`, positive in tension.
    Force {
        /// MCAP `log_time`, ns.
        t_ns: i64,
        /// Axial force, N, positive in tension.
        force_n: f64,
    },
    /// `/temperature/shock`.
    TempShock {
        /// MCAP `log_time`, ns.
        t_ns: i64,
        /// Temperature, °C.
        temperature_c: f64,
    },
    /// `/temperature/ambient`.
    TempAmbient {
        /// MCAP `log_time`, ns.
        t_ns: i64,
        /// Temperature, °C.
        temperature_c: f64,
    },
    /// `/truth/gas_pressure`: instantaneous static gas pressure, bar gauge.
    TruthPressure {
        /// MCAP `log_time`, ns.
        t_ns: i64,
        /// Static gas pressure, bar gauge.
        static_bar: f64,
    },
    /// `/truth/velocity`: true extension velocity of the damper, m/s
    /// (positive = extension).
    TruthVelocity {
        /// MCAP `log_time`, ns.
        t_ns: i64,
        /// Extension velocity, m/s, positive in extension.
        velocity_mps: f64,
    },
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
            | Sample::TruthPressure { t_ns, .. }
            | Sample::TruthVelocity { t_ns, .. } => t_ns,
        }
    }

    /// The same sample `dt_ns` later.
    #[must_use]
    pub fn shifted(mut self, dt_ns: i64) -> Sample {
        match &mut self {
            Sample::Position { t_ns, .. }
            | Sample::Acceleration { t_ns, .. }
            | Sample::Force { t_ns, .. }
            | Sample::TempShock { t_ns, .. }
            | Sample::TempAmbient { t_ns, .. }
            | Sample::TruthPressure { t_ns, .. }
            | Sample::TruthVelocity { t_ns, .. } => *t_ns += dt_ns,
        }
        self
    }

    /// Rank of the sample's topic for ordering samples with equal `t_ns`:
    /// acceleration (0), position, force, shock temperature, ambient
    /// temperature, truth pressure, truth velocity (6). The accelerometer
    /// comes first (SPEC §3.1).
    #[must_use]
    pub fn topic_rank(&self) -> u8 {
        match self {
            Sample::Acceleration { .. } => 0,
            Sample::Position { .. } => 1,
            Sample::Force { .. } => 2,
            Sample::TempShock { .. } => 3,
            Sample::TempAmbient { .. } => 4,
            Sample::TruthPressure { .. } => 5,
            Sample::TruthVelocity { .. } => 6,
        }
    }

    /// The sample of topic rank `rank` ([`Sample::topic_rank`]; 6 and above:
    /// truth velocity) at `t_ns` with the topic's fields in SPEC order: `v1`
    /// is the second field of `/acceleration` (`a2_mps2`), unused elsewhere.
    #[must_use]
    pub fn from_rank(rank: u8, t_ns: i64, v0: f64, v1: f64) -> Sample {
        match rank {
            0 => Sample::Acceleration {
                t_ns,
                a1_mps2: v0,
                a2_mps2: v1,
            },
            1 => Sample::Position {
                t_ns,
                position_m: v0,
            },
            2 => Sample::Force { t_ns, force_n: v0 },
            3 => Sample::TempShock {
                t_ns,
                temperature_c: v0,
            },
            4 => Sample::TempAmbient {
                t_ns,
                temperature_c: v0,
            },
            5 => Sample::TruthPressure {
                t_ns,
                static_bar: v0,
            },
            _ => Sample::TruthVelocity {
                t_ns,
                velocity_mps: v0,
            },
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
            Sample::TruthVelocity { .. } => topic::TRUTH_VELOCITY,
        }
    }
}

/// Column store of one run (what the whole-file reader returns).
/// Each stream keeps its samples in file order with their `t_ns`.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct RunLog {
    /// The run's metadata (`shocktwin.run`).
    pub metadata: RunMetadata,
    /// `/position`: `(t_ns, position_m)`.
    pub position: Vec<(i64, f64)>,
    /// `/acceleration`: `(t_ns, a1_mps2, a2_mps2)`.
    pub acceleration: Vec<(i64, f64, f64)>,
    /// `/force`: `(t_ns, force_n)`.
    pub force: Vec<(i64, f64)>,
    /// `/temperature/shock`: `(t_ns, temperature_c)`.
    pub temp_shock: Vec<(i64, f64)>,
    /// `/temperature/ambient`: `(t_ns, temperature_c)`.
    pub temp_ambient: Vec<(i64, f64)>,
    /// `/truth/gas_pressure`: `(t_ns, static_bar)`.
    pub truth_pressure: Vec<(i64, f64)>,
    /// `/truth/velocity`: `(t_ns, velocity_mps)`.
    pub truth_velocity: Vec<(i64, f64)>,
    /// Messages on topics this format does not know, by topic (counted, not kept).
    pub unknown_topics: BTreeMap<String, u64>,
    /// Non-fatal findings (skipped messages with topic and field, ignored
    /// topics, ...); see [`reader`] for what is fatal.
    pub problems: Vec<String>,
}

/// A SPEC §2 sensor topic: its name and the JSON fields of its messages.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct TopicSpec {
    /// Topic name, e.g. `/acceleration`.
    pub topic: &'static str,
    /// Required numeric fields of each message, in the order they are written.
    pub fields: &'static [&'static str],
    /// Name of the JSON schema record.
    pub schema_name: &'static str,
    /// One-line description used in the schema.
    pub description: &'static str,
}

/// The sensor topics of SPEC §2 and the two simulator-truth topics, in
/// topic-rank order (see [`Sample::topic_rank`]).
pub const TOPICS: [TopicSpec; 7] = [
    TopicSpec {
        topic: topic::ACCELERATION,
        fields: &["a1_mps2", "a2_mps2"],
        schema_name: "shocktwin.Acceleration",
        description: "Accelerometer pair: a1 on the rod end, a2 on the body end, m/s^2",
    },
    TopicSpec {
        topic: topic::POSITION,
        fields: &["position_m"],
        schema_name: "shocktwin.Position",
        description: "Potentiometer: shock extension relative to mid-stroke, m",
    },
    TopicSpec {
        topic: topic::FORCE,
        fields: &["force_n"],
        schema_name: "shocktwin.Force",
        description: "Loadcell: axial force, positive in tension, N",
    },
    TopicSpec {
        topic: topic::TEMP_SHOCK,
        fields: &["temperature_c"],
        schema_name: "shocktwin.Temperature",
        description: "Thermocouple on the shock body, degC",
    },
    TopicSpec {
        topic: topic::TEMP_AMBIENT,
        fields: &["temperature_c"],
        schema_name: "shocktwin.Temperature",
        description: "Ambient thermocouple, degC",
    },
    TopicSpec {
        topic: topic::TRUTH_PRESSURE,
        fields: &["static_bar"],
        schema_name: "shocktwin.TruthGasPressure",
        description: "Simulator truth: instantaneous static gas pressure, bar gauge",
    },
    TopicSpec {
        topic: topic::TRUTH_VELOCITY,
        fields: &["velocity_mps"],
        schema_name: "shocktwin.TruthVelocity",
        description:
            "Simulator truth: extension velocity of the damper, positive in extension, m/s",
    },
];

/// The spec of a known sensor topic, with its rank, or `None`.
#[must_use]
pub fn topic_spec(topic: &str) -> Option<(u8, &'static TopicSpec)> {
    TOPICS
        .iter()
        .enumerate()
        .find(|(_, spec)| spec.topic == topic)
        .map(|(rank, spec)| (rank as u8, spec))
}

/// The JSON schema (encoding `jsonschema`) the writer uses for a sensor topic:
/// an object whose fields are numbers. A message may carry `null` for a missing
/// value; the schema still says `"number"`, because Foxglove's JSON-schema
/// parser accepts only a single type name per field (a `["number","null"]`
/// union makes it drop the whole topic).
#[must_use]
pub fn json_schema(spec: &TopicSpec) -> String {
    let props = spec
        .fields
        .iter()
        .map(|field| format!("\"{field}\":{{\"type\":\"number\"}}"))
        .collect::<Vec<_>>()
        .join(",");
    let required = spec
        .fields
        .iter()
        .map(|f| format!("\"{f}\""))
        .collect::<Vec<_>>()
        .join(",");
    format!(
        "{{\"$schema\":\"https://json-schema.org/draft/2020-12/schema\",\"title\":\"{}\",\"description\":\"{}\",\"type\":\"object\",\"properties\":{{{props}}},\"required\":[{required}]}}",
        spec.schema_name, spec.description
    )
}

/// What an `asset_id` / `run_id` may be, for error messages.
pub const ID_FORMAT: &str = "[A-Za-z0-9._-]{1,64}, not \".\" or \"..\"";

/// Whether `s` is a valid `asset_id` / `run_id`: `[A-Za-z0-9._-]{1,64}`
/// (SPEC §2), and not `.` or `..`: ids name the daemon's recording
/// directories and files, and an asset `..` wrote its recording outside
/// `record_dir` (sixty-second session, a helper trying the daemon).
#[must_use]
pub fn is_valid_id(s: &str) -> bool {
    (1..=64).contains(&s.len())
        && s != "."
        && s != ".."
        && s.bytes()
            .all(|b| b.is_ascii_alphanumeric() || matches!(b, b'.' | b'_' | b'-'))
}

impl RunMetadata {
    /// Whether the run says it is simulated: the `simulated` key (`true` or
    /// `false`, as `shocktwin simulate` writes it and `shocktwin import
    /// --meta simulated=true` does); `None` when the key is absent or holds
    /// anything else.
    #[must_use]
    pub fn simulated(&self) -> Option<bool> {
        match self.extra.get("simulated").map(|v| v.trim()) {
            Some("true") => Some(true),
            Some("false") => Some(false),
            _ => None,
        }
    }

    /// The `shocktwin.run` string map of this metadata (floats in Rust's
    /// shortest round-trip form).
    #[must_use]
    pub fn to_map(&self) -> BTreeMap<String, String> {
        let mut map = self.extra.clone();
        map.insert("asset_id".into(), self.asset_id.clone());
        map.insert("run_id".into(), self.run_id.clone());
        if let Some(v) = self.charge_pressure_bar {
            map.insert("charge_pressure_bar".into(), v.to_string());
        }
        if let Some(v) = &self.excitation {
            map.insert("excitation".into(), v.clone());
        }
        if let Some(v) = self.frequency_hz {
            map.insert("frequency_hz".into(), v.to_string());
        }
        if let Some(v) = self.stroke_pp_m {
            map.insert("stroke_pp_m".into(), v.to_string());
        }
        map
    }

    /// Parses and validates a `shocktwin.run` string map. `file` names the
    /// source in errors.
    pub fn from_map(file: &str, map: &BTreeMap<String, String>) -> Result<Self, LogError> {
        let invalid = |key: &str, reason: String| LogError::InvalidMetadata {
            file: file.to_owned(),
            key: key.to_owned(),
            reason,
        };
        let id = |key: &str| -> Result<String, LogError> {
            let value = map
                .get(key)
                .ok_or_else(|| invalid(key, "is missing".into()))?;
            if is_valid_id(value) {
                Ok(value.clone())
            } else {
                Err(invalid(key, format!("value {value:?} is not {ID_FORMAT}")))
            }
        };
        let number = |key: &str| -> Result<Option<f64>, LogError> {
            map.get(key)
                .map(|v| {
                    v.trim()
                        .parse::<f64>()
                        .map_err(|_| invalid(key, format!("value {v:?} is not a number")))
                })
                .transpose()
        };
        let known = [
            "asset_id",
            "run_id",
            "charge_pressure_bar",
            "excitation",
            "frequency_hz",
            "stroke_pp_m",
        ];
        Ok(RunMetadata {
            asset_id: id("asset_id")?,
            run_id: id("run_id")?,
            charge_pressure_bar: number("charge_pressure_bar")?,
            excitation: map.get("excitation").cloned(),
            frequency_hz: number("frequency_hz")?,
            stroke_pp_m: number("stroke_pp_m")?,
            extra: map
                .iter()
                .filter(|(k, _)| !known.contains(&k.as_str()))
                .map(|(k, v)| (k.clone(), v.clone()))
                .collect(),
        })
    }
}
