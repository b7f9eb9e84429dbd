//! `shocktwin replay --model BUNDLE FILE.mcap... --out OUT.(mcap|jsonl|csv)`:
//! runs logs through the streaming estimator as fast as the machine allows
//! (one worker per core, one run per worker at a time; with a core to spare
//! per worker, each file is read and decoded on a second thread) and writes
//! the `/estimate` stream.
//!
//! - `.jsonl` / `.csv`: one row per tick with `run_id`, `asset_id`, `t_s`
//!   (seconds since the run's first message) and the `/estimate` fields.
//! - `.mcap`: the run's input samples and its `/estimate` messages in one
//!   shocktwin log, so that both open together in MCAP tools. With several
//!   inputs, `OUT.mcap` names a pattern: one file per run,
//!   `OUT-<run_id>.mcap`.
//!
//! When a log carries a label (`charge_pressure_bar`), the per-run RMSE of
//! the instantaneous and 1 s average pressure against it is printed, over the
//! ticks where the 1 s average exists (the damper excited).
//! An unreadable input is reported and skipped; the exit status is then 1.

use std::fmt::Write as _;
use std::fs::File;
use std::io::{BufWriter, Seek, Write};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Instant;

use anyhow::{bail, Context, Result};
use dt_core::bundle::Bundle;
use dt_core::charge::UnitBaseline;
use dt_core::estimate::{Estimate, ESTIMATE_SCHEMA_JSON};
use dt_core::estimator::{Estimator, EstimatorConfig, EstimatorCounters};
use dt_core::features::Group;
use dt_core::log::{
    read_log, topic, LogDecoder, LogEvent, LogWriter, RunLog, RunMetadata, Sample, SampleMessage,
    Undecoded, WriteOptions,
};
use dt_core::road::RoadCalibration;

use crate::cli::ReplayArgs;

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Format {
    Mcap,
    Jsonl,
    Csv,
}

fn format_of(out: &Path) -> Result<Format> {
    match out.extension().and_then(|e| e.to_str()) {
        Some("mcap") => Ok(Format::Mcap),
        Some("jsonl") => Ok(Format::Jsonl),
        Some("csv") => Ok(Format::Csv),
        _ => bail!(
            "{}: output must end in .mcap, .jsonl or .csv",
            out.display()
        ),
    }
}

/// One replayed run.
struct Replayed {
    file: PathBuf,
    run_id: String,
    asset_id: String,
    label_bar: Option<f64>,
    t0_ns: i64,
    estimates: Vec<Estimate>,
    counters: EstimatorCounters,
    samples: usize,
    seconds: f64,
}

/// A unit baseline file: the three numbers of [`UnitBaseline`], bare or
/// under `observer_baseline` (with provenance beside them).
fn read_baseline(path: &Path) -> Result<UnitBaseline> {
    let text = std::fs::read_to_string(path)
        .with_context(|| format!("--observer-baseline {}", path.display()))?;
    let value: serde_json::Value = serde_json::from_str(&text)
        .with_context(|| format!("--observer-baseline {}: not JSON", path.display()))?;
    UnitBaseline::from_document(value)
        .map_err(|e| anyhow::anyhow!("--observer-baseline {}: {e}", path.display()))
}

/// Runs `shocktwin replay`.
pub fn run(args: &ReplayArgs) -> Result<std::process::ExitCode> {
    let format = format_of(&args.out)?;
    if args.files.is_empty() {
        bail!("replay: no input files");
    }
    let bundle = Arc::new(
        Bundle::load(&args.model)
            .with_context(|| format!("loading bundle {}", args.model.display()))?,
    );
    let mut cfg = EstimatorConfig::from_bundle(&bundle);
    if let Some(path) = &args.observer_baseline {
        if !bundle.groups.contains(&Group::Observer) {
            bail!(
                "--observer-baseline {}: the bundle {} does not read the charge observer \
                 (no `observer` group), so a baseline has nothing to correct",
                path.display(),
                args.model.display()
            );
        }
        cfg.observer_baseline = Some(read_baseline(path)?);
    }
    let road = road_calibration(args)?;
    let model = Model {
        bundle: Arc::clone(&bundle),
        road,
    };
    let several = args.files.len() > 1;
    let mcap_out = |run_id: &str| -> PathBuf {
        if several {
            let stem = args.out.with_extension("");
            PathBuf::from(format!("{}-{run_id}.mcap", stem.display()))
        } else {
            args.out.clone()
        }
    };

    let cores = std::thread::available_parallelism().map_or(1, usize::from);
    let workers = args.jobs.unwrap_or(cores).clamp(1, args.files.len());
    // A core to spare per worker: each streamed file is read and decoded on
    // a thread of its own beside its estimator.
    let pipelined = 2 * workers <= cores;
    let next = AtomicUsize::new(0);
    let results: Mutex<Vec<(usize, Result<Replayed>)>> = Mutex::new(Vec::new());
    let started = Instant::now();
    let bar = crate::progress::bar(args.files.len() as u64, "replay");
    std::thread::scope(|scope| {
        for _ in 0..workers {
            scope.spawn(|| loop {
                let i = next.fetch_add(1, Ordering::Relaxed);
                let Some(file) = args.files.get(i) else { break };
                let res = replay_file(file, &model, cfg, format, &mcap_out, pipelined);
                bar.inc(1);
                results
                    .lock()
                    .unwrap_or_else(std::sync::PoisonError::into_inner)
                    .push((i, res));
            });
        }
    });
    bar.finish_and_clear();
    let wall_s = started.elapsed().as_secs_f64();
    let mut results = results
        .into_inner()
        .unwrap_or_else(std::sync::PoisonError::into_inner);
    results.sort_by_key(|(i, _)| *i);

    let mut failed = 0usize;
    let mut ok = Vec::new();
    for (_, res) in results {
        match res {
            Ok(r) => ok.push(r),
            Err(err) => {
                failed += 1;
                eprintln!("shocktwin replay: {err:#}");
            }
        }
    }
    match format {
        Format::Jsonl | Format::Csv => write_table(&args.out, format, &ok)?,
        Format::Mcap => {}
    }
    print_summary(&ok, wall_s, &args.out, several && format == Format::Mcap);
    Ok(if failed > 0 {
        std::process::ExitCode::FAILURE
    } else {
        std::process::ExitCode::SUCCESS
    })
}

/// `--road` (with `--road-baseline`): the road calibration every file is
/// read with.
fn road_calibration(args: &ReplayArgs) -> Result<Option<RoadCalibration>> {
    Ok(match &args.road {
        Some(path) => {
            let text = std::fs::read_to_string(path)
                .with_context(|| format!("--road {}", path.display()))?;
            let cal = RoadCalibration::from_json(&path.display().to_string(), &text)
                .map_err(|e| anyhow::anyhow!("--road {e}"))?;
            match &args.road_baseline {
                Some(spec) => {
                    let (drive, bar) = crate::cmd_road::parse_baseline(spec)?;
                    let health = dt_core::bundle::HealthConfig::default();
                    let base = crate::cmd_road::read_one(&drive, &cal, health)
                        .with_context(|| format!("--road-baseline {spec}"))?;
                    Some(
                        cal.with_baseline(&base.blocks, bar)
                            .map_err(|e| anyhow::anyhow!("--road-baseline {spec}: {e}"))?,
                    )
                }
                None => Some(cal),
            }
        }
        None if args.road_baseline.is_some() => bail!("--road-baseline needs --road"),
        None => None,
    })
}

/// The bundle, and the road calibration every file is read with (`--road`).
struct Model {
    bundle: Arc<Bundle>,
    road: Option<RoadCalibration>,
}

impl Model {
    fn estimator(&self, cfg: EstimatorConfig, name: &str) -> Result<Estimator> {
        let est = Estimator::new(Arc::clone(&self.bundle), cfg)
            .with_context(|| format!("{name}: estimator"))?;
        match &self.road {
            Some(cal) => est
                .with_road(cal.clone())
                .map_err(|e| anyhow::anyhow!("{name}: road observer: {e}")),
            None => Ok(est),
        }
    }
}

/// Replays one file: as it is read when it is clean and in order
/// ([`replay_streaming`]), else the whole-file way, which sorts the samples
/// and reports what it skipped.
fn replay_file(
    file: &Path,
    model: &Model,
    cfg: EstimatorConfig,
    format: Format,
    mcap_out: &dyn Fn(&str) -> PathBuf,
    pipelined: bool,
) -> Result<Replayed> {
    let started = Instant::now();
    if let Some(replayed) =
        replay_streaming(file, model, cfg, format, mcap_out, started, pipelined)?
    {
        return Ok(replayed);
    }
    replay_whole(file, model, cfg, format, mcap_out, started)
}

/// What the reader of a streamed file passes on: the events of the file in
/// order, then whether it ended complete; or the first thing that makes the
/// streaming path give way (a message that does not decode, an unknown
/// topic), or a read error.
enum Decoded {
    Sample(Sample),
    /// Boxed: the metadata comes once, the samples millions of times.
    Metadata(Box<RunMetadata>),
    /// A message that does not decode, or a topic this format does not know.
    GiveWay,
    Failed(anyhow::Error),
    /// The end of the file; `true` when the decoder found it complete.
    End(bool),
}

/// The events of `input` as [`LogDecoder`] reads them, 1 MiB at a time,
/// ending with [`Decoded::End`] (or at the first [`Decoded::GiveWay`] or
/// [`Decoded::Failed`]). The samples are decoded [`SAMPLES_AT_ONCE`] at a
/// time into a buffer kept here ([`LogDecoder::next_samples`]), then handed
/// out one by one: the same events in the same order as `next_event` gives.
fn decoded(mut input: File, name: String) -> impl Iterator<Item = Decoded> {
    // `None` once the end, a give-way or a failure was passed on.
    let mut decoder = Some(LogDecoder::new(&name));
    let mut samples: Vec<Sample> = Vec::with_capacity(SAMPLES_AT_ONCE);
    let mut handed = 0;
    // The event that ended the last run of samples, handed out after them.
    let mut after: Option<Decoded> = None;
    std::iter::from_fn(move || loop {
        if let Some(&sample) = samples.get(handed) {
            handed += 1;
            return Some(Decoded::Sample(sample));
        }
        if let Some(event) = after.take() {
            return Some(event);
        }
        samples.clear();
        handed = 0;
        if let Some(event) = decoder
            .as_mut()?
            .next_samples(&mut samples, SAMPLES_AT_ONCE)
        {
            after = match event {
                Ok(LogEvent::Sample(s)) => Some(Decoded::Sample(s)),
                Ok(LogEvent::Metadata(m)) => Some(Decoded::Metadata(Box::new(m))),
                Ok(LogEvent::End) => None,
                Ok(LogEvent::Unknown { .. }) | Err(_) => {
                    decoder = None;
                    Some(Decoded::GiveWay)
                }
            };
            continue;
        }
        if !samples.is_empty() {
            continue;
        }
        match decoder.as_mut()?.feed_from(&mut input, 1 << 20) {
            Ok(0) => return Some(Decoded::End(decoder.take()?.finish().is_ok())),
            Ok(_) => {}
            Err(e) => {
                decoder = None;
                return Some(Decoded::Failed(
                    anyhow::Error::new(e).context(format!("reading {name}")),
                ));
            }
        }
    })
}

/// Samples [`decoded`] decodes at a time: 32 kB, well inside the L1 cache.
const SAMPLES_AT_ONCE: usize = 1024;

/// Events a reading thread hands over at a time.
const DECODED_BATCH: usize = 4096;

/// A batch's text is handed over once it passes this many bytes, whatever
/// its count of events (a few large messages must not pile up).
const BATCH_TEXT_BYTES: usize = 1 << 20;

/// What the reading thread hands over: events in file order, the sensor
/// messages among them with their JSON text not parsed yet.
struct Batch {
    items: Vec<Handed>,
    /// The sensor messages' texts, one after the other.
    text: Vec<u8>,
}

enum Handed {
    Event(Decoded),
    /// A sensor message whose text ends at this offset of the batch's
    /// `text` (and starts where the previous one ended).
    Sample(SampleMessage, usize),
}

impl Batch {
    fn new() -> Self {
        Batch {
            items: Vec::with_capacity(DECODED_BATCH),
            text: Vec::with_capacity(DECODED_BATCH * 64),
        }
    }

    fn full(&self) -> bool {
        self.items.len() >= DECODED_BATCH || self.text.len() >= BATCH_TEXT_BYTES
    }

    /// The batch's events, its sensor messages parsed here (a message that
    /// does not parse gives way, as [`decoded`] does).
    fn decoded(self, name: &str) -> impl Iterator<Item = Decoded> + '_ {
        let Batch { items, text } = self;
        let mut start = 0;
        items.into_iter().map(move |item| match item {
            Handed::Event(event) => event,
            Handed::Sample(message, end) => {
                let data = &text[start..end];
                start = end;
                message
                    .decode(name, data)
                    .map_or(Decoded::GiveWay, Decoded::Sample)
            }
        })
    }
}

/// Reads and splits `input` into batches on `tx` until its end, a give-way,
/// a failure, or the receiver is gone. The JSON of the sensor messages is
/// left to the receiving thread, so that the two threads share the work.
fn read_batches(mut input: File, name: &str, tx: &std::sync::mpsc::SyncSender<Batch>) {
    let mut decoder = LogDecoder::new(name);
    let mut batch = Batch::new();
    loop {
        while let Some(event) = decoder.next_undecoded(&mut batch.text) {
            let item = match event {
                Ok(Undecoded::Sample(message)) => Handed::Sample(message, batch.text.len()),
                Ok(Undecoded::Event(LogEvent::Metadata(m))) => {
                    Handed::Event(Decoded::Metadata(Box::new(m)))
                }
                Ok(Undecoded::Event(LogEvent::Sample(s))) => Handed::Event(Decoded::Sample(s)),
                Ok(Undecoded::Event(LogEvent::End)) => continue,
                Ok(Undecoded::Event(LogEvent::Unknown { .. })) | Err(_) => {
                    batch.items.push(Handed::Event(Decoded::GiveWay));
                    let _ = tx.send(batch);
                    return;
                }
            };
            batch.items.push(item);
            if batch.full()
                && tx
                    .send(std::mem::replace(&mut batch, Batch::new()))
                    .is_err()
            {
                return; // the replay gave way: stop reading
            }
        }
        let last = match decoder.feed_from(&mut input, 1 << 20) {
            Ok(0) => Decoded::End(decoder.finish().is_ok()),
            Ok(_) => continue,
            Err(e) => Decoded::Failed(anyhow::Error::new(e).context(format!("reading {name}"))),
        };
        batch.items.push(Handed::Event(last));
        let _ = tx.send(batch);
        return;
    }
}

/// Replays `file` while reading it, with neither the file nor its samples
/// held in memory. Valid when every message decodes, every topic is known,
/// the file is complete and its samples come in the order the whole-file
/// path sorts them into, `(t_ns, topic rank)`: the estimator then sees the
/// same samples in the same order and both paths give the same output.
/// `Ok(None)` at the first thing that is not so; the caller then replays
/// the file the whole-file way ([`replay_whole`]), which sorts and reports.
///
/// With `pipelined`, a second thread reads the file (zstd, the MCAP records)
/// while this one parses the sensor messages' JSON and runs the estimator,
/// which shares a replay's work about evenly between the two; the events
/// reach the estimator in the same order, so the output is the same.
fn replay_streaming(
    file: &Path,
    model: &Model,
    cfg: EstimatorConfig,
    format: Format,
    mcap_out: &dyn Fn(&str) -> PathBuf,
    started: Instant,
    pipelined: bool,
) -> Result<Option<Replayed>> {
    let name = file.display().to_string();
    let input = File::open(file).with_context(|| format!("opening {name}"))?;
    let est = model.estimator(cfg, &name)?;
    if !pipelined {
        let events = decoded(input, name);
        return replay_events(file, est, events, format, mcap_out, started);
    }
    std::thread::scope(|scope| {
        let (tx, rx) = std::sync::mpsc::sync_channel::<Batch>(4);
        let reader = std::thread::Builder::new().name("replay-decode".into());
        let reader_name = name.clone();
        let spawned = reader.spawn_scoped(scope, move || read_batches(input, &reader_name, &tx));
        spawned.with_context(|| format!("{}: starting its reader thread", file.display()))?;
        // Dropping the receiver (on return) stops the reader at its next batch.
        let events = rx.into_iter().flat_map(|batch| batch.decoded(&name));
        replay_events(file, est, events, format, mcap_out, started)
    })
}

/// The streaming replay of the events of `file` ([`replay_streaming`]).
fn replay_events(
    file: &Path,
    mut est: Estimator,
    events: impl Iterator<Item = Decoded>,
    format: Format,
    mcap_out: &dyn Fn(&str) -> PathBuf,
    started: Instant,
) -> Result<Option<Replayed>> {
    let mut metadata: Option<RunMetadata> = None;
    let mut writer = None;
    let mut estimates = Vec::new();
    let mut last: Option<(i64, u8)> = None;
    let (mut t0_ns, mut samples) = (0i64, 0usize);
    let mut complete = false;
    for item in events {
        let s = match item {
            Decoded::Sample(s) => s,
            Decoded::Metadata(m) => {
                if format == Format::Mcap {
                    writer = Some(LogWriter::create(
                        mcap_out(&m.run_id),
                        &m,
                        WriteOptions::default(),
                    )?);
                }
                metadata = Some(*m);
                continue;
            }
            Decoded::GiveWay => return Ok(None),
            Decoded::Failed(e) => return Err(e),
            Decoded::End(ok) => {
                complete = ok;
                break;
            }
        };
        let key = (s.t_ns(), s.topic_rank());
        if last.is_some_and(|l| key < l) {
            return Ok(None);
        }
        if last.is_none() {
            t0_ns = key.0;
        }
        last = Some(key);
        samples += 1;
        if est.push(s).is_err() {
            return Ok(None);
        }
        take_estimates(&mut est, writer.as_mut(), Some(&s), &mut estimates)?;
    }
    let Some(metadata) = metadata else {
        return Ok(None);
    };
    if !complete || est.finish().is_err() {
        return Ok(None);
    }
    take_estimates(&mut est, writer.as_mut(), None, &mut estimates)?;
    if let Some(w) = writer {
        w.finish()?;
    }
    Ok(Some(Replayed {
        file: file.to_path_buf(),
        run_id: metadata.run_id,
        asset_id: metadata.asset_id,
        label_bar: metadata.charge_pressure_bar,
        t0_ns,
        counters: est.counters(),
        samples,
        estimates,
        seconds: started.elapsed().as_secs_f64(),
    }))
}

/// Replays `file` read whole: the samples sorted by `(t_ns, topic rank)`,
/// skipped messages and ignored topics reported.
fn replay_whole(
    file: &Path,
    model: &Model,
    cfg: EstimatorConfig,
    format: Format,
    mcap_out: &dyn Fn(&str) -> PathBuf,
    started: Instant,
) -> Result<Replayed> {
    let log = read_log(file)?;
    for problem in &log.problems {
        tracing::warn!(file = %file.display(), "{problem}");
    }
    let mut est = model.estimator(cfg, &file.display().to_string())?;
    let mut estimates = Vec::new();
    let mut writer = match format {
        Format::Mcap => {
            let path = mcap_out(&log.metadata.run_id);
            Some(LogWriter::create(
                &path,
                &log.metadata,
                WriteOptions::default(),
            )?)
        }
        _ => None,
    };
    for s in log.samples_in_order() {
        est.push(s).with_context(|| format!("{}", file.display()))?;
        take_estimates(&mut est, writer.as_mut(), Some(&s), &mut estimates)?;
    }
    est.finish()
        .with_context(|| format!("{}", file.display()))?;
    take_estimates(&mut est, writer.as_mut(), None, &mut estimates)?;
    if let Some(w) = writer {
        w.finish()?;
    }
    Ok(Replayed {
        file: file.to_path_buf(),
        run_id: log.metadata.run_id.clone(),
        asset_id: log.metadata.asset_id.clone(),
        label_bar: log.metadata.charge_pressure_bar,
        t0_ns: t0(&log),
        counters: est.counters(),
        samples: log.sample_count(),
        estimates,
        seconds: started.elapsed().as_secs_f64(),
    })
}

/// After a sample (`Some`, written to the MCAP output first) or at the end
/// (`None`): moves the estimator's new estimates into `estimates` and, with an
/// MCAP output, into the log after the sample.
fn take_estimates<W: Write + Seek>(
    est: &mut Estimator,
    writer: Option<&mut LogWriter<W>>,
    sample: Option<&Sample>,
    estimates: &mut Vec<Estimate>,
) -> Result<()> {
    let Some(w) = writer else {
        estimates.extend(est.drain());
        return Ok(());
    };
    if let Some(s) = sample {
        w.write_sample(s)?;
    }
    for e in est.drain() {
        w.write_json(topic::ESTIMATE, ESTIMATE_SCHEMA_JSON, e.t_ns, &e)?;
        estimates.push(e);
    }
    Ok(())
}

fn t0(log: &RunLog) -> i64 {
    log.t0_ns().unwrap_or(0)
}

const FIELDS: [&str; 13] = [
    "run_id",
    "asset_id",
    "t_s",
    "pressure_bar",
    "pressure_avg_bar",
    "pressure_lo_bar",
    "pressure_hi_bar",
    "expected_bar",
    "health",
    "velocity_mps",
    "force_model_n",
    "oil_temp_c",
    "label_bar",
];

/// `,x`, written in place (no `String` per field): `x` in the layout of
/// Rust's `Display` (the shortest digits that read back to `x` exactly, no
/// exponent), or nothing for a value that is not finite. The digits come from `zmij` (Schubfach, as `serde_json` prints
/// them; several times faster than `Display`). Where the shortest needs 16
/// or 17 significant digits and more than one last digit reads back to `x`,
/// the two may take different ones (261 of the test's two million numbers):
/// the text then differs from `Display`'s in that digit, the number read
/// back does not. An integer's trailing `.0` is dropped and very large or
/// small magnitudes (an exponent) are left to `Display`. Test:
/// `csv_numbers_read_back_exactly_in_displays_layout`.
fn push_num(line: &mut String, x: f64) {
    line.push(',');
    if x.is_finite() {
        let mut buf = zmij::Buffer::new();
        let s = buf.format_finite(x);
        if s.contains('e') {
            let _ = write!(line, "{x}");
        } else {
            line.push_str(s.strip_suffix(".0").unwrap_or(s));
        }
    }
}

fn write_table(out: &Path, format: Format, runs: &[Replayed]) -> Result<()> {
    let file = File::create(out).with_context(|| format!("creating {}", out.display()))?;
    let mut w = BufWriter::with_capacity(1 << 20, file);
    if format == Format::Csv {
        writeln!(w, "{}", FIELDS.join(","))?;
    }
    let mut line = String::new();
    for r in runs {
        for e in &r.estimates {
            let t_s = (e.t_ns - r.t0_ns) as f64 * 1e-9;
            line.clear();
            if format == Format::Csv {
                let _ = write!(line, "{},{},{t_s:.3}", r.run_id, r.asset_id);
                push_num(&mut line, e.pressure_bar);
                push_num(&mut line, e.pressure_avg_bar);
                push_num(&mut line, e.pressure_lo_bar);
                push_num(&mut line, e.pressure_hi_bar);
                push_num(&mut line, e.expected_bar);
                let _ = write!(line, ",{}", e.health);
                push_num(&mut line, e.velocity_mps);
                push_num(&mut line, e.force_model_n);
                push_num(&mut line, e.oil_temp_c);
                push_num(&mut line, r.label_bar.unwrap_or(f64::NAN));
            } else {
                let mut v = serde_json::to_value(e)?;
                let obj = v.as_object_mut().expect("an Estimate is an object");
                obj.remove("t_ns");
                obj.insert("run_id".into(), r.run_id.clone().into());
                obj.insert("asset_id".into(), r.asset_id.clone().into());
                obj.insert("t_s".into(), ((t_s * 1e3).round() / 1e3).into());
                if let Some(label) = r.label_bar {
                    obj.insert("label_bar".into(), label.into());
                }
                line = serde_json::to_string(&v)?;
            }
            writeln!(w, "{line}")?;
        }
    }
    w.flush()
        .with_context(|| format!("writing {}", out.display()))?;
    Ok(())
}

/// RMSE of the instantaneous and the 1 s average pressure against the label,
/// over ticks with a finite 1 s average; `None` without a label or ticks.
fn rmse(r: &Replayed) -> Option<(f64, f64, usize)> {
    let label = r.label_bar?;
    let (mut s_inst, mut s_avg, mut n) = (0.0, 0.0, 0usize);
    for e in &r.estimates {
        if e.pressure_avg_bar.is_finite() && e.pressure_bar.is_finite() {
            s_inst += (e.pressure_bar - label).powi(2);
            s_avg += (e.pressure_avg_bar - label).powi(2);
            n += 1;
        }
    }
    (n > 0).then(|| ((s_inst / n as f64).sqrt(), (s_avg / n as f64).sqrt(), n))
}

/// What the charge observer made of a run's velocity reversals, when it
/// saw any; says so when none was read because the calibration does not
/// cover the run's excitation.
fn observer_line(o: &dt_core::charge::ObserverCounters) -> Option<String> {
    if o.detected == 0 {
        return None;
    }
    let mut line = format!(
        "charge observer: {} reversals, {} read, {} spared, {} failed their window, {} rejected, \
         {} at an excitation the calibration does not cover",
        o.detected, o.used, o.spared, o.skipped, o.rejected, o.uncalibrated
    );
    if o.not_calibrated_here() {
        line.push_str(
            " (the estimate kept its prior: calibrate the observer at this excitation, \
             `python -m train.observer fit`)",
        );
    }
    Some(line)
}

fn print_summary(runs: &[Replayed], wall_s: f64, out: &Path, pattern: bool) {
    println!(
        "{:<28} {:>9} {:>8} {:>8} {:>11} {:>11} {:>8} {:>9}",
        "run", "label", "ticks", "final", "RMSE inst", "RMSE 1 s", "health", "speed"
    );
    let mut data_s = 0.0;
    for r in runs {
        let last = r.estimates.last();
        let dur_s = r.estimates.len() as f64 * 0.02;
        data_s += dur_s;
        let (inst, avg) = rmse(r).map_or(("n/a".into(), "n/a".into()), |(i, a, _)| {
            (format!("{i:.3}"), format!("{a:.3}"))
        });
        println!(
            "{:<28} {:>9} {:>8} {:>8} {:>11} {:>11} {:>8} {:>8.0}x",
            r.run_id,
            r.label_bar.map_or("-".into(), |l| format!("{l:.2}")),
            r.estimates.len(),
            last.map_or("-".into(), |e| format!("{:.2}", e.pressure_avg_bar)),
            inst,
            avg,
            last.map_or("-".into(), |e| e.health.to_string()),
            dur_s / r.seconds.max(1e-9),
        );
        let c = r.counters;
        if c.late_dropped + c.clock_jumps + c.missing_samples + c.timestamp_outliers > 0 {
            println!(
                "  {}: {} samples, {} late dropped, {} re-ordered, {} clock jumps, {} timestamp outliers, {} missing, {} ticks without inputs",
                r.file.display(),
                r.samples,
                c.late_dropped,
                c.reordered,
                c.clock_jumps,
                c.timestamp_outliers,
                c.missing_samples,
                c.ticks_without_inputs
            );
        }
        if let Some(line) = observer_line(&c.observer) {
            println!("  {}: {line}", r.file.display());
        }
        if let Some(road) = c.road {
            println!(
                "  {}: road observer: {} blocks read, {} at rest, {} slower than calibrated, {} without positions, {} settling, {} unsolved{}",
                r.file.display(),
                road.read,
                road.at_rest,
                road.slower_than_calibrated,
                road.without_positions,
                road.settling,
                road.unsolved,
                road.why_none().map_or(String::new(), |w| format!(" ({w})"))
            );
        }
    }
    println!(
        "replayed {} run(s), {:.0} s of data in {:.2} s wall ({:.0}x real time); estimates in {}{}",
        runs.len(),
        data_s,
        wall_s,
        data_s / wall_s.max(1e-9),
        out.display(),
        if pattern {
            " (one file per run: OUT-<run_id>.mcap)"
        } else {
            ""
        }
    );
}

#[cfg(test)]
mod tests {
    use super::*;
    use dt_core::log::{Compression, Sample};

    /// The CSV's numbers read back to the same bits, in `Display`'s layout
    /// and length, and differ from `Display`'s text in a few last digits
    /// only (each at 16 or more significant digits): a million random bit
    /// patterns (every magnitude), a million values at the scales the
    /// columns hold, and the edges (integers, ±0, tiny, huge).
    #[test]
    fn csv_numbers_read_back_exactly_in_displays_layout() {
        let mut state = 0x9e37_79b9_7f4a_7c15_u64;
        let mut next = move || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            state
        };
        let edges = [
            0.0,
            -0.0,
            1.0,
            12.0,
            -5.0,
            0.1,
            1e-7,
            1e-300,
            5e-324,
            1e15,
            1e16,
            1e17,
            1e21,
            f64::MAX,
            f64::MIN_POSITIVE,
            123_456.789,
            -0.000_123,
            f64::NAN,
            f64::INFINITY,
        ];
        let randoms: Vec<f64> = (0..1_000_000).map(|_| f64::from_bits(next())).collect();
        let scaled: Vec<f64> = (0..1_000_000)
            .map(|i| {
                let u = (next() >> 11) as f64 / (1u64 << 53) as f64;
                let scale = [1e-3, 1.0, 20.0, 1e3, 1e5][i % 5];
                (u - 0.3) * scale
            })
            .collect();
        let (mut ours, mut std_) = (String::new(), String::new());
        let (mut differ, mut fewest) = (0usize, usize::MAX);
        for x in edges.into_iter().chain(randoms).chain(scaled) {
            ours.clear();
            push_num(&mut ours, x);
            std_.clear();
            std_.push(',');
            if x.is_finite() {
                let _ = write!(std_, "{x}");
            }
            if ours == std_ {
                continue;
            }
            differ += 1;
            let what = format!("{:#x}: {ours} against {std_}", x.to_bits());
            let back: f64 = ours[1..].parse().expect(&what);
            assert_eq!(back.to_bits(), x.to_bits(), "{what}");
            assert_eq!(ours.len(), std_.len(), "{what}");
            let digits = ours.bytes().filter(u8::is_ascii_digit).count();
            let same = ours
                .bytes()
                .zip(std_.bytes())
                .take_while(|(a, b)| a == b)
                .count();
            assert!(same == ours.len() - 1, "{what}");
            fewest = fewest.min(digits);
        }
        eprintln!("{differ} of 2,000,019 differ from Display in their last digit, the fewest digits {fewest}");
        assert!(differ < 2_000, "{differ} of 2,000,019 differ from Display");
    }

    fn bundle() -> Arc<Bundle> {
        let dir = PathBuf::from(env!("CARGO_MANIFEST_DIR"))
            .join("../dt-core/tests/fixtures/bundle-mlp13");
        Arc::new(Bundle::load(&dir).expect("fixture bundle"))
    }

    /// 30 s of a 2 Hz stroke with every topic the fixture bundle reads, in
    /// `(t_ns, topic rank)` order.
    fn samples() -> Vec<Sample> {
        let mut out = Vec::new();
        for ms in 0..30_000i64 {
            let t_ns = 1_000_000_000 + ms * 1_000_000;
            let phase = ms as f64 * 1e-3 * 2.0 * std::f64::consts::PI * 2.0;
            out.push(Sample::Acceleration {
                t_ns,
                a1_mps2: 6.0 * phase.sin(),
                a2_mps2: 0.3 * phase.cos(),
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
                    temperature_c: 30.0 + ms as f64 * 1e-4,
                });
                out.push(Sample::TempAmbient {
                    t_ns,
                    temperature_c: 20.0,
                });
            }
        }
        out
    }

    fn write(path: &Path, samples: &[Sample]) {
        let meta = RunMetadata {
            asset_id: "unit-a".into(),
            run_id: "r1".into(),
            charge_pressure_bar: Some(7.0),
            ..RunMetadata::default()
        };
        let options = WriteOptions {
            compression: Compression::Zstd,
            chunk_size: Some(64 << 10),
        };
        let mut w = LogWriter::create(path, &meta, options).unwrap();
        for s in samples {
            w.write_sample(s).unwrap();
        }
        w.finish().unwrap();
    }

    fn rows(r: &Replayed) -> Vec<String> {
        r.estimates
            .iter()
            .map(|e| serde_json::to_string(e).unwrap())
            .collect()
    }

    #[test]
    fn a_file_in_order_streams_and_replays_as_the_same_samples_sorted() {
        let dir = tempfile::tempdir().unwrap();
        let in_order = dir.path().join("in-order.mcap");
        let shuffled = dir.path().join("shuffled.mcap");
        let samples = samples();
        write(&in_order, &samples);
        // the same samples with every 997th one written after its
        // successor: out of `(t_ns, topic rank)` order in the file
        let mut moved = samples.clone();
        for k in (0..moved.len() - 1).step_by(997) {
            moved.swap(k, k + 1);
        }
        assert!(moved
            .windows(2)
            .any(|w| (w[1].t_ns(), w[1].topic_rank()) < (w[0].t_ns(), w[0].topic_rank())));
        write(&shuffled, &moved);

        let (b, cfg) = (
            Model {
                bundle: bundle(),
                road: None,
            },
            EstimatorConfig::from_bundle(&bundle()),
        );
        let no_mcap = |_: &str| PathBuf::new();
        let t = Instant::now();
        let streamed = replay_streaming(&in_order, &b, cfg, Format::Csv, &no_mcap, t, false)
            .unwrap()
            .expect("a clean file in order streams");
        for pipelined in [false, true] {
            assert!(
                replay_streaming(&shuffled, &b, cfg, Format::Csv, &no_mcap, t, pipelined)
                    .unwrap()
                    .is_none(),
                "a file out of order must not stream"
            );
        }
        // Read and decoded on a second thread: the same rows.
        let pipelined = replay_streaming(&in_order, &b, cfg, Format::Csv, &no_mcap, t, true)
            .unwrap()
            .expect("a clean file in order streams, pipelined too");
        assert_eq!(rows(&pipelined), rows(&streamed));
        assert_eq!(pipelined.samples, streamed.samples);
        assert_eq!(pipelined.counters, streamed.counters);
        let whole = replay_file(&shuffled, &b, cfg, Format::Csv, &no_mcap, true).unwrap();
        let whole_in_order = replay_whole(&in_order, &b, cfg, Format::Csv, &no_mcap, t).unwrap();

        assert!(
            streamed.estimates.len() > 1000,
            "{}",
            streamed.estimates.len()
        );
        assert_eq!(rows(&streamed), rows(&whole));
        assert_eq!(rows(&streamed), rows(&whole_in_order));
        assert_eq!(streamed.samples, samples.len());
        assert_eq!(whole.samples, samples.len());
        assert_eq!(streamed.t0_ns, whole.t0_ns);
        assert_eq!(streamed.label_bar, Some(7.0));
        assert_eq!(
            (streamed.run_id.as_str(), streamed.asset_id.as_str()),
            ("r1", "unit-a")
        );
    }

    #[test]
    fn a_message_that_does_not_parse_gives_way_to_the_whole_file_path_either_way() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("one-bad.mcap");
        let samples = samples();
        let meta = RunMetadata {
            asset_id: "unit-a".into(),
            run_id: "r1".into(),
            ..RunMetadata::default()
        };
        let mut w = LogWriter::create(&path, &meta, WriteOptions::default()).unwrap();
        let middle = samples.len() / 2;
        for (k, s) in samples.iter().enumerate() {
            w.write_sample(s).unwrap();
            if k == middle {
                // in order, on the sensor topic, but its value is text
                let bad = serde_json::json!({ "temperature_c": "warm" });
                w.write_json(topic::TEMP_AMBIENT, "", s.t_ns(), &bad)
                    .unwrap();
            }
        }
        w.finish().unwrap();
        let (b, cfg) = (
            Model {
                bundle: bundle(),
                road: None,
            },
            EstimatorConfig::from_bundle(&bundle()),
        );
        let no_mcap = |_: &str| PathBuf::new();
        let t = Instant::now();
        let mut replayed = Vec::new();
        for pipelined in [false, true] {
            assert!(
                replay_streaming(&path, &b, cfg, Format::Csv, &no_mcap, t, pipelined)
                    .unwrap()
                    .is_none(),
                "a message that does not parse must give way (pipelined: {pipelined})"
            );
            replayed.push(replay_file(&path, &b, cfg, Format::Csv, &no_mcap, pipelined).unwrap());
        }
        // The whole-file path skips the one message and keeps every other.
        assert_eq!(replayed[0].samples, samples.len());
        assert_eq!(rows(&replayed[0]), rows(&replayed[1]));
        assert!(replayed[0].estimates.len() > 1000);
    }

    #[test]
    fn a_truncated_file_does_not_stream_and_is_reported_whole() {
        let dir = tempfile::tempdir().unwrap();
        let full = dir.path().join("full.mcap");
        write(&full, &samples());
        let bytes = std::fs::read(&full).unwrap();
        let cut = dir.path().join("cut.mcap");
        std::fs::write(&cut, &bytes[..bytes.len() / 2]).unwrap();
        let (b, cfg) = (
            Model {
                bundle: bundle(),
                road: None,
            },
            EstimatorConfig::from_bundle(&bundle()),
        );
        let no_mcap = |_: &str| PathBuf::new();
        let t = Instant::now();
        for pipelined in [false, true] {
            assert!(
                replay_streaming(&cut, &b, cfg, Format::Csv, &no_mcap, t, pipelined)
                    .unwrap()
                    .is_none()
            );
            let err = replay_file(&cut, &b, cfg, Format::Csv, &no_mcap, pipelined)
                .err()
                .expect("a truncated file is an error, as before");
            assert!(format!("{err:#}").contains("cut.mcap"), "{err:#}");
        }
    }
}
