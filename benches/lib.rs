//! Criterion benchmarks for shocktwin live in this package's `[[bench]]`
//! targets; this library holds what several of them share.

use dt_core::log::Sample;

const MS: i64 = 1_000_000;

/// Deterministic noise in [-1, 1].
#[must_use]
pub fn noise(i: i64) -> f64 {
    let x = (i as u64)
        .wrapping_mul(0x9E37_79B9_7F4A_7C15)
        .rotate_left(17);
    (x >> 11) as f64 / (1u64 << 52) as f64 - 1.0
}

/// `ms` milliseconds of a 2 Hz, 80 mm p-p dyno run at SPEC rates from
/// `t0_ns`, in time order; the body accelerometer carries a seal friction
/// flip of `friction_n` newtons through a 30 kg mount (0: noise only).
#[must_use]
pub fn dyno_samples(t0_ns: i64, ms: i64, friction_n: f64) -> Vec<Sample> {
    let w = 2.0 * std::f64::consts::PI * 2.0;
    let amp = 0.04;
    let mut out = Vec::with_capacity((ms * 1160 / 1000) as usize);
    for i in 0..ms {
        let t_ns = t0_ns + i * MS;
        let x = i as f64 * 1e-3;
        let v = amp * w * (w * x).cos();
        out.push(Sample::Acceleration {
            t_ns,
            a1_mps2: -amp * w * w * (w * x).sin() + 0.3 + 0.05 * noise(i),
            a2_mps2: friction_n / 30.0 * (v / 0.005).tanh() + 0.05 * noise(i + 7),
        });
        if i % 10 == 0 {
            out.push(Sample::Position {
                t_ns,
                position_m: amp * (w * x).sin() + 5e-4 * noise(3 * i),
            });
        }
        if i % 20 == 3 {
            out.push(Sample::Force {
                t_ns,
                force_n: 6000.0 * v - 380.0 + 20.0 * noise(5 * i),
            });
        }
        if i % 1000 == 250 {
            out.push(Sample::TempShock {
                t_ns,
                temperature_c: 25.0 + x * 0.01,
            });
            out.push(Sample::TempAmbient {
                t_ns,
                temperature_c: 21.5,
            });
        }
    }
    out
}
