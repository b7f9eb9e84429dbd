//! Nominal force model of the damper (paper eqs. 4–9, §5.3; SPEC §3.3).
//!
//! **Inputs** extension rate `ẏ` (m/s), acceleration `ÿ` (m/s²), extension
//! `y` (m, from mid-stroke) and oil temperature `T_oil` (°C). **Output** the
//! axial force, N, positive in tension, and its parts. **Parameters**
//! [`ForceParams`]; the `_reb` set applies for `ẏ ≥ 0`, the `_com` set for
//! `ẏ < 0`.
//!
//! ```text
//! ν(T)   = nu_40 · exp(−beta (T_oil − 40))                      viscosity, cSt
//! F_port = smin(k_leak ν |ẏ|, f_preload + k_spring |ẏ|)         (eqs. 4, 6, 9)
//! smin(a, b) = a b / (a^k_tr + b^k_tr)^(1/k_tr)   (0 when a or b is 0)
//! F_main = k_main ν^0.25 |ẏ|^1.75                               (eq. 5)
//! p_s    = (charge_bar·1e5 + p_atm) · (T_oil + 273.15) / 293.15  (eq. 7, Pa abs)
//! F_gas  = p_s a_rod (v_gas / (v_gas + a_rod y))^1.4 − p_atm a_rod   (eq. 8)
//! F      = sign(ẏ) (F_port + F_main) − k_hys ÿ − F_gas          (eq. 9)
//! ```
//!
//! with `p_atm` = 101 325 Pa. The hysteresis term of eq. 4 stays outside the
//! smooth minimum, which thus only sees non-negative magnitudes. The model is
//! the **nominal** unit (`charge_bar` of the parameters);
//! [`ForceModel::force_at_charge`] and [`ForceModel::gas_force_n`] take any
//! charge pressure. The heat input of the thermal model is the dissipative
//! part, `(F_port + F_main)·|ẏ| ≥ 0`; the gas spring is conservative and the
//! hysteresis (inertia-like) term does no net work over a cycle.
//!
//! A gas volume `v_gas + a_rod y ≤ 0` (a position far outside the stroke) has
//! no physical meaning; the gas force is then NaN.
//!
//! Source: SPEC §3.3; paper eqs. 4–9 (after Reybrouck 1994, the parallel
//! combination of Duym).

use crate::params::{ForceParams, CHARGE_REF_TEMP_C, KELVIN_OFFSET, P_ATM_PA};
use serde::{Deserialize, Serialize};

/// Adiabatic index of nitrogen (eq. 8).
pub const GAMMA_N2: f64 = 1.4;

/// The parts of eq. 9, each signed as it enters the sum.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct ForceBreakdown {
    /// `F`, N, positive in tension.
    pub total_n: f64,
    /// `sign(ẏ)·F_port`, N.
    pub port_n: f64,
    /// `sign(ẏ)·F_main`, N.
    pub main_n: f64,
    /// `−k_hys·ÿ`, N.
    pub hys_n: f64,
    /// `−F_gas`, N (compressive for a charged unit).
    pub gas_n: f64,
}

impl ForceBreakdown {
    /// The damping part `port + main + hys` (signed), N.
    #[must_use]
    pub fn damping_n(&self) -> f64 {
        self.port_n + self.main_n + self.hys_n
    }
}

/// Smooth minimum of two non-negative magnitudes (SPEC §3.3):
/// `a b / (a^k + b^k)^(1/k)`, 0 when `a` or `b` is 0.
///
/// Evaluated scaled by `max(a, b)` so that large forces and large `k` do not
/// overflow. It lies in `[min(a,b)·2^(−1/k), min(a,b)]`.
#[must_use]
pub fn smin(a: f64, b: f64, k: f64) -> f64 {
    if a == 0.0 || b == 0.0 {
        return 0.0;
    }
    let m = a.max(b);
    let (ra, rb) = (a / m, b / m);
    #[allow(clippy::float_cmp)] // exact: the fast path for the common k_tr = 2
    let norm = if k == 2.0 {
        (ra * ra + rb * rb).sqrt()
    } else {
        (ra.powf(k) + rb.powf(k)).powf(1.0 / k)
    };
    a * rb / norm
}

/// The nominal force model of SPEC §3.3.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ForceModel {
    params: ForceParams,
}

impl ForceModel {
    /// A model with these parameters (see [`ForceParams::validate`]).
    #[must_use]
    pub fn new(params: ForceParams) -> Self {
        Self { params }
    }

    /// The parameters.
    #[must_use]
    pub fn params(&self) -> &ForceParams {
        &self.params
    }

    /// Oil kinematic viscosity at `oil_c`, cSt: `nu_40·exp(−beta(T−40))`.
    #[must_use]
    pub fn viscosity(&self, oil_c: f64) -> f64 {
        self.params.nu_40 * (-self.params.beta * (oil_c - 40.0)).exp()
    }

    /// `(F_port, F_main)`, N, both ≥ 0, for `velocity_mps` at `oil_c`.
    #[must_use]
    pub fn port_main_n(&self, velocity_mps: f64, oil_c: f64) -> (f64, f64) {
        let p = &self.params;
        let speed = velocity_mps.abs();
        let (k_leak, f_preload, k_spring, k_main) = if velocity_mps >= 0.0 {
            (p.k_leak_reb, p.f_preload_reb, p.k_spring_reb, p.k_main_reb)
        } else {
            (p.k_leak_com, p.f_preload_com, p.k_spring_com, p.k_main_com)
        };
        let nu = self.viscosity(oil_c);
        let port = smin(k_leak * nu * speed, f_preload + k_spring * speed, p.k_tr);
        // |ẏ|^1.75 = |ẏ| · |ẏ|^0.75 = |ẏ| · (√|ẏ| · ⁴√|ẏ|); ν^0.25 = √√ν.
        let sqrt_speed = speed.sqrt();
        let main = k_main * nu.sqrt().sqrt() * speed * sqrt_speed * sqrt_speed.sqrt();
        (port, main)
    }

    /// Static gas pressure at `oil_c` for a charge pressure `charge_bar`
    /// (bar gauge at 20 °C), Pa absolute (eq. 7).
    #[must_use]
    pub fn static_pressure_pa(charge_bar: f64, oil_c: f64) -> f64 {
        (charge_bar * 1.0e5 + P_ATM_PA) * (oil_c + KELVIN_OFFSET)
            / (CHARGE_REF_TEMP_C + KELVIN_OFFSET)
    }

    /// `F_gas`, N (positive: pushes the rod out), at extension `position_m`
    /// and `oil_c` for charge pressure `charge_bar` (eqs. 7–8).
    #[must_use]
    pub fn gas_force_n(&self, charge_bar: f64, position_m: f64, oil_c: f64) -> f64 {
        let p = &self.params;
        let volume = p.v_gas + p.a_rod * position_m;
        if volume <= 0.0 {
            return f64::NAN;
        }
        let ps = Self::static_pressure_pa(charge_bar, oil_c);
        ps * p.a_rod * (p.v_gas / volume).powf(GAMMA_N2) - P_ATM_PA * p.a_rod
    }

    /// Eq. 9 for the nominal unit (`charge_bar` of the parameters).
    #[must_use]
    pub fn force(
        &self,
        velocity_mps: f64,
        accel_mps2: f64,
        position_m: f64,
        oil_c: f64,
    ) -> ForceBreakdown {
        self.force_at_charge(
            velocity_mps,
            accel_mps2,
            position_m,
            oil_c,
            self.params.charge_bar,
        )
    }

    /// Eq. 9 for a unit charged to `charge_bar` (bar gauge at 20 °C).
    #[must_use]
    pub fn force_at_charge(
        &self,
        velocity_mps: f64,
        accel_mps2: f64,
        position_m: f64,
        oil_c: f64,
        charge_bar: f64,
    ) -> ForceBreakdown {
        let (port, main) = self.port_main_n(velocity_mps, oil_c);
        let sign = if velocity_mps >= 0.0 { 1.0 } else { -1.0 };
        let port_n = sign * port;
        let main_n = sign * main;
        let hys_n = -self.params.k_hys * accel_mps2;
        let gas_n = -self.gas_force_n(charge_bar, position_m, oil_c);
        ForceBreakdown {
            total_n: port_n + main_n + hys_n + gas_n,
            port_n,
            main_n,
            hys_n,
            gas_n,
        }
    }

    /// Heat input to the oil, W: `(F_port + F_main)·|ẏ|` (≥ 0).
    #[must_use]
    pub fn dissipative_power_w(&self, velocity_mps: f64, oil_c: f64) -> f64 {
        let (port, main) = self.port_main_n(velocity_mps, oil_c);
        (port + main) * velocity_mps.abs()
    }
}

#[cfg(test)]
// Exact float equality is intended in these tests: same arithmetic, same result.
#[allow(clippy::float_cmp)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn model() -> ForceModel {
        ForceModel::new(ForceParams::default())
    }

    /// The SPEC §3.3 formulas written out literally (no scaling, `powf`).
    fn literal(p: &ForceParams, v: f64, a: f64, y: f64, t: f64) -> f64 {
        let reb = v >= 0.0;
        let (kl, fp, ks, km) = if reb {
            (p.k_leak_reb, p.f_preload_reb, p.k_spring_reb, p.k_main_reb)
        } else {
            (p.k_leak_com, p.f_preload_com, p.k_spring_com, p.k_main_com)
        };
        let nu = p.nu_40 * (-p.beta * (t - 40.0)).exp();
        let la = kl * nu * v.abs();
        let lb = fp + ks * v.abs();
        let port = if la == 0.0 || lb == 0.0 {
            0.0
        } else {
            la * lb / (la.powf(p.k_tr) + lb.powf(p.k_tr)).powf(1.0 / p.k_tr)
        };
        let main = km * nu.powf(0.25) * v.abs().powf(1.75);
        let ps = (p.charge_bar * 1e5 + 101_325.0) * (t + 273.15) / 293.15;
        let gas =
            ps * p.a_rod * (p.v_gas / (p.v_gas + p.a_rod * y)).powf(1.4) - 101_325.0 * p.a_rod;
        let sign = if v >= 0.0 { 1.0 } else { -1.0 };
        sign * (port + main) - p.k_hys * a - gas
    }

    #[test]
    fn rest_gives_only_the_gas_force() {
        let m = model();
        let f = m.force(0.0, 0.0, 0.0, 20.0);
        assert_eq!((f.port_n, f.main_n, f.hys_n), (0.0, 0.0, 0.0));
        // 12 bar gauge on a 20 mm rod at 20 °C: 12e5 Pa × 3.1416e-4 m² = 377 N.
        let expected = -12.0e5 * std::f64::consts::PI * 1e-4;
        assert!((f.gas_n - expected).abs() < 1e-9, "{}", f.gas_n);
        assert_eq!(f.total_n, f.gas_n);
    }

    #[test]
    fn gas_force_follows_eqs_7_and_8() {
        let m = model();
        // Hotter gas pushes harder (absolute pressure ∝ T in K).
        let cold = m.gas_force_n(12.0, 0.0, 20.0);
        let hot = m.gas_force_n(12.0, 0.0, 80.0);
        let p = m.params();
        let expected_hot = (12e5 + P_ATM_PA) * 353.15 / 293.15 * p.a_rod - P_ATM_PA * p.a_rod;
        assert!((hot - expected_hot).abs() < 1e-9 && hot > cold);
        // Compressing (y < 0) shrinks the gas volume and raises the force.
        assert!(m.gas_force_n(12.0, -0.04, 20.0) > cold);
        assert!(m.gas_force_n(12.0, 0.04, 20.0) < cold);
        // At zero gauge charge and 20 °C, at mid-stroke, no net force.
        assert!(m.gas_force_n(0.0, 0.0, 20.0).abs() < 1e-12);
        // Charge-parameterised force: only the gas part moves with charge.
        let a = m.force_at_charge(0.3, 1.0, 0.01, 50.0, 4.0);
        let b = m.force(0.3, 1.0, 0.01, 50.0);
        assert_eq!((a.port_n, a.main_n, a.hys_n), (b.port_n, b.main_n, b.hys_n));
        assert!(a.gas_n > b.gas_n);
        assert!(m.gas_force_n(12.0, -1.0, 20.0).is_nan());
    }

    #[test]
    fn direction_sets_are_used() {
        let mut p = ForceParams {
            k_leak_com: 0.0,
            k_main_com: 0.0,
            ..ForceParams::default()
        };
        let m = ForceModel::new(p);
        // Compression: no leak (smin → 0) and no main: only gas and hysteresis.
        let f = m.force(-0.5, 0.0, 0.0, 40.0);
        assert_eq!((f.port_n, f.main_n), (0.0, 0.0));
        // Rebound is unaffected by the compression set.
        let r = m.force(0.5, 0.0, 0.0, 40.0);
        let r0 = model().force(0.5, 0.0, 0.0, 40.0);
        assert_eq!(r, r0);
        assert!(r.port_n > 0.0 && r.main_n > 0.0);
        // ẏ = 0 belongs to the rebound set: a huge compression preload does not matter.
        p.f_preload_com = 1e9;
        assert_eq!(
            ForceModel::new(p).force(0.0, 0.0, 0.0, 40.0),
            model().force(0.0, 0.0, 0.0, 40.0)
        );
    }

    #[test]
    fn prior_curve_is_in_the_public_range() {
        // physics-notes: a SUV damper +0.53 m/s 2178 N, −0.53 m/s −744 N.
        let m = model();
        let reb = m.force(0.53, 0.0, 0.0, 40.0).damping_n();
        let com = m.force(-0.53, 0.0, 0.0, 40.0).damping_n();
        assert!((1500.0..2800.0).contains(&reb), "{reb}");
        assert!((-1000.0..-450.0).contains(&com), "{com}");
        // Warmer oil, less damping.
        assert!(m.force(0.53, 0.0, 0.0, 80.0).damping_n() < reb);
    }

    #[test]
    fn smin_properties() {
        assert_eq!(smin(0.0, 5.0, 2.0), 0.0);
        assert_eq!(smin(5.0, 0.0, 2.0), 0.0);
        assert!((smin(3.0, 4.0, 2.0) - 12.0 / 5.0).abs() < 1e-15);
        // Equal arguments: a · 2^(−1/k).
        assert!((smin(7.0, 7.0, 3.0) - 7.0 * 2f64.powf(-1.0 / 3.0)).abs() < 1e-12);
        // No overflow for large forces or sharp transitions.
        assert!((smin(1e200, 1e100, 4.0) - 1e100).abs() < 1e88);
        assert!((smin(2000.0, 1000.0, 400.0) - 1000.0).abs() < 1e-6 * 1000.0);
    }

    proptest! {
        #[test]
        fn smin_is_bounded_symmetric_and_monotone(
            a in 0.0..1e5f64, b in 0.0..1e5f64, k in 0.5..20.0f64, da in 0.0..1e3f64,
        ) {
            let s = smin(a, b, k);
            let lo = a.min(b) * 2f64.powf(-1.0 / k);
            prop_assert!(s <= a.min(b) * (1.0 + 1e-12) && s >= lo * (1.0 - 1e-12));
            prop_assert!((s - smin(b, a, k)).abs() <= 1e-12 * s.max(1.0));
            prop_assert!(smin(a + da, b, k) >= s * (1.0 - 1e-12));
        }

        /// Port + main dissipate: (F_port + F_main)·sign(ẏ)·ẏ ≥ 0.
        #[test]
        fn damping_dissipates_energy(
            v in -3.0..3.0f64, a in -50.0..50.0f64, y in -0.05..0.05f64, t in -30.0..150.0f64,
            k_tr in 0.5..10.0f64, k_hys in 0.0..10.0f64,
        ) {
            let m = ForceModel::new(ForceParams { k_tr, k_hys, ..ForceParams::default() });
            let f = m.force(v, a, y, t);
            prop_assert!((f.port_n + f.main_n) * v >= 0.0);
            prop_assert!(m.dissipative_power_w(v, t) >= 0.0);
            prop_assert!(((f.port_n + f.main_n) * v - m.dissipative_power_w(v, t)).abs() <= 1e-9 * m.dissipative_power_w(v, t).max(1.0));
            prop_assert!((f.total_n - (f.port_n + f.main_n + f.hys_n + f.gas_n)).abs() <= 1e-9 * f.total_n.abs().max(1.0));
        }

        #[test]
        fn matches_the_literal_formulas(
            v in -3.0..3.0f64, a in -50.0..50.0f64, y in -0.05..0.05f64, t in -30.0..150.0f64,
            k_tr in 0.5..10.0f64, charge in 0.0..30.0f64,
        ) {
            let p = ForceParams { k_tr, charge_bar: charge, ..ForceParams::default() };
            let got = ForceModel::new(p).force(v, a, y, t).total_n;
            let want = literal(&p, v, a, y, t);
            prop_assert!((got - want).abs() <= 1e-9 * want.abs().max(1.0), "{got} vs {want}");
        }
    }
}
