//! Shared helpers: a daemon on `127.0.0.1:0` with the placeholder twin,
//! MCAP streams built in memory (good, NaN/out-of-order, wrong schema,
//! truncated mid-chunk, oversized chunk, not MCAP), a client that sends them
//! in small pieces, and readers of the HTTP API and of recorded files.

use std::collections::BTreeMap;
use std::io::Cursor;
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Duration;

use dt_core::estimate::Estimate;
use dt_core::log::{
    json_schema, topic_spec, Compression, LogWriter, RunMetadata, Sample, WriteOptions,
};
use dt_server::server::{self, Config, Listeners, ServeError, TickCounterFactory};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::oneshot;
use tokio::task::JoinHandle;

/// Generous bound on any wait of a real-time test (they take well under a second).
pub const WAIT: Duration = Duration::from_secs(30);
/// 50 Hz tick, ns.
pub const TICK_NS: i64 = 20_000_000;

/// A running daemon.
pub struct Daemon {
    pub ingest: SocketAddr,
    pub http: SocketAddr,
    stop: Option<oneshot::Sender<()>>,
    task: JoinHandle<Result<(), ServeError>>,
    pub client: reqwest::Client,
}

/// The test configuration: small limits, everything else default.
pub fn test_config() -> Config {
    let mut c = Config::default();
    c.limits.max_record_bytes = 64 << 10;
    c.limits.max_chunk_uncompressed_bytes = 256 << 10;
    c.limits.queue_depth = 64;
    c.limits.history_len = 50;
    c.server.inbox_rescan_s = 0.2;
    c.server.inbox_settle_s = 0.3;
    c
}

impl Daemon {
    /// Binds `127.0.0.1:0` twice and runs the daemon with the placeholder twin.
    pub async fn start(config: Config) -> Daemon {
        Self::start_with(config, Arc::new(TickCounterFactory)).await
    }

    /// As [`Daemon::start`], with the twins of `twins` (a bundle's estimator).
    pub async fn start_with(config: Config, twins: Arc<dyn server::TwinFactory>) -> Daemon {
        let ingest = TcpListener::bind("127.0.0.1:0").await.unwrap();
        let http = TcpListener::bind("127.0.0.1:0").await.unwrap();
        let (ingest_addr, http_addr) = (ingest.local_addr().unwrap(), http.local_addr().unwrap());
        let (stop, stopped) = oneshot::channel::<()>();
        let task = tokio::spawn(server::run(
            config,
            Listeners { ingest, http },
            twins,
            async move {
                let _ = stopped.await;
            },
        ));
        Daemon {
            ingest: ingest_addr,
            http: http_addr,
            stop: Some(stop),
            task,
            client: reqwest::Client::new(),
        }
    }

    /// The SIGTERM of the tests: resolves the shutdown future, waits for the drain.
    pub async fn stop(self) {
        tokio::time::timeout(WAIT, self.stop_untimed())
            .await
            .expect("daemon did not stop in time");
    }

    /// [`Daemon::stop`] without a time limit, for tests with the clock
    /// paused (where a timer would fire while waiting on real I/O).
    pub async fn stop_untimed(mut self) {
        let _ = self.stop.take().unwrap().send(());
        self.task
            .await
            .expect("daemon task panicked")
            .expect("daemon failed");
    }

    /// The error of a daemon that fails to start (within [`WAIT`]).
    pub async fn failure(self) -> String {
        match tokio::time::timeout(WAIT, self.task).await {
            Ok(Ok(Err(e))) => e.to_string(),
            Ok(Ok(Ok(()))) => panic!("the daemon ran and stopped without an error"),
            Ok(Err(e)) => panic!("daemon task panicked: {e}"),
            Err(tokio::time::error::Elapsed { .. }) => {
                panic!("the daemon started (no error within {WAIT:?})")
            }
        }
    }

    pub fn url(&self, path: &str) -> String {
        format!("http://{}{path}", self.http)
    }

    pub async fn get(&self, path: &str) -> reqwest::Response {
        tokio::time::timeout(WAIT, self.client.get(self.url(path)).send())
            .await
            .expect("HTTP request timed out")
            .expect("HTTP request failed")
    }

    pub async fn get_json(&self, path: &str) -> serde_json::Value {
        let r = self.get(path).await;
        assert_eq!(r.status(), 200, "GET {path}");
        r.json().await.unwrap()
    }

    pub async fn metrics(&self) -> String {
        let r = self.get("/metrics").await;
        assert_eq!(r.status(), 200);
        r.text().await.unwrap()
    }

    /// One asset's summary in `GET /v1/assets`, if it is known.
    pub async fn asset_summary(&self, asset: &str) -> Option<serde_json::Value> {
        let v = self.get_json("/v1/assets").await;
        v["assets"]
            .as_array()
            .unwrap()
            .iter()
            .find(|a| a["asset_id"] == asset)
            .cloned()
    }

    /// `ticks` of one asset in `GET /v1/assets` (0 if unknown).
    pub async fn asset_ticks(&self, asset: &str) -> u64 {
        self.asset_summary(asset)
            .await
            .map_or(0, |a| a["ticks"].as_u64().unwrap())
    }
}

/// The value of one metric line `name{labels} value` (labels as written).
pub fn metric(text: &str, series: &str) -> Option<f64> {
    text.lines().find_map(|line| {
        let rest = line.strip_prefix(series)?;
        rest.strip_prefix(' ')?.trim().parse().ok()
    })
}

/// An MCAP stream and what it holds.
#[derive(Debug, Clone)]
pub struct Stream {
    pub bytes: Vec<u8>,
    /// Samples written.
    pub samples: u64,
    /// Ticks the 50 Hz clock has over the samples: `(t_last - t_first) / 20 ms`.
    pub ticks: u64,
    /// First sample time.
    pub t0_ns: i64,
}

pub fn meta(asset: &str, run: &str) -> RunMetadata {
    RunMetadata {
        asset_id: asset.into(),
        run_id: run.into(),
        ..RunMetadata::default()
    }
}

/// A dyno-like run of `duration_ms`: acceleration 1 kHz, position 100 Hz,
/// force 50 Hz, temperatures 1 Hz, in time order.
pub fn run_samples(t0_ns: i64, duration_ms: i64) -> Vec<Sample> {
    let mut out = Vec::new();
    for ms in 0..duration_ms {
        let t_ns = t0_ns + ms * 1_000_000;
        let phase = ms as f64 * 1e-3 * 2.0 * std::f64::consts::PI * 2.0;
        out.push(Sample::Acceleration {
            t_ns,
            a1_mps2: phase.sin(),
            a2_mps2: 0.01,
        });
        if ms % 10 == 0 {
            out.push(Sample::Position {
                t_ns,
                position_m: 0.04 * phase.sin(),
            });
        }
        if ms % 20 == 0 {
            out.push(Sample::Force {
                t_ns,
                force_n: 800.0 * phase.cos(),
            });
        }
        if ms % 1000 == 0 {
            out.push(Sample::TempShock {
                t_ns,
                temperature_c: 30.0,
            });
            out.push(Sample::TempAmbient {
                t_ns,
                temperature_c: 20.0,
            });
        }
    }
    out
}

fn ticks_of(samples: &[Sample]) -> u64 {
    let t0 = samples[0].t_ns();
    let t_last = samples.iter().map(Sample::t_ns).max().unwrap();
    ((t_last - t0) / TICK_NS) as u64
}

/// Writes `samples` with `dt_core::log::LogWriter` into memory.
pub fn write_stream(meta: &RunMetadata, samples: &[Sample], options: WriteOptions) -> Stream {
    let mut w = LogWriter::new(Cursor::new(Vec::new()), meta, options).unwrap();
    for s in samples {
        w.write_sample(s).unwrap();
    }
    Stream {
        bytes: w.finish().unwrap().into_inner(),
        samples: samples.len() as u64,
        ticks: ticks_of(samples),
        t0_ns: samples[0].t_ns(),
    }
}

/// zstd chunks of 16 KiB: several chunks per second of data, all under the
/// test limit of 64 KiB per record.
pub fn chunked() -> WriteOptions {
    WriteOptions {
        compression: Compression::Zstd,
        chunk_size: Some(16 << 10),
    }
}

pub fn good_stream(asset: &str, run: &str, t0_ns: i64, duration_ms: i64) -> Stream {
    write_stream(
        &meta(asset, run),
        &run_samples(t0_ns, duration_ms),
        chunked(),
    )
}

/// Every 10th position is NaN; every 100th acceleration sample is swapped
/// with its successor (out of order). Returns the stream, NaN count and
/// swap count.
pub fn nan_out_of_order_stream(asset: &str, run: &str, t0_ns: i64) -> (Stream, u64, u64) {
    let mut samples = run_samples(t0_ns, 2000);
    let mut nans = 0;
    let mut n_pos = 0;
    for s in &mut samples {
        if let Sample::Position { position_m, .. } = s {
            if n_pos % 10 == 3 {
                *position_m = f64::NAN;
                nans += 1;
            }
            n_pos += 1;
        }
    }
    // Swap acceleration pairs (ms 100k+55, +56): they are adjacent in the
    // list (no other topic at those times).
    let mut swaps = 0;
    let mut i = 0;
    while i + 1 < samples.len() {
        let t = samples[i].t_ns() - t0_ns;
        if t % 100_000_000 == 55_000_000
            && matches!(samples[i], Sample::Acceleration { .. })
            && matches!(samples[i + 1], Sample::Acceleration { .. })
        {
            samples.swap(i, i + 1);
            swaps += 1;
            i += 2;
        } else {
            i += 1;
        }
    }
    (
        write_stream(&meta(asset, run), &samples, chunked()),
        nans,
        swaps,
    )
}

/// A stream whose `/position` channel has a schema without `position_m`;
/// 500 ms of good acceleration data come first.
pub fn wrong_schema_stream(asset: &str, run: &str, t0_ns: i64) -> Vec<u8> {
    let mut w = mcap::WriteOptions::new()
        .compression(Some(mcap::Compression::Zstd))
        .chunk_size(Some(8 << 10))
        .create(Cursor::new(Vec::new()))
        .unwrap();
    w.write_metadata(&mcap::records::Metadata {
        name: "shocktwin.run".into(),
        metadata: BTreeMap::from([
            ("asset_id".to_owned(), asset.to_owned()),
            ("run_id".to_owned(), run.to_owned()),
        ]),
    })
    .unwrap();
    let (_, acc_spec) = topic_spec("/acceleration").unwrap();
    let acc_schema = w
        .add_schema(
            acc_spec.schema_name,
            "jsonschema",
            json_schema(acc_spec).as_bytes(),
        )
        .unwrap();
    let acc = w
        .add_channel(acc_schema, "/acceleration", "json", &BTreeMap::new())
        .unwrap();
    let header = |channel_id: u16, sequence: u32, t_ns: i64| mcap::records::MessageHeader {
        channel_id,
        sequence,
        log_time: t_ns as u64,
        publish_time: t_ns as u64,
    };
    for ms in 0..500 {
        let t = t0_ns + ms * 1_000_000;
        w.write_to_known_channel(
            &header(acc, ms as u32, t),
            br#"{"a1_mps2":0.5,"a2_mps2":0.0}"#,
        )
        .unwrap();
    }
    let bad_schema = w
        .add_schema(
            "shocktwin.Position",
            "jsonschema",
            br#"{"type":"object","properties":{"pos_mm":{"type":"number"}},"required":["pos_mm"]}"#,
        )
        .unwrap();
    let pos = w
        .add_channel(bad_schema, "/position", "json", &BTreeMap::new())
        .unwrap();
    for ms in 500..1000 {
        let t = t0_ns + ms * 1_000_000;
        w.write_to_known_channel(&header(pos, ms as u32, t), br#"{"pos_mm":1.0}"#)
            .unwrap();
    }
    w.finish().unwrap();
    w.into_inner().into_inner()
}

/// Top-level MCAP records `(offset, opcode, total length)` after the magic.
pub fn top_level_records(bytes: &[u8]) -> Vec<(usize, u8, usize)> {
    let mut out = Vec::new();
    let mut pos = 8;
    while pos + 9 <= bytes.len() {
        let op = bytes[pos];
        let len = u64::from_le_bytes(bytes[pos + 1..pos + 9].try_into().unwrap()) as usize;
        out.push((pos, op, 9 + len));
        pos += 9 + len;
    }
    out
}

/// Cuts `bytes` in the middle of its second chunk record; returns the cut
/// stream and the number of whole chunks before the cut.
pub fn truncate_mid_chunk(bytes: &[u8]) -> Vec<u8> {
    let chunks: Vec<_> = top_level_records(bytes)
        .into_iter()
        .filter(|&(_, op, _)| op == 0x06)
        .collect();
    assert!(chunks.len() >= 3, "need a few chunks, got {}", chunks.len());
    let (off, _, len) = chunks[1];
    bytes[..off + len / 2].to_vec()
}

/// Sends `bytes` in `piece`-byte writes, closes the sending side and reads
/// the daemon's report line. Write errors are ignored (the daemon may stop
/// reading a bad stream early).
pub async fn send(addr: SocketAddr, bytes: &[u8], piece: usize) -> serde_json::Value {
    let fut = async {
        let mut s = TcpStream::connect(addr).await.unwrap();
        for p in bytes.chunks(piece) {
            if s.write_all(p).await.is_err() {
                break;
            }
            tokio::task::yield_now().await;
        }
        let _ = s.shutdown().await;
        let mut reply = String::new();
        s.read_to_string(&mut reply).await.unwrap();
        serde_json::from_str(reply.trim()).unwrap_or_else(|e| panic!("report {reply:?}: {e}"))
    };
    tokio::time::timeout(WAIT, fut)
        .await
        .expect("stream not answered in time")
}

/// Every `/estimate` message of a recorded MCAP file.
pub fn read_estimates(path: &Path) -> Vec<Estimate> {
    let bytes = std::fs::read(path).unwrap();
    mcap::MessageStream::new(&bytes)
        .unwrap()
        .map(|m| {
            let m = m.unwrap();
            assert_eq!(m.channel.topic, "/estimate");
            let e: Estimate = serde_json::from_slice(&m.data).unwrap();
            assert_eq!(e.t_ns as u64, m.log_time);
            e
        })
        .collect()
}

/// Files of a directory, sorted; not the hidden ones (the daemon's lock).
pub fn files_in(dir: &Path) -> Vec<PathBuf> {
    let mut v: Vec<PathBuf> = match std::fs::read_dir(dir) {
        Ok(rd) => rd
            .map(|e| e.unwrap().path())
            .filter(|p| p.is_file() && !p.file_name().unwrap().to_string_lossy().starts_with('.'))
            .collect(),
        Err(_) => Vec::new(),
    };
    v.sort();
    v
}

/// Polls `cond` every 20 ms until true, at most [`WAIT`].
pub async fn wait_until<F, Fut>(what: &str, mut cond: F)
where
    F: FnMut() -> Fut,
    Fut: std::future::Future<Output = bool>,
{
    let deadline = tokio::time::Instant::now() + WAIT;
    while !cond().await {
        assert!(
            tokio::time::Instant::now() < deadline,
            "timed out waiting for {what}"
        );
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
}
