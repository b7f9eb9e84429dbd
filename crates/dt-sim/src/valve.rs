//! One hydraulic valve: a bleed in parallel with a preloaded blow-off shim
//! stack (or a check disc). This is the plant's **digressive** valve law —
//! deliberately not the twin's power law (SPEC §3.3, eqs. 4–6).
//!
//! Flow as a function of the pressure drop `Δp` (Pa) across the valve:
//!
//! * bleed: laminar + turbulent resistance in series,
//!   `Δp = a(T) Q + b Q²`, `a(T) = a40 · ν(T)/ν40`,
//!   `b = ρ / (2 Cd² A_bleed²)` (sharp-edged orifice), solved for `Q`;
//! * shim stack: opening area grows linearly with `Δp` above the cracking
//!   pressure and saturates smoothly at full opening,
//!   `A_s = A_max · u / √(1 + u²)`, `u = k_s · r(Δp − p_crack) / A_max`, flow
//!   `Q_s = Cd A_s √(2Δp/ρ)`, where `r(d) = (d + √(d² + w²)) / 2` is a
//!   hyperbolic ramp (knee width `w` = 0.3 bar) that smooths the cracking
//!   knee (algebraic forms: no transcendental functions in the hot loop);
//! * `Q(Δp) = Q_bleed + Q_s`, strictly increasing in `Δp`.
//!
//! The plant knows the flow (from the kinematics) and needs `Δp`: [`Valve::dp_pa`]
//! inverts `Q(Δp)` by safeguarded Newton iteration, bracketed by the
//! bleed-only drop (an upper bound). The dissipated power is `Δp · Q` (W).
//! Source: orifice equation (any fluid-power text); the shim law is a
//! common first-order simplification of a deflecting clamped disc.

/// Smoothing width of the shim knee, Pa.
const KNEE_PA: f64 = 0.3e5;

/// Static description of a valve at a given temperature-independent state.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Valve {
    /// Laminar bleed resistance at 40 °C, Pa·s/m³.
    pub lam40_pa_s_m3: f64,
    /// Turbulent bleed coefficient `b`, Pa·s²/m⁶.
    pub turb_pa_s2_m6: f64,
    /// Cracking pressure, Pa.
    pub crack_pa: f64,
    /// Shim opening gain, m²/Pa.
    pub gain_m2_pa: f64,
    /// Full shim opening, m².
    pub max_m2: f64,
    /// `Cd · √(2/ρ)`, m^1.5/kg^0.5.
    pub cd_sqrt_2_rho: f64,
}

impl Valve {
    /// Builds a valve from its table parameters.
    #[must_use]
    pub fn new(
        lam40_pa_s_m3: f64,
        bleed_area_m2: f64,
        crack_pa: f64,
        gain_m2_pa: f64,
        max_m2: f64,
        cd: f64,
        rho_kg_m3: f64,
    ) -> Self {
        Valve {
            lam40_pa_s_m3,
            turb_pa_s2_m6: rho_kg_m3 / (2.0 * cd * cd * bleed_area_m2 * bleed_area_m2),
            crack_pa,
            gain_m2_pa,
            max_m2,
            cd_sqrt_2_rho: cd * (2.0 / rho_kg_m3).sqrt(),
        }
    }

    /// Flow through the valve and its derivative `dQ/dΔp` at `dp_pa ≥ 0`,
    /// with the viscosity ratio `nu_ratio = ν(T)/ν40`.
    #[must_use]
    pub fn flow(&self, dp_pa: f64, nu_ratio: f64) -> (f64, f64) {
        let dp = dp_pa.max(0.0);
        let a = self.lam40_pa_s_m3 * nu_ratio;
        let b = self.turb_pa_s2_m6;
        let disc = (a * a + 4.0 * b * dp).sqrt();
        // Q_b = (−a + √(a² + 4bΔp)) / 2b, written without cancellation.
        let q_b = 2.0 * dp / (a + disc);
        let dq_b = 1.0 / disc;
        // Shim: hyperbolic ramp above cracking (closed well below it).
        let d = dp - self.crack_pa;
        if d < -50.0 * KNEE_PA {
            return (q_b, dq_b);
        }
        let root = (d * d + KNEE_PA * KNEE_PA).sqrt();
        let ramp = 0.5 * (d + root);
        let dramp = 0.5 * (1.0 + d / root);
        let u = self.gain_m2_pa * ramp / self.max_m2;
        let s = (1.0 + u * u).sqrt();
        let area = self.max_m2 * u / s;
        let darea = self.gain_m2_pa * dramp / (s * s * s);
        let sq = dp.sqrt();
        let q_s = self.cd_sqrt_2_rho * area * sq;
        let dq_s = if sq > 0.0 {
            self.cd_sqrt_2_rho * (darea * sq + area * 0.5 / sq)
        } else {
            0.0
        };
        (q_b + q_s, dq_b + dq_s)
    }

    /// Pressure drop (Pa, ≥ 0) that passes `q_m3s ≥ 0`; `warm_pa` is a
    /// starting guess (e.g. the previous step's answer). Returns `None` if
    /// the iteration fails to converge (a numerical failure the caller
    /// turns into an error).
    #[must_use]
    pub fn dp_pa(&self, q_m3s: f64, nu_ratio: f64, warm_pa: f64) -> Option<f64> {
        if q_m3s <= 0.0 {
            return Some(0.0);
        }
        let a = self.lam40_pa_s_m3 * nu_ratio;
        // Bleed only passes less flow than the valve: its Δp bounds the answer.
        let mut hi = a * q_m3s + self.turb_pa_s2_m6 * q_m3s * q_m3s;
        let mut lo = 0.0;
        let mut x = if warm_pa > 0.0 && warm_pa < hi {
            warm_pa
        } else {
            0.5 * hi
        };
        let tol = 1e-9 * q_m3s;
        for _ in 0..60 {
            let (q, dq) = self.flow(x, nu_ratio);
            let r = q - q_m3s;
            if r.abs() <= tol {
                return Some(x);
            }
            if r > 0.0 {
                hi = x;
            } else {
                lo = x;
            }
            let newton = x - r / dq;
            if dq > 0.0 && newton > lo && newton < hi {
                // Quadratic convergence: a step this small leaves an error
                // far below it.
                if (newton - x).abs() <= 1e-7 * x {
                    return Some(newton);
                }
                x = newton;
            } else {
                x = 0.5 * (lo + hi);
            }
            if hi - lo <= 1e-9 * hi {
                return Some(x);
            }
        }
        None
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn inverse_matches_forward() {
        let v = Valve::new(4.0e9, 3.4e-6, 10e5, 2.5e-12, 16e-6, 0.7, 860.0);
        for q in [1e-6, 3e-5, 1e-4, 3e-4, 7e-4, 2e-3] {
            for nu in [0.4, 1.0, 2.0] {
                let dp = v.dp_pa(q, nu, 0.0).unwrap();
                let (q2, _) = v.flow(dp, nu);
                assert!((q2 - q).abs() < 1e-8 * q, "q {q} nu {nu}: {q2}");
            }
        }
    }

    #[test]
    fn derivative_matches_finite_difference() {
        let v = Valve::new(4.0e9, 3.4e-6, 10e5, 2.5e-12, 16e-6, 0.7, 860.0);
        for dp in [1e4, 5e5, 9.9e5, 1.1e6, 3e6] {
            let (q1, d) = v.flow(dp, 1.0);
            let (q2, _) = v.flow(dp * (1.0 + 1e-6), 1.0);
            let fd = (q2 - q1) / (dp * 1e-6);
            assert!((fd - d).abs() < 1e-4 * d.abs(), "{dp}: {fd} vs {d}");
        }
    }
}
