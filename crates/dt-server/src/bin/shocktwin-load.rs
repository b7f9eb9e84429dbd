//! `shocktwin-load`: the load test of `shocktwin serve` (a bench, not part of
//! `make test`).
//!
//! ```text
//! cargo build --release -p dt-server
//! target/release/shocktwin-load --serve target/release/shocktwin \
//!     --model crates/dt-core/tests/fixtures/bundle-mlp13 --assets 100,250,500 --duration-s 60
//! ```
//!
//! N simulated assets stream one run each, **in real time**, over loopback
//! TCP into one daemon: one tokio task and one connection per asset. The run
//! is simulated once in memory (`dt-sim`, or read from `--run FILE`); its
//! sensor samples (1 kHz acceleration, 100 Hz position, 50 Hz force, 1 Hz
//! temperatures; simulator truth topics left out) are re-timed per asset so
//! that each sample's `log_time` is the wall-clock instant at which it is
//! due, and written incrementally with `dt_core::log::LogWriter` (unchunked
//! by default) into a buffer that is flushed to the socket every
//! `--send-period-ms`. Each asset has its own `asset_id` and `run_id`; starts
//! are spread over `--ramp-s`.
//!
//! Measured:
//! - **delay** (the target: p99 ≤ `--target-p99-ms`): the daemon's
//!   `shocktwin_estimate_delay_seconds` histograms of this test's assets,
//!   summed — wall time from the read that returned the sample completing a
//!   tick to the estimate being taken by every sink; p50/p99 interpolated in
//!   the buckets.
//! - **end-to-end lag**: `shocktwin_asset_lag_seconds` scraped every
//!   `--scrape-s` while every asset streams. Since `log_time` is the send
//!   instant, it is now − send time of the newest sample the daemon has
//!   processed: it includes time spent in socket buffers, which the daemon's
//!   histogram cannot see, plus up to one send period.
//! - **send lateness**: how late the generator's writes were against their
//!   schedule (a generator or a blocked socket falling behind).
//! - **ticks lost**: each run's one-line JSON report must be `completed` with
//!   `ticks` equal to what a direct `Estimator` over the same samples emits.
//! - CPU of the daemon and of the generator (`/proc/PID/task/*/schedstat`),
//!   load average before and after.
//!
//! With `--serve BIN` the tool starts a fresh daemon per asset count
//! (ephemeral loopback ports, `--nice`, recording into a temporary
//! directory unless `--no-record`) and stops it with SIGTERM; otherwise it
//! uses the daemon at `--ingest`/`--http` (`--daemon-pid` for its CPU).
//! Loopback only. Exit status 0 when every asset count held.

use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::io::{BufRead, BufReader, Seek, SeekFrom, Write};
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, ExitCode, Stdio};
use std::sync::{Arc, Mutex, PoisonError};
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use anyhow::{bail, Context};
use clap::Parser;
use dt_core::bundle::Bundle;
use dt_core::estimator::{Estimator, EstimatorConfig};
use dt_core::log::{Compression, LogWriter, RunMetadata, Sample, WriteOptions};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;

/// Load test of `shocktwin serve`: N assets streaming in real time over loopback.
#[derive(Debug, Parser)]
#[command(name = "shocktwin-load")]
struct Args {
    /// Asset counts to test, comma separated (one daemon each with --serve).
    #[arg(long, value_delimiter = ',', required = true)]
    assets: Vec<usize>,
    /// Model bundle: the daemon's (--serve) and the reference for the tick count.
    #[arg(long)]
    model: PathBuf,
    /// Start a fresh daemon from this `shocktwin` binary for each asset count.
    #[arg(long)]
    serve: Option<PathBuf>,
    /// Niceness of the started daemon (negative needs privileges).
    #[arg(long, default_value_t = 0, allow_hyphen_values = true)]
    nice: i32,
    /// Do not record estimates (the started daemon records into a temporary directory by default).
    #[arg(long)]
    no_record: bool,
    /// Chunk compression of the started daemon's recordings (`record.compression`:
    /// zstd, lz4 or none; default: the daemon's, zstd).
    #[arg(long)]
    record_compression: Option<String>,
    /// Give the started daemon a fleet store (`--db`) in a temporary directory
    /// (default: `--no-db`).
    #[arg(long)]
    store: bool,
    /// Ingest address of an already running daemon (without --serve).
    #[arg(long, default_value = "127.0.0.1:7410")]
    ingest: SocketAddr,
    /// HTTP address of an already running daemon (without --serve).
    #[arg(long, default_value = "127.0.0.1:7411")]
    http: SocketAddr,
    /// PID of an already running daemon, for its CPU time.
    #[arg(long)]
    daemon_pid: Option<u32>,
    /// Seconds of each run streamed (at most the run's length).
    #[arg(long, default_value_t = 60.0)]
    duration_s: f64,
    /// Run log to stream (default: a quick 12 bar, 2 Hz run simulated in memory).
    #[arg(long)]
    run: Option<PathBuf>,
    /// Road calibration: every asset is driven on roads (`road = true`), read
    /// by the road observer (the started daemon gets `--road` and a
    /// configuration with `[defaults] road = true`; give a road `--run`).
    #[arg(long)]
    road: Option<PathBuf>,
    /// Each connection writes what is due every this many milliseconds.
    #[arg(long, default_value_t = 10)]
    send_period_ms: u64,
    /// MCAP chunk size in bytes (0: unchunked, every message sent when due).
    #[arg(long, default_value_t = 0)]
    chunk_bytes: u64,
    /// Connection starts are spread over this many seconds.
    #[arg(long, default_value_t = 2.0)]
    ramp_s: f64,
    /// Seconds between scrapes of /metrics for the end-to-end lag.
    #[arg(long, default_value_t = 5.0)]
    scrape_s: f64,
    /// The target: p99 of the delay, milliseconds.
    #[arg(long, default_value_t = 50.0)]
    target_p99_ms: f64,
    /// Generator worker threads (default: tokio's, one per core).
    #[arg(long)]
    threads: Option<usize>,
    /// Also write each result as one JSON line to this file (appended).
    #[arg(long)]
    json_out: Option<PathBuf>,
}

/// Generator lateness histogram: 1 ms bins, the last one is "≥ 10 s".
const LATE_BINS: usize = 10_001;

/// The run every asset streams: samples with times relative to its first.
struct Template {
    /// `(offset from the first sample, sample with its original time)`.
    samples: Vec<(i64, Sample)>,
    /// Estimates a direct `Estimator` emits over these samples.
    expected_ticks: u64,
    meta: RunMetadata,
}

fn main() -> ExitCode {
    let args = Args::parse();
    match run(&args) {
        Ok(true) => ExitCode::SUCCESS,
        Ok(false) => ExitCode::from(1),
        Err(e) => {
            eprintln!("shocktwin-load: {e:#}");
            ExitCode::from(2)
        }
    }
}

fn run(args: &Args) -> anyhow::Result<bool> {
    if args.send_period_ms == 0 || args.duration_s <= 0.0 || args.assets.contains(&0) {
        bail!("--send-period-ms, --duration-s and every --assets count must be positive");
    }
    if args.serve.is_none() && !(args.ingest.ip().is_loopback() && args.http.ip().is_loopback()) {
        bail!("loopback only: --ingest and --http must be 127.0.0.1 or ::1 addresses");
    }
    let template = load_template(args)?;
    eprintln!(
        "template: {} samples over {:.1} s, {} estimates expected per asset",
        template.samples.len(),
        template.samples.last().map_or(0, |s| s.0) as f64 * 1e-9,
        template.expected_ticks
    );
    let template = Arc::new(template);
    let mut rt = tokio::runtime::Builder::new_multi_thread();
    if let Some(n) = args.threads {
        rt.worker_threads(n);
    }
    let rt = rt.enable_all().build().context("tokio runtime")?;
    let mut all_held = true;
    for &n in &args.assets {
        let result = match &args.serve {
            Some(bin) => {
                let daemon = SpawnedDaemon::start(bin, args, n)?;
                let r = rt.block_on(load_once(
                    args,
                    &template,
                    n,
                    daemon.ingest,
                    daemon.http,
                    Some(daemon.pid),
                ));
                let stopped = daemon.stop();
                let mut r = r?;
                r.daemon_exit_ok = Some(stopped.is_ok());
                if let Err(e) = stopped {
                    eprintln!("daemon: {e:#}");
                }
                r
            }
            None => rt.block_on(load_once(
                args,
                &template,
                n,
                args.ingest,
                args.http,
                args.daemon_pid,
            ))?,
        };
        let held = result.held(args.target_p99_ms * 1e-3, args.send_period_ms);
        all_held &= held;
        println!("{}", result.line(held));
        if let Some(path) = &args.json_out {
            let mut f = std::fs::OpenOptions::new()
                .create(true)
                .append(true)
                .open(path)
                .with_context(|| format!("{}", path.display()))?;
            writeln!(f, "{}", result.json(held, args))?;
        }
    }
    Ok(all_held)
}

/// Simulates (or reads) the run, keeps the sensor topics for `duration_s`
/// and counts the estimates a direct `Estimator` emits.
fn load_template(args: &Args) -> anyhow::Result<Template> {
    let (meta, mut samples) = if let Some(path) = &args.run {
        let log =
            dt_core::log::read_log(path).with_context(|| format!("reading {}", path.display()))?;
        (log.metadata.clone(), log.samples_sorted())
    } else {
        let spec = dt_sim::run::RunSpec {
            quick: true,
            ..dt_sim::run::RunSpec::paper(12.0, 2.0, 1)
        };
        let mut samples = Vec::new();
        dt_sim::run::simulate_run_with(&spec, &spec.params(), |s| {
            samples.push(*s);
            Ok(())
        })
        .context("simulating the template run")?;
        (spec.metadata(), samples)
    };
    samples.retain(|s| {
        !matches!(
            s,
            Sample::TruthPressure { .. } | Sample::TruthVelocity { .. }
        )
    });
    let Some(t0) = samples.first().map(Sample::t_ns) else {
        bail!("the run has no sensor samples");
    };
    let span_ns = (args.duration_s * 1e9) as i64;
    let samples: Vec<(i64, Sample)> = samples
        .into_iter()
        .map(|s| (s.t_ns() - t0, s))
        .take_while(|(dt, _)| *dt <= span_ns)
        .collect();
    let bundle = Arc::new(
        Bundle::load(&args.model).with_context(|| format!("bundle {}", args.model.display()))?,
    );
    let cfg = EstimatorConfig::from_bundle(&bundle);
    let mut est = Estimator::new(bundle, cfg).context("estimator")?;
    if let Some(path) = &args.road {
        let text =
            std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
        let cal = dt_core::road::RoadCalibration::from_json(&path.display().to_string(), &text)
            .map_err(anyhow::Error::msg)?;
        est = est.with_road(cal).map_err(anyhow::Error::msg)?;
    }
    let mut expected_ticks = 0u64;
    for (_, s) in &samples {
        est.push(*s).context("reference estimator")?;
        expected_ticks += est.drain().count() as u64;
    }
    est.finish().context("reference estimator")?;
    expected_ticks += est.drain().count() as u64;
    Ok(Template {
        samples,
        expected_ticks,
        meta,
    })
}

/// A `Write + Seek` that appends to a shared buffer the task drains into the
/// socket (`LogWriter` asks for the position only; the writer is unchunked
/// or writes whole chunks, so it never seeks back).
#[derive(Clone)]
struct SharedBuf {
    buf: Arc<Mutex<Vec<u8>>>,
    pos: u64,
}

impl SharedBuf {
    /// Swaps what was written for `spare` (emptied first), so that both
    /// buffers keep their capacity from one send to the next.
    fn take_into(&self, spare: &mut Vec<u8>) {
        spare.clear();
        std::mem::swap(
            &mut *self.buf.lock().unwrap_or_else(PoisonError::into_inner),
            spare,
        );
    }
}

impl Write for SharedBuf {
    fn write(&mut self, data: &[u8]) -> std::io::Result<usize> {
        self.buf
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .extend_from_slice(data);
        self.pos += data.len() as u64;
        Ok(data.len())
    }

    fn flush(&mut self) -> std::io::Result<()> {
        Ok(())
    }
}

impl Seek for SharedBuf {
    fn seek(&mut self, to: SeekFrom) -> std::io::Result<u64> {
        match to {
            SeekFrom::Current(0) | SeekFrom::End(0) => Ok(self.pos),
            SeekFrom::Start(p) if p == self.pos => Ok(self.pos),
            _ => Err(std::io::Error::other("a socket stream cannot seek back")),
        }
    }
}

/// What one asset's connection did.
struct AssetResult {
    report: Option<serde_json::Value>,
    error: Option<String>,
    late_ms: Vec<u64>,
}

#[allow(clippy::too_many_arguments)]
async fn stream_asset(
    template: Arc<Template>,
    ingest: SocketAddr,
    asset_id: String,
    start: Instant,
    start_wall_ns: i64,
    period: Duration,
    chunk_bytes: u64,
) -> AssetResult {
    let mut late_ms = vec![0u64; LATE_BINS];
    let result = stream_asset_inner(
        &template,
        ingest,
        &asset_id,
        start,
        start_wall_ns,
        period,
        chunk_bytes,
        &mut late_ms,
    )
    .await;
    match result {
        Ok(report) => AssetResult {
            report: Some(report),
            error: None,
            late_ms,
        },
        Err(e) => AssetResult {
            report: None,
            error: Some(format!("{asset_id}: {e:#}")),
            late_ms,
        },
    }
}

#[allow(clippy::too_many_arguments)]
async fn stream_asset_inner(
    template: &Template,
    ingest: SocketAddr,
    asset_id: &str,
    start: Instant,
    start_wall_ns: i64,
    period: Duration,
    chunk_bytes: u64,
    late_ms: &mut [u64],
) -> anyhow::Result<serde_json::Value> {
    tokio::time::sleep_until(start.into()).await;
    let mut sock = TcpStream::connect(ingest).await.context("connect")?;
    sock.set_nodelay(true)?;
    let mut meta = template.meta.clone();
    meta.asset_id = asset_id.to_owned();
    "load".clone_into(&mut meta.run_id);
    meta.extra
        .insert("load_test".into(), "shocktwin-load".into());
    let out = SharedBuf {
        buf: Arc::new(Mutex::new(Vec::with_capacity(64 << 10))),
        pos: 0,
    };
    let options = WriteOptions {
        compression: Compression::Lz4,
        chunk_size: (chunk_bytes > 0).then_some(chunk_bytes),
    };
    let mut writer = LogWriter::new(out.clone(), &meta, options)?;
    let mut bytes = Vec::with_capacity(64 << 10);
    let mut next = 0usize;
    let samples = &template.samples;
    let mut k: u32 = 0;
    // Bounded: one iteration per send period of the run, plus the end.
    while next < samples.len() {
        k += 1;
        let due_at = start + period * k;
        tokio::time::sleep_until(due_at.into()).await;
        let due_ns = i64::try_from(due_at.saturating_duration_since(start).as_nanos())?;
        while next < samples.len() && samples[next].0 <= due_ns {
            let (dt, s) = samples[next];
            writer.write_sample(&retime(&s, start_wall_ns + dt))?;
            next += 1;
        }
        out.take_into(&mut bytes);
        if !bytes.is_empty() {
            sock.write_all(&bytes).await.context("send")?;
        }
        let late = Instant::now().saturating_duration_since(due_at).as_millis();
        late_ms[usize::try_from(late)
            .unwrap_or(usize::MAX)
            .min(LATE_BINS - 1)] += 1;
    }
    writer.finish()?;
    out.take_into(&mut bytes);
    sock.write_all(&bytes).await.context("send")?;
    sock.shutdown().await.context("shutdown")?;
    let mut reply = Vec::new();
    tokio::time::timeout(
        Duration::from_secs(120),
        (&mut sock).take(1 << 20).read_to_end(&mut reply),
    )
    .await
    .context("no report within 120 s")?
    .context("reading the report")?;
    let text = String::from_utf8_lossy(&reply);
    let line = text.lines().last().context("empty reply")?;
    serde_json::from_str(line).with_context(|| format!("report {line:?}"))
}

fn retime(s: &Sample, t_ns: i64) -> Sample {
    let mut s = *s;
    match &mut s {
        Sample::Position { t_ns: t, .. }
        | Sample::Acceleration { t_ns: t, .. }
        | Sample::Force { t_ns: t, .. }
        | Sample::TempShock { t_ns: t, .. }
        | Sample::TempAmbient { t_ns: t, .. }
        | Sample::TruthPressure { t_ns: t, .. }
        | Sample::TruthVelocity { t_ns: t, .. } => *t = t_ns,
    }
    s
}

/// The result of one asset count.
struct LoadResult {
    assets: usize,
    expected_ticks: u64,
    completed_exact: usize,
    ticks_lost: i64,
    failures: Vec<String>,
    /// Summed delay histogram: `(le, cumulative count)`, +Inf last.
    delay_buckets: Vec<(f64, f64)>,
    delay_count: f64,
    delay_sum_s: f64,
    lag_samples_s: Vec<f64>,
    late_ms: Vec<u64>,
    wall_s: f64,
    daemon_cpu_s: Option<f64>,
    /// The daemon's peak resident memory, MiB (`VmHWM`), read before it stops.
    daemon_peak_rss_mib: Option<f64>,
    generator_cpu_s: f64,
    loadavg_before: String,
    loadavg_after: String,
    daemon_exit_ok: Option<bool>,
}

async fn load_once(
    args: &Args,
    template: &Arc<Template>,
    n: usize,
    ingest: SocketAddr,
    http: SocketAddr,
    daemon_pid: Option<u32>,
) -> anyhow::Result<LoadResult> {
    wait_ready(http).await?;
    let nonce = SystemTime::now().duration_since(UNIX_EPOCH)?.as_millis() % 1_000_000;
    let prefix = format!("load-{nonce}-");
    let loadavg_before = loadavg();
    let daemon_cpu0 = daemon_pid.map(cpu_seconds);
    let gen_cpu0 = cpu_seconds(std::process::id());
    let period = Duration::from_millis(args.send_period_ms);
    let t_start = Instant::now() + Duration::from_millis(200);
    let wall_start_ns =
        i64::try_from(SystemTime::now().duration_since(UNIX_EPOCH)?.as_nanos())? + 200_000_000;
    let mut tasks = Vec::with_capacity(n);
    for i in 0..n {
        let offset = Duration::from_secs_f64(args.ramp_s * i as f64 / n as f64);
        tasks.push(tokio::spawn(stream_asset(
            Arc::clone(template),
            ingest,
            format!("{prefix}{i:05}"),
            t_start + offset,
            wall_start_ns + i64::try_from(offset.as_nanos())?,
            period,
            args.chunk_bytes,
        )));
    }
    // End-to-end lag while every asset streams: after the ramp, before the first ends.
    let run_s = template.samples.last().map_or(0, |s| s.0) as f64 * 1e-9;
    let scrape_from = t_start + Duration::from_secs_f64(args.ramp_s + 1.0);
    let scrape_until = t_start + Duration::from_secs_f64((run_s - 1.0).max(0.0));
    let mut lag_samples_s = Vec::new();
    let mut at = scrape_from;
    while at < scrape_until {
        tokio::time::sleep_until(at.into()).await;
        if let Ok(text) = http_get(http, "/metrics").await {
            lag_samples_s.extend(
                series_values(&text, "shocktwin_asset_lag_seconds", &prefix).map(|(_, v)| v),
            );
        }
        at += Duration::from_secs_f64(args.scrape_s.max(0.5));
    }
    let mut results = Vec::with_capacity(n);
    for t in tasks {
        results.push(t.await.context("asset task panicked")?);
    }
    let wall_s = t_start.elapsed().as_secs_f64();
    let daemon_cpu_s = match (daemon_pid, daemon_cpu0) {
        (Some(pid), Some(c0)) => Some(cpu_seconds(pid) - c0),
        _ => None,
    };
    let generator_cpu_s = cpu_seconds(std::process::id()) - gen_cpu0;
    let metrics = http_get(http, "/metrics").await.context("final /metrics")?;
    let mut r = aggregate(template, n, results, &metrics, &prefix)?;
    r.lag_samples_s = lag_samples_s;
    r.wall_s = wall_s;
    r.daemon_cpu_s = daemon_cpu_s;
    r.daemon_peak_rss_mib = daemon_pid.and_then(peak_rss_mib);
    r.generator_cpu_s = generator_cpu_s;
    r.loadavg_before = loadavg_before;
    Ok(r)
}

/// Checks the reports against the expected tick count and sums this test's
/// delay histograms out of the final `/metrics` text.
fn aggregate(
    template: &Template,
    n: usize,
    results: Vec<AssetResult>,
    metrics: &str,
    prefix: &str,
) -> anyhow::Result<LoadResult> {
    let mut failures = Vec::new();
    let mut completed_exact = 0;
    let mut ticks_lost = 0i64;
    let mut late_ms = vec![0u64; LATE_BINS];
    let expected = i64::try_from(template.expected_ticks)?;
    for r in results {
        for (a, b) in late_ms.iter_mut().zip(&r.late_ms) {
            *a += b;
        }
        match (r.report, r.error) {
            (Some(rep), _) => {
                let ticks = rep["ticks"].as_i64().unwrap_or(-1);
                if rep["status"] == "completed" && rep["flushed"] == true && ticks == expected {
                    completed_exact += 1;
                } else {
                    ticks_lost += (expected - ticks.max(0)).max(0);
                    if failures.len() < 10 {
                        failures.push(rep.to_string());
                    }
                }
            }
            (None, e) => {
                ticks_lost += expected;
                if failures.len() < 10 {
                    failures.push(e.unwrap_or_default());
                }
            }
        }
    }
    let mut buckets: BTreeMap<String, f64> = BTreeMap::new();
    for (labels, v) in series_values(metrics, "shocktwin_estimate_delay_seconds_bucket", prefix) {
        if let Some(le) = labels
            .split("le=\"")
            .nth(1)
            .and_then(|r| r.split('"').next())
        {
            *buckets.entry(le.to_owned()).or_default() += v;
        }
    }
    let mut delay_buckets: Vec<(f64, f64)> = buckets
        .into_iter()
        .map(|(le, c)| {
            (
                if le == "+Inf" {
                    f64::INFINITY
                } else {
                    le.parse().unwrap_or(f64::NAN)
                },
                c,
            )
        })
        .collect();
    delay_buckets.sort_by(|a, b| a.0.total_cmp(&b.0));
    let delay_count = series_values(metrics, "shocktwin_estimate_delay_seconds_count", prefix)
        .map(|(_, v)| v)
        .sum();
    let delay_sum_s = series_values(metrics, "shocktwin_estimate_delay_seconds_sum", prefix)
        .map(|(_, v)| v)
        .sum();
    Ok(LoadResult {
        assets: n,
        expected_ticks: template.expected_ticks,
        completed_exact,
        ticks_lost,
        failures,
        delay_buckets,
        delay_count,
        delay_sum_s,
        lag_samples_s: Vec::new(),
        late_ms,
        wall_s: f64::NAN,
        daemon_cpu_s: None,
        daemon_peak_rss_mib: None,
        generator_cpu_s: f64::NAN,
        loadavg_before: String::new(),
        loadavg_after: loadavg(),
        daemon_exit_ok: None,
    })
}

/// `(labels, value)` of every sample of `name` whose `asset` label starts with `prefix`.
fn series_values<'a>(
    text: &'a str,
    name: &'a str,
    prefix: &'a str,
) -> impl Iterator<Item = (&'a str, f64)> + 'a {
    let needle = format!("asset=\"{prefix}");
    text.lines().filter_map(move |line| {
        let rest = line.strip_prefix(name)?.strip_prefix('{')?;
        let (labels, value) = rest.split_once("} ")?;
        if !labels.contains(&needle) {
            return None;
        }
        Some((labels, value.trim().parse().ok()?))
    })
}

impl LoadResult {
    /// Quantile `q` of the summed delay histogram, linear within a bucket;
    /// infinite when it falls in the overflow bucket.
    fn delay_quantile_s(&self, q: f64) -> f64 {
        let total = self.delay_count;
        if total <= 0.0 {
            return f64::NAN;
        }
        let target = q * total;
        let (mut lo, mut c_lo) = (0.0, 0.0);
        for &(le, c) in &self.delay_buckets {
            if c >= target {
                if le.is_infinite() {
                    return f64::INFINITY;
                }
                let frac = if c > c_lo {
                    (target - c_lo) / (c - c_lo)
                } else {
                    1.0
                };
                return lo + (le - lo) * frac;
            }
            (lo, c_lo) = (le, c);
        }
        f64::INFINITY
    }

    /// Fraction of estimates with a delay ≤ `bound_s` (a bucket bound).
    fn fraction_within(&self, bound_s: f64) -> f64 {
        self.delay_buckets
            .iter()
            .find(|(le, _)| (le - bound_s).abs() < 1e-12)
            .map_or(f64::NAN, |(_, c)| c / self.delay_count)
    }

    fn late_quantile_ms(&self, q: f64) -> u64 {
        let total: u64 = self.late_ms.iter().sum();
        let target = (q * total as f64).ceil() as u64;
        let mut acc = 0;
        for (ms, &c) in self.late_ms.iter().enumerate() {
            acc += c;
            if acc >= target.max(1) {
                return ms as u64;
            }
        }
        LATE_BINS as u64
    }

    fn lag_quantile_s(&self, q: f64) -> f64 {
        let mut v = self.lag_samples_s.clone();
        if v.is_empty() {
            return f64::NAN;
        }
        v.sort_by(f64::total_cmp);
        v[((q * (v.len() - 1) as f64).round() as usize).min(v.len() - 1)]
    }

    /// Held: every run complete with every tick, p99 delay within the
    /// target, and real time kept end to end (p99 send lateness and p99
    /// lag within the target plus one send period).
    fn held(&self, target_s: f64, period_ms: u64) -> bool {
        let period_s = period_ms as f64 * 1e-3;
        self.completed_exact == self.assets
            && self.ticks_lost == 0
            && self.delay_count >= (self.assets as u64 * self.expected_ticks) as f64
            && self.delay_quantile_s(0.99) <= target_s
            && (self.late_quantile_ms(0.99) as f64) * 1e-3 <= target_s
            && self
                .lag_quantile_s(0.99)
                .partial_cmp(&(target_s + period_s))
                != Some(std::cmp::Ordering::Greater)
            && self.daemon_exit_ok != Some(false)
    }

    fn line(&self, held: bool) -> String {
        let mut s = format!(
            "N={:5} {}: runs complete with every tick {}/{}, ticks lost {}, delay p50 {:.2} ms p99 {:.2} ms (≤50 ms: {:.3}%, {} estimates), \
             e2e lag p50 {:.1} ms p99 {:.1} ms max {:.1} ms ({} samples), send lateness p99 {} ms max {} ms, \
             CPU daemon {} generator {:.0}% over {:.0} s, daemon peak RSS {}, load avg {} -> {}",
            self.assets,
            if held { "HELD" } else { "BROKE" },
            self.completed_exact,
            self.assets,
            self.ticks_lost,
            self.delay_quantile_s(0.5) * 1e3,
            self.delay_quantile_s(0.99) * 1e3,
            self.fraction_within(0.05) * 100.0,
            self.delay_count,
            self.lag_quantile_s(0.5) * 1e3,
            self.lag_quantile_s(0.99) * 1e3,
            self.lag_quantile_s(1.0) * 1e3,
            self.lag_samples_s.len(),
            self.late_quantile_ms(0.99),
            self.late_quantile_ms(1.0),
            self.daemon_cpu_s
                .map_or_else(|| "n/a".to_owned(), |c| format!("{:.0}%", 100.0 * c / self.wall_s)),
            100.0 * self.generator_cpu_s / self.wall_s,
            self.wall_s,
            self.daemon_peak_rss_mib
                .map_or_else(|| "n/a".to_owned(), |m| format!("{m:.0} MiB")),
            self.loadavg_before,
            self.loadavg_after,
        );
        if self.daemon_exit_ok == Some(false) {
            s.push_str(", daemon did not exit 0 on SIGTERM");
        }
        for f in &self.failures {
            s.push_str("\n    failed: ");
            s.push_str(f);
        }
        s
    }

    fn json(&self, held: bool, args: &Args) -> serde_json::Value {
        serde_json::json!({
            "assets": self.assets,
            "held": held,
            "duration_s": args.duration_s,
            "send_period_ms": args.send_period_ms,
            "chunk_bytes": args.chunk_bytes,
            "record": args.serve.is_some() && !args.no_record,
            "record_compression": args.record_compression,
            "store": args.serve.is_some() && args.store,
            "nice": args.nice,
            "expected_ticks_per_asset": self.expected_ticks,
            "runs_complete_every_tick": self.completed_exact,
            "ticks_lost": self.ticks_lost,
            "delay_p50_ms": self.delay_quantile_s(0.5) * 1e3,
            "delay_p99_ms": self.delay_quantile_s(0.99) * 1e3,
            "delay_mean_ms": self.delay_sum_s / self.delay_count * 1e3,
            "delay_fraction_le_50ms": self.fraction_within(0.05),
            "estimates": self.delay_count,
            "e2e_lag_p50_ms": self.lag_quantile_s(0.5) * 1e3,
            "e2e_lag_p99_ms": self.lag_quantile_s(0.99) * 1e3,
            "e2e_lag_max_ms": self.lag_quantile_s(1.0) * 1e3,
            "send_late_p99_ms": self.late_quantile_ms(0.99),
            "send_late_max_ms": self.late_quantile_ms(1.0),
            "daemon_cpu_percent": self.daemon_cpu_s.map(|c| 100.0 * c / self.wall_s),
            "generator_cpu_percent": 100.0 * self.generator_cpu_s / self.wall_s,
            "daemon_peak_rss_mib": self.daemon_peak_rss_mib,
            "wall_s": self.wall_s,
            "loadavg_before": self.loadavg_before,
            "loadavg_after": self.loadavg_after,
            "failures": self.failures,
        })
    }
}

/// CPU time of every thread of `pid`, s (`/proc/PID/task/*/schedstat`, ns
/// on CPU; threads that already exited are not counted).
fn cpu_seconds(pid: u32) -> f64 {
    let Ok(dir) = std::fs::read_dir(format!("/proc/{pid}/task")) else {
        return f64::NAN;
    };
    let mut ns = 0u64;
    for entry in dir.flatten() {
        if let Ok(text) = std::fs::read_to_string(entry.path().join("schedstat")) {
            ns += text
                .split_whitespace()
                .next()
                .and_then(|v| v.parse::<u64>().ok())
                .unwrap_or(0);
        }
    }
    ns as f64 * 1e-9
}

/// Peak resident memory of `pid`, MiB (`VmHWM` of `/proc/PID/status`).
fn peak_rss_mib(pid: u32) -> Option<f64> {
    let text = std::fs::read_to_string(format!("/proc/{pid}/status")).ok()?;
    let kib: f64 = text
        .lines()
        .find_map(|l| l.strip_prefix("VmHWM:"))?
        .split_whitespace()
        .next()?
        .parse()
        .ok()?;
    Some(kib / 1024.0)
}

fn loadavg() -> String {
    std::fs::read_to_string("/proc/loadavg").map_or_else(
        |_| "n/a".to_owned(),
        |s| s.split_whitespace().take(3).collect::<Vec<_>>().join(" "),
    )
}

/// A minimal HTTP/1.0 GET (the daemon's API is plain HTTP on loopback).
async fn http_get(addr: SocketAddr, path: &str) -> anyhow::Result<String> {
    let fetch = async {
        let mut s = TcpStream::connect(addr).await?;
        s.write_all(format!("GET {path} HTTP/1.0\r\nHost: {addr}\r\n\r\n").as_bytes())
            .await?;
        let mut body = Vec::new();
        (&mut s).take(256 << 20).read_to_end(&mut body).await?;
        anyhow::Ok(body)
    };
    let bytes = tokio::time::timeout(Duration::from_secs(30), fetch)
        .await
        .context("HTTP timeout")??;
    let text = String::from_utf8_lossy(&bytes);
    let (head, body) = text.split_once("\r\n\r\n").context("no HTTP header")?;
    if !head.lines().next().is_some_and(|l| l.contains(" 200 ")) {
        bail!("GET {path}: {}", head.lines().next().unwrap_or(""));
    }
    Ok(body.to_owned())
}

async fn wait_ready(http: SocketAddr) -> anyhow::Result<()> {
    for _ in 0..100 {
        if http_get(http, "/readyz").await.is_ok() {
            return Ok(());
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    bail!("the daemon at {http} is not ready (GET /readyz)")
}

/// A daemon started for one asset count.
struct SpawnedDaemon {
    child: Child,
    pid: u32,
    ingest: SocketAddr,
    http: SocketAddr,
    record_dir: Option<PathBuf>,
}

impl SpawnedDaemon {
    fn start(bin: &Path, args: &Args, n: usize) -> anyhow::Result<Self> {
        let record_dir = (!args.no_record).then(|| {
            std::env::temp_dir().join(format!("shocktwin-load-{}-{n}", std::process::id()))
        });
        let mut cmd = if args.nice == 0 {
            Command::new(bin)
        } else {
            let mut c = Command::new("nice");
            c.arg("-n").arg(args.nice.to_string()).arg(bin);
            c
        };
        cmd.args([
            "serve",
            "--listen",
            "127.0.0.1:0",
            "--http",
            "127.0.0.1:0",
            "--model",
        ])
        .arg(&args.model)
        .env("SHOCKTWIN_MAX_CONNECTIONS", (n + 16).to_string())
        // Every simulated vehicle connects from loopback.
        .env("SHOCKTWIN_MAX_CONNECTIONS_PER_PEER", (n + 16).to_string())
        // Every simulated vehicle comes from 127.0.0.1: one peer standing in
        // for many, so the per-peer byte rate would measure itself.
        .env("SHOCKTWIN_MAX_INGEST_BYTES_PER_S_PER_PEER", "0")
        .env("RUST_LOG", "warn,dt_server::cmd_serve=info")
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::piped());
        if let Some(d) = &record_dir {
            cmd.arg("--record-dir").arg(d);
        }
        let mut config_text = String::new();
        if let Some(road) = &args.road {
            config_text.push_str("[defaults]\nroad = true\n");
            cmd.arg("--road").arg(road);
        }
        if let Some(c) = &args.record_compression {
            let _ = write!(config_text, "[record]\ncompression = {c:?}\n");
        }
        if !config_text.is_empty() {
            let config = std::env::temp_dir()
                .join(format!("shocktwin-load-{}-{n}.toml", std::process::id()));
            std::fs::write(&config, config_text)
                .with_context(|| format!("writing {}", config.display()))?;
            cmd.arg("--config").arg(config);
        }
        if args.store {
            let db = std::env::temp_dir()
                .join(format!("shocktwin-load-{}-{n}.sqlite", std::process::id()));
            cmd.arg("--db").arg(db);
        } else {
            cmd.arg("--no-db");
        }
        let mut child = cmd
            .spawn()
            .with_context(|| format!("starting {}", bin.display()))?;
        let pid = child.id();
        let stderr = child.stderr.take().context("daemon stderr")?;
        let mut lines = BufReader::new(stderr).lines();
        let mut addrs = None;
        let mut said = Vec::new();
        // Bounded: the daemon logs the line at start; give up after 200 lines.
        for _ in 0..200 {
            let Some(Ok(line)) = lines.next() else { break };
            said.push(line.clone());
            let field = |key: &str| {
                line.split_whitespace()
                    .find_map(|w| w.strip_prefix(key))
                    .and_then(|v| v.parse::<SocketAddr>().ok())
            };
            if line.contains("listening") {
                if let (Some(i), Some(h)) = (field("listen="), field("http=")) {
                    addrs = Some((i, h));
                    break;
                }
            }
        }
        let Some((ingest, http)) = addrs else {
            let _ = child.kill();
            bail!(
                "{} serve did not log its addresses; it said:\n{}",
                bin.display(),
                said.join("\n")
            );
        };
        // Keep draining its log (warnings go to our stderr) so it never blocks.
        std::thread::spawn(move || {
            for line in lines.map_while(Result::ok) {
                eprintln!("daemon: {line}");
            }
        });
        Ok(Self {
            child,
            pid,
            ingest,
            http,
            record_dir,
        })
    }

    /// SIGTERM, then waits (bounded) for exit status 0.
    fn stop(mut self) -> anyhow::Result<()> {
        let status = Command::new("kill")
            .args(["-TERM", &self.pid.to_string()])
            .status()
            .context("kill -TERM")?;
        if !status.success() {
            bail!("kill -TERM {} failed", self.pid);
        }
        let deadline = Instant::now() + Duration::from_secs(60);
        let result = loop {
            if let Some(s) = self.child.try_wait()? {
                break if s.success() {
                    Ok(())
                } else {
                    Err(anyhow::anyhow!("daemon exited with {s}"))
                };
            }
            if Instant::now() > deadline {
                let _ = self.child.kill();
                break Err(anyhow::anyhow!(
                    "daemon did not stop within 60 s of SIGTERM"
                ));
            }
            std::thread::sleep(Duration::from_millis(50));
        };
        if let Some(d) = &self.record_dir {
            let _ = std::fs::remove_dir_all(d);
        }
        result
    }
}
