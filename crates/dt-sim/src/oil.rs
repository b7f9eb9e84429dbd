//! Oil viscosity against temperature: the Walther / ASTM D341 form
//! (physics-notes, "Oil viscosity is specified at 40 and 100 °C"):
//!
//! `log10(log10(ν + 0.7)) = A − B · log10(T)`, ν in mm²/s (cSt), T in K,
//! with `A`, `B` fixed by the two specified points `ν40`, `ν100`.
//!
//! The valves use the ratio `ν(T)/ν40` to scale their laminar (viscous)
//! resistance. This is deliberately not the twin's exponential
//! `ν40 · exp(−β (T − 40))` (SPEC §3.3).

use crate::params::KELVIN;

/// Walther line of one oil.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Walther {
    a: f64,
    b: f64,
    nu40_cst: f64,
}

impl Walther {
    /// Fits the line through `ν40` and `ν100` (mm²/s).
    #[must_use]
    pub fn new(nu40_cst: f64, nu100_cst: f64) -> Self {
        let w = |nu: f64| (nu + 0.7).log10().log10();
        let (l40, l100) = ((40.0 + KELVIN).log10(), (100.0 + KELVIN).log10());
        let b = (w(nu40_cst) - w(nu100_cst)) / (l100 - l40);
        let a = w(nu40_cst) + b * l40;
        Walther { a, b, nu40_cst }
    }

    /// Kinematic viscosity at `temp_c`, mm²/s.
    #[must_use]
    pub fn nu_cst(&self, temp_c: f64) -> f64 {
        let lt = (temp_c + KELVIN).log10();
        10f64.powf(10f64.powf(self.a - self.b * lt)) - 0.7
    }

    /// `ν(T) / ν40`.
    #[must_use]
    pub fn ratio_to_40(&self, temp_c: f64) -> f64 {
        self.nu_cst(temp_c) / self.nu40_cst
    }
}
