//! Thermal model of the damper: oil and cylinder heat balance (paper eqs. 2–3,
//! §5.2; SPEC §3.2), integrated with classical fourth-order Runge–Kutta.
//!
//! **State** `T_oil`, `T_cyl` (°C at the interface, kelvin inside the
//! radiation term). **Inputs** heat input `P` (W) and ambient temperature
//! `T_amb` (°C), held over each step. **Parameters** [`ThermalParams`]:
//! `c_oil`, `c_cyl` (J/K), `ha_in`, `ha_out` (W/K), `eps_sigma_a` (W/K⁴).
//!
//! ```text
//! c_oil dT_oil/dt = ha_in (T_cyl − T_oil) + P                               (2)
//! c_cyl dT_cyl/dt = ha_in (T_oil − T_cyl) + ha_out (T_amb − T_cyl)
//!                   + eps_sigma_a (T_amb⁴ − T_cyl⁴)        [T⁴ in kelvin]    (3)
//! ```
//!
//! Temperature *differences* are the same in °C and K, so only the radiation
//! term converts (`T + 273.15`); the state stays in °C to keep round-off low.
//! For a time grid `t_0 … t_n`, each step `[t_i, t_{i+1}]` is one RK4 step
//! with `P` and `T_amb` held at their values at `t_i` (SPEC §3.2). The heat
//! input the twin uses is the dissipative force times speed,
//! `(F_port + F_main)·|ẏ|` (see [`crate::force`]).
//!
//! Source: SPEC §3.2; paper eqs. 2–3; RK4 as in Hairer, Nørsett, Wanner,
//! *Solving ODEs I*, §II.1.

use crate::error::PhysicsError;
use crate::kalman::check_len;
use crate::params::{ThermalParams, KELVIN_OFFSET};
use serde::{Deserialize, Serialize};

/// The longest RK4 step [`ThermalModel::simulate`] takes, s: a longer
/// interval of its grid is taken in equal steps within it. RK4 is stable for
/// `|λ h| < 2.78`; the twin's time constants are tens of seconds (the
/// campaign's calibration: `|λ| ≤ 0.16 /s`), so 2 s keeps `|λ h|` near 0.3,
/// where RK4's error is small too.
pub const MAX_STEP_S: f64 = 2.0;

/// The most RK4 steps [`ThermalModel::simulate`] takes over one interval of
/// its grid (a longer interval is an error: give a finer grid).
pub const MAX_SUBSTEPS: f64 = 1e6;

/// Oil and cylinder temperature, °C.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ThermalState {
    /// Damping-fluid temperature, °C.
    pub oil_c: f64,
    /// Cylinder (body) temperature, °C.
    pub cyl_c: f64,
}

/// The two-node thermal model of SPEC §3.2.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ThermalModel {
    params: ThermalParams,
}

impl ThermalModel {
    /// A model with these parameters (validate them with
    /// [`ThermalParams::validate`]; [`ThermalModel::simulate`] does).
    #[must_use]
    pub fn new(params: ThermalParams) -> Self {
        Self { params }
    }

    /// The parameters.
    #[must_use]
    pub fn params(&self) -> &ThermalParams {
        &self.params
    }

    /// Time derivatives `(dT_oil/dt, dT_cyl/dt)` in K/s (eqs. 2–3).
    #[must_use]
    pub fn derivative(&self, state: ThermalState, power_w: f64, ambient_c: f64) -> (f64, f64) {
        let p = &self.params;
        let cyl_k = state.cyl_c + KELVIN_OFFSET;
        let amb_k = ambient_c + KELVIN_OFFSET;
        let cyl2 = cyl_k * cyl_k;
        let amb2 = amb_k * amb_k;
        let conduction = p.ha_in * (state.cyl_c - state.oil_c);
        let d_oil = (conduction + power_w) / p.c_oil;
        let d_cyl = (-conduction
            + p.ha_out * (ambient_c - state.cyl_c)
            + p.eps_sigma_a * (amb2 * amb2 - cyl2 * cyl2))
            / p.c_cyl;
        (d_oil, d_cyl)
    }

    /// One classical RK4 step of `dt_s` seconds with `power_w` and
    /// `ambient_c` held over the step.
    #[must_use]
    pub fn step(
        &self,
        state: ThermalState,
        dt_s: f64,
        power_w: f64,
        ambient_c: f64,
    ) -> ThermalState {
        let at = |s: ThermalState, k: (f64, f64), h: f64| ThermalState {
            oil_c: s.oil_c + h * k.0,
            cyl_c: s.cyl_c + h * k.1,
        };
        let k1 = self.derivative(state, power_w, ambient_c);
        let k2 = self.derivative(at(state, k1, 0.5 * dt_s), power_w, ambient_c);
        let k3 = self.derivative(at(state, k2, 0.5 * dt_s), power_w, ambient_c);
        let k4 = self.derivative(at(state, k3, dt_s), power_w, ambient_c);
        let h6 = dt_s / 6.0;
        ThermalState {
            oil_c: state.oil_c + h6 * (k1.0 + 2.0 * k2.0 + 2.0 * k3.0 + k4.0),
            cyl_c: state.cyl_c + h6 * (k1.1 + 2.0 * k2.1 + 2.0 * k3.1 + k4.1),
        }
    }

    /// Integrates over the grid `t_s` (non-decreasing, s) from
    /// `(oil0_c, cyl0_c)` at `t_s[0]`: one RK4 step per interval with
    /// `power_w[i]`, `ambient_c[i]` held over `[t_i, t_{i+1}]`, or, for an
    /// interval longer than [`MAX_STEP_S`], as many equal RK4 steps as keep
    /// each within it. That is a deviation from SPEC §3.2's one step per
    /// interval, which diverged on a one-minute grid (−6e82 °C, then NaN,
    /// without an error; a helper's trial): the pipeline's 20 ms grid and
    /// every grid up to 2 s are integrated as before, bit for bit. Returns
    /// `(oil_c, cyl_c)`, each as long as `t_s`, starting with the initial
    /// state; a temperature that is not finite (a heat input of 1e300 W)
    /// is an error naming the grid point.
    pub fn simulate(
        &self,
        t_s: &[f64],
        power_w: &[f64],
        ambient_c: &[f64],
        oil0_c: f64,
        cyl0_c: f64,
    ) -> Result<(Vec<f64>, Vec<f64>), PhysicsError> {
        self.params.validate()?;
        check_len("power_w", power_w.len(), t_s.len(), "t_s")?;
        check_len("ambient_c", ambient_c.len(), t_s.len(), "t_s")?;
        if let Some(i) = t_s
            .windows(2)
            .position(|w| !w[0].is_finite() || !w[1].is_finite() || w[1] < w[0])
        {
            return Err(PhysicsError::NotMonotonic {
                name: "t_s",
                index: i + 1,
            });
        }
        let mut oil = Vec::with_capacity(t_s.len());
        let mut cyl = Vec::with_capacity(t_s.len());
        if t_s.is_empty() {
            return Ok((oil, cyl));
        }
        if !(oil0_c.is_finite() && cyl0_c.is_finite()) {
            // not blamed on the first step's inputs (a review)
            return Err(PhysicsError::Numerical {
                model: "thermal",
                t_ns: (t_s[0] * 1e9) as i64,
                what: format!(
                    "initial temperatures oil0_c = {oil0_c}, cyl0_c = {cyl0_c} must be finite"
                ),
            });
        }
        let mut state = ThermalState {
            oil_c: oil0_c,
            cyl_c: cyl0_c,
        };
        oil.push(state.oil_c);
        cyl.push(state.cyl_c);
        for i in 1..t_s.len() {
            let (dt_s, power, ambient) = (t_s[i] - t_s[i - 1], power_w[i - 1], ambient_c[i - 1]);
            // one step up to MAX_STEP_S (then bit for bit as before)
            let steps = if dt_s > MAX_STEP_S {
                (dt_s / MAX_STEP_S).ceil()
            } else {
                1.0
            };
            if steps > MAX_SUBSTEPS {
                return Err(PhysicsError::Numerical {
                    model: "thermal",
                    t_ns: (t_s[i] * 1e9) as i64,
                    what: format!(
                        "the step to t_s[{i}] = {} s is {dt_s} s, more than {MAX_SUBSTEPS} steps of \
                         at most {MAX_STEP_S} s: give a finer grid",
                        t_s[i]
                    ),
                });
            }
            let h = dt_s / steps;
            for _ in 0..steps as u64 {
                state = self.step(state, h, power, ambient);
            }
            if !(state.oil_c.is_finite() && state.cyl_c.is_finite()) {
                return Err(PhysicsError::Numerical {
                    model: "thermal",
                    t_ns: (t_s[i] * 1e9) as i64,
                    what: format!(
                        "temperature not finite at t_s[{i}] = {} s (heat input power_w[{}] = {power:e} W, \
                         ambient_c[{}] = {ambient} °C)",
                        t_s[i],
                        i - 1,
                        i - 1
                    ),
                });
            }
            oil.push(state.oil_c);
            cyl.push(state.cyl_c);
        }
        Ok((oil, cyl))
    }
}

#[cfg(test)]
// Exact float equality is intended in these tests: same arithmetic, same result.
#[allow(clippy::float_cmp)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    /// A one-minute grid is integrated in steps of at most 2 s: its values
    /// are those of the same model on a 1 s grid, to RK4's truncation
    /// (it diverged, −6e82 °C then NaN, with the campaign's calibration); a
    /// grid within 2 s is integrated one step an interval, as before.
    #[test]
    fn a_coarse_grid_is_integrated_in_stable_steps() {
        // the demo campaign's calibration (`out/physics.json`, rounded)
        let model = ThermalModel::new(ThermalParams {
            c_oil: 561.8,
            c_cyl: 813.1,
            ha_in: 43.3,
            ha_out: 2.5,
            eps_sigma_a: 1.14e-10,
            ..ThermalParams::default()
        });
        let t_min: Vec<f64> = (0..=61).map(|k| f64::from(k) * 60.0).collect();
        let t_sec: Vec<f64> = (0..=3660).map(f64::from).collect();
        let run =
            |t: &[f64]| model.simulate(t, &vec![300.0; t.len()], &vec![20.0; t.len()], 20.0, 20.0);
        let (oil_min, _) = run(&t_min).unwrap();
        let (oil_sec, _) = run(&t_sec).unwrap();
        for (k, o) in oil_min.iter().enumerate() {
            assert!(
                (o - oil_sec[k * 60]).abs() < 1e-4,
                "{k}: {o} against {}",
                oil_sec[k * 60]
            );
        }
        assert!(oil_min[61] > 30.0, "it warms up: {}", oil_min[61]);
        // within the stable step: one RK4 step per interval
        let (oil_one, cyl_one) = run(&t_sec[..3]).unwrap();
        let s = ThermalState {
            oil_c: 20.0,
            cyl_c: 20.0,
        };
        let s1 = model.step(s, 1.0, 300.0, 20.0);
        let s2 = model.step(s1, 1.0, 300.0, 20.0);
        assert_eq!((oil_one[2], cyl_one[2]), (s2.oil_c, s2.cyl_c));
    }

    /// A temperature that is not finite is an error naming the grid point.
    #[test]
    fn a_temperature_that_is_not_finite_is_an_error() {
        let model = ThermalModel::new(ThermalParams::default());
        let e = model
            .simulate(
                &[0.0, 1.0, 2.0],
                &[1e300, 1e300, 0.0],
                &[20.0; 3],
                20.0,
                20.0,
            )
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("t_s[") && e.contains("power_w[") && e.contains("not finite"),
            "{e}"
        );
    }

    fn linear_params() -> ThermalParams {
        ThermalParams {
            c_oil: 400.0,
            c_cyl: 900.0,
            ha_in: 8.0,
            ha_out: 3.0,
            eps_sigma_a: 0.0,
            ..ThermalParams::default()
        }
    }

    /// Closed form of the linear case (`eps_sigma_a = 0`, constant `P` and
    /// `T_amb`): `x' = A x + b`, `x(t) = x_ss + V e^{Λt} V⁻¹ (x0 − x_ss)` for
    /// the 2×2 `A`.
    fn closed_form(p: &ThermalParams, x0: [f64; 2], power: f64, amb: f64, t: f64) -> [f64; 2] {
        let a = [
            [-p.ha_in / p.c_oil, p.ha_in / p.c_oil],
            [p.ha_in / p.c_cyl, -(p.ha_in + p.ha_out) / p.c_cyl],
        ];
        let b = [power / p.c_oil, p.ha_out * amb / p.c_cyl];
        // Steady state: A x_ss = -b.
        let det = a[0][0] * a[1][1] - a[0][1] * a[1][0];
        let xss = [
            (-b[0] * a[1][1] + b[1] * a[0][1]) / det,
            (-a[0][0] * b[1] + a[1][0] * b[0]) / det,
        ];
        // Eigen-decomposition of A (real, distinct for a positive system).
        let tr = a[0][0] + a[1][1];
        let disc = (tr * tr / 4.0 - det).sqrt();
        let l = [tr / 2.0 + disc, tr / 2.0 - disc];
        // Eigenvector for λ: (a01, λ − a00).
        let v = [[a[0][1], a[0][1]], [l[0] - a[0][0], l[1] - a[0][0]]];
        let vdet = v[0][0] * v[1][1] - v[0][1] * v[1][0];
        let d = [x0[0] - xss[0], x0[1] - xss[1]];
        let c = [
            (v[1][1] * d[0] - v[0][1] * d[1]) / vdet,
            (-v[1][0] * d[0] + v[0][0] * d[1]) / vdet,
        ];
        let e = [c[0] * (l[0] * t).exp(), c[1] * (l[1] * t).exp()];
        [
            xss[0] + v[0][0] * e[0] + v[0][1] * e[1],
            xss[1] + v[1][0] * e[0] + v[1][1] * e[1],
        ]
    }

    fn rk4_error(dt: f64, t_end: f64) -> f64 {
        let p = linear_params();
        let model = ThermalModel::new(p);
        let n = (t_end / dt).round() as usize;
        let mut s = ThermalState {
            oil_c: 20.0,
            cyl_c: 25.0,
        };
        for _ in 0..n {
            s = model.step(s, dt, 300.0, 18.0);
        }
        let exact = closed_form(&p, [20.0, 25.0], 300.0, 18.0, t_end);
        (s.oil_c - exact[0]).abs().max((s.cyl_c - exact[1]).abs())
    }

    #[test]
    fn rk4_matches_closed_form_with_fourth_order_convergence() {
        // Steps large enough for truncation error to dominate round-off.
        let t_end = 600.0;
        let e1 = rk4_error(20.0, t_end);
        let e2 = rk4_error(10.0, t_end);
        let e3 = rk4_error(5.0, t_end);
        assert!(e1 < 1e-3, "error at dt = 20 s: {e1}");
        for (coarse, fine) in [(e1, e2), (e2, e3)] {
            let ratio = coarse / fine;
            assert!(
                (13.0..19.0).contains(&ratio),
                "halving dt divided the error by {ratio} (expected ≈ 16)"
            );
        }
        // The 50 Hz pipeline step is far inside the accurate range.
        assert!(rk4_error(0.02, 60.0) < 1e-9);
    }

    #[test]
    fn simulate_holds_inputs_over_each_step_and_starts_at_initial_state() {
        let model = ThermalModel::new(ThermalParams::default());
        let t = [0.0, 1.0, 1.5, 1.5, 3.0];
        let power = [100.0, 0.0, 50.0, 7.0, f64::NAN];
        let amb = [20.0, 21.0, 22.0, 23.0, f64::NAN];
        let (oil, cyl) = model.simulate(&t, &power, &amb, 30.0, 25.0).unwrap();
        assert_eq!((oil.len(), cyl.len()), (5, 5));
        assert_eq!((oil[0], cyl[0]), (30.0, 25.0));
        let mut s = ThermalState {
            oil_c: 30.0,
            cyl_c: 25.0,
        };
        for i in 1..5 {
            s = model.step(s, t[i] - t[i - 1], power[i - 1], amb[i - 1]);
            assert_eq!((oil[i], cyl[i]), (s.oil_c, s.cyl_c));
        }
        // A zero-length step changes nothing; the last inputs are never used.
        assert_eq!(oil[3], oil[2]);
        assert!(oil[4].is_finite());
    }

    #[test]
    fn simulate_rejects_bad_inputs() {
        let model = ThermalModel::new(ThermalParams::default());
        let err = model
            .simulate(&[0.0, 1.0], &[0.0], &[20.0, 20.0], 20.0, 20.0)
            .unwrap_err();
        assert!(err.to_string().contains("power_w"), "{err}");
        let err = model
            .simulate(&[0.0, 2.0, 1.0], &[0.0; 3], &[20.0; 3], 20.0, 20.0)
            .unwrap_err();
        assert!(err.to_string().contains("t_s"), "{err}");
        let bad = ThermalModel::new(ThermalParams {
            c_oil: -1.0,
            ..ThermalParams::default()
        });
        assert!(bad
            .simulate(&[0.0], &[0.0], &[0.0], 20.0, 20.0)
            .unwrap_err()
            .to_string()
            .contains("c_oil"));
    }

    #[test]
    fn radiation_cools_a_hot_cylinder_towards_ambient() {
        let p = ThermalParams {
            ha_out: 0.0,
            ..ThermalParams::default()
        };
        let model = ThermalModel::new(p);
        let s = ThermalState {
            oil_c: 80.0,
            cyl_c: 80.0,
        };
        let (d_oil, d_cyl) = model.derivative(s, 0.0, 20.0);
        assert_eq!(d_oil, 0.0);
        let expected = p.eps_sigma_a * (293.15f64.powi(4) - 353.15f64.powi(4)) / p.c_cyl;
        assert!(
            (d_cyl - expected).abs() < 1e-12 * expected.abs(),
            "{d_cyl} vs {expected}"
        );
    }

    proptest! {
        /// With no ambient coupling the stored heat c_oil·T_oil + c_cyl·T_cyl
        /// grows by exactly the heat put in (RK4 keeps linear invariants).
        #[test]
        fn energy_is_conserved_without_ambient_coupling(
            c_oil in 50.0..2000.0f64,
            c_cyl in 50.0..5000.0f64,
            ha_in in 0.0..50.0f64,
            steps in prop::collection::vec((0.001..2.0f64, 0.0..2000.0f64), 1..100),
            oil0 in -20.0..120.0f64,
            cyl0 in -20.0..120.0f64,
        ) {
            let p = ThermalParams { c_oil, c_cyl, ha_in, ha_out: 0.0, eps_sigma_a: 0.0, ..ThermalParams::default() };
            let model = ThermalModel::new(p);
            let mut s = ThermalState { oil_c: oil0, cyl_c: cyl0 };
            let mut heat_in = 0.0;
            for (dt, power) in steps {
                s = model.step(s, dt, power, 500.0);
                heat_in += power * dt;
            }
            let stored = c_oil * (s.oil_c - oil0) + c_cyl * (s.cyl_c - cyl0);
            let scale = heat_in.abs() + c_oil * oil0.abs() + c_cyl * cyl0.abs() + 1.0;
            prop_assert!((stored - heat_in).abs() <= 1e-11 * scale, "stored {stored} vs in {heat_in}");
        }
    }
}
