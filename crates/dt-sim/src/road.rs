//! A road drive file for the dyno: the suspension stroke of a car driven at
//! a constant speed over a random road, played by the actuator instead of a
//! sine — what a test engineer uses to reproduce driving on a
//! servo-hydraulic dyno.
//!
//! **Road.** ISO 8608: the road's vertical displacement has the spatial PSD
//! `G_d(n) = G_d(n₀) (n / n₀)^−2`, `n₀ = 0.1` cycles/m, with `G_d(n₀)` the
//! geometric mean of its class (A 16, B 64, C 256, D 1024, E 4096 × 10⁻⁶
//! m³). At speed `v` the temporal PSD is `G(f) = G_d(f / v) / v`.
//!
//! **Stroke.** A linear quarter-car (its constants below; they shape the
//! drive file only — the damper on the dyno is the truth plant's):
//! `m_s ẍ_s = −k_s (x_s − x_u) − c_s (ẋ_s − ẋ_u)`,
//! `m_u ẍ_u = k_s (x_s − x_u) + c_s (ẋ_s − ẋ_u) − k_t (x_u − z)`; with
//! `A = m_s s² + c_s s + k_s`, `B = c_s s + k_s`,
//! `C = m_u s² + c_s s + k_s + k_t`, the suspension deflection is
//! `x_u − x_s = k_t m_s s² Z / (A C − B²)`. Its PSD is `|H(j2πf)|² G(f)`.
//!
//! **Synthesis.** [`COMPONENTS`] sines on a logarithmic grid over
//! [`BAND_HZ`] (the frequency of each drawn uniformly within its bin, so the
//! drive does not repeat), amplitude `√(2 S(f_i) Δf_i)`, phase uniform;
//! drawn from the campaign seed, so every charge of a campaign plays the
//! same drive file. Position, velocity and acceleration are exact sums.

use rand::{Rng as _, SeedableRng};
use rand_chacha::ChaCha8Rng;

use crate::mix_seed;

/// Sines in the drive file.
pub const COMPONENTS: usize = 240;
/// The drive file's band, Hz (the quarter-car's body and wheel-hop modes).
pub const BAND_HZ: (f64, f64) = (0.5, 20.0);
/// Quarter-car: sprung mass, kg.
pub const QC_SPRUNG_KG: f64 = 350.0;
/// Quarter-car: unsprung mass, kg.
pub const QC_UNSPRUNG_KG: f64 = 45.0;
/// Quarter-car: suspension spring, N/m.
pub const QC_SPRING_NPM: f64 = 22.0e3;
/// Quarter-car: tyre stiffness, N/m.
pub const QC_TYRE_NPM: f64 = 200.0e3;
/// Quarter-car: linear damping (for the drive file only), N·s/m.
pub const QC_DAMPING_NSPM: f64 = 1.8e3;

/// An ISO 8608 road class.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum RoadClass {
    /// Very good.
    A,
    /// Good.
    B,
    /// Average.
    C,
    /// Poor.
    D,
    /// Very poor.
    E,
}

impl RoadClass {
    /// `G_d(n₀)`, the class's geometric mean displacement PSD at 0.1
    /// cycles/m, m³.
    #[must_use]
    pub fn psd_n0_m3(self) -> f64 {
        match self {
            RoadClass::A => 16e-6,
            RoadClass::B => 64e-6,
            RoadClass::C => 256e-6,
            RoadClass::D => 1024e-6,
            RoadClass::E => 4096e-6,
        }
    }

    /// `A` … `E`.
    #[must_use]
    pub fn letter(self) -> char {
        match self {
            RoadClass::A => 'A',
            RoadClass::B => 'B',
            RoadClass::C => 'C',
            RoadClass::D => 'D',
            RoadClass::E => 'E',
        }
    }

    /// The class named by `c` (`A` … `E`, either case).
    #[must_use]
    pub fn from_letter(c: char) -> Option<Self> {
        Some(match c.to_ascii_uppercase() {
            'A' => RoadClass::A,
            'B' => RoadClass::B,
            'C' => RoadClass::C,
            'D' => RoadClass::D,
            'E' => RoadClass::E,
            _ => return None,
        })
    }
}

/// A road drive: a car at `speed_kmh` over a road of `class`, the drive
/// file drawn from `seed`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RoadDrive {
    /// Vehicle speed, km/h.
    pub speed_kmh: f64,
    /// Road class.
    pub class: RoadClass,
    /// Seed of the drive file (a campaign's: every charge plays the same).
    pub seed: u64,
}

/// One sine of a drive file: `amp sin(ω τ + φ)`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Component {
    /// Amplitude, m.
    pub amp_m: f64,
    /// Angular frequency, rad/s.
    pub omega: f64,
    /// Phase, rad.
    pub phase: f64,
}

/// `|H(j2πf)|²` of the quarter-car's deflection over the road input.
#[must_use]
pub fn deflection_gain2(f_hz: f64) -> f64 {
    let w = std::f64::consts::TAU * f_hz;
    // s = jw: s² = −w². Complex arithmetic by hand on (re, im) pairs.
    let a = (QC_SPRING_NPM - QC_SPRUNG_KG * w * w, QC_DAMPING_NSPM * w);
    let b = (QC_SPRING_NPM, QC_DAMPING_NSPM * w);
    let c = (
        QC_SPRING_NPM + QC_TYRE_NPM - QC_UNSPRUNG_KG * w * w,
        QC_DAMPING_NSPM * w,
    );
    let mul = |x: (f64, f64), y: (f64, f64)| (x.0 * y.0 - x.1 * y.1, x.0 * y.1 + x.1 * y.0);
    let ac = mul(a, c);
    let bb = mul(b, b);
    let den = (ac.0 - bb.0, ac.1 - bb.1);
    let num = QC_TYRE_NPM * QC_SPRUNG_KG * w * w;
    num * num / (den.0 * den.0 + den.1 * den.1)
}

impl RoadDrive {
    /// The stroke's one-sided PSD at `f_hz`, m²/Hz.
    #[must_use]
    pub fn stroke_psd(&self, f_hz: f64) -> f64 {
        let v = self.speed_kmh / 3.6;
        let n = f_hz / v;
        let road = self.class.psd_n0_m3() * (n / 0.1).powi(-2) / v;
        deflection_gain2(f_hz) * road
    }

    /// The drive file's sines.
    #[must_use]
    pub fn components(&self) -> Vec<Component> {
        let mut rng = ChaCha8Rng::seed_from_u64(mix_seed(&[
            self.seed,
            self.speed_kmh.to_bits(),
            u64::from(self.class.letter()),
            0x726f_6164,
        ]));
        let (lo, hi) = BAND_HZ;
        let ratio = (hi / lo).powf(1.0 / COMPONENTS as f64);
        (0..COMPONENTS)
            .map(|i| {
                let f0 = lo * ratio.powi(i as i32);
                let f1 = f0 * ratio;
                let f = f0 + (f1 - f0) * rng.random::<f64>();
                Component {
                    amp_m: (2.0 * self.stroke_psd(f) * (f1 - f0)).sqrt(),
                    omega: std::f64::consts::TAU * f,
                    phase: std::f64::consts::TAU * rng.random::<f64>(),
                }
            })
            .collect()
    }

    /// E.g. `roadC60`.
    #[must_use]
    pub fn tag(&self) -> String {
        format!("road{}{}", self.class.letter(), self.speed_kmh)
    }
}

/// RMS stroke of `components`, m.
#[must_use]
pub fn rms_m(components: &[Component]) -> f64 {
    (components.iter().map(|c| c.amp_m * c.amp_m).sum::<f64>() / 2.0).sqrt()
}

/// The displacement's mean frequency `√(Σ a² ω² / Σ a²) / 2π`, Hz (its
/// zero-crossing rate over two): the frequency the gas spring's heat
/// exchange sees.
#[must_use]
pub fn mean_frequency_hz(components: &[Component]) -> f64 {
    let m0: f64 = components.iter().map(|c| c.amp_m * c.amp_m).sum();
    let m2: f64 = components
        .iter()
        .map(|c| c.amp_m * c.amp_m * c.omega * c.omega)
        .sum();
    (m2 / m0).sqrt() / std::f64::consts::TAU
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn quarter_car_gain_passes_the_road_above_wheel_hop_and_not_below_the_body_mode() {
        // Below the body mode the car follows the road (no deflection);
        // between body (≈1.2 Hz) and wheel hop (≈11 Hz) the deflection is
        // the road's; far above it, the wheel stops following.
        assert!(deflection_gain2(0.05) < 1e-3);
        assert!((deflection_gain2(4.0).sqrt() - 1.0).abs() < 0.25);
        assert!(deflection_gain2(60.0) < 0.05);
    }

    #[test]
    fn drive_files_are_seeded_and_their_rms_matches_the_psd() {
        let d = RoadDrive {
            speed_kmh: 60.0,
            class: RoadClass::C,
            seed: 1,
        };
        assert_eq!(d.components(), d.components());
        assert_ne!(d.components(), RoadDrive { seed: 2, ..d }.components());
        // ∫ S df by the trapezoid rule on a fine grid against the synthesis.
        let (lo, hi) = BAND_HZ;
        let n = 20_000;
        let df = (hi - lo) / f64::from(n);
        let var: f64 = (0..=n)
            .map(|i| {
                let w = if i == 0 || i == n { 0.5 } else { 1.0 };
                w * d.stroke_psd(lo + df * f64::from(i)) * df
            })
            .sum();
        let rms = rms_m(&d.components());
        assert!(
            (rms / var.sqrt() - 1.0).abs() < 0.05,
            "{rms} vs {}",
            var.sqrt()
        );
        // Class C at 60 km/h: a suspension stroke of about a centimetre rms.
        assert!((0.005..0.02).contains(&rms), "{rms}");
    }
}
