//! The streaming estimator with the fixture bundle (`crates/dt-core/tests/fixtures/bundle-mlp13`:
//! permutation 13, 4 × 64 `ReLU` MLP, random float64 weights):
//!
//! - `estimator/tick`: one 50 Hz tick — pushing its samples (20 accelerometer,
//!   2 potentiometer, 1 loadcell, temperatures once a second) through the
//!   re-order window, the Kalman filter, boxcars, thermal and force models,
//!   the MLP, the 1 s average and the health machine, and taking its estimate;
//! - `bundle/predict_one_{dense,f64,tract}`: the network alone on one row:
//!   the float32 SIMD path the estimator runs, the float64 dense path it
//!   replaced (`predict_f64`, one row, its result `Vec` included) and tract;
//! - `replay_1h/*`: one hour of one asset (≈ 4.15 M messages, a zstd MCAP in
//!   memory written once by `LogWriter`): `read_log_bytes` alone, the
//!   estimator alone, and both (what `shocktwin replay` does per file). Real
//!   time factor = 3600 s / median.

#![allow(missing_docs)]

use std::io::Cursor;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::Duration;

use criterion::{criterion_group, criterion_main, Criterion, Throughput};
use dt_core::bundle::Bundle;
use dt_core::estimator::{estimate_log, Estimator, EstimatorConfig};
use dt_core::log::{read_log_bytes, LogWriter, RunMetadata, Sample, WriteOptions};

const MS: i64 = 1_000_000;

fn bundle() -> Arc<Bundle> {
    let dir = PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../crates/dt-core/tests/fixtures/bundle-mlp13");
    Arc::new(Bundle::load(dir).expect("fixture bundle"))
}

/// `ms` milliseconds of a 2 Hz, 80 mm p-p dyno run at SPEC rates, in time order.
fn samples(t0: i64, ms: i64) -> Vec<Sample> {
    dt_bench::dyno_samples(t0, ms, 0.0)
}

fn bench_tick(c: &mut Criterion) {
    const PERIOD_MS: i64 = 10_000;
    let b = bundle();
    // 10 s of samples grouped by tick; replayed with a growing time offset
    // (the sine is periodic in 0.5 s), so the estimator runs for ever.
    let pattern = samples(0, PERIOD_MS);
    let mut ticks: Vec<Vec<Sample>> = vec![Vec::new(); (PERIOD_MS / 20) as usize];
    for s in pattern {
        ticks[(s.t_ns() / (20 * MS)) as usize].push(s);
    }
    // A copy of `s` at `t_ns + dt` (only the variants `samples` writes).
    let shift = |s: Sample, dt: i64| match s {
        Sample::Acceleration {
            t_ns,
            a1_mps2,
            a2_mps2,
        } => Sample::Acceleration {
            t_ns: t_ns + dt,
            a1_mps2,
            a2_mps2,
        },
        Sample::Position { t_ns, position_m } => Sample::Position {
            t_ns: t_ns + dt,
            position_m,
        },
        Sample::Force { t_ns, force_n } => Sample::Force {
            t_ns: t_ns + dt,
            force_n,
        },
        Sample::TempShock {
            t_ns,
            temperature_c,
        } => Sample::TempShock {
            t_ns: t_ns + dt,
            temperature_c,
        },
        Sample::TempAmbient {
            t_ns,
            temperature_c,
        } => Sample::TempAmbient {
            t_ns: t_ns + dt,
            temperature_c,
        },
        other => other,
    };
    let mut est = Estimator::new(Arc::clone(&b), EstimatorConfig::from_bundle(&b)).unwrap();
    let (mut k, mut offset, mut out) = (0usize, 0i64, 0u64);
    let mut group = c.benchmark_group("estimator");
    group.throughput(Throughput::Elements(1));
    group.bench_function("tick", |bench| {
        bench.iter(|| {
            for s in &ticks[k] {
                est.push(shift(*s, offset)).unwrap();
            }
            for e in est.drain() {
                out += u64::from(e.pressure_bar.is_finite());
            }
            k += 1;
            if k == ticks.len() {
                k = 0;
                offset += PERIOD_MS * MS;
            }
        });
    });
    group.finish();
    assert!(out > 0, "the estimator gave no pressure");

    let row: Vec<f64> = b.twin.normalisation.mean.iter().map(|m| m + 0.1).collect();
    let mut group = c.benchmark_group("bundle");
    group.bench_function("predict_one_dense", |bench| {
        bench.iter(|| b.predict_one(std::hint::black_box(&row)).unwrap());
    });
    group.bench_function("predict_one_f64", |bench| {
        bench.iter(|| b.predict_f64(std::hint::black_box(&row)).unwrap());
    });
    group.bench_function("predict_one_tract", |bench| {
        bench.iter(|| b.predict_reference(std::hint::black_box(&row)).unwrap());
    });
    group.finish();
}

/// One hour of one asset as a zstd MCAP in memory.
fn one_hour_log() -> (Vec<u8>, usize) {
    let meta = RunMetadata {
        asset_id: "bench-unit".into(),
        run_id: "bench-1h".into(),
        ..RunMetadata::default()
    };
    let mut w = LogWriter::new(
        Cursor::new(Vec::with_capacity(64 << 20)),
        &meta,
        WriteOptions::default(),
    )
    .unwrap();
    let mut n = 0;
    for minute in 0..60 {
        for s in samples(minute * 60_000 * MS, 60_000) {
            w.write_sample(&s).unwrap();
            n += 1;
        }
    }
    (w.finish().unwrap().into_inner(), n)
}

fn bench_replay(c: &mut Criterion) {
    let b = bundle();
    let cfg = EstimatorConfig::from_bundle(&b);
    let (bytes, n_messages) = one_hour_log();
    let log = read_log_bytes("bench-1h", &bytes).unwrap();
    eprintln!(
        "replay_1h: {n_messages} messages, {:.1} MiB zstd MCAP",
        bytes.len() as f64 / f64::from(1 << 20)
    );
    let mut group = c.benchmark_group("replay_1h");
    group.sample_size(10);
    group.measurement_time(Duration::from_secs(40));
    group.throughput(Throughput::Elements(n_messages as u64));
    group.bench_function("read_log_bytes", |bench| {
        bench.iter(|| read_log_bytes("bench-1h", &bytes).unwrap());
    });
    group.bench_function("estimate_log", |bench| {
        bench.iter(|| estimate_log(Arc::clone(&b), cfg, &log).unwrap());
    });
    group.bench_function("read_and_estimate", |bench| {
        bench.iter(|| {
            let log = read_log_bytes("bench-1h", &bytes).unwrap();
            estimate_log(Arc::clone(&b), cfg, &log).unwrap()
        });
    });
    group.finish();
}

criterion_group!(benches, bench_tick, bench_replay);
criterion_main!(benches);
