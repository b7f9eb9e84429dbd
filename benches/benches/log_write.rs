//! Run-log writer and reader throughput: messages per second on one core,
//! with the simulator's topic mix (per 1 ms: one acceleration sample, a
//! position sample every 10, a force sample every 20, temperatures every 1000).

#![allow(missing_docs)]

use std::io::Cursor;

use criterion::{criterion_group, criterion_main, Criterion, Throughput};
use dt_core::log::{
    read_log_bytes, Compression, LogDecoder, LogEvent, LogWriter, RunMetadata, Sample, WriteOptions,
};

/// Samples of `ms` milliseconds of a run (the dyno run the estimator bench reads).
fn samples(ms: i64) -> Vec<Sample> {
    dt_bench::dyno_samples(0, ms, 0.0)
}

fn write(samples: &[Sample], compression: Compression) -> Vec<u8> {
    let meta = RunMetadata {
        asset_id: "bench".into(),
        run_id: "r1".into(),
        ..RunMetadata::default()
    };
    let options = WriteOptions {
        compression,
        ..WriteOptions::default()
    };
    let mut w = LogWriter::new(Cursor::new(Vec::with_capacity(8 << 20)), &meta, options).unwrap();
    for s in samples {
        w.write_sample(s).unwrap();
    }
    w.finish().unwrap().into_inner()
}

fn bench(c: &mut Criterion) {
    let samples = samples(200_000); // 200 s of a run, ~230 k messages
    let mut group = c.benchmark_group("log");
    group.sample_size(10);
    group.throughput(Throughput::Elements(samples.len() as u64));
    for (name, compression) in [
        ("zstd", Compression::Zstd),
        ("lz4", Compression::Lz4),
        ("none", Compression::None),
    ] {
        group.bench_function(format!("write_{name}"), |b| {
            b.iter(|| write(&samples, compression));
        });
    }
    let bytes = write(&samples, Compression::Zstd);
    group.bench_function("read_zstd", |b| {
        b.iter(|| read_log_bytes("bench", &bytes).unwrap());
    });
    // what `shocktwin replay` does with a clean file: decode while reading,
    // 1 MiB at a time, nothing kept
    group.bench_function("stream_zstd", |b| {
        b.iter(|| {
            let mut decoder = LogDecoder::new("bench");
            let mut n = 0usize;
            for piece in bytes.chunks(1 << 20) {
                decoder.feed(piece);
                while let Some(event) = decoder.next_event() {
                    if let Ok(LogEvent::Sample(s)) = event {
                        n += usize::from(s.t_ns() >= 0);
                    }
                }
            }
            decoder.finish().unwrap();
            n
        });
    });
    group.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
