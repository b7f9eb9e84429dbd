//! Simulator speed: the truth plant alone, and a whole quick run with its
//! sensors and MCAP writing (in memory). The campaign figure of the report
//! comes from `time shocktwin simulate` (files on disk, both cores).

// criterion_group! generates an undocumented pub function.
#![allow(missing_docs)]

use std::io::Cursor;

use criterion::{criterion_group, criterion_main, Criterion, Throughput};
use dt_core::log::{LogWriter, WriteOptions};
use dt_sim::{simulate_run_with, Plant, PlantConfig, PlantParams, RunSpec, SimError};

fn plant_seconds(p: &PlantParams, seconds: f64) -> f64 {
    let config = PlantConfig {
        charge_bar: 12.0,
        frequency_hz: 2.0,
        stroke_pp_m: 0.08,
        excitation_start_s: 0.0,
        road: None,
    };
    let mut plant = Plant::with_seed(p, &config, 1).expect("plant");
    let steps = (seconds / plant.dt_s()).round() as u64;
    let mut acc = 0.0;
    for _ in 0..steps {
        acc += plant.step().expect("step").force_n;
    }
    acc
}

fn bench(c: &mut Criterion) {
    let p = PlantParams::nominal();
    let mut g = c.benchmark_group("simulate");
    g.sample_size(10);

    // 10 simulated seconds = 40 000 sub-steps.
    g.throughput(Throughput::Elements(40_000));
    g.bench_function("plant_10s_2hz_substeps", |b| {
        b.iter(|| plant_seconds(&p, 10.0));
    });

    // A quick run: 70 simulated seconds, 88 347 messages (incl. truth).
    let spec = RunSpec {
        quick: true,
        ..RunSpec::paper(12.0, 4.0, 1)
    };
    g.throughput(Throughput::Elements(88_347));
    g.bench_function("quick_run_12bar_4hz_mcap_messages", |b| {
        b.iter(|| {
            let mut w = LogWriter::new(
                Cursor::new(Vec::with_capacity(3 << 20)),
                &spec.metadata(),
                WriteOptions::default(),
            )
            .expect("writer");
            let summary = simulate_run_with(&spec, &p, |s| {
                w.write_sample(s).map_err(|source| SimError::Log {
                    run_id: spec.run_id(),
                    source: Box::new(source),
                })
            })
            .expect("run");
            let bytes = w.finish().expect("finish").into_inner();
            (summary.messages, bytes.len())
        });
    });
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
