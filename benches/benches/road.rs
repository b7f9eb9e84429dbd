//! The road observer (`dt_core::road`) with the calibration fixture
//! (`crates/dt-core/tests/fixtures/road.json`: 10 s blocks, 0.5 s lag):
//!
//! - `road/observer_60s`: 60 s of a 2 Hz, 80 mm p-p stroke at SPEC rates
//!   through a fresh [`RoadObserver`]: the stroke filter on every sample and
//!   five blocks read (each: the smoother, the force basis through the mount
//!   at 4 kHz, a 10 000 × ~150 least squares by Householder QR). Real-time
//!   factor = 60 s / median; one block ≈ median / 5.
//! - `estimator_60s/{plain,road}`: the same minute through the estimator
//!   with the fixture bundle, without and with the road observer beside it
//!   (the ratio is the observer's share of a road asset's cost).

#![allow(missing_docs)]

use std::path::PathBuf;
use std::sync::Arc;
use std::time::Duration;

use criterion::{criterion_group, criterion_main, Criterion};
use dt_core::bundle::{Bundle, HealthConfig};
use dt_core::estimator::{Estimator, EstimatorConfig};
use dt_core::log::Sample;
use dt_core::road::{RoadCalibration, RoadObserver};

const MS: i64 = 1_000_000;

fn fixture(name: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../crates/dt-core/tests/fixtures")
        .join(name)
}

fn noise(i: i64) -> f64 {
    let x = (i as u64)
        .wrapping_mul(0x9E37_79B9_7F4A_7C15)
        .rotate_left(17);
    (x >> 11) as f64 / (1u64 << 52) as f64 - 1.0
}

/// `ms` milliseconds of a 2 Hz, 80 mm p-p stroke with a friction flip in `a2`.
fn samples(ms: i64) -> Vec<Sample> {
    let w = 2.0 * std::f64::consts::PI * 2.0;
    let amp = 0.04;
    let mut out = Vec::new();
    for i in 0..ms {
        let t_ns = i * MS;
        let x = i as f64 * 1e-3;
        let v = amp * w * (w * x).cos();
        out.push(Sample::Acceleration {
            t_ns,
            a1_mps2: -amp * w * w * (w * x).sin() + 0.3 + 0.05 * noise(i),
            a2_mps2: 1.2 * (v / 0.005).tanh() / 30.0 + 0.05 * noise(i + 7),
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

fn bench_road(c: &mut Criterion) {
    let text = std::fs::read_to_string(fixture("road.json")).expect("road fixture");
    let cal = RoadCalibration::from_json("road.json", &text).expect("road calibration");
    let minute = samples(60_000);
    let mut g = c.benchmark_group("road");
    g.sample_size(10).measurement_time(Duration::from_secs(20));
    g.bench_function("observer_60s", |b| {
        b.iter(|| {
            let mut obs =
                RoadObserver::new(cal.clone(), HealthConfig::default()).expect("observer");
            let mut n = 0;
            for s in &minute {
                obs.push(s);
                n += obs.drain().len();
            }
            obs.finish();
            n + obs.drain().len()
        });
    });
    g.finish();

    let bundle = Arc::new(Bundle::load(fixture("bundle-mlp13")).expect("fixture bundle"));
    let cfg = EstimatorConfig::from_bundle(&bundle);
    let mut g = c.benchmark_group("estimator_60s");
    g.sample_size(10).measurement_time(Duration::from_secs(20));
    for road in [false, true] {
        g.bench_function(if road { "road" } else { "plain" }, |b| {
            b.iter(|| {
                let mut est = Estimator::new(Arc::clone(&bundle), cfg).expect("estimator");
                if road {
                    est = est.with_road(cal.clone()).expect("road");
                }
                let mut n = 0;
                for s in &minute {
                    est.push(*s).expect("push");
                    n += est.drain().count();
                }
                est.finish().expect("finish");
                n + est.drain().count()
            });
        });
    }
    g.finish();
}

criterion_group!(benches, bench_road);
criterion_main!(benches);
