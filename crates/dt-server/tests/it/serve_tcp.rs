//! TCP ingest over real sockets: concurrent good and bad MCAP streams sent
//! in small pieces; every tick of the good ones accounted for, each bad one
//! closed with its reason, the daemon unaffected.

use std::time::Duration;

use dt_core::log::{Compression, WriteOptions};
use dt_server::server::config::AssetOverrides;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;

use crate::common::{
    files_in, good_stream, meta, metric, nan_out_of_order_stream, read_estimates, run_samples,
    send, test_config, truncate_mid_chunk, write_stream, wrong_schema_stream, Daemon, TICK_NS,
};

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
#[allow(clippy::too_many_lines)] // one scenario, checked from every side
async fn concurrent_streams_good_and_bad() {
    let record = tempfile::tempdir().unwrap();
    let mut config = test_config();
    config.server.record_dir = Some(record.path().to_owned());
    config.assets.insert(
        "pump-2".into(),
        AssetOverrides {
            nominal_bar: Some(10.0),
            ..AssetOverrides::default()
        },
    );
    let d = Daemon::start(config).await;

    let good1 = good_stream("pump-1", "r1", 1_000_000_000_000, 2000);
    let good2 = good_stream("pump-2", "r1", 5_000_000_000_000, 1500);
    let good3 = write_stream(
        &meta("pump-3", "lz4"),
        &run_samples(7_000_000_000, 1200),
        WriteOptions {
            compression: Compression::Lz4,
            chunk_size: Some(16 << 10),
        },
    );
    let (nan, nans, swaps) = nan_out_of_order_stream("pump-4", "nan", 3_000_000_000);
    let full5 = good_stream("pump-5", "cut", 9_000_000_000, 3000);
    let truncated = truncate_mid_chunk(&full5.bytes);
    let schema = wrong_schema_stream("pump-6", "schema", 2_000_000_000);
    let too_large = write_stream(
        &meta("pump-7", "big"),
        &run_samples(0, 2000),
        WriteOptions {
            compression: Compression::None,
            chunk_size: Some(1 << 20),
        },
    );
    assert!(too_large.bytes.len() > 64 << 10);
    let junk = b"GET / HTTP/1.1\r\nHost: example\r\n\r\n".repeat(50);

    let inputs: Vec<(&str, Vec<u8>, usize)> = vec![
        ("good1", good1.bytes.clone(), 997),
        ("good2", good2.bytes.clone(), 1500),
        ("good3", good3.bytes.clone(), 4096),
        ("nan", nan.bytes.clone(), 613),
        ("truncated", truncated, 1024),
        ("schema", schema, 777),
        ("too_large", too_large.bytes.clone(), 8192),
        ("junk", junk, 100),
    ];
    let addr = d.ingest;
    let tasks: Vec<_> = inputs
        .into_iter()
        .map(|(name, bytes, piece)| {
            tokio::spawn(async move { (name, send(addr, &bytes, piece).await) })
        })
        .collect();
    let mut reports = std::collections::HashMap::new();
    for t in tasks {
        let (name, report) = t.await.unwrap();
        reports.insert(name, report);
    }

    // Good streams: every sample decoded, every tick estimated and flushed.
    for (name, s) in [
        ("good1", &good1),
        ("good2", &good2),
        ("good3", &good3),
        ("nan", &nan),
    ] {
        let r = &reports[name];
        assert_eq!(r["status"], "completed", "{name}: {r}");
        assert_eq!(r["samples"], s.samples, "{name}: {r}");
        assert_eq!(r["ticks"], s.ticks, "{name}: {r}");
        assert_eq!(r["flushed"], true, "{name}: {r}");
    }
    assert_eq!(good1.ticks, 99);
    // Bad streams: closed with the reason; the good data before the error estimated.
    let r = &reports["truncated"];
    assert_eq!(
        (r["status"].as_str(), r["kind"].as_str()),
        (Some("failed"), Some("truncated")),
        "{r}"
    );
    let partial = r["ticks"].as_u64().unwrap();
    assert!(partial > 0 && partial < full5.ticks, "{r}");
    let r = &reports["schema"];
    assert_eq!(r["kind"], "schema", "{r}");
    assert!(r["reason"].as_str().unwrap().contains("/position"), "{r}");
    assert_eq!(
        r["ticks"], 24,
        "500 ms of good data before the bad channel: {r}"
    );
    let r = &reports["too_large"];
    assert_eq!(r["kind"], "too_large", "{r}");
    let r = &reports["junk"];
    assert_eq!(r["kind"], "invalid_mcap", "{r}");
    assert_eq!(r["asset_id"], serde_json::Value::Null);

    // The API sees the same.
    assert_eq!(d.asset_ticks("pump-1").await, good1.ticks);
    assert_eq!(d.asset_ticks("pump-5").await, partial);
    let v = d.get_json("/v1/assets").await;
    let pump2 = v["assets"]
        .as_array()
        .unwrap()
        .iter()
        .find(|a| a["asset_id"] == "pump-2")
        .unwrap()
        .clone();
    assert_eq!(pump2["expected_bar"], 10.0, "per-asset config: {pump2}");
    assert_eq!(pump2["health"], "unknown");
    assert!(
        pump2["pressure_bar"].is_null(),
        "placeholder twin: no pressure"
    );
    assert_eq!(pump2["last_run_status"], "completed");
    // Its log does not say whether it is simulated: neither does the API.
    assert!(pump2["simulated"].is_null(), "{pump2}");
    assert_eq!(
        pump2["last_t_ns"].as_i64().unwrap(),
        good2.t0_ns + good2.ticks as i64 * TICK_NS
    );
    let pump5 = d.get_json("/v1/assets/pump-5").await;
    assert_eq!(pump5["last_run_status"], "failed");
    assert!(
        pump5["last_run_reason"]
            .as_str()
            .unwrap()
            .contains("truncated"),
        "{pump5}"
    );

    let detail = d.get_json("/v1/assets/pump-1?history=5").await;
    let hist = detail["history"].as_array().unwrap();
    assert_eq!(hist.len(), 5);
    let last_t = good1.t0_ns + good1.ticks as i64 * TICK_NS;
    assert_eq!(hist[4]["t_ns"].as_i64().unwrap(), last_t);
    assert_eq!(hist[0]["t_ns"].as_i64().unwrap(), last_t - 4 * TICK_NS);
    let all = d.get_json("/v1/assets/pump-1").await;
    assert_eq!(
        all["history"].as_array().unwrap().len(),
        50,
        "bounded by history_len"
    );
    assert_eq!(d.get("/v1/assets/nope").await.status(), 404);

    // Metrics: errors by kind, connections, messages, ticks, anomalies, lag.
    // A closed connection leaves the active gauge once its task has ended,
    // which a loaded machine can put a moment after the client saw its report.
    let mut m = d.metrics().await;
    for _ in 0..100 {
        if metric(&m, "shocktwin_connections_active") == Some(0.0) {
            break;
        }
        tokio::time::sleep(std::time::Duration::from_millis(50)).await;
        m = d.metrics().await;
    }
    for kind in ["truncated", "schema", "too_large", "invalid_mcap"] {
        assert_eq!(
            metric(&m, &format!("shocktwin_errors_total{{kind=\"{kind}\"}}")),
            Some(1.0),
            "{kind}\n{m}"
        );
    }
    assert_eq!(metric(&m, "shocktwin_connections_total"), Some(8.0), "{m}");
    assert_eq!(metric(&m, "shocktwin_connections_active"), Some(0.0), "{m}");
    let decoded: u64 = reports
        .values()
        .map(|r| r["samples"].as_u64().unwrap())
        .sum();
    assert_eq!(
        metric(&m, "shocktwin_messages_total{source=\"tcp\"}"),
        Some(decoded as f64),
        "{m}"
    );
    assert_eq!(
        metric(&m, "shocktwin_ticks_total{asset=\"pump-1\"}"),
        Some(good1.ticks as f64)
    );
    assert_eq!(
        metric(&m, "shocktwin_input_anomalies_total{kind=\"nan_samples\"}"),
        Some(nans as f64),
        "{m}"
    );
    assert_eq!(
        metric(&m, "shocktwin_input_anomalies_total{kind=\"out_of_order\"}"),
        Some(swaps as f64),
        "{m}"
    );
    assert!(nans > 0 && swaps > 0);
    assert_eq!(
        metric(&m, "shocktwin_runs_total{kind=\"completed\"}"),
        Some(4.0)
    );
    assert_eq!(
        metric(&m, "shocktwin_runs_total{kind=\"failed\"}"),
        Some(4.0)
    );
    // Sample times near the epoch: the lag is large and positive.
    let lag = metric(&m, "shocktwin_asset_lag_seconds{asset=\"pump-1\"}").unwrap();
    assert!(lag > 1e8, "lag {lag}");

    // Recorded estimates: every tick of the good run, in order.
    let files = files_in(&record.path().join("pump-1"));
    assert_eq!(files.len(), 1, "{files:?}");
    assert!(files[0].ends_with("pump-1/r1.0000.mcap"));
    let est = read_estimates(&files[0]);
    assert_eq!(est.len() as u64, good1.ticks);
    for (k, e) in est.iter().enumerate() {
        assert_eq!(e.t_ns, good1.t0_ns + (k as i64 + 1) * TICK_NS);
        assert!(e.pressure_bar.is_nan());
    }
    let cut = read_estimates(&files_in(&record.path().join("pump-5"))[0]);
    assert_eq!(cut.len() as u64, partial, "the partial run is recorded too");

    // Still serving.
    assert_eq!(d.get("/healthz").await.status(), 200);
    assert_eq!(d.get("/readyz").await.status(), 200);
    let again = good_stream("pump-1", "r2", 2_000_000_000_000, 500);
    let r = send(d.ingest, &again.bytes, 2048).await;
    assert_eq!(r["status"], "completed", "{r}");
    assert_eq!(r["ticks"], again.ticks);
    d.stop().await;
}

/// Reads the one reply line of a refused connection.
/// The per-connection memory cap: a chunk that is small on the wire but
/// declares more uncompressed bytes than `limits.max_chunk_uncompressed_bytes`
/// is refused before it is decompressed; a stream beside it is unaffected.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_chunk_over_the_uncompressed_cap_is_refused_and_others_carry_on() {
    let mut config = test_config();
    config.limits.max_record_bytes = 1 << 20;
    config.limits.max_chunk_uncompressed_bytes = 64 << 10;
    assert_eq!(
        config.limits.connection_memory_bound(),
        (1 << 20) + (64 << 10) + (64 << 10)
    );
    let d = Daemon::start(config).await;
    let bomb = write_stream(
        &meta("pump-bomb", "r1"),
        &run_samples(0, 4000),
        WriteOptions {
            compression: Compression::Zstd,
            chunk_size: Some(512 << 10),
        },
    );
    // Small on the wire: the cap is on the uncompressed size, not the record.
    assert!(bomb.bytes.len() < 1 << 20, "{}", bomb.bytes.len());
    let good = good_stream("pump-good", "r1", 1_000_000_000_000, 2000);
    let (r_bomb, r_good) = tokio::join!(
        send(d.ingest, &bomb.bytes, 4096),
        send(d.ingest, &good.bytes, 4096)
    );
    assert_eq!(r_bomb["kind"], "too_large", "{r_bomb}");
    assert!(
        r_bomb["reason"].as_str().unwrap().contains("uncompressed"),
        "{r_bomb}"
    );
    assert_eq!(r_good["status"], "completed", "{r_good}");
    assert_eq!(r_good["ticks"], good.ticks, "{r_good}");
    let metrics = d.metrics().await;
    assert_eq!(
        metric(&metrics, "shocktwin_errors_total{kind=\"too_large\"}"),
        Some(1.0),
        "{metrics}"
    );
}

async fn refused_reply(addr: std::net::SocketAddr) -> serde_json::Value {
    let mut c = TcpStream::connect(addr).await.unwrap();
    let mut reply = String::new();
    tokio::time::timeout(Duration::from_secs(5), c.read_to_string(&mut reply))
        .await
        .expect("a refused client is answered at once, not left waiting")
        .unwrap();
    serde_json::from_str(reply.trim()).unwrap()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn connections_beyond_the_limit_are_refused_at_once() {
    let mut config = test_config();
    config.limits.max_connections = 1;
    let d = Daemon::start(config).await;
    let first = good_stream("hold", "r1", 0, 1000);
    // The first client sends half its stream and keeps the connection open.
    let mut holder = TcpStream::connect(d.ingest).await.unwrap();
    holder
        .write_all(&first.bytes[..first.bytes.len() / 2])
        .await
        .unwrap();
    crate::common::wait_until("the first connection", || async {
        metric(&d.metrics().await, "shocktwin_connections_active") == Some(1.0)
    })
    .await;
    let r = refused_reply(d.ingest).await;
    assert_eq!(r["status"], "refused", "{r}");
    assert!(
        r["reason"]
            .as_str()
            .unwrap()
            .contains("limit of 1 connections"),
        "{r}"
    );
    // The first client finishes; the next one is served.
    holder
        .write_all(&first.bytes[first.bytes.len() / 2..])
        .await
        .unwrap();
    holder.shutdown().await.unwrap();
    let mut reply = String::new();
    holder.read_to_string(&mut reply).await.unwrap();
    assert!(reply.contains("\"completed\""), "{reply}");
    // The slot is given back when the connection's task ends, just after its
    // reply: a client that reconnects within that instant is refused (it
    // was, once, in a clean-clone run), so wait for it as a vehicle's retry would.
    crate::common::wait_until("the first connection's slot", || async {
        metric(&d.metrics().await, "shocktwin_connections_active") == Some(0.0)
    })
    .await;
    let next = good_stream("next", "r1", 0, 600);
    let r = send(d.ingest, &next.bytes, 1000).await;
    assert_eq!(r["status"], "completed", "{r}");
    assert_eq!(r["ticks"], next.ticks);
    let m = d.metrics().await;
    assert!(m.contains("kind=\"refused_max_connections\""), "{m}");
    d.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn silent_connections_neither_lock_out_vehicles_nor_keep_their_slots() {
    // The issue's attack, scaled down: as many silent sockets as the daemon allows
    // one address, from one address.
    let mut config = test_config();
    config.limits.max_connections = 8;
    config.limits.max_connections_per_peer = 4;
    // Long enough that the fifth connection is tried while the four are
    // still open, on a loaded machine too.
    config.limits.first_data_timeout_s = 5.0;
    let d = Daemon::start(config).await;
    let mut silent = Vec::new();
    for _ in 0..4 {
        silent.push(TcpStream::connect(d.ingest).await.unwrap());
    }
    crate::common::wait_until("the silent connections", || async {
        metric(&d.metrics().await, "shocktwin_connections_active") == Some(4.0)
    })
    .await;
    // A fifth from the same address is refused at once, naming the per-peer limit ...
    let r = refused_reply(d.ingest).await;
    assert!(
        r["reason"]
            .as_str()
            .unwrap()
            .contains("the most one address may have"),
        "{r}"
    );
    // ... and the silent ones are closed after first_data_timeout_s, freeing their slots.
    for mut c in silent {
        let mut buf = Vec::new();
        let n = tokio::time::timeout(crate::common::WAIT, c.read_to_end(&mut buf))
            .await
            .expect("a silent connection is closed after first_data_timeout_s");
        assert!(n.is_ok());
    }
    let s = good_stream("vehicle", "r1", 0, 600);
    let r = send(d.ingest, &s.bytes, 1000).await;
    assert_eq!(r["status"], "completed", "{r}");
    let m = d.metrics().await;
    assert!(m.contains("kind=\"first_data_timeout\""), "{m}");
    assert!(m.contains("kind=\"refused_per_peer\""), "{m}");
    d.stop().await;
}

/// Time matters here: with the clock paused, the idle timeout fires as soon
/// as the daemon has nothing else to do, deterministically.
#[tokio::test(start_paused = true)]
async fn idle_connection_is_closed_with_its_estimates_kept() {
    let mut config = test_config();
    config.limits.idle_timeout_s = 30.0;
    let d = Daemon::start(config).await;
    let s = good_stream("idle", "r1", 0, 2000);
    let mut c = TcpStream::connect(d.ingest).await.unwrap();
    let cut = crate::common::top_level_records(&s.bytes)
        .into_iter()
        .filter(|&(_, op, _)| op == 0x06)
        .nth(3)
        .map(|(off, _, _)| off)
        .unwrap();
    c.write_all(&s.bytes[..cut]).await.unwrap();
    let t0 = tokio::time::Instant::now();
    let mut reply = String::new();
    c.read_to_string(&mut reply).await.unwrap();
    let r: serde_json::Value = serde_json::from_str(reply.trim()).unwrap();
    assert_eq!(r["kind"], "idle_timeout", "{r}");
    assert!(t0.elapsed() >= Duration::from_secs(30));
    let ticks = r["ticks"].as_u64().unwrap();
    assert!(ticks > 0 && ticks < s.ticks, "{r}");
    // No timeouts around real I/O while the clock is paused.
    let v: serde_json::Value = d
        .client
        .get(d.url("/v1/assets/idle"))
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    assert_eq!(v["ticks"], ticks);
    assert_eq!(v["last_run_status"], "failed");
    d.stop_untimed().await;
}

/// `limits.max_ingest_bytes_per_s_per_peer`: one address's streams together
/// are read no faster than the rate (beyond one second of burst), and are
/// slowed down, not cut off: both runs complete with every tick. Only a lower
/// bound on the time is asserted (a loaded machine can only be slower).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_peer_over_its_byte_rate_is_slowed_not_cut_off() {
    let a = good_stream("rate-a", "r1", 0, 3_000);
    let b = good_stream("rate-b", "r1", 0, 3_000);
    let total = (a.bytes.len() + b.bytes.len()) as u64;
    // About five seconds' worth at the limit.
    let rate = (total / 5).max(4096);
    let mut config = test_config();
    config.limits.max_ingest_bytes_per_s_per_peer = rate;
    let d = Daemon::start(config).await;
    assert!(
        total > 3 * rate,
        "{total} bytes: too few to measure a rate of {rate}"
    );
    let started = std::time::Instant::now();
    let (ra, rb) = tokio::join!(
        send(d.ingest, &a.bytes, 4096),
        send(d.ingest, &b.bytes, 4096)
    );
    let took = started.elapsed().as_secs_f64();
    for (r, s) in [(&ra, &a), (&rb, &b)] {
        assert_eq!(r["status"], "completed", "{r}");
        assert_eq!(r["ticks"].as_u64(), Some(s.ticks), "{r}");
    }
    let floor = (total - rate) as f64 / rate as f64;
    assert!(
        took >= 0.9 * floor,
        "{total} bytes in {took:.2} s: faster than {rate} B/s allows ({floor:.2} s)"
    );
    d.stop().await;
}

/// A run ends at its file's footer and end magic, without a half-close (a
/// TLS client may have none): the end magic arriving in a later read than
/// the footer completes it too (the run was taken for truncated when the
/// daemon ended it at the footer before the magic came).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_run_ends_at_its_end_magic_without_a_half_close() {
    let d = Daemon::start(test_config()).await;
    let s = good_stream("whole", "r1", 0, 3000);
    let mut c = TcpStream::connect(d.ingest).await.unwrap();
    c.write_all(&s.bytes[..s.bytes.len() - 8]).await.unwrap();
    // the last chunk is read, and the footer with it (one write)
    crate::common::wait_until("the last chunk to be read", || async {
        d.asset_ticks("whole").await >= s.ticks - 1
    })
    .await;
    c.write_all(&s.bytes[s.bytes.len() - 8..]).await.unwrap();
    let mut reply = String::new();
    c.read_to_string(&mut reply).await.unwrap();
    let r: serde_json::Value = serde_json::from_str(reply.trim()).unwrap();
    assert_eq!(r["status"], "completed", "{r}");
    assert_eq!(r["ticks"], s.ticks, "{r}");
    d.stop().await;
}

/// Undecodable messages are skipped and the run goes on; the run's report
/// says how many and why the first was (before, only the log said so).
/// A run of `duration_ms` with, after every `every`-th sample (from the
/// `every / 2`-th), a message on a second `/acceleration` channel whose
/// field is not a number: the stream, its good samples and its bad messages.
fn with_bad_messages(asset: &str, duration_ms: i64, every: usize) -> (Vec<u8>, u64, u64) {
    let samples = run_samples(0, duration_ms);
    let mut w = dt_core::log::LogWriter::new(
        std::io::Cursor::new(Vec::new()),
        &meta(asset, "r1"),
        crate::common::chunked(),
    )
    .unwrap();
    let (_, acc) = dt_core::log::topic_spec("/acceleration").unwrap();
    let schema = dt_core::log::json_schema(acc);
    let mut bad = 0_u64;
    for (i, s) in samples.iter().enumerate() {
        w.write_sample(s).unwrap();
        if i % every == every / 2 {
            let wrong = serde_json::json!({"a1_mps2": "1,5", "a2_mps2": 0.0});
            w.write_json("/acceleration", &schema, s.t_ns(), &wrong)
                .unwrap();
            bad += 1;
        }
    }
    (w.finish().unwrap().into_inner(), samples.len() as u64, bad)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_run_reports_the_messages_it_skipped() {
    let d = Daemon::start(test_config()).await;
    let (bytes, samples, skipped) = with_bad_messages("skips", 3000, 1000);
    let r = send(d.ingest, &bytes, 4096).await;
    assert_eq!(r["status"], "completed", "{r}");
    assert_eq!(r["samples"], samples, "{r}");
    assert_eq!(r["skipped_messages"], skipped, "{r}");
    let first = r["first_skipped"].as_str().unwrap_or_default();
    assert!(
        first.contains("/acceleration") && first.contains("a1_mps2"),
        "{r}"
    );
    // A run with none says 0 and no reason.
    let r = send(d.ingest, &good_stream("clean", "r1", 0, 1000).bytes, 4096).await;
    assert_eq!(r["skipped_messages"], 0, "{r}");
    assert!(r.get("first_skipped").is_none(), "{r}");
    d.stop().await;
}

/// A clock that jumps back mid-run: its samples are too late for the
/// reordering window and dropped. The run completed with a third of its
/// data lost, and only the fleet-wide counters said so (a helper's trial):
/// the run's report counts them, beside the counter.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_run_says_how_many_samples_it_could_not_use() {
    let d = Daemon::start(test_config()).await;
    // from 2 s on, the clock reads 1 s earlier
    let samples: Vec<_> = run_samples(0, 3000)
        .into_iter()
        .map(|s| {
            if s.t_ns() >= 2_000_000_000 {
                s.shifted(-1_000_000_000)
            } else {
                s
            }
        })
        .collect();
    let jumped = write_stream(&meta("jumps", "r1"), &samples, crate::common::chunked());
    let r = send(d.ingest, &jumped.bytes, 4096).await;
    assert_eq!(r["status"], "completed", "{r}");
    let dropped = r["dropped_samples"].as_u64().unwrap();
    assert!(dropped > 0, "{r}");
    let counted = metric(
        &d.metrics().await,
        r#"shocktwin_input_anomalies_total{kind="dropped_late"}"#,
    );
    assert_eq!(counted, Some(dropped as f64), "{r}");
    assert_eq!(r["clock_jumps"], 0, "{r}");
    // A run without says 0.
    let r = send(d.ingest, &good_stream("steady", "r1", 0, 1000).bytes, 4096).await;
    assert_eq!(r["dropped_samples"], 0, "{r}");
    d.stop().await;
}

/// A logger that writes one field wrong in every message wrote one warning
/// a message (a helper's trial: 50 lines for 50): the first few are said,
/// then that the rest are counted; the report has the count.
#[tokio::test(flavor = "current_thread")]
async fn skipped_messages_are_logged_a_few_times_then_counted() {
    use std::sync::{Arc, Mutex};
    #[derive(Clone, Default)]
    struct Lines(Arc<Mutex<Vec<u8>>>);
    impl std::io::Write for Lines {
        fn write(&mut self, b: &[u8]) -> std::io::Result<usize> {
            self.0.lock().unwrap().extend_from_slice(b);
            Ok(b.len())
        }
        fn flush(&mut self) -> std::io::Result<()> {
            Ok(())
        }
    }
    let lines = Lines::default();
    let writer = lines.clone();
    // this test's thread only: the ingest task runs on it (a current-thread runtime)
    let _log = tracing::subscriber::set_default(
        tracing_subscriber::fmt()
            .with_ansi(false)
            .with_writer(move || writer.clone())
            .finish(),
    );
    let d = Daemon::start(test_config()).await;
    let (bytes, _, bad) = with_bad_messages("noisy", 2000, 100);
    let r = send(d.ingest, &bytes, 4096).await;
    assert_eq!(r["skipped_messages"], bad, "{r}");
    d.stop().await;
    let text = String::from_utf8(lines.0.lock().unwrap().clone()).unwrap();
    let said = text.matches("skipped message:").count();
    assert!(bad > 20 && said == 6, "{said} of {bad} said:\n{text}");
    assert!(text.contains("further skipped messages of this stream are counted"));
}
