//! The dyno: a displacement-controlled actuator on the rod end and a
//! compliant mount under the body end.
//!
//! Axis: along the extension, from the body end toward the rod end (the rod
//! end is on the actuator below, the body on the crosshead above, so this
//! axis points down). Extension `y = x_rod − x_body` (SPEC §1).
//!
//! **Actuator** (imposed): `x_rod(t) = A e(τ) [sin ωτ + h₃ sin 3ωτ]`,
//! `τ = t − t_start`, `A` = half the peak-to-peak stroke, `h₃` the servo's
//! third-harmonic distortion and `e(τ)` a raised-cosine amplitude ramp over
//! `actuator_ramp_s`; velocity and acceleration are its exact derivatives.
//! Before `t_start` the rod rests at mid-stroke. A road drive file
//! ([`crate::road`]) replaces the sine by its sum of sines, under the same
//! ramp.
//!
//! **Mount** (body end): `m ẍ_b = F − k x_b − c ẋ_b`, `F` the damper force
//! (tension pulls the body toward the rod). Integrated by semi-implicit
//! (symplectic) Euler at the plant sub-step (`ω_n dt ≈ 0.16`, stable and
//! non-dissipative). Its velocity is the leapfrog's, half a step behind the
//! position; the velocity at the step's time, which the damper's stroke
//! velocity, the mount's own damping and the truth take, is that half step
//! advanced by the last acceleration (`v + a dt / 2`, second order; before
//! the twenty-first session the half-step velocity was taken as it was, so
//! the damper's friction flipped on a body velocity 0.125 ms old). The
//! loadcell in series with the mount reads `k x_b + c ẋ_b = F − m ẍ_b`.

use std::f64::consts::PI;
use std::sync::Arc;

use crate::road::Component;

/// Imposed rod-end motion.
#[derive(Debug, Clone, PartialEq)]
pub struct Actuator {
    /// Half stroke, m.
    pub amp_m: f64,
    /// Angular frequency, rad/s.
    pub omega: f64,
    /// Third-harmonic fraction.
    pub h3: f64,
    /// Ramp duration, s.
    pub ramp_s: f64,
    /// Start of the excitation, s.
    pub start_s: f64,
    /// A road drive file's sines, played instead of the sine.
    pub road: Option<Arc<[Component]>>,
}

impl Actuator {
    /// Position, velocity, acceleration of the rod end at `t_s`.
    #[must_use]
    pub fn kinematics(&self, t_s: f64) -> (f64, f64, f64) {
        let tau = t_s - self.start_s;
        if tau <= 0.0 || (self.road.is_none() && (self.amp_m == 0.0 || self.omega == 0.0)) {
            return (0.0, 0.0, 0.0);
        }
        let (e, de, dde) = if tau < self.ramp_s {
            let k = PI / self.ramp_s;
            (
                0.5 * (1.0 - (k * tau).cos()),
                0.5 * k * (k * tau).sin(),
                0.5 * k * k * (k * tau).cos(),
            )
        } else {
            (1.0, 0.0, 0.0)
        };
        let (a, s, ds, dds) = if let Some(road) = &self.road {
            let (mut s, mut ds, mut dds) = (0.0, 0.0, 0.0);
            for c in road.iter() {
                let (sin, cos) = (c.omega * tau + c.phase).sin_cos();
                s += c.amp_m * sin;
                ds += c.amp_m * c.omega * cos;
                dds -= c.amp_m * c.omega * c.omega * sin;
            }
            (1.0, s, ds, dds)
        } else {
            let w = self.omega;
            let th = w * tau;
            (
                self.amp_m,
                th.sin() + self.h3 * (3.0 * th).sin(),
                w * (th.cos() + 3.0 * self.h3 * (3.0 * th).cos()),
                -w * w * (th.sin() + 9.0 * self.h3 * (3.0 * th).sin()),
            )
        };
        (
            a * e * s,
            a * (de * s + e * ds),
            a * (dde * s + 2.0 * de * ds + e * dds),
        )
    }
}

/// State of the compliant body-end mount.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Mount {
    /// Body-end displacement along the axis, m.
    pub x_m: f64,
    /// Body-end velocity over the last step (the leapfrog's half step,
    /// `dt / 2` behind `x_m`), m/s; [`Mount::velocity_now`] is at `x_m`'s time.
    pub v_mps: f64,
    /// Body-end acceleration of the last step, m/s².
    pub a_mps2: f64,
    mass_kg: f64,
    k_n_per_m: f64,
    c_ns_per_m: f64,
}

impl Mount {
    /// A mount at static equilibrium under the force `force_n`.
    #[must_use]
    pub fn new(mass_kg: f64, k_n_per_m: f64, c_ns_per_m: f64, force_n: f64) -> Self {
        Mount {
            x_m: force_n / k_n_per_m,
            v_mps: 0.0,
            a_mps2: 0.0,
            mass_kg,
            k_n_per_m,
            c_ns_per_m,
        }
    }

    /// Body-end velocity at the time of `x_m` (the half step advanced by
    /// the last acceleration), m/s.
    #[must_use]
    pub fn velocity_now(&self, dt_s: f64) -> f64 {
        self.v_mps + 0.5 * dt_s * self.a_mps2
    }

    /// Force the mount passes to the frame (what the loadcell carries) at
    /// the time of `x_m`, N.
    #[must_use]
    pub fn frame_force_n(&self, dt_s: f64) -> f64 {
        self.k_n_per_m * self.x_m + self.c_ns_per_m * self.velocity_now(dt_s)
    }

    /// One semi-implicit Euler step under the damper force `force_n`.
    pub fn step(&mut self, force_n: f64, dt_s: f64) {
        self.a_mps2 = (force_n - self.frame_force_n(dt_s)) / self.mass_kg;
        self.v_mps += dt_s * self.a_mps2;
        self.x_m += dt_s * self.v_mps;
    }
}
