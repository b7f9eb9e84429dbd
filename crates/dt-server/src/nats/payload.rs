//! The telemetry payload on `shocktwin.telemetry.<asset>` (SPEC §10; the
//! contract is written out in `docs/nats.md`): one JSON object per message,
//! a batch of one run's samples in time order.
//!
//! ```json
//! {"v": 1, "asset_id": "unit-7", "run_id": "r-0042", "batch": 0, "end": false,
//!  "meta": {"charge_pressure_bar": "12"},
//!  "position": [[1700000000000000000, 0.0123], ...],
//!  "acceleration": [[t_ns, a1_mps2, a2_mps2], ...],
//!  "force": [[t_ns, force_n], ...],
//!  "temperature_shock": [[t_ns, c], ...], "temperature_ambient": [[t_ns, c], ...]}
//! ```
//!
//! - `v` is the payload version (1); unknown fields are ignored, so fields
//!   can be added without breaking older workers.
//! - `batch` counts the run's batches from 0; a run starts at batch 0 and
//!   ends with a batch whose `end` is true (it may carry samples). A batch
//!   number not above the last one taken is *going back in time*: refused.
//! - `meta` is the run's `shocktwin.run` record (SPEC §2, string values);
//!   read from batch 0, ignored later.
//! - Topics are arrays of `[t_ns, value...]` in SPEC §2 units and signs;
//!   `null` is a missing value (NaN). Absent topics are empty. Truth topics
//!   (`truth_gas_pressure`, `truth_velocity`) are accepted for simulated and
//!   dyno data.
//!
//! The subject token is the asset id with `.` written as `~` (a NATS subject
//! token cannot hold a dot, and `~` is outside SPEC §2's charset, so the
//! mapping is one to one); see [`subject_token`].

use std::collections::BTreeMap;

use dt_core::log::{is_valid_id, RunMetadata, Sample};
use serde::{Deserialize, Deserializer, Serialize};

/// The payload version this build writes and reads.
pub const PAYLOAD_VERSION: u32 = 1;

/// One telemetry message.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct TelemetryBatch {
    /// [`PAYLOAD_VERSION`].
    pub v: u32,
    /// The asset (SPEC §2 charset).
    pub asset_id: String,
    /// The run (SPEC §2 charset).
    pub run_id: String,
    /// Batch number within the run, from 0.
    pub batch: u64,
    /// The last batch of the run.
    #[serde(default)]
    pub end: bool,
    /// The run's `shocktwin.run` metadata record (batch 0).
    #[serde(default, skip_serializing_if = "BTreeMap::is_empty")]
    pub meta: BTreeMap<String, String>,
    /// `/position`: `[t_ns, position_m]`.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub position: Vec<(i64, Num)>,
    /// `/acceleration`: `[t_ns, a1_mps2, a2_mps2]`.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub acceleration: Vec<(i64, Num, Num)>,
    /// `/force`: `[t_ns, force_n]`, positive in tension.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub force: Vec<(i64, Num)>,
    /// `/temperature/shock`: `[t_ns, temperature_c]`.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub temperature_shock: Vec<(i64, Num)>,
    /// `/temperature/ambient`: `[t_ns, temperature_c]`.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub temperature_ambient: Vec<(i64, Num)>,
    /// `/truth/gas_pressure`: `[t_ns, static_bar]` (simulated and dyno data).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub truth_gas_pressure: Vec<(i64, Num)>,
    /// `/truth/velocity`: `[t_ns, velocity_mps]` (simulated and dyno data).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub truth_velocity: Vec<(i64, Num)>,
}

/// A number of the payload: JSON `null` is NaN (and NaN is written `null`).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Num(pub f64);

impl Serialize for Num {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        if self.0.is_finite() {
            s.serialize_f64(self.0)
        } else {
            s.serialize_none()
        }
    }
}

impl<'de> Deserialize<'de> for Num {
    fn deserialize<D: Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        Ok(Num(Option::<f64>::deserialize(d)?.unwrap_or(f64::NAN)))
    }
}

/// Why a message was refused (the dead-letter reason).
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum PayloadError {
    /// Not JSON of this shape.
    #[error("undecodable payload: {0}")]
    Decode(String),
    /// Another payload version.
    #[error("payload version {0}, this worker reads {PAYLOAD_VERSION}")]
    Version(u32),
    /// An id outside SPEC §2's charset.
    #[error("field `{field}`: {value:?} is not {}", dt_core::log::ID_FORMAT)]
    BadId {
        /// `asset_id` or `run_id`.
        field: &'static str,
        /// The value (cut to 80 characters).
        value: String,
    },
    /// The subject names another asset than the payload.
    #[error("the subject names asset token `{token}`, the payload's `asset_id` is `{asset}` (its token: `{expected}`)")]
    SubjectMismatch {
        /// The subject's asset token.
        token: String,
        /// The payload's asset.
        asset: String,
        /// The token `asset` maps to.
        expected: String,
    },
    /// Batch 0 without a usable `meta` record.
    #[error("batch 0 metadata: {0}")]
    Meta(String),
}

impl PayloadError {
    /// Short label for metrics and the dead-letter header.
    #[must_use]
    pub fn kind(&self) -> &'static str {
        match self {
            PayloadError::Decode(_) => "decode",
            PayloadError::Version(_) => "version",
            PayloadError::BadId { .. } => "charset",
            PayloadError::SubjectMismatch { .. } => "subject",
            PayloadError::Meta(_) => "metadata",
        }
    }
}

/// The subject token of an asset id: `.` written as `~`.
#[must_use]
pub fn subject_token(asset_id: &str) -> String {
    asset_id.replace('.', "~")
}

/// The asset id of a subject token (inverse of [`subject_token`]).
#[must_use]
pub fn asset_of_token(token: &str) -> String {
    token.replace('~', ".")
}

impl TelemetryBatch {
    /// Decodes and checks a message received on the subject whose asset
    /// token is `token`.
    pub fn decode(token: &str, bytes: &[u8]) -> Result<Self, PayloadError> {
        // names the field's path, not only a column (a helper's trial:
        // "invalid type: string "x", expected f64 at line 1 column 91")
        let mut de = serde_json::Deserializer::from_slice(bytes);
        let b: TelemetryBatch = serde_path_to_error::deserialize(&mut de).map_err(|e| {
            let path = e.path().to_string();
            PayloadError::Decode(if path == "." {
                e.into_inner().to_string()
            } else {
                format!("field `{path}`: {}", e.into_inner())
            })
        })?;
        // nothing after the object (what `serde_json::from_slice` checks)
        de.end()
            .map_err(|e| PayloadError::Decode(format!("after the object: {e}")))?;
        if b.v != PAYLOAD_VERSION {
            return Err(PayloadError::Version(b.v));
        }
        for (field, value) in [("asset_id", &b.asset_id), ("run_id", &b.run_id)] {
            if !is_valid_id(value) {
                return Err(PayloadError::BadId {
                    field,
                    value: value.chars().take(80).collect(),
                });
            }
        }
        let expected = subject_token(&b.asset_id);
        if token != expected {
            return Err(PayloadError::SubjectMismatch {
                token: token.chars().take(80).collect(),
                asset: b.asset_id.clone(),
                expected,
            });
        }
        Ok(b)
    }

    /// The run's metadata (from `meta`, with the batch's ids).
    pub fn metadata(&self) -> Result<RunMetadata, PayloadError> {
        let mut map = self.meta.clone();
        map.insert("asset_id".into(), self.asset_id.clone());
        map.insert("run_id".into(), self.run_id.clone());
        RunMetadata::from_map("telemetry", &map).map_err(|e| PayloadError::Meta(e.to_string()))
    }

    /// Number of samples carried.
    #[must_use]
    pub fn len(&self) -> usize {
        self.position.len()
            + self.acceleration.len()
            + self.force.len()
            + self.temperature_shock.len()
            + self.temperature_ambient.len()
            + self.truth_gas_pressure.len()
            + self.truth_velocity.len()
    }

    /// Whether no samples are carried.
    #[must_use]
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Adds one sample to its topic.
    pub fn push(&mut self, s: &Sample) {
        match *s {
            Sample::Position { t_ns, position_m } => self.position.push((t_ns, Num(position_m))),
            Sample::Acceleration {
                t_ns,
                a1_mps2,
                a2_mps2,
            } => self.acceleration.push((t_ns, Num(a1_mps2), Num(a2_mps2))),
            Sample::Force { t_ns, force_n } => self.force.push((t_ns, Num(force_n))),
            Sample::TempShock {
                t_ns,
                temperature_c,
            } => self.temperature_shock.push((t_ns, Num(temperature_c))),
            Sample::TempAmbient {
                t_ns,
                temperature_c,
            } => self.temperature_ambient.push((t_ns, Num(temperature_c))),
            Sample::TruthPressure { t_ns, static_bar } => {
                self.truth_gas_pressure.push((t_ns, Num(static_bar)));
            }
            Sample::TruthVelocity { t_ns, velocity_mps } => {
                self.truth_velocity.push((t_ns, Num(velocity_mps)));
            }
        }
    }

    /// The samples, sorted by time and topic rank (the estimator's release
    /// order; within a batch any order is equivalent, SPEC §3).
    #[must_use]
    pub fn samples(&self) -> Vec<Sample> {
        let mut out = Vec::with_capacity(self.len());
        out.extend(
            self.acceleration
                .iter()
                .map(|&(t_ns, a1, a2)| Sample::Acceleration {
                    t_ns,
                    a1_mps2: a1.0,
                    a2_mps2: a2.0,
                }),
        );
        out.extend(self.position.iter().map(|&(t_ns, y)| Sample::Position {
            t_ns,
            position_m: y.0,
        }));
        out.extend(
            self.force
                .iter()
                .map(|&(t_ns, f)| Sample::Force { t_ns, force_n: f.0 }),
        );
        out.extend(
            self.temperature_shock
                .iter()
                .map(|&(t_ns, c)| Sample::TempShock {
                    t_ns,
                    temperature_c: c.0,
                }),
        );
        out.extend(
            self.temperature_ambient
                .iter()
                .map(|&(t_ns, c)| Sample::TempAmbient {
                    t_ns,
                    temperature_c: c.0,
                }),
        );
        out.extend(
            self.truth_gas_pressure
                .iter()
                .map(|&(t_ns, p)| Sample::TruthPressure {
                    t_ns,
                    static_bar: p.0,
                }),
        );
        out.extend(
            self.truth_velocity
                .iter()
                .map(|&(t_ns, v)| Sample::TruthVelocity {
                    t_ns,
                    velocity_mps: v.0,
                }),
        );
        out.sort_by_key(|s| (s.t_ns(), s.topic_rank()));
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trip_keeps_samples_and_nan() {
        let mut b = TelemetryBatch {
            v: 1,
            asset_id: "bus.7".into(),
            run_id: "r1".into(),
            ..TelemetryBatch::default()
        };
        b.push(&Sample::Position {
            t_ns: 5,
            position_m: 0.1,
        });
        b.push(&Sample::Acceleration {
            t_ns: 3,
            a1_mps2: f64::NAN,
            a2_mps2: -2.5,
        });
        let bytes = serde_json::to_vec(&b).unwrap();
        let d = TelemetryBatch::decode("bus~7", &bytes).unwrap();
        let s = d.samples();
        assert_eq!(s.len(), 2);
        assert_eq!(s[0].t_ns(), 3);
        assert!(
            matches!(s[0], Sample::Acceleration { a1_mps2, a2_mps2, .. } if a1_mps2.is_nan() && (a2_mps2 + 2.5).abs() < 1e-12)
        );
    }

    #[test]
    fn refusals_name_the_field() {
        let ok = br#"{"v":1,"asset_id":"a","run_id":"r","batch":0}"#;
        assert!(TelemetryBatch::decode("a", ok).is_ok());
        let e = TelemetryBatch::decode("a", br#"{"v":2,"asset_id":"a","run_id":"r","batch":0}"#)
            .unwrap_err();
        assert_eq!(e.kind(), "version");
        let e = TelemetryBatch::decode("a", br#"{"v":1,"asset_id":"a b","run_id":"r","batch":0}"#)
            .unwrap_err();
        assert!(e.to_string().contains("asset_id"), "{e}");
        let e = TelemetryBatch::decode("b", ok).unwrap_err();
        assert_eq!(e.kind(), "subject");
        assert!(
            e.to_string().contains("asset token `b`")
                && e.to_string().contains("`asset_id` is `a`"),
            "{e}"
        );
        let e = TelemetryBatch::decode(
            "a",
            br#"{"v":1,"asset_id":"a","run_id":"r","batch":0,"force":[[1,"x"]]}"#,
        )
        .unwrap_err();
        assert_eq!(e.kind(), "decode");
        // the field's path, not only a column
        assert!(e.to_string().contains("field `force[0][1]`"), "{e}");
        let e = TelemetryBatch::decode("a", br#"{"v":1,"asset_id":"a","run_id":"r"}"#).unwrap_err();
        assert!(e.to_string().contains("batch"), "{e}");
        assert!(TelemetryBatch::decode("a", b"\xff\x00garbage").is_err());
        // trailing bytes, or a second object, are refused (a review: the
        // path-naming decoder alone took them)
        for tail in [&b"garbage"[..], &br#"{"v":1}"#[..]] {
            let bytes = [&ok[..], tail].concat();
            let e = TelemetryBatch::decode("a", &bytes).unwrap_err();
            assert_eq!(e.kind(), "decode", "{e}");
        }
        assert!(TelemetryBatch::decode("a", &[&ok[..], b" \n"].concat()).is_ok());
    }
}
