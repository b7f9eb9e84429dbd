//! The nitrogen charge in the reservoir (SPEC §1 "charge pressure").
//!
//! * Amount of gas from the label: `m R = (p_charge + p_atm) · V₀ / 293.15 K`
//!   (ideal gas; the charge pressure is the static pressure at 20 °C with
//!   the oil at 20 °C and the rod at mid-stroke).
//! * Reference (mid-stroke) volume shrinks as the oil expands:
//!   `V_ref = V₀ − V_oil · β_oil · (T_oil − 20 °C)` — an effect the twin
//!   (ideal gas at oil temperature, fixed volume) does not model.
//! * Static pressure (what `/truth/gas_pressure` `static_bar` reports, gauge):
//!   `p_s = m R · T_gas / V_ref`, with the **gas** temperature, which lags
//!   the oil temperature: `dT_gas/dt = (T_oil − T_gas) / τ_gas`.
//! * Instantaneous pressure while stroking: polytropic about the reference,
//!   `p = p_s · (V_ref / V)^n`, `V = V_ref + A_rod · y − V_void`
//!   (rod out → more room for gas; oil that has not yet refilled a
//!   cavitation void stays in the reservoir). The index
//!   `n = 1 + (γ − 1)(ωτ)² / (1 + (ωτ)²)` goes from isothermal (slow) to
//!   adiabatic (fast) with the excitation frequency ω and the gas pocket's
//!   heat-exchange time constant τ (`gas_ht_tau_s`). The spring is treated as
//!   conservative (its hysteresis loss is below 1 % of the valve heat).
//!
//! Units: pressures Pa absolute, volumes m³, temperatures °C.

use crate::params::{PlantParams, CHARGE_REF_C, KELVIN, P_ATM_PA};
use crate::SimError;

/// The gas spring of one run.
#[derive(Debug, Clone, PartialEq)]
pub struct GasSpring {
    /// `m R`, J/K.
    mr_j_per_k: f64,
    v0_m3: f64,
    oil_v_beta_m3_per_k: f64,
    rod_area_m2: f64,
    /// Polytropic index for this run's excitation.
    pub n: f64,
    tau_s: f64,
}

impl GasSpring {
    /// The gas charge of `params` at `charge_bar` (gauge at 20 °C), for an
    /// excitation at `frequency_hz` (0 for rest).
    #[must_use]
    pub fn new(params: &PlantParams, charge_bar: f64, frequency_hz: f64) -> Self {
        let v0 = params.gas_volume_m3;
        let wt = 2.0 * std::f64::consts::PI * frequency_hz * params.gas_ht_tau_s;
        let phi = wt * wt / (1.0 + wt * wt);
        GasSpring {
            mr_j_per_k: (charge_bar * 1e5 + P_ATM_PA) * v0 / (CHARGE_REF_C + KELVIN),
            v0_m3: v0,
            oil_v_beta_m3_per_k: params.oil_volume_m3 * params.oil_expansion_per_k,
            rod_area_m2: params.rod_area_m2(),
            n: 1.0 + (params.gas_gamma - 1.0) * phi,
            tau_s: params.gas_tau_s,
        }
    }

    /// Mid-stroke gas volume at oil temperature `oil_c`, m³.
    #[must_use]
    pub fn ref_volume_m3(&self, oil_c: f64) -> f64 {
        self.v0_m3 - self.oil_v_beta_m3_per_k * (oil_c - CHARGE_REF_C)
    }

    /// Static (mid-stroke) absolute pressure, Pa.
    #[must_use]
    pub fn static_pa(&self, gas_c: f64, oil_c: f64) -> f64 {
        self.mr_j_per_k * (gas_c + KELVIN) / self.ref_volume_m3(oil_c)
    }

    /// Gas volume at extension `y_m` with a cavitation void `void_m3`, m³.
    #[must_use]
    pub fn volume_m3(&self, oil_c: f64, y_m: f64, void_m3: f64) -> f64 {
        self.ref_volume_m3(oil_c) + self.rod_area_m2 * y_m - void_m3
    }

    /// Instantaneous absolute pressure, Pa; an error if the gas volume is
    /// not positive (oil overfill).
    pub fn pressure_pa(
        &self,
        gas_c: f64,
        oil_c: f64,
        y_m: f64,
        void_m3: f64,
    ) -> Result<f64, SimError> {
        let v_ref = self.ref_volume_m3(oil_c);
        let v = self.volume_m3(oil_c, y_m, void_m3);
        if !(v > 0.0 && v_ref > 0.0) {
            return Err(SimError::Numerical {
                what: "gas volume (oil expansion filled the reservoir)",
                value: v,
            });
        }
        Ok(self.static_pa(gas_c, oil_c) * (v_ref / v).powf(self.n))
    }

    /// Advances the gas temperature by `dt_s` toward `oil_c` (exact
    /// first-order step).
    #[must_use]
    pub fn lag_gas_c(&self, gas_c: f64, oil_c: f64, dt_s: f64) -> f64 {
        oil_c + (gas_c - oil_c) * (-dt_s / self.tau_s).exp()
    }
}
