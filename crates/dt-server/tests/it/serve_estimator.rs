//! The real estimator behind the daemon: what the daemon streams and records
//! equals a direct `dt_core::estimator::Estimator` run over the same samples.

use std::path::PathBuf;
use std::sync::Arc;

use dt_core::estimate::Estimate;
use dt_core::estimator::Estimator;
use dt_core::log::Sample;
use dt_server::server::{Config, EstimatorFactory};

use crate::common::{
    chunked, meta, read_estimates, run_samples, send, test_config, write_stream, Daemon,
};

fn bundle_dir() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../dt-core/tests/fixtures/bundle-mlp13")
}

fn same(a: f64, b: f64) -> bool {
    a.to_bits() == b.to_bits() || (a.is_nan() && b.is_nan())
}

fn assert_same(got: &[Estimate], want: &[Estimate]) {
    assert_eq!(got.len(), want.len());
    for (g, w) in got.iter().zip(want) {
        assert_eq!((g.t_ns, g.health), (w.t_ns, w.health));
        for (x, y) in [
            (g.pressure_bar, w.pressure_bar),
            (g.pressure_avg_bar, w.pressure_avg_bar),
            (g.expected_bar, w.expected_bar),
            (g.velocity_mps, w.velocity_mps),
            (g.force_model_n, w.force_model_n),
            (g.oil_temp_c, w.oil_temp_c),
        ] {
            assert!(same(x, y), "t_ns {}: {x} != {y}", g.t_ns);
        }
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn daemon_output_equals_the_estimator_run_directly() {
    // `record.compression` as an operator writes it; the file says which it got.
    for (setting, chunks) in [(None, "zstd"), (Some("lz4"), "lz4"), (Some("none"), "")] {
        let record = setting.map_or(String::new(), |c| {
            format!("[record]\ncompression = {c:?}\n")
        });
        let recorded = Box::pin(daemon_output_against_the_estimator(
            Config::from_toml(&record).unwrap(),
        ))
        .await;
        let summary = mcap::Summary::read(&recorded).unwrap().unwrap();
        assert!(!summary.chunk_indexes.is_empty(), "{setting:?}: no chunk");
        for c in &summary.chunk_indexes {
            assert_eq!(c.compression, chunks, "{setting:?}");
        }
    }
    assert!(Config::from_toml("[record]\ncompression = \"gzip\"\n")
        .unwrap_err()
        .contains("gzip"));
}

/// Streams a run to a daemon with `base`'s record settings, checks its
/// reply and its recording against the estimator run directly; returns the
/// recorded file's bytes.
async fn daemon_output_against_the_estimator(base: Config) -> Vec<u8> {
    let factory = EstimatorFactory::load(&bundle_dir(), None).unwrap();
    let record = tempfile::tempdir().unwrap();
    let mut config = test_config();
    config.record = base.record;
    config.server.record_dir = Some(record.path().to_owned());
    let asset_cfg = config.asset("unit-1");

    let samples: Vec<Sample> = run_samples(1_000_000_000, 3000);
    let stream = write_stream(&meta("unit-1", "est"), &samples, chunked());
    let mut direct = Estimator::new(
        Arc::new(dt_core::bundle::Bundle::load(bundle_dir()).unwrap()),
        factory.config_for(&asset_cfg),
    )
    .unwrap();
    let mut want = Vec::new();
    for s in &samples {
        direct.push(*s).unwrap();
        want.extend(direct.drain());
    }
    direct.finish().unwrap();
    want.extend(direct.drain());
    assert!(want.len() > 100);
    assert!(
        want.iter().any(|e| e.pressure_bar.is_finite()),
        "the model gives pressures"
    );

    let d = Daemon::start_with(config, Arc::new(factory)).await;
    let r = send(d.ingest, &stream.bytes, 1500).await;
    assert_eq!(r["status"], "completed", "{r}");
    assert_eq!(r["ticks"], want.len());
    d.stop().await;

    let path = record.path().join("unit-1").join("est.0000.mcap");
    let got = read_estimates(&path);
    assert_same(&got, &want);
    std::fs::read(path).unwrap()
}

/// A vehicle without a sensor its model reads (here the loadcell of model
/// 13): the run fails naming the topic; it ended `completed` with every
/// pressure NaN.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_run_without_a_sensor_the_model_reads_fails_naming_it() {
    let factory = EstimatorFactory::load(&bundle_dir(), None).unwrap();
    let samples: Vec<Sample> = run_samples(1_000_000_000, 3000)
        .into_iter()
        .filter(|s| !matches!(s, Sample::Force { .. }))
        .collect();
    let stream = write_stream(&meta("unit-2", "no-loadcell"), &samples, chunked());
    let d = Daemon::start_with(test_config(), Arc::new(factory)).await;
    let r = send(d.ingest, &stream.bytes, 1500).await;
    assert_eq!(r["status"], "failed", "{r}");
    assert_eq!(r["kind"], "twin", "{r}");
    let reason = r["reason"].as_str().unwrap();
    assert!(reason.contains(r#"lacks topics ["/force"]"#), "{r}");
    d.stop().await;
}
