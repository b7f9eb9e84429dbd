//! Twin-tube hydraulics: chambers, valves, cavitation, seal friction.
//!
//! Three oil spaces: the rebound chamber above the piston (annulus
//! `A_a = A_p − A_rod`), the compression chamber below it (`A_p`), and the
//! reservoir between the tubes at the gas pressure `p_g`. Oil is taken as
//! incompressible (its 2 `GPa` bulk modulus, from the notes, puts the compliance far above
//! the dyno band). With `v = ẏ`:
//!
//! * **rebound** (`v > 0`): `A_a v` flows through the piston rebound valve
//!   (rebound → compression chamber), `A_rod v` is drawn from the reservoir
//!   through the base intake valve:
//!   `p_c = p_g − Δp_bi(A_rod v)`, `p_r = p_c + Δp_reb(A_a v)`;
//! * **compression** (`v < 0`): `A_a |v|` flows through the piston
//!   compression valve into the rebound chamber, `A_rod |v|` through the base
//!   compression valve into the reservoir:
//!   `p_c = p_g + Δp_bc(A_rod |v|)`, `p_r = max(p_c − Δp_pc(A_a |v|), p_cav)`;
//! * **cavitation / aeration**: if the refill would need `p_c < p_cav`
//!   (low gas pressure and a fast stroke), the compression chamber holds
//!   `p_cav`, the intake passes only its maximum flow
//!   `Q_max = Q_bi(p_g − p_cav)` and a void grows:
//!   `dV_void/dt = A_rod v − Q_max`. While a void exists both chambers sit at
//!   `p_cav` in compression (the piston moves into the void: no valve force,
//!   the "lag at reversal" of the workshop manuals in the notes) and the void
//!   shrinks at `A_rod |v| + Q_max`; the dead band grows with the void volume.
//!
//! Axial force on the rod, positive in tension (SPEC §1):
//! `F = p_r A_a − p_c A_p + p_atm A_rod + F_fric`; at rest this is
//! `−(p_g − p_atm) A_rod` (the gas pushes the rod out).
//!
//! Seal/guide friction: `F_fric = (F_c + k_seal · p_g,gauge) tanh(v / v_s) + c_f v`
//! (Coulomb, pressure-energised seal, smoothed; plus a viscous part).
//!
//! Dissipated power (W, all ≥ 0): `Σ Δp_i Q_i` over the valves (into the oil)
//! and `F_fric v` (into the inner tube at the rod guide). Energy identity
//! per step: `F_hyd v = P_valves − p_g dV_gas/dt − p_cav dV_void/dt + p_atm A_rod v`.

use crate::oil::Walther;
use crate::params::{PlantParams, P_ATM_PA};
use crate::valve::Valve;
use crate::SimError;

/// Output of one hydraulic evaluation.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct HydraulicOut {
    /// Damper force (hydraulic + friction), N, positive in tension.
    pub force_n: f64,
    /// Friction part of `force_n`, N.
    pub friction_n: f64,
    /// Rebound-chamber pressure, Pa abs.
    pub p_reb_pa: f64,
    /// Compression-chamber pressure, Pa abs.
    pub p_comp_pa: f64,
    /// Heat from the valves, W.
    pub valve_power_w: f64,
    /// Heat from friction, W.
    pub friction_power_w: f64,
    /// Rate of change of the void volume, m³/s.
    pub dvoid_m3_per_s: f64,
    /// True if the compression chamber is at the cavitation pressure.
    pub cavitating: bool,
}

/// The damper's hydraulic circuit.
#[derive(Debug, Clone, PartialEq)]
pub struct TwinTube {
    reb: Valve,
    pc: Valve,
    bc: Valve,
    bi: Valve,
    a_p: f64,
    a_r: f64,
    a_a: f64,
    p_cav: f64,
    f_c: f64,
    k_seal_n_per_pa: f64,
    c_f: f64,
    v_s: f64,
    /// Oil viscosity law.
    pub oil: Walther,
    warm: [f64; 4],
}

impl TwinTube {
    /// The circuit of `p`.
    #[must_use]
    pub fn new(p: &PlantParams) -> Self {
        let rho = p.oil_density_kg_m3;
        let cd = p.valve_cd;
        TwinTube {
            reb: Valve::new(
                p.reb_lam_pa_s_m3,
                p.reb_bleed_area_m2,
                p.reb_crack_pa,
                p.reb_shim_gain_m2_pa,
                p.reb_shim_max_m2,
                cd,
                rho,
            ),
            pc: Valve::new(
                p.pc_lam_pa_s_m3,
                p.pc_bleed_area_m2,
                p.pc_crack_pa,
                p.pc_shim_gain_m2_pa,
                p.pc_shim_max_m2,
                cd,
                rho,
            ),
            bc: Valve::new(
                p.bc_lam_pa_s_m3,
                p.bc_bleed_area_m2,
                p.bc_crack_pa,
                p.bc_shim_gain_m2_pa,
                p.bc_shim_max_m2,
                cd,
                rho,
            ),
            bi: Valve::new(
                p.bi_lam_pa_s_m3,
                p.bi_bleed_area_m2,
                p.bi_crack_pa,
                p.bi_shim_gain_m2_pa,
                p.bi_shim_max_m2,
                cd,
                rho,
            ),
            a_p: p.piston_area_m2(),
            a_r: p.rod_area_m2(),
            a_a: p.annulus_area_m2(),
            p_cav: p.cavitation_pa,
            f_c: p.friction_coulomb_n,
            k_seal_n_per_pa: p.friction_seal_n_per_bar / 1e5,
            c_f: p.friction_viscous_ns_m,
            v_s: p.friction_v_smooth_mps,
            oil: Walther::new(p.oil_nu40_cst, p.oil_nu100_cst),
            warm: [0.0; 4],
        }
    }

    fn dp(&mut self, which: usize, q: f64, nu_ratio: f64) -> Result<f64, SimError> {
        let valve = match which {
            0 => &self.reb,
            1 => &self.pc,
            2 => &self.bc,
            _ => &self.bi,
        };
        let dp = valve
            .dp_pa(q, nu_ratio, self.warm[which])
            .ok_or(SimError::Numerical {
                what: "valve pressure drop did not converge (flow m^3/s)",
                value: q,
            })?;
        self.warm[which] = dp;
        Ok(dp)
    }

    /// Maximum refill flow through the base intake valve at gas pressure
    /// `p_g_pa` (abs), m³/s.
    #[must_use]
    pub fn max_refill_m3s(&self, p_g_pa: f64, nu_ratio: f64) -> f64 {
        self.bi.flow((p_g_pa - self.p_cav).max(0.0), nu_ratio).0
    }

    /// Evaluates the circuit at velocity `v_mps`, gas pressure `p_g_pa`
    /// (abs), void volume `void_m3`, viscosity ratio `nu_ratio`.
    pub fn evaluate(
        &mut self,
        v_mps: f64,
        p_g_pa: f64,
        void_m3: f64,
        nu_ratio: f64,
    ) -> Result<HydraulicOut, SimError> {
        let (a_p, a_r, a_a, p_cav) = (self.a_p, self.a_r, self.a_a, self.p_cav);
        let mut out = HydraulicOut::default();
        let mut cav = void_m3 > 0.0;
        let mut dp_bi = 0.0;
        if !cav && v_mps > 0.0 {
            dp_bi = self.dp(3, a_r * v_mps, nu_ratio)?;
            cav = p_g_pa - dp_bi < p_cav;
        }
        let (p_c, p_r, power);
        if cav {
            let q_max = self.max_refill_m3s(p_g_pa, nu_ratio);
            out.dvoid_m3_per_s = a_r * v_mps - q_max;
            p_c = p_cav;
            let mut pw = (p_g_pa - p_cav).max(0.0) * q_max;
            if v_mps > 0.0 {
                let q = a_a * v_mps;
                let dp_reb = self.dp(0, q, nu_ratio)?;
                p_r = p_cav + dp_reb;
                pw += dp_reb * q;
            } else {
                p_r = p_cav;
            }
            power = pw;
            out.cavitating = true;
        } else if v_mps > 0.0 {
            let q = a_a * v_mps;
            let dp_reb = self.dp(0, q, nu_ratio)?;
            p_c = p_g_pa - dp_bi;
            p_r = p_c + dp_reb;
            power = dp_reb * q + dp_bi * a_r * v_mps;
        } else {
            let speed = -v_mps;
            let q_bc = a_r * speed;
            let q_pc = a_a * speed;
            let dp_bc = self.dp(2, q_bc, nu_ratio)?;
            let dp_pc = self.dp(1, q_pc, nu_ratio)?;
            p_c = p_g_pa + dp_bc;
            p_r = (p_c - dp_pc).max(p_cav);
            power = dp_bc * q_bc + (p_c - p_r) * q_pc;
        }
        let f_hyd = p_r * a_a - p_c * a_p + P_ATM_PA * a_r;
        let f_c = self.f_c + self.k_seal_n_per_pa * (p_g_pa - P_ATM_PA).max(0.0);
        let f_fric = f_c * (v_mps / self.v_s).tanh() + self.c_f * v_mps;
        out.force_n = f_hyd + f_fric;
        out.friction_n = f_fric;
        out.p_reb_pa = p_r;
        out.p_comp_pa = p_c;
        out.valve_power_w = power;
        out.friction_power_w = f_fric * v_mps;
        Ok(out)
    }
}
