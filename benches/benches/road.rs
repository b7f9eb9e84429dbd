//! The road observer (`dt_core::road`) with the calibration fixture
//! (`crates/dt-core/tests/fixtures/road.json`: 10 s blocks, 0.5 s lag):
//!
//! - `road/observer_60s`: 60 s of a 2 Hz, 80 mm p-p stroke at SPEC rates
//!   through a fresh [`RoadObserver`]: the stroke filter on every sample and
//!   five blocks read (each: the smoother, the force basis through the mount
//!   at 4 kHz, a 10 000 × ~150 least squares by scaled normal equations
//!   refined once). Real-time
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
use dt_core::road::{RoadCalibration, RoadObserver};

fn fixture(name: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../crates/dt-core/tests/fixtures")
        .join(name)
}

fn bench_road(c: &mut Criterion) {
    let text = std::fs::read_to_string(fixture("road.json")).expect("road fixture");
    let cal = RoadCalibration::from_json("road.json", &text).expect("road calibration");
    let minute = dt_bench::dyno_samples(0, 60_000, 1.2);
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
