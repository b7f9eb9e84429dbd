//! Velocity estimation: a linear Kalman filter fusing the potentiometer with
//! the relative acceleration of the accelerometer pair (paper eq. 1, §5.1;
//! SPEC §3.1).
//!
//! **State** `x = [y, ẏ, b_a]`: extension (m), extension rate (m/s) and the
//! bias of the relative acceleration (m/s²). **Input** `u = a1 − a2` (m/s²),
//! held from the last accelerometer sample. **Measurement** the potentiometer
//! `z` (m). Over an interval `dt` (s):
//!
//! ```text
//! F = [[1, dt, -dt²/2], [0, 1, -dt], [0, 0, 1]]     B = G = [dt²/2, dt, 0]ᵀ
//! x ← F x + B u        P ← F P Fᵀ + Q,   Q = σ_a² G Gᵀ + diag(0, 0, σ_b² dt)
//! H = [1, 0, 0],  R = σ_z²,  Joseph-form update
//!   P ← (I − K H) P (I − K H)ᵀ + K R Kᵀ
//! ```
//!
//! **Events** are taken in time order; at equal times an accelerometer sample
//! comes first. An accelerometer sample at `t` propagates from the previous
//! event time to `t` with the held `u`, then holds its own value; a position
//! sample propagates the same way, then updates. The filter starts at the
//! first position sample with `x = [z₀, 0, 0]`, `P = diag(σ_z², 1, 1)` (no
//! update at that sample); accelerometer samples before it only set the held
//! value, which is 0 m/s² until the first accelerometer sample.
//!
//! **Missing samples**: a NaN (or infinite) sample is treated as absent — it
//! neither propagates nor changes the held input — and is counted
//! ([`KalmanFilter::missing_accel`], [`KalmanFilter::missing_position`]).
//! Because constant-input kinematics compose exactly, the *mean* predicted to
//! any time does not depend on how the interval is split; the covariance does
//! (Q is per propagation step, as in SPEC §3.1).
//!
//! **Position-only mode** (no accelerometers, [`KalmanFilter::position_only`]):
//! a constant-acceleration model on the potentiometer alone, state
//! `x = [y, ẏ, ÿ]` (m, m/s, m/s²), driven by continuous white jerk of power
//! spectral density `q` (m²/s⁵):
//!
//! ```text
//! F = [[1, dt, dt²/2], [0, 1, dt], [0, 0, 1]]
//! Q = q [[dt⁵/20, dt⁴/8, dt³/6], [dt⁴/8, dt³/3, dt²/2], [dt³/6, dt²/2, dt]]
//! ```
//!
//! started at the first position sample with `x = [z₀, 0, 0]`,
//! `P = diag(σ_z², 1, 100)` (accelerations of the dyno reach 25 m/s²).
//! [`POSITION_ONLY_JERK_PSD`] (1e4 m²/s⁵) gives a ≈ 15 Hz tracking bandwidth
//! with a 100 Hz, 1 mm potentiometer: `ω ≈ (q / (σ_z² dt))^(1/6)`.
//!
//! Source: SPEC §3.1; paper eq. 1; the filter equations follow the standard
//! linear KF (Bar-Shalom, Li, Kirubarajan, *Estimation with Applications to
//! Tracking and Navigation*, 2001, §5.2 and §6.2 for the white-jerk model),
//! in the same form as `filterpy.kalman.KalmanFilter` (`predict(u)`,
//! Joseph-form `update`).

use nalgebra::{Matrix3, Vector3};
use serde::{Deserialize, Serialize};

use crate::error::PhysicsError;
use crate::params::KalmanParams;

/// White-jerk power spectral density of the position-only filter, m²/s⁵.
pub const POSITION_ONLY_JERK_PSD: f64 = 1.0e4;

const NS_PER_S: f64 = 1.0e9;

/// Which process model the filter runs.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub enum KalmanMode {
    /// SPEC §3.1: `[y, ẏ, b_a]` driven by the relative acceleration.
    AccelBias,
    /// No accelerometers: `[y, ẏ, ÿ]` with white-jerk process noise of this
    /// power spectral density (m²/s⁵).
    PositionOnly {
        /// White-jerk PSD, m²/s⁵.
        jerk_psd: f64,
    },
}

/// The velocity estimator of SPEC §3.1 (or its position-only variant).
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct KalmanFilter {
    params: KalmanParams,
    mode: KalmanMode,
    x: Vector3<f64>,
    p: Matrix3<f64>,
    /// Time of the last event taken (only meaningful once initialised).
    t_ns: i64,
    initialised: bool,
    /// Time of the last accelerometer sample taken (order check before init).
    last_accel_ns: Option<i64>,
    u_mps2: f64,
    missing_accel: u64,
    missing_position: u64,
    /// `F`, `Q` of the last propagation interval (samples come at a fixed
    /// rate, so the next interval is usually the same): a cache, not state.
    #[serde(skip)]
    last_transition: Option<Transition>,
}

/// `F(dt)`, `B(dt)` and `Q(dt)` of one interval of `dt_ns`, written for their
/// structure: `F = [[1, dt, f02], [0, 1, f12], [0, 0, 1]]`, `B = [dt²/2, dt, 0]ᵀ`
/// and the upper triangle of the symmetric `Q`.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Transition {
    dt_ns: i64,
    dt_s: f64,
    half_dt2: f64,
    f02: f64,
    f12: f64,
    /// `[Q00, Q01, Q02, Q11, Q12, Q22]`.
    q: [f64; 6],
}

impl Transition {
    /// The model of `mode` over `dt_ns` (the same values, entry for entry,
    /// as the matrices of the module docs).
    fn new(mode: KalmanMode, params: &KalmanParams, dt_ns: i64) -> Self {
        let dt = dt_ns as f64 / NS_PER_S;
        let dt2 = dt * dt;
        let half_dt2 = 0.5 * dt2;
        match mode {
            KalmanMode::AccelBias => {
                // Q = σ_a² G Gᵀ + diag(0, 0, σ_b² dt), G = [dt²/2, dt, 0]ᵀ.
                let sa2 = params.sigma_accel * params.sigma_accel;
                let sb2 = params.sigma_bias * params.sigma_bias;
                Self {
                    dt_ns,
                    dt_s: dt,
                    half_dt2,
                    f02: -0.5 * dt2,
                    f12: -dt,
                    q: [
                        half_dt2 * half_dt2 * sa2,
                        half_dt2 * dt * sa2,
                        0.0,
                        dt * dt * sa2,
                        0.0,
                        sb2 * dt,
                    ],
                }
            }
            KalmanMode::PositionOnly { jerk_psd: q } => {
                let dt3 = dt2 * dt;
                let dt4 = dt3 * dt;
                let dt5 = dt4 * dt;
                Self {
                    dt_ns,
                    dt_s: dt,
                    half_dt2,
                    f02: 0.5 * dt2,
                    f12: dt,
                    q: [
                        dt5 / 20.0 * q,
                        dt4 / 8.0 * q,
                        dt3 / 6.0 * q,
                        dt3 / 3.0 * q,
                        dt2 / 2.0 * q,
                        dt * q,
                    ],
                }
            }
        }
    }

    /// `F x + B u`.
    fn mean(&self, x: &Vector3<f64>, u: f64) -> Vector3<f64> {
        Vector3::new(
            x[0] + self.dt_s * x[1] + self.f02 * x[2] + self.half_dt2 * u,
            x[1] + self.f12 * x[2] + self.dt_s * u,
            x[2],
        )
    }

    /// `F P Fᵀ + Q` for a symmetric `P` (its upper triangle is read; the
    /// result is symmetric).
    fn covariance(&self, p: &Matrix3<f64>) -> Matrix3<f64> {
        let (a, c, e) = (self.dt_s, self.f02, self.f12);
        let (p00, p01, p02) = (p[(0, 0)], p[(0, 1)], p[(0, 2)]);
        let (p11, p12, p22) = (p[(1, 1)], p[(1, 2)], p[(2, 2)]);
        // F P (the entries F P Fᵀ needs), then (F P) Fᵀ.
        let fp00 = p00 + a * p01 + c * p02;
        let fp01 = p01 + a * p11 + c * p12;
        let fp02 = p02 + a * p12 + c * p22;
        let fp11 = p11 + e * p12;
        let fp12 = p12 + e * p22;
        let [q00, q01, q02, q11, q12, q22] = self.q;
        symmetric(
            fp00 + a * fp01 + c * fp02 + q00,
            fp01 + e * fp02 + q01,
            fp02 + q02,
            fp11 + e * fp12 + q11,
            fp12 + q12,
            p22 + q22,
        )
    }
}

/// The symmetric matrix with this upper triangle.
fn symmetric(p00: f64, p01: f64, p02: f64, p11: f64, p12: f64, p22: f64) -> Matrix3<f64> {
    Matrix3::new(p00, p01, p02, p01, p11, p12, p02, p12, p22)
}

impl KalmanFilter {
    /// A SPEC §3.1 filter (position + relative acceleration + bias).
    #[must_use]
    pub fn new(params: KalmanParams) -> Self {
        Self::with_mode(params, KalmanMode::AccelBias)
    }

    /// A position-only filter (constant-acceleration model, white jerk of
    /// PSD `jerk_psd` m²/s⁵); only `params.sigma_position` is used.
    #[must_use]
    pub fn position_only(params: KalmanParams, jerk_psd: f64) -> Self {
        Self::with_mode(params, KalmanMode::PositionOnly { jerk_psd })
    }

    fn with_mode(params: KalmanParams, mode: KalmanMode) -> Self {
        Self {
            params,
            mode,
            x: Vector3::zeros(),
            p: Matrix3::zeros(),
            t_ns: 0,
            initialised: false,
            last_accel_ns: None,
            u_mps2: 0.0,
            missing_accel: 0,
            missing_position: 0,
            last_transition: None,
        }
    }

    /// The process model.
    #[must_use]
    pub fn mode(&self) -> KalmanMode {
        self.mode
    }

    /// The noise parameters.
    #[must_use]
    pub fn params(&self) -> &KalmanParams {
        &self.params
    }

    /// Takes an accelerometer sample `a_rel = a1 − a2` (m/s²) at `t_ns`:
    /// propagates to `t_ns` with the held input (once initialised), then holds
    /// `a_rel`. A non-finite sample is skipped and counted.
    pub fn accel(&mut self, t_ns: i64, a_rel_mps2: f64) -> Result<(), PhysicsError> {
        if let KalmanMode::PositionOnly { .. } = self.mode {
            return Err(PhysicsError::WrongMode(
                "kalman: accelerometer sample given to a position-only filter",
            ));
        }
        if !a_rel_mps2.is_finite() {
            self.missing_accel += 1;
            return Ok(());
        }
        if let Some(last) = self.last_accel_ns {
            if t_ns < last {
                return Err(PhysicsError::OutOfOrder {
                    what: "kalman accelerometer sample".into(),
                    t_ns,
                    last_t_ns: last,
                });
            }
        }
        if self.initialised {
            self.propagate_to(t_ns, "kalman accelerometer sample")?;
        }
        self.last_accel_ns = Some(t_ns);
        self.u_mps2 = a_rel_mps2;
        Ok(())
    }

    /// Takes a potentiometer sample `z` (m) at `t_ns`: the first one
    /// initialises the filter, later ones propagate to `t_ns` and update
    /// (Joseph form). A non-finite sample is skipped and counted.
    #[allow(non_snake_case)]
    pub fn position(&mut self, t_ns: i64, z_m: f64) -> Result<(), PhysicsError> {
        if !z_m.is_finite() {
            self.missing_position += 1;
            return Ok(());
        }
        if !self.initialised {
            if let Some(last) = self.last_accel_ns {
                if t_ns < last {
                    return Err(PhysicsError::OutOfOrder {
                        what: "kalman position sample".into(),
                        t_ns,
                        last_t_ns: last,
                    });
                }
            }
            let s2 = self.params.sigma_position * self.params.sigma_position;
            let p_last = match self.mode {
                KalmanMode::AccelBias => 1.0,
                KalmanMode::PositionOnly { .. } => 100.0,
            };
            self.x = Vector3::new(z_m, 0.0, 0.0);
            self.p = Matrix3::from_diagonal(&Vector3::new(s2, 1.0, p_last));
            self.t_ns = t_ns;
            self.initialised = true;
            return Ok(());
        }
        self.propagate_to(t_ns, "kalman position sample")?;

        // Update with H = [1, 0, 0], R = σ_z²; P is symmetric, so only its
        // upper triangle is computed.
        let R = self.params.sigma_position * self.params.sigma_position;
        let p = &self.p;
        let (p00, p01, p02) = (p[(0, 0)], p[(0, 1)], p[(0, 2)]);
        let (p11, p12, p22) = (p[(1, 1)], p[(1, 2)], p[(2, 2)]);
        let s = p00 + R;
        if !(s.is_finite() && s > 0.0) {
            return Err(PhysicsError::Numerical {
                model: "kalman",
                t_ns,
                what: format!("innovation variance {s} is not finite and positive"),
            });
        }
        let (k0, k1, k2) = (p00 / s, p01 / s, p02 / s);
        let innovation = z_m - self.x[0];
        self.x += Vector3::new(k0, k1, k2) * innovation;
        // Joseph form P ← L P Lᵀ + K R Kᵀ with L = I − K H: the identity
        // with the first column e₁ − K. `lp` = L P (the entries needed).
        let l00 = 1.0 - k0;
        let (lp00, lp01, lp02) = (l00 * p00, l00 * p01, l00 * p02);
        let (lp10, lp11, lp12) = (p01 - k1 * p00, p11 - k1 * p01, p12 - k1 * p02);
        let (lp20, lp22) = (p02 - k2 * p00, p22 - k2 * p02);
        self.p = symmetric(
            lp00 * l00 + k0 * k0 * R,
            lp01 - lp00 * k1 + k0 * k1 * R,
            lp02 - lp00 * k2 + k0 * k2 * R,
            lp11 - lp10 * k1 + k1 * k1 * R,
            lp12 - lp10 * k2 + k1 * k2 * R,
            lp22 - lp20 * k2 + k2 * k2 * R,
        );
        self.check_finite(t_ns)
    }

    /// Propagates to `t_ns` with the held input (SPEC §3.1 predict step).
    fn propagate_to(&mut self, t_ns: i64, what: &str) -> Result<(), PhysicsError> {
        if t_ns < self.t_ns {
            return Err(PhysicsError::OutOfOrder {
                what: what.into(),
                t_ns,
                last_t_ns: self.t_ns,
            });
        }
        if t_ns == self.t_ns {
            return Ok(());
        }
        let tr = self.transition(t_ns - self.t_ns);
        self.x = tr.mean(&self.x, self.input());
        self.p = tr.covariance(&self.p);
        self.t_ns = t_ns;
        self.check_finite(t_ns)
    }

    /// The model over `dt_ns`: the last interval's when it repeats.
    fn transition(&mut self, dt_ns: i64) -> Transition {
        match self.last_transition {
            Some(tr) if tr.dt_ns == dt_ns => tr,
            _ => {
                let tr = Transition::new(self.mode, &self.params, dt_ns);
                self.last_transition = Some(tr);
                tr
            }
        }
    }

    /// The input `u` of the mode (the held relative acceleration, or 0).
    fn input(&self) -> f64 {
        match self.mode {
            KalmanMode::AccelBias => self.u_mps2,
            KalmanMode::PositionOnly { .. } => 0.0,
        }
    }

    fn check_finite(&self, t_ns: i64) -> Result<(), PhysicsError> {
        let (x, p) = (&self.x, &self.p);
        // P is symmetric: its upper triangle; `v * 0.0` is 0 for a finite `v`
        // and NaN otherwise.
        let zero = x[0] * 0.0
            + x[1] * 0.0
            + x[2] * 0.0
            + p[(0, 0)] * 0.0
            + p[(0, 1)] * 0.0
            + p[(0, 2)] * 0.0
            + p[(1, 1)] * 0.0
            + p[(1, 2)] * 0.0
            + p[(2, 2)] * 0.0;
        let diag_ok = p[(0, 0)] >= 0.0 && p[(1, 1)] >= 0.0 && p[(2, 2)] >= 0.0;
        if zero == 0.0 && diag_ok {
            Ok(())
        } else {
            Err(self.not_finite(t_ns))
        }
    }

    #[cold]
    fn not_finite(&self, t_ns: i64) -> PhysicsError {
        PhysicsError::Numerical {
            model: "kalman",
            t_ns,
            what: format!(
                "state or covariance not finite / negative variance: x = {:?}, diag P = {:?}",
                self.x.as_slice(),
                [self.p[(0, 0)], self.p[(1, 1)], self.p[(2, 2)]]
            ),
        }
    }

    /// Whether the first position sample has been taken.
    #[must_use]
    pub fn is_initialised(&self) -> bool {
        self.initialised
    }

    /// The state after the last event (`[y, ẏ, b_a]`, or `[y, ẏ, ÿ]` in
    /// position-only mode); `None` before the first position sample.
    #[must_use]
    pub fn state(&self) -> Option<[f64; 3]> {
        self.initialised.then(|| [self.x[0], self.x[1], self.x[2]])
    }

    /// The mean propagated to `t_ns ≥` the last event time with the held
    /// input, without changing the filter; `None` before initialisation or
    /// for an earlier time.
    #[must_use]
    pub fn predicted_state(&self, t_ns: i64) -> Option<[f64; 3]> {
        if !self.initialised || t_ns < self.t_ns {
            return None;
        }
        let x =
            Transition::new(self.mode, &self.params, t_ns - self.t_ns).mean(&self.x, self.input());
        Some([x[0], x[1], x[2]])
    }

    /// The covariance after the last event (row-major); `None` before the
    /// first position sample.
    #[must_use]
    pub fn covariance(&self) -> Option<[[f64; 3]; 3]> {
        let p = &self.p;
        self.initialised.then(|| {
            [
                [p[(0, 0)], p[(0, 1)], p[(0, 2)]],
                [p[(1, 0)], p[(1, 1)], p[(1, 2)]],
                [p[(2, 0)], p[(2, 1)], p[(2, 2)]],
            ]
        })
    }

    /// The held relative acceleration, m/s².
    #[must_use]
    pub fn held_accel(&self) -> f64 {
        self.u_mps2
    }

    /// Time of the last event taken, ns; `None` before initialisation.
    #[must_use]
    pub fn last_event_ns(&self) -> Option<i64> {
        self.initialised.then_some(self.t_ns)
    }

    /// Skipped (non-finite) accelerometer samples.
    #[must_use]
    pub fn missing_accel(&self) -> u64 {
        self.missing_accel
    }

    /// Skipped (non-finite) position samples.
    #[must_use]
    pub fn missing_position(&self) -> u64 {
        self.missing_position
    }
}

/// The filter's state at each accelerometer sample time (SPEC §8
/// `KalmanFilter.run`).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct KalmanTrace {
    /// Accelerometer sample times, ns.
    pub t_ns: Vec<i64>,
    /// `y`, m (NaN before the first position sample).
    pub position_m: Vec<f64>,
    /// `ẏ`, m/s.
    pub velocity_mps: Vec<f64>,
    /// `b_a`, m/s².
    pub bias_mps2: Vec<f64>,
    /// Skipped (non-finite) accelerometer samples.
    pub missing_accel: u64,
    /// Skipped (non-finite) position samples.
    pub missing_position: u64,
}

/// Runs a SPEC §3.1 filter over two time-sorted streams and returns the state
/// at each accelerometer sample time, after every event at that time (events
/// in time order, accelerometer first at equal times). At a skipped (NaN)
/// accelerometer sample the row is the mean predicted to its time. Position
/// samples after the last accelerometer sample do not produce rows.
pub fn run_kalman(
    params: KalmanParams,
    t_acc_ns: &[i64],
    a_rel_mps2: &[f64],
    t_pos_ns: &[i64],
    pos_m: &[f64],
) -> Result<KalmanTrace, PhysicsError> {
    params.validate()?;
    check_len("a_rel", a_rel_mps2.len(), t_acc_ns.len(), "t_acc")?;
    check_len("pos", pos_m.len(), t_pos_ns.len(), "t_pos")?;
    check_sorted("t_acc", t_acc_ns)?;
    check_sorted("t_pos", t_pos_ns)?;

    let n = t_acc_ns.len();
    let mut out = KalmanTrace {
        t_ns: t_acc_ns.to_vec(),
        position_m: Vec::with_capacity(n),
        velocity_mps: Vec::with_capacity(n),
        bias_mps2: Vec::with_capacity(n),
        ..KalmanTrace::default()
    };
    let mut kf = KalmanFilter::new(params);
    let mut j = 0;
    let mut i = 0;
    while i < n {
        let t = t_acc_ns[i];
        while j < t_pos_ns.len() && t_pos_ns[j] < t {
            kf.position(t_pos_ns[j], pos_m[j])?;
            j += 1;
        }
        let mut i_end = i;
        while i_end < n && t_acc_ns[i_end] == t {
            kf.accel(t, a_rel_mps2[i_end])?;
            i_end += 1;
        }
        while j < t_pos_ns.len() && t_pos_ns[j] == t {
            kf.position(t_pos_ns[j], pos_m[j])?;
            j += 1;
        }
        let state = kf.predicted_state(t).unwrap_or([f64::NAN; 3]);
        for _ in i..i_end {
            out.position_m.push(state[0]);
            out.velocity_mps.push(state[1]);
            out.bias_mps2.push(state[2]);
        }
        i = i_end;
    }
    out.missing_accel = kf.missing_accel();
    out.missing_position = kf.missing_position();
    Ok(out)
}

pub(crate) fn check_len(
    name: &'static str,
    got: usize,
    expected: usize,
    reference: &'static str,
) -> Result<(), PhysicsError> {
    if got == expected {
        Ok(())
    } else {
        Err(PhysicsError::LengthMismatch {
            name,
            got,
            expected,
            reference,
        })
    }
}

fn check_sorted(name: &'static str, t: &[i64]) -> Result<(), PhysicsError> {
    match t.windows(2).position(|w| w[1] < w[0]) {
        None => Ok(()),
        Some(i) => Err(PhysicsError::NotMonotonic { name, index: i + 1 }),
    }
}

#[cfg(test)]
// Exact float equality is intended in these tests: same arithmetic, same result.
#[allow(clippy::float_cmp)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    const MS: i64 = 1_000_000;

    /// Exact zero-order-hold kinematics: `u` held over each 1 ms step.
    type Trajectory = (Vec<f64>, Vec<f64>, Vec<f64>);

    fn zoh_trajectory(n: usize, accel: impl Fn(f64) -> f64) -> Trajectory {
        let dt = 1.0e-3;
        let (mut y, mut v) = (0.01, 0.3);
        let (mut ys, mut vs, mut us) = (Vec::new(), Vec::new(), Vec::new());
        for i in 0..n {
            let u = accel(i as f64 * dt);
            ys.push(y);
            vs.push(v);
            us.push(u);
            y += v * dt + 0.5 * u * dt * dt;
            v += u * dt;
        }
        (ys, vs, us)
    }

    #[test]
    fn tracks_exact_kinematics_with_zero_noise() {
        let n = 3000;
        let (ys, vs, us) = zoh_trajectory(n, |t| -6.0 * (12.0 * t).sin());
        let params = KalmanParams {
            sigma_accel: 0.0,
            sigma_bias: 0.0,
            sigma_position: 1.0e-6,
        };
        let t_acc: Vec<i64> = (0..n as i64).map(|i| i * MS).collect();
        let t_pos: Vec<i64> = (0..n as i64).step_by(10).map(|i| i * MS).collect();
        let pos: Vec<f64> = (0..n).step_by(10).map(|i| ys[i]).collect();
        // The accelerometer sample at t_i holds u_i over [t_i, t_i+1): feed
        // u_i at t_i; the state at t_i does not yet depend on it.
        let trace = run_kalman(params, &t_acc, &us, &t_pos, &pos).unwrap();
        for i in 1000..n {
            assert!(
                (trace.velocity_mps[i] - vs[i]).abs() < 1e-6,
                "i = {i}: {} vs {}",
                trace.velocity_mps[i],
                vs[i]
            );
            assert!((trace.position_m[i] - ys[i]).abs() < 1e-8, "i = {i}");
            assert!(
                trace.bias_mps2[i].abs() < 1e-5,
                "i = {i}: bias {}",
                trace.bias_mps2[i]
            );
        }
        // It started with v = 0, so it really did learn the velocity.
        assert!(trace.velocity_mps[0].abs() < 1e-12);
    }

    #[test]
    fn constant_bias_is_estimated() {
        let n = 30_000; // 30 s at 1 kHz
        let bias = 0.49; // 50 mg
        let (ys, vs, us) = zoh_trajectory(n, |t| {
            -0.04
                * (2.0 * std::f64::consts::PI * 2.0).powi(2)
                * (2.0 * std::f64::consts::PI * 2.0 * t).sin()
        });
        let measured: Vec<f64> = us.iter().map(|u| u + bias).collect();
        let t_acc: Vec<i64> = (0..n as i64).map(|i| i * MS).collect();
        let t_pos: Vec<i64> = (0..n as i64).step_by(10).map(|i| i * MS).collect();
        let pos: Vec<f64> = (0..n).step_by(10).map(|i| ys[i]).collect();
        let trace = run_kalman(KalmanParams::default(), &t_acc, &measured, &t_pos, &pos).unwrap();
        let last = n - 1;
        assert!(
            (trace.bias_mps2[last] - bias).abs() < 0.02,
            "bias {}",
            trace.bias_mps2[last]
        );
        let max_v_err = (n - 5000..n)
            .map(|i| (trace.velocity_mps[i] - vs[i]).abs())
            .fold(0.0, f64::max);
        assert!(max_v_err < 0.01, "velocity error {max_v_err}");
    }

    #[test]
    fn nan_samples_are_skipped_and_counted() {
        let params = KalmanParams::default();
        let mut a = KalmanFilter::new(params);
        let mut b = KalmanFilter::new(params);
        for kf in [&mut a, &mut b] {
            kf.position(0, 0.01).unwrap();
            kf.accel(MS, 1.0).unwrap();
        }
        b.accel(2 * MS, f64::NAN).unwrap();
        b.position(3 * MS, f64::NAN).unwrap();
        for kf in [&mut a, &mut b] {
            kf.accel(5 * MS, 2.0).unwrap();
            kf.position(10 * MS, 0.011).unwrap();
        }
        assert_eq!(a.state(), b.state());
        assert_eq!(a.covariance(), b.covariance());
        assert_eq!((b.missing_accel(), b.missing_position()), (1, 1));
        assert_eq!((a.missing_accel(), a.missing_position()), (0, 0));
    }

    #[test]
    fn accel_before_first_position_only_sets_held_value() {
        let mut kf = KalmanFilter::new(KalmanParams::default());
        kf.accel(0, 3.0).unwrap();
        assert_eq!(kf.state(), None);
        kf.position(5 * MS, 0.02).unwrap();
        assert_eq!(kf.state(), Some([0.02, 0.0, 0.0]));
        let s2 = 1e-6;
        assert_eq!(
            kf.covariance().unwrap(),
            [[s2, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]
        );
        // The held 3 m/s² now drives the propagation.
        kf.accel(15 * MS, 0.0).unwrap();
        let x = kf.state().unwrap();
        assert!((x[1] - 0.03).abs() < 1e-12 && (x[0] - (0.02 + 0.5 * 3.0 * 1e-4)).abs() < 1e-12);
    }

    #[test]
    fn accel_comes_first_at_equal_times() {
        // Same events given as streams: the row at t = 10 ms includes the
        // position update at 10 ms, which followed the accelerometer sample.
        let params = KalmanParams::default();
        let trace = run_kalman(
            params,
            &[0, 10 * MS, 20 * MS],
            &[1.0, 2.0, 3.0],
            &[0, 10 * MS],
            &[0.0, 0.001],
        )
        .unwrap();
        let mut kf = KalmanFilter::new(params);
        kf.accel(0, 1.0).unwrap();
        kf.position(0, 0.0).unwrap();
        kf.accel(10 * MS, 2.0).unwrap();
        kf.position(10 * MS, 0.001).unwrap();
        let x10 = kf.state().unwrap();
        assert_eq!(trace.position_m[1], x10[0]);
        assert_eq!(trace.velocity_mps[1], x10[1]);
        kf.accel(20 * MS, 3.0).unwrap();
        assert_eq!(trace.velocity_mps[2], kf.state().unwrap()[1]);
    }

    #[test]
    fn errors_instead_of_panics() {
        let mut kf = KalmanFilter::new(KalmanParams {
            sigma_position: 0.0,
            ..KalmanParams::default()
        });
        kf.position(0, 0.0).unwrap();
        // P00 = σ_z² = 0 and no time passes: innovation variance 0.
        let err = kf.position(0, 0.0).unwrap_err();
        assert!(
            matches!(
                err,
                PhysicsError::Numerical {
                    model: "kalman",
                    ..
                }
            ),
            "{err}"
        );

        let mut kf = KalmanFilter::new(KalmanParams::default());
        kf.position(10 * MS, 0.0).unwrap();
        assert!(matches!(
            kf.accel(5 * MS, 0.0),
            Err(PhysicsError::OutOfOrder { .. })
        ));

        let err = run_kalman(KalmanParams::default(), &[0, 1], &[0.0], &[], &[]).unwrap_err();
        assert!(err.to_string().contains("a_rel"), "{err}");
        let err = run_kalman(KalmanParams::default(), &[2, 1], &[0.0, 0.0], &[], &[]).unwrap_err();
        assert!(err.to_string().contains("t_acc"), "{err}");

        let mut kf = KalmanFilter::position_only(KalmanParams::default(), POSITION_ONLY_JERK_PSD);
        assert!(matches!(kf.accel(0, 1.0), Err(PhysicsError::WrongMode(_))));
    }

    #[test]
    fn position_only_tracks_a_sine() {
        let params = KalmanParams::default();
        let mut kf = KalmanFilter::position_only(params, POSITION_ONLY_JERK_PSD);
        let w = 2.0 * std::f64::consts::PI * 2.0;
        let mut max_err: f64 = 0.0;
        for i in 0..2000 {
            let t = f64::from(i) * 0.01;
            kf.position(i64::from(i) * 10 * MS, 0.04 * (w * t).sin())
                .unwrap();
            if i > 500 {
                let v = kf.state().unwrap()[1];
                max_err = max_err.max((v - 0.04 * w * (w * t).cos()).abs());
            }
        }
        // Peak velocity 0.5 m/s; a constant-acceleration model lags a little.
        assert!(max_err < 0.02, "velocity error {max_err}");
    }

    #[derive(Debug, Clone)]
    enum Event {
        Accel(f64),
        Position(f64),
    }

    fn event() -> impl Strategy<Value = (i64, Event)> {
        (
            0i64..50_000_000,
            prop_oneof![
                (-50.0..50.0f64).prop_map(Event::Accel),
                (-0.05..0.05f64).prop_map(Event::Position)
            ],
        )
    }

    fn is_spd(p: &[[f64; 3]; 3]) -> bool {
        let m = Matrix3::from_fn(|i, j| p[i][j]);
        let scale = m.abs().max();
        let sym = (m - m.transpose()).abs().max() <= 1e-12 * scale;
        sym && m.cholesky().is_some()
    }

    proptest! {
        #[test]
        fn covariance_stays_symmetric_positive_definite(
            sigma_accel in 1e-3..10.0f64,
            sigma_bias in 1e-4..1.0f64,
            sigma_position in 1e-4..1e-2f64,
            events in prop::collection::vec(event(), 1..300),
        ) {
            let mut kf = KalmanFilter::new(KalmanParams { sigma_accel, sigma_bias, sigma_position });
            let mut t = 0;
            kf.position(t, 0.0).unwrap();
            for (dt, e) in events {
                t += dt;
                match e {
                    Event::Accel(a) => kf.accel(t, a).unwrap(),
                    Event::Position(z) => kf.position(t, z).unwrap(),
                }
                let p = kf.covariance().unwrap();
                prop_assert!(is_spd(&p), "P = {p:?}");
            }
        }

        #[test]
        fn position_only_covariance_stays_spd(
            sigma_position in 1e-4..1e-2f64,
            dts in prop::collection::vec(1i64..50_000_000, 1..200),
        ) {
            let params = KalmanParams { sigma_position, ..KalmanParams::default() };
            let mut kf = KalmanFilter::position_only(params, POSITION_ONLY_JERK_PSD);
            let mut t = 0;
            for dt in dts {
                t += dt;
                kf.position(t, 0.01).unwrap();
                prop_assert!(is_spd(&kf.covariance().unwrap()));
            }
        }
    }
}

#[cfg(test)]
#[allow(clippy::needless_range_loop)] // textbook index loops on purpose
mod reference_tests {
    //! Against a textbook KF written out with plain arrays (standard-form
    //! covariance update, explicit F, B, Q of SPEC §3.1).
    use super::*;

    type M = [[f64; 3]; 3];

    fn mul(a: &M, b: &M) -> M {
        let mut c = [[0.0; 3]; 3];
        for i in 0..3 {
            for j in 0..3 {
                for k in 0..3 {
                    c[i][j] += a[i][k] * b[k][j];
                }
            }
        }
        c
    }

    fn tr(a: &M) -> M {
        let mut c = [[0.0; 3]; 3];
        for i in 0..3 {
            for j in 0..3 {
                c[i][j] = a[j][i];
            }
        }
        c
    }

    struct Textbook {
        x: [f64; 3],
        p: M,
        u: f64,
        t: f64,
        sa: f64,
        sb: f64,
        sz: f64,
    }

    impl Textbook {
        fn predict(&mut self, t: f64) {
            let dt = t - self.t;
            let f = [[1.0, dt, -dt * dt / 2.0], [0.0, 1.0, -dt], [0.0, 0.0, 1.0]];
            let b = [dt * dt / 2.0, dt, 0.0];
            let mut x = [0.0; 3];
            for i in 0..3 {
                x[i] = (0..3).map(|k| f[i][k] * self.x[k]).sum::<f64>() + b[i] * self.u;
            }
            self.x = x;
            let mut p = mul(&mul(&f, &self.p), &tr(&f));
            for i in 0..3 {
                for j in 0..3 {
                    p[i][j] += self.sa * self.sa * b[i] * b[j];
                }
            }
            p[2][2] += self.sb * self.sb * dt;
            self.p = p;
            self.t = t;
        }

        fn update(&mut self, z: f64) {
            let s = self.p[0][0] + self.sz * self.sz;
            let k = [self.p[0][0] / s, self.p[1][0] / s, self.p[2][0] / s];
            let r = z - self.x[0];
            let mut p = self.p;
            for i in 0..3 {
                self.x[i] += k[i] * r;
                for j in 0..3 {
                    p[i][j] = self.p[i][j] - k[i] * self.p[0][j];
                }
            }
            self.p = p;
        }
    }

    #[test]
    fn matches_textbook_filter() {
        let params = KalmanParams {
            sigma_accel: 0.3,
            sigma_bias: 0.01,
            sigma_position: 2e-3,
        };
        let mut kf = KalmanFilter::new(params);
        let mut tb = Textbook {
            x: [0.0; 3],
            p: [[0.0; 3]; 3],
            u: 0.0,
            t: 0.0,
            sa: params.sigma_accel,
            sb: params.sigma_bias,
            sz: params.sigma_position,
        };
        // Deterministic pseudo-random event stream.
        let mut state: u64 = 12345;
        let mut rnd = || {
            state = state
                .wrapping_mul(6_364_136_223_846_793_005)
                .wrapping_add(1_442_695_040_888_963_407);
            (state >> 11) as f64 / (1u64 << 53) as f64
        };
        let z0 = 0.01;
        kf.position(0, z0).unwrap();
        tb.x = [z0, 0.0, 0.0];
        tb.p = [[4e-6, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
        let mut t_ns = 0i64;
        for _ in 0..5000 {
            t_ns += (rnd() * 3e6) as i64;
            let t = t_ns as f64 / 1e9;
            if rnd() < 0.8 {
                let a = 20.0 * (rnd() - 0.5);
                kf.accel(t_ns, a).unwrap();
                tb.predict(t);
                tb.u = a;
            } else {
                let z = 0.04 * (rnd() - 0.5);
                kf.position(t_ns, z).unwrap();
                tb.predict(t);
                tb.update(z);
            }
            let x = kf.state().unwrap();
            let p = kf.covariance().unwrap();
            for i in 0..3 {
                assert!(
                    (x[i] - tb.x[i]).abs() <= 1e-9 * (1.0 + tb.x[i].abs()),
                    "x[{i}] {} vs {}",
                    x[i],
                    tb.x[i]
                );
                for j in 0..3 {
                    let tol = 1e-7 * tb.p[i][i].sqrt() * tb.p[j][j].sqrt() + 1e-18;
                    assert!(
                        (p[i][j] - tb.p[i][j]).abs() <= tol,
                        "P[{i}][{j}] {} vs {}",
                        p[i][j],
                        tb.p[i][j]
                    );
                }
            }
        }
    }
}
