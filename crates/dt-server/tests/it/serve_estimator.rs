//! The real estimator behind the daemon: what the daemon streams and records
//! equals a direct `dt_core::estimator::Estimator` run over the same samples.

use std::path::PathBuf;
use std::sync::Arc;

use dt_core::estimate::Estimate;
use dt_core::estimator::Estimator;
use dt_core::log::Sample;
use dt_server::server::{self, EstimatorFactory, Listeners};
use tokio::net::TcpListener;
use tokio::sync::oneshot;

use crate::common::{chunked, meta, read_estimates, run_samples, send, test_config, write_stream};

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
    let factory = EstimatorFactory::load(&bundle_dir(), None).unwrap();
    let record = tempfile::tempdir().unwrap();
    let mut config = test_config();
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

    let ingest = TcpListener::bind("127.0.0.1:0").await.unwrap();
    let http = TcpListener::bind("127.0.0.1:0").await.unwrap();
    let addr = ingest.local_addr().unwrap();
    let (stop, stopped) = oneshot::channel::<()>();
    let daemon = tokio::spawn(server::run(
        config,
        Listeners { ingest, http },
        Arc::new(factory),
        async move {
            let _ = stopped.await;
        },
    ));
    let r = send(addr, &stream.bytes, 1500).await;
    assert_eq!(r["status"], "completed", "{r}");
    assert_eq!(r["ticks"], want.len());
    stop.send(()).unwrap();
    daemon.await.unwrap().unwrap();

    let got = read_estimates(&record.path().join("unit-1").join("est.0000.mcap"));
    assert_same(&got, &want);
}
