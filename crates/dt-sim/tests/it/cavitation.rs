//! Cavitation / aeration: only at low charge and high speed; it costs force
//! near reversal and heat.

use crate::{plant, run_for};
use dt_sim::PlantParams;

struct Stats {
    void_fraction: f64,
    max_void_ml: f64,
    /// Valve heat over the measured cycles, J.
    heat_j: f64,
    /// Mean compression force (N, > 0 = compressive) in the first 15 % of
    /// each compression stroke, after the start ramp.
    early_compression_n: f64,
}

fn stats(charge_bar: f64, frequency_hz: f64) -> Stats {
    let p = PlantParams::nominal();
    let mut plant = plant(&p, charge_bar, frequency_hz);
    let period = 1.0 / frequency_hz;
    let seconds = 2.0 + 12.0 * period;
    let (mut void_t, mut max_void, mut heat, mut total) = (0.0, 0.0f64, 0.0, 0.0);
    let (mut early_sum, mut early_n) = (0.0, 0.0);
    let omega = std::f64::consts::TAU * frequency_hz;
    run_for(&mut plant, seconds, |t| {
        if t.t_s < 2.0 + 2.0 * period {
            return;
        }
        total += t.dt_s;
        if t.void_m3 > 0.0 || t.cavitating {
            void_t += t.dt_s;
        }
        max_void = max_void.max(t.void_m3);
        heat += t.valve_power_w * t.dt_s;
        // Rod position A sin(wt): compression (y falling) starts at wt = pi/2.
        let phase = (omega * t.t_s).rem_euclid(std::f64::consts::TAU);
        let start = std::f64::consts::FRAC_PI_2;
        if phase > start && phase < start + 0.15 * std::f64::consts::PI {
            early_sum += -t.force_n;
            early_n += 1.0;
        }
    });
    Stats {
        void_fraction: void_t / total,
        max_void_ml: max_void * 1e6,
        heat_j: heat,
        early_compression_n: early_sum / early_n,
    }
}

#[test]
fn low_charge_high_speed_cavitates() {
    let s = stats(0.5, 4.0);
    assert!(s.void_fraction > 0.2, "void fraction {}", s.void_fraction);
    assert!(s.max_void_ml > 1.0, "max void {} mL", s.max_void_ml);
}

#[test]
fn nominal_charge_never_cavitates() {
    for f in [1.0, 2.0, 4.0] {
        let s = stats(12.0, f);
        assert!(s.void_fraction == 0.0, "12 bar {f} Hz: {}", s.void_fraction);
    }
    let s = stats(7.0, 4.0);
    assert!(s.void_fraction == 0.0, "7 bar 4 Hz: {}", s.void_fraction);
}

#[test]
fn low_charge_low_speed_does_not_cavitate() {
    let s = stats(0.5, 1.0);
    assert!(s.void_fraction < 0.01, "0.5 bar 1 Hz: {}", s.void_fraction);
}

#[test]
fn cavitation_loses_force_after_reversal_and_heat() {
    let low = stats(0.5, 4.0);
    let ok = stats(7.0, 4.0);
    // Without a void the early compression force is several hundred N;
    // with one the piston moves into the void.
    assert!(
        ok.early_compression_n > 300.0,
        "7 bar: {}",
        ok.early_compression_n
    );
    assert!(
        low.early_compression_n < 0.5 * ok.early_compression_n,
        "0.5 bar {} N vs 7 bar {} N",
        low.early_compression_n,
        ok.early_compression_n
    );
    // The gas spring is conservative, so without cavitation the charge
    // barely changes the valve heat (2 Hz); at 4 Hz the void costs heat.
    let low2 = stats(0.5, 2.0);
    let ok2 = stats(7.0, 2.0);
    let ratio2 = low2.heat_j / ok2.heat_j;
    let ratio4 = low.heat_j / ok.heat_j;
    eprintln!("valve heat ratio 0.5/7 bar: 2 Hz {ratio2:.4}, 4 Hz {ratio4:.4}");
    assert!((ratio2 - 1.0).abs() < 0.01, "2 Hz ratio {ratio2}");
    assert!(
        ratio4 < ratio2 - 0.02,
        "4 Hz ratio {ratio4} vs 2 Hz {ratio2}"
    );
}
