//! What the estimator emits: one [`Estimate`] per 50 Hz tick (SPEC §2
//! `/estimate`, §6 health).
//!
//! Data only: the estimator (`dt_core::estimator`) produces these, the
//! daemon (`dt-server`), `replay` and the Python bindings consume them.
//! A value the estimator cannot give (not enough data yet, a placeholder
//! twin) is `NaN`; JSON has no NaN, so it is written as `null` and read back
//! as `NaN`.

use serde::{Deserialize, Deserializer, Serialize};

/// Health of an asset's gas charge (SPEC §6), judged on the 1 s average
/// charge pressure with hysteresis and a dwell time.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Health {
    /// At or above the warn threshold.
    Ok,
    /// Below the warn threshold (default 9 bar).
    Low,
    /// Below the fault threshold (default 5 bar).
    Leak,
    /// Not enough excitation or data to judge.
    #[default]
    Unknown,
}

impl Health {
    /// The SPEC §6 name (`ok`, `low`, `leak`, `unknown`).
    #[must_use]
    pub fn as_str(self) -> &'static str {
        match self {
            Health::Ok => "ok",
            Health::Low => "low",
            Health::Leak => "leak",
            Health::Unknown => "unknown",
        }
    }
}

impl std::fmt::Display for Health {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.as_str())
    }
}

/// One estimate at a 50 Hz tick (SPEC §2 `/estimate` fields).
///
/// `t_ns` is the tick time on the run's clock (the MCAP `log_time` of the
/// `/estimate` message). Pressures are bar gauge; the charge pressure is
/// referred to 20 °C (SPEC §1).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Estimate {
    /// Tick time, ns (same epoch as the input samples).
    pub t_ns: i64,
    /// Instantaneous charge-pressure estimate, bar gauge.
    #[serde(deserialize_with = "f64_or_nan")]
    pub pressure_bar: f64,
    /// 1 s moving average of `pressure_bar`, bar gauge.
    #[serde(deserialize_with = "f64_or_nan")]
    pub pressure_avg_bar: f64,
    /// Lower end of the central 95 % interval of the charge pressure at the
    /// tick, bar gauge (SPEC §2a); NaN when the estimator cannot say (a
    /// bundle with neither the charge observer nor a held-out interval, or
    /// one with the latter while there is no 1 s average). Absent in older
    /// records.
    #[serde(default = "nan", deserialize_with = "f64_or_nan")]
    pub pressure_lo_bar: f64,
    /// Upper end of that interval, bar gauge.
    #[serde(default = "nan", deserialize_with = "f64_or_nan")]
    pub pressure_hi_bar: f64,
    /// The asset's nominal charge pressure, bar gauge (SPEC §6).
    #[serde(deserialize_with = "f64_or_nan")]
    pub expected_bar: f64,
    /// Health decision (SPEC §6).
    pub health: Health,
    /// Kalman velocity `ẏ` at the tick, m/s.
    #[serde(deserialize_with = "f64_or_nan")]
    pub velocity_mps: f64,
    /// Modelled force at the tick (eq. 9), N, positive in tension.
    #[serde(deserialize_with = "f64_or_nan")]
    pub force_model_n: f64,
    /// Modelled oil temperature at the tick, °C.
    #[serde(deserialize_with = "f64_or_nan")]
    pub oil_temp_c: f64,
    /// `pressure_bar` before the floor at 0 bar gauge (`at_ambient_floor` in
    /// `estimator`): what a statistic over many ticks should take, since the
    /// floor biases a mean upwards near 0. Not part of `/estimate`: not
    /// written, and NaN when read from a record.
    #[serde(skip, default = "nan")]
    pub unfloored_bar: f64,
    /// Half the width of the 95 % interval before the floor (its lower bound
    /// floored at 0 makes `(hi − lo) / 2` too narrow); NaN without an
    /// interval. Not part of `/estimate`, as `unfloored_bar`.
    #[serde(skip, default = "nan")]
    pub unfloored_half_bar: f64,
}

/// JSON schema (`jsonschema` encoding) of the `/estimate` topic's messages.
pub const ESTIMATE_SCHEMA_JSON: &str = r#"{"type":"object","title":"shocktwin estimate","properties":{"t_ns":{"type":"integer"},"pressure_bar":{"type":"number"},"pressure_avg_bar":{"type":"number"},"pressure_lo_bar":{"type":"number"},"pressure_hi_bar":{"type":"number"},"expected_bar":{"type":"number"},"health":{"type":"string","enum":["ok","low","leak","unknown"]},"velocity_mps":{"type":"number"},"force_model_n":{"type":"number"},"oil_temp_c":{"type":"number"}},"required":["pressure_bar","pressure_avg_bar","expected_bar","health","velocity_mps","force_model_n","oil_temp_c"]}"#;

fn nan() -> f64 {
    f64::NAN
}

/// Reads a JSON number, or `null` as NaN (`serde_json` writes NaN as `null`).
fn f64_or_nan<'de, D: Deserializer<'de>>(d: D) -> Result<f64, D::Error> {
    Ok(Option::<f64>::deserialize(d)?.unwrap_or(f64::NAN))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn health_serializes_lowercase() {
        let names: Vec<String> = [Health::Ok, Health::Low, Health::Leak, Health::Unknown]
            .iter()
            .map(|h| serde_json::to_string(h).unwrap())
            .collect();
        assert_eq!(names, ["\"ok\"", "\"low\"", "\"leak\"", "\"unknown\""]);
        assert_eq!(Health::Leak.to_string(), "leak");
    }

    #[test]
    fn nan_round_trips_through_null() {
        let e = Estimate {
            t_ns: 20_000_000,
            pressure_bar: f64::NAN,
            pressure_avg_bar: 11.5,
            pressure_lo_bar: 10.0,
            pressure_hi_bar: f64::NAN,
            expected_bar: 12.0,
            health: Health::Ok,
            velocity_mps: -0.25,
            force_model_n: 812.0,
            oil_temp_c: 31.0,
            unfloored_bar: -0.4,
            unfloored_half_bar: 2.1,
        };
        let json = serde_json::to_string(&e).unwrap();
        assert!(json.contains("\"pressure_bar\":null"), "{json}");
        // the unfloored pair is the daemon's own, not the topic's
        assert!(!json.contains("unfloored"), "{json}");
        assert!(json.contains("\"health\":\"ok\""), "{json}");
        let back: Estimate = serde_json::from_str(&json).unwrap();
        assert!(back.pressure_bar.is_nan());
        assert_eq!(back.pressure_avg_bar.to_bits(), 11.5_f64.to_bits());
        assert_eq!(back.pressure_lo_bar.to_bits(), 10.0_f64.to_bits());
        assert!(back.pressure_hi_bar.is_nan());
        assert!(back.unfloored_bar.is_nan() && back.unfloored_half_bar.is_nan());
        // A v1 record (no interval) still reads, with NaN bounds.
        let v1 = json
            .replace(",\"pressure_lo_bar\":10.0", "")
            .replace(",\"pressure_hi_bar\":null", "");
        let old: Estimate = serde_json::from_str(&v1).unwrap();
        assert!(old.pressure_lo_bar.is_nan() && old.pressure_hi_bar.is_nan());
        assert_eq!(back.t_ns, e.t_ns);
        assert_eq!(back.health, Health::Ok);
    }

    #[test]
    fn schema_is_valid_json_naming_every_field() {
        let schema: serde_json::Value = serde_json::from_str(ESTIMATE_SCHEMA_JSON).unwrap();
        let props = schema["properties"].as_object().unwrap();
        for field in [
            "pressure_bar",
            "pressure_avg_bar",
            "pressure_lo_bar",
            "pressure_hi_bar",
            "expected_bar",
            "health",
            "velocity_mps",
            "force_model_n",
            "oil_temp_c",
        ] {
            assert!(props.contains_key(field), "schema lacks {field}");
        }
    }
}
