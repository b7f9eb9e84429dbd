//! Parameters of the twin's physics models (SPEC §3), with the SPEC (Python)
//! names, serde (JSON with exactly these names) and validation.
//!
//! - [`KalmanParams`]: velocity estimator, SPEC §3.1 (paper eq. 1).
//! - [`ThermalParams`]: oil/cylinder heat balance, SPEC §3.2 (paper eqs. 2–3).
//! - [`ForceParams`]: nominal force model, SPEC §3.3 (paper eqs. 4–9).
//! - [`PhysicsParams`]: all three, as stored in `physics.json` and `twin.json`.
//!
//! The `Default`s are *priors* for a twin-tube road damper with a 20 mm rod at
//! 12 bar nominal charge on the paper's dyno (80 mm p-p at 1–4 Hz); each is
//! documented at its field with its source (`reference/physics-notes.md`).
//! Calibration (`train.fit_physics`) replaces the thermal and force priors by
//! fitted values.

use serde::{Deserialize, Serialize};

pub use crate::charge::ObserverParams;
use crate::error::PhysicsError;

/// Standard atmospheric pressure, Pa (SPEC §3.3 `p_atm`).
pub const P_ATM_PA: f64 = 101_325.0;

/// Kelvin offset of the Celsius scale.
pub const KELVIN_OFFSET: f64 = 273.15;

/// Reference temperature of the charge pressure, °C (SPEC §1: referred to 20 °C).
pub const CHARGE_REF_TEMP_C: f64 = 20.0;

/// Kalman filter noise parameters (SPEC §3.1).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct KalmanParams {
    /// `σ_a`, m/s²: standard deviation of the relative acceleration `u = a1 − a2`
    /// held over one propagation step (enters `Q = σ_a² G Gᵀ`).
    ///
    /// Prior 0.2 m/s²: an ADXL345-class pair has ≈ 6.5 mg ≈ 0.064 m/s² rms
    /// noise each at 1 kHz, ≈ 0.09 m/s² for the difference; doubled for
    /// quantisation (3.9 mg/LSB) and non-linearity (±0.5 % FS).
    pub sigma_accel: f64,
    /// `σ_b`, m/s²/√s: random-walk density of the accelerometer-pair bias
    /// (enters `Q[2][2] = σ_b² dt`).
    ///
    /// Prior 0.005 m/s²/√s: the 0 g offset (±50 mg typical) is constant up to
    /// a thermal drift of ±0.17 mg/°C, i.e. slow; the random walk lets the
    /// filter follow that drift over minutes.
    pub sigma_bias: f64,
    /// `σ_z`, m: potentiometer measurement noise (`R = σ_z²`).
    ///
    /// Prior 1 mm: a conductive-plastic 150 mm potentiometer is linear to
    /// ±0.05–0.1 % FS (0.08–0.15 mm) and repeatable to ≈ 0.01 mm; 1 mm also
    /// covers the ADC and cable noise of a field installation.
    pub sigma_position: f64,
}

impl Default for KalmanParams {
    fn default() -> Self {
        Self {
            sigma_accel: 0.2,
            sigma_bias: 0.005,
            sigma_position: 1.0e-3,
        }
    }
}

impl KalmanParams {
    /// Checks that every parameter is finite and non-negative.
    ///
    /// Zero noise is allowed (an exact model); the filter reports a numerical
    /// error if the innovation variance then becomes non-positive.
    pub fn validate(&self) -> Result<(), PhysicsError> {
        non_negative("sigma_accel", self.sigma_accel)?;
        non_negative("sigma_bias", self.sigma_bias)?;
        non_negative("sigma_position", self.sigma_position)
    }
}

/// Lumped parameters of the thermal model (SPEC §3.2, paper eqs. 2–3).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ThermalParams {
    /// `m_oil c_oil`, J/K: heat capacity of the damping fluid.
    ///
    /// Prior 500 J/K: ≈ 0.27 kg of mineral damper oil at ≈ 1.9 kJ/(kg K).
    pub c_oil: f64,
    /// `m_cyl c_cyl`, J/K: heat capacity of the cylinder (tubes, end caps).
    ///
    /// Prior 700 J/K: ≈ 1.5 kg of steel at 0.47 kJ/(kg K).
    pub c_cyl: f64,
    /// `h_oil A_cyl^in`, W/K: oil–cylinder conductance.
    ///
    /// Prior 10 W/K: ≈ 0.04 m² of wetted tube wall at ≈ 250 W/(m² K)
    /// (oil in forced motion).
    pub ha_in: f64,
    /// `h_amb A_cyl^out`, W/K: cylinder–ambient convective conductance.
    ///
    /// Prior 2.5 W/K: ≈ 0.05 m² outer surface at ≈ 50 W/(m² K) (dyno with
    /// cooling air); with the force priors a 1 Hz, 80 mm p-p test
    /// (≈ 100 W) then settles near 60 °C, as in the paper (§4.1).
    pub ha_out: f64,
    /// `ε σ A_cyl^out`, W/K⁴: radiation coefficient.
    ///
    /// Prior 2.3e-9 W/K⁴: ε ≈ 0.8 (painted steel) × σ = 5.67e-8 W/(m² K⁴)
    /// × 0.05 m².
    pub eps_sigma_a: f64,
    /// The shock thermocouple's contact gain κ (dimensionless, 0 < κ ≤ 1 for a
    /// surface sensor): it reads `T_amb + κ (T_cyl − T_amb)` plus the offset it
    /// had against the ambient thermocouple when the model started, because
    /// a sensor taped to the tube loses heat to the air through its leads.
    /// An extension of SPEC §3.2 (default 1: the reading is `T_cyl`). It
    /// does not enter the heat balance, only `temp_resid_c`; calibration
    /// needs it because with κ = 1 the fit pays for a sensor that reads low
    /// with an oil node that runs hot.
    #[serde(default = "unit_gain")]
    pub tc_gain: f64,
    /// First-order lag of the shock thermocouple, s (default 0: none).
    /// Like `tc_gain`, only in `temp_resid_c`.
    #[serde(default)]
    pub tc_lag_s: f64,
}

fn unit_gain() -> f64 {
    1.0
}

impl Default for ThermalParams {
    fn default() -> Self {
        Self {
            c_oil: 500.0,
            c_cyl: 700.0,
            ha_in: 10.0,
            ha_out: 2.5,
            eps_sigma_a: 2.3e-9,
            tc_gain: 1.0,
            tc_lag_s: 0.0,
        }
    }
}

impl ThermalParams {
    /// Checks heat capacities are finite and positive, conductances finite
    /// and non-negative.
    pub fn validate(&self) -> Result<(), PhysicsError> {
        positive("c_oil", self.c_oil)?;
        positive("c_cyl", self.c_cyl)?;
        non_negative("ha_in", self.ha_in)?;
        non_negative("ha_out", self.ha_out)?;
        non_negative("eps_sigma_a", self.eps_sigma_a)?;
        positive("tc_gain", self.tc_gain)?;
        non_negative("tc_lag_s", self.tc_lag_s)
    }
}

/// Parameters of the nominal force model (SPEC §3.3, paper eqs. 4–9).
///
/// `_reb` coefficients apply for `ẏ ≥ 0` (rebound), `_com` for `ẏ < 0`.
/// Viscosity is the kinematic viscosity in mm²/s (cSt), so `k_leak` is in
/// N·s/m per cSt and `k_main` in N·(s/m)^1.75 per cSt^0.25.
///
/// The priors reproduce, to ±25 %, the public force curve of a large SUV
/// damper (physics-notes: +0.13 m/s 902 N, +0.53 m/s 2178 N, +1.06 m/s
/// 4054 N; −0.53 m/s −744 N, −1.06 m/s −971 N) at 40 °C.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ForceParams {
    /// Leak-port coefficient, rebound (prior 533: 8000 N·s/m at 15 cSt).
    pub k_leak_reb: f64,
    /// Leak-port coefficient, compression (prior 270: 4050 N·s/m at 15 cSt).
    pub k_leak_com: f64,
    /// Shim-stack preload force, rebound, N (prior 600).
    pub f_preload_reb: f64,
    /// Shim-stack preload force, compression, N (prior 300).
    pub f_preload_com: f64,
    /// Shim-stack spring rate, rebound, N·s/m (prior 2000).
    pub k_spring_reb: f64,
    /// Shim-stack spring rate, compression, N·s/m (prior 400).
    pub k_spring_com: f64,
    /// Main-port coefficient, rebound (prior 670).
    pub k_main_reb: f64,
    /// Main-port coefficient, compression (prior 150).
    pub k_main_com: f64,
    /// Exponent of the smooth minimum (transition sharpness), dimensionless
    /// (prior 2).
    pub k_tr: f64,
    /// Hysteresis coefficient, N·s²/m (an equivalent fluid mass, kg;
    /// prior 2).
    pub k_hys: f64,
    /// Kinematic oil viscosity at 40 °C, mm²/s (prior 15 cSt, a typical
    /// damper fluid).
    pub nu_40: f64,
    /// Viscosity temperature coefficient, 1/K: `ν(T) = nu_40·exp(−beta(T−40))`
    /// (prior 0.02: damping fades ≈ 2 %/°C, physics-notes).
    pub beta: f64,
    /// Nominal charge pressure, bar gauge at 20 °C (prior 12, the paper's
    /// nominal unit).
    pub charge_bar: f64,
    /// Rod cross-section, m² (prior π·(10 mm)² = 3.1416e-4, a 20 mm rod).
    pub a_rod: f64,
    /// Static gas volume at mid-stroke, m³ (prior 1e-4 = 100 cm³: the rod
    /// stroke of ±40 mm changes it by ±12.6 %).
    pub v_gas: f64,
}

impl Default for ForceParams {
    fn default() -> Self {
        Self {
            k_leak_reb: 533.0,
            k_leak_com: 270.0,
            f_preload_reb: 600.0,
            f_preload_com: 300.0,
            k_spring_reb: 2000.0,
            k_spring_com: 400.0,
            k_main_reb: 670.0,
            k_main_com: 150.0,
            k_tr: 2.0,
            k_hys: 2.0,
            nu_40: 15.0,
            beta: 0.02,
            charge_bar: 12.0,
            a_rod: std::f64::consts::PI * 0.01 * 0.01,
            v_gas: 1.0e-4,
        }
    }
}

impl ForceParams {
    /// Checks every coefficient: damping coefficients, preloads, `k_hys` and
    /// `beta` finite and non-negative; `k_tr`, `nu_40`, `a_rod`, `v_gas`
    /// finite and positive; `charge_bar` finite with a positive absolute
    /// pressure (`charge_bar > −1.01325`).
    pub fn validate(&self) -> Result<(), PhysicsError> {
        non_negative("k_leak_reb", self.k_leak_reb)?;
        non_negative("k_leak_com", self.k_leak_com)?;
        non_negative("f_preload_reb", self.f_preload_reb)?;
        non_negative("f_preload_com", self.f_preload_com)?;
        non_negative("k_spring_reb", self.k_spring_reb)?;
        non_negative("k_spring_com", self.k_spring_com)?;
        non_negative("k_main_reb", self.k_main_reb)?;
        non_negative("k_main_com", self.k_main_com)?;
        positive("k_tr", self.k_tr)?;
        non_negative("k_hys", self.k_hys)?;
        positive("nu_40", self.nu_40)?;
        non_negative("beta", self.beta)?;
        finite("charge_bar", self.charge_bar)?;
        if self.charge_bar * 1.0e5 + P_ATM_PA <= 0.0 {
            return Err(PhysicsError::InvalidParameter {
                name: "charge_bar",
                value: self.charge_bar,
                reason: "absolute charge pressure must be positive (charge_bar > -1.01325)",
            });
        }
        positive("a_rod", self.a_rod)?;
        positive("v_gas", self.v_gas)
    }
}

/// All physics parameters of a twin (`physics.json`; the `physics` part of
/// `twin.json`).
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PhysicsParams {
    /// SPEC §3.1.
    pub kalman: KalmanParams,
    /// SPEC §3.2.
    pub thermal: ThermalParams,
    /// SPEC §3.3.
    pub force: ForceParams,
    /// The gas-charge observer ([`crate::charge`]); absent in physics
    /// calibrated before it existed (no observer columns then).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub observer: Option<ObserverParams>,
}

impl PhysicsParams {
    /// Validates all three parameter sets; the error names the first bad one.
    pub fn validate(&self) -> Result<(), PhysicsError> {
        self.kalman.validate()?;
        self.thermal.validate()?;
        self.force.validate()?;
        self.observer
            .as_ref()
            .map_or(Ok(()), ObserverParams::validate)
    }
}

fn finite(name: &'static str, value: f64) -> Result<(), PhysicsError> {
    if value.is_finite() {
        Ok(())
    } else {
        Err(PhysicsError::InvalidParameter {
            name,
            value,
            reason: "must be finite",
        })
    }
}

fn non_negative(name: &'static str, value: f64) -> Result<(), PhysicsError> {
    finite(name, value)?;
    if value >= 0.0 {
        Ok(())
    } else {
        Err(PhysicsError::InvalidParameter {
            name,
            value,
            reason: "must be non-negative",
        })
    }
}

fn positive(name: &'static str, value: f64) -> Result<(), PhysicsError> {
    finite(name, value)?;
    if value > 0.0 {
        Ok(())
    } else {
        Err(PhysicsError::InvalidParameter {
            name,
            value,
            reason: "must be positive",
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn defaults_are_valid() {
        PhysicsParams::default().validate().unwrap();
    }

    #[test]
    fn json_uses_spec_names_and_round_trips() {
        let p = PhysicsParams::default();
        let json = serde_json::to_value(p).unwrap();
        let force = json["force"].as_object().unwrap();
        let mut names: Vec<&str> = force.keys().map(String::as_str).collect();
        names.sort_unstable();
        let mut expected = vec![
            "k_leak_reb",
            "k_leak_com",
            "f_preload_reb",
            "f_preload_com",
            "k_spring_reb",
            "k_spring_com",
            "k_main_reb",
            "k_main_com",
            "k_tr",
            "k_hys",
            "nu_40",
            "beta",
            "charge_bar",
            "a_rod",
            "v_gas",
        ];
        expected.sort_unstable();
        assert_eq!(names, expected);
        let thermal = json["thermal"].as_object().unwrap();
        for key in ["c_oil", "c_cyl", "ha_in", "ha_out", "eps_sigma_a"] {
            assert!(thermal.contains_key(key), "{key}");
        }
        for key in ["sigma_accel", "sigma_bias", "sigma_position"] {
            assert!(
                json["kalman"].as_object().unwrap().contains_key(key),
                "{key}"
            );
        }
        let back: PhysicsParams = serde_json::from_value(json).unwrap();
        assert_eq!(back, p);
    }

    #[test]
    fn unknown_field_is_rejected() {
        let mut json = serde_json::to_value(PhysicsParams::default()).unwrap();
        json["thermal"]["c_oill"] = serde_json::json!(1.0);
        let err = serde_json::from_value::<PhysicsParams>(json).unwrap_err();
        assert!(err.to_string().contains("c_oill"), "{err}");
    }

    #[test]
    fn validation_names_the_bad_parameter() {
        let mut p = PhysicsParams::default();
        p.thermal.c_cyl = 0.0;
        let err = p.validate().unwrap_err();
        assert!(err.to_string().contains("c_cyl"), "{err}");

        let mut p = PhysicsParams::default();
        p.force.v_gas = f64::NAN;
        assert!(p.validate().unwrap_err().to_string().contains("v_gas"));

        let mut p = PhysicsParams::default();
        p.kalman.sigma_bias = -1.0;
        assert!(p.validate().unwrap_err().to_string().contains("sigma_bias"));

        let mut p = PhysicsParams::default();
        p.force.charge_bar = -2.0;
        assert!(p.validate().unwrap_err().to_string().contains("charge_bar"));
    }
}
