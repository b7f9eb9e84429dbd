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
//!
//! The rows are written as the estimates come, not kept: a replay's memory
//! does not grow with the length of its runs. With several inputs replayed
//! side by side, each run's rows go to a temporary file of its own beside
//! the output first (closed when the run ends, deleted once copied) and are
//! copied into it in input order at the end.

use std::fmt::Write as _;
use std::fs::File;
use std::io::{BufWriter, Seek, SeekFrom, Write};
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
use tempfile::TempPath;

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
    label_bar: Option<f64>,
    tally: Tally,
    counters: EstimatorCounters,
    samples: usize,
    seconds: f64,
    /// Why the estimate is an extrapolation of the network
    /// ([`Bundle::untrained_excitation`]).
    untrained: Option<String>,
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
    let runs = RunIds::new(&args.files);
    let results: Mutex<Vec<Done>> = Mutex::new(Vec::new());
    // The table (CSV, JSONL), created before any work: one input's rows go
    // straight into it, several inputs' into a part each ([`write_table`]).
    let (staged, mut table) = table_output(&args.out, format)?;
    let direct = Mutex::new(if several { None } else { table.take() });
    let started = Instant::now();
    let bar = crate::progress::bar(args.files.len() as u64, "replay");
    std::thread::scope(|scope| {
        for _ in 0..workers {
            scope.spawn(|| loop {
                let i = next.fetch_add(1, Ordering::Relaxed);
                let Some(file) = args.files.get(i) else { break };
                let table = match direct.lock().map(|mut d| d.take()) {
                    Ok(Some(part)) => Ok(Some(part)),
                    _ if several && format != Format::Mcap => Part::beside(&args.out).map(Some),
                    _ => Ok(None),
                };
                let run_out = |run_id: &str| runs.claim(i, run_id).map(|()| mcap_out(run_id));
                let (res, part) = match table {
                    Ok(table) => {
                        replay_rows(file, &model, &cfg, format, &run_out, pipelined, table)
                    }
                    Err(e) => (Err(e), None),
                };
                bar.inc(1);
                results
                    .lock()
                    .unwrap_or_else(std::sync::PoisonError::into_inner)
                    .push(Done { i, res, part });
            });
        }
    });
    bar.finish_and_clear();
    let wall_s = started.elapsed().as_secs_f64();
    let mut results = results
        .into_inner()
        .unwrap_or_else(std::sync::PoisonError::into_inner);
    results.sort_by_key(|d| d.i);

    let mut failed = 0usize;
    let mut ok = Vec::new();
    let mut parts = Vec::new();
    for done in results {
        match done.res {
            Ok(r) => ok.push(r),
            Err(err) => {
                failed += 1;
                eprintln!("shocktwin replay: {err:#}");
            }
        }
        parts.extend(done.part);
    }
    if let Some(table) = table {
        write_table(table, &parts)?;
    }
    if let Some(staged) = staged {
        finish_staged(staged, !ok.is_empty(), &args.out)?;
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
    fn estimator(&self, cfg: &EstimatorConfig, name: &str) -> Result<Estimator> {
        let est = Estimator::new(Arc::clone(&self.bundle), *cfg)
            .with_context(|| format!("{name}: estimator"))?;
        match &self.road {
            Some(cal) => est
                .with_road(cal.clone())
                .map_err(|e| anyhow::anyhow!("{name}: road observer: {e}")),
            None => Ok(est),
        }
    }
}

/// With `--road`: a dyno sine run is refused ([`dt_core::road::refuse_dyno_run`]).
fn refuse_dyno_run(file: &Path, est: &Estimator, meta: &RunMetadata) -> Result<()> {
    if est.road().is_some() {
        dt_core::road::refuse_dyno_run(meta)
            .map_err(|e| anyhow::anyhow!("{}: {e}", file.display()))?;
    }
    Ok(())
}

/// Replays one file: as it is read when it is clean and in order
/// ([`replay_streaming`]), else the whole-file way, which sorts the samples
/// and reports what it skipped.
fn replay_file(
    file: &Path,
    model: &Model,
    cfg: &EstimatorConfig,
    out: &mut Output,
    pipelined: bool,
) -> Result<Replayed> {
    let started = Instant::now();
    if let Some(replayed) = replay_streaming(file, model, cfg, out, started, pipelined)? {
        return Ok(replayed);
    }
    out.rewind()
        .with_context(|| format!("{}: read whole", file.display()))?;
    replay_whole(file, model, cfg, out, started)
}

/// Replays `file` with its rows into `table`, then keeps them or drops them
/// (a run that failed); an error there does not hide the run's own.
fn replay_rows(
    file: &Path,
    model: &Model,
    cfg: &EstimatorConfig,
    format: Format,
    run_out: &dyn Fn(&str) -> Result<PathBuf>,
    pipelined: bool,
    mut table: Option<Part>,
) -> (Result<Replayed>, Option<TempPath>) {
    let mut out = Output {
        format,
        run_out,
        table: table.as_mut(),
    };
    let res = replay_file(file, model, cfg, &mut out, pipelined);
    match table.map(|t| t.done(res.is_ok())).transpose() {
        Ok(part) => (res, part.flatten()),
        Err(e) => (res.and(Err(e)), None),
    }
}

/// One input replayed (its index among the inputs): its run or why not,
/// and the part its rows wait in (several inputs).
struct Done {
    i: usize,
    res: Result<Replayed>,
    part: Option<TempPath>,
}

/// Several inputs' table: after its header, each kept part's rows in input
/// order (each part's file is deleted when `parts` is dropped).
fn write_table(mut table: Part, parts: &[TempPath]) -> Result<()> {
    for path in parts {
        let mut part = File::open(path).with_context(|| format!("a part of {}", table.what))?;
        std::io::copy(&mut part, &mut table.w)
            .with_context(|| format!("writing {}", table.what))?;
    }
    table.done(true).map(|_| ())
}

/// The run ids of several inputs, each claimed by the first input that
/// reads it: two inputs of one run id (the same run given twice, or two
/// imports under one `--run-id`) would write one `OUT-<run_id>.mcap` at once
/// (a corrupt file) or mix their rows under one `run_id` in the table, so
/// the one read second is refused, naming the other (with several workers
/// that need not be the one given second: the metadata is read as each
/// file streams).
struct RunIds<'a> {
    files: &'a [PathBuf],
    claimed: Mutex<std::collections::HashMap<String, usize>>,
}

impl<'a> RunIds<'a> {
    fn new(files: &'a [PathBuf]) -> Self {
        Self {
            files,
            claimed: Mutex::default(),
        }
    }

    /// Claims `run_id` for input `i` (again, for a replay read whole after
    /// its streamed read gave way); an error when another input holds it.
    fn claim(&self, i: usize, run_id: &str) -> Result<()> {
        let mut claimed = self
            .claimed
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        let holder = *claimed.entry(run_id.to_owned()).or_insert(i);
        if holder == i {
            return Ok(());
        }
        bail!(
            "{}: run id `{run_id}` is also the run id of {}, replayed in this call: their \
             estimates cannot be told apart in one output (rows under one `run_id`, one \
             `<out>-{run_id}.mcap`); not replayed. Replay it on its own, or import it again \
             with another `--run-id`",
            self.files[i].display(),
            self.files[holder].display()
        )
    }
}

/// Where a replay's estimates go.
struct Output<'a> {
    format: Format,
    /// The run's MCAP output by its run id (`.mcap`), once the run id is
    /// claimed among the inputs' ([`RunIds::claim`]).
    run_out: &'a dyn Fn(&str) -> Result<PathBuf>,
    /// The run's table rows (`.csv`, `.jsonl`).
    table: Option<&'a mut Part>,
}

impl Output<'_> {
    /// Drops the table rows written so far (a replay that gave way).
    fn rewind(&mut self) -> Result<()> {
        self.table.as_deref_mut().map_or(Ok(()), Part::rewind)
    }
}

/// Where one run's table rows are written as they come: the output itself
/// (one input; after its header) or a file of its own beside it (several;
/// deleted when dropped), so that no file stays open once the run is done.
struct Part {
    w: BufWriter<File>,
    /// Where the run's rows start.
    start: u64,
    /// What it is, for errors: the output, or a part of it.
    what: String,
    /// A part's own file.
    path: Option<TempPath>,
}

/// The table's write buffer: with 1 MiB writes most new page-cache pages are
/// written whole (ext4 zeroes a page first written in part; with 8 KiB
/// writes that was 4 % of a one-core replay).
const TABLE_BUFFER: usize = 1 << 20;

/// The file a table output `out` is written to before it is renamed over
/// `out`: hidden, beside it, with the permissions a new `out` would get. None
/// when `out` exists and is not a regular file (a pipe, `/dev/stdout`),
/// which is written directly.
fn staged_table(out: &Path) -> Result<Option<TempPath>> {
    if std::fs::metadata(out).is_ok_and(|m| !m.is_file()) {
        return Ok(None);
    }
    let mut builder = tempfile::Builder::new();
    builder.prefix(".replay-").suffix(".part");
    #[cfg(unix)]
    {
        use std::os::unix::fs::PermissionsExt as _;
        // as `File::create` would (the umask applies)
        builder.permissions(std::fs::Permissions::from_mode(0o666));
    }
    let file = builder
        .tempfile_in(dir_of(out))
        .with_context(|| format!("creating {} (a file beside it first)", out.display()))?;
    Ok(Some(file.into_temp_path()))
}

/// The table output (CSV, JSONL; none for MCAP), and the file it is staged
/// in: written beside `out` and renamed over it once a run is in it (a
/// replay of which no run could be read left an earlier output truncated to
/// its header). A pipe or device is written directly.
fn table_output(out: &Path, format: Format) -> Result<(Option<TempPath>, Option<Part>)> {
    if format == Format::Mcap {
        return Ok((None, None));
    }
    let staged = staged_table(out)?;
    let part = Part::output(staged.as_deref().unwrap_or(out), out, format)?;
    Ok((staged, Some(part)))
}

/// Renames a staged table over `out` when a run is in it (`any`); else
/// drops it and says `out` was left as it was.
fn finish_staged(staged: TempPath, any: bool, out: &Path) -> Result<()> {
    if any {
        staged
            .persist(out)
            .with_context(|| format!("writing {}", out.display()))?;
    } else {
        drop(staged);
        eprintln!(
            "shocktwin replay: no run replayed: {} left as it was",
            out.display()
        );
    }
    Ok(())
}

impl Part {
    /// The output `out`, created at `path` (`out` itself, or the file it is
    /// staged in) with its header. Not sought: `out` may be a pipe (rows
    /// dropped there are an error).
    fn output(path: &Path, out: &Path, format: Format) -> Result<Self> {
        let (file, start) = create_table(path, out, format)?;
        Ok(Part {
            w: BufWriter::with_capacity(TABLE_BUFFER, file),
            start,
            what: out.display().to_string(),
            path: None,
        })
    }

    /// A part of the output `out`, in a file of its own beside it.
    fn beside(out: &Path) -> Result<Self> {
        let what = format!("a part of {}", out.display());
        let (file, path) = tempfile::NamedTempFile::new_in(dir_of(out))
            .with_context(|| format!("creating {what} beside it"))?
            .into_parts();
        Ok(Part {
            w: BufWriter::with_capacity(TABLE_BUFFER, file),
            start: 0,
            what,
            path: Some(path),
        })
    }

    /// Drops the rows written so far.
    fn rewind(&mut self) -> Result<()> {
        let (w, start) = (&mut self.w, self.start);
        let mut drop_rows = || {
            w.flush()?;
            w.get_mut().set_len(start)?;
            w.get_mut().seek(SeekFrom::Start(start)).map(|_| ())
        };
        drop_rows().with_context(|| format!("dropping the rows written to {}", self.what))
    }

    /// The run is over: its rows written out (`ok`) or dropped. The file is
    /// closed; a part's path is kept while its rows are.
    fn done(mut self, ok: bool) -> Result<Option<TempPath>> {
        match (ok, self.path.take()) {
            (false, Some(_)) => Ok(None),
            (false, None) => {
                self.rewind()?;
                Ok(None)
            }
            (true, path) => {
                self.w
                    .flush()
                    .with_context(|| format!("writing {}", self.what))?;
                Ok(path)
            }
        }
    }
}

/// The directory `out` is in.
fn dir_of(out: &Path) -> &Path {
    match out.parent() {
        Some(dir) if !dir.as_os_str().is_empty() => dir,
        _ => Path::new("."),
    }
}

/// The table `out` (CSV, JSONL), created with its header; the header's
/// length.
fn create_table(path: &Path, out: &Path, format: Format) -> Result<(File, u64)> {
    let mut file = File::create(path).with_context(|| format!("creating {}", out.display()))?;
    let header = match format {
        Format::Csv => format!("{}\n", FIELDS.join(",")),
        _ => String::new(),
    };
    file.write_all(header.as_bytes())
        .with_context(|| format!("writing {}", out.display()))?;
    Ok((file, header.len() as u64))
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
    cfg: &EstimatorConfig,
    out: &mut Output,
    started: Instant,
    pipelined: bool,
) -> Result<Option<Replayed>> {
    let name = file.display().to_string();
    let input = File::open(file).with_context(|| format!("opening {name}"))?;
    let est = model.estimator(cfg, &name)?;
    if !pipelined {
        let events = decoded(input, name);
        return replay_events(file, est, events, out, started);
    }
    std::thread::scope(|scope| {
        let (tx, rx) = std::sync::mpsc::sync_channel::<Batch>(4);
        let reader = std::thread::Builder::new().name("replay-decode".into());
        let reader_name = name.clone();
        let spawned = reader.spawn_scoped(scope, move || read_batches(input, &reader_name, &tx));
        spawned.with_context(|| format!("{}: starting its reader thread", file.display()))?;
        // Dropping the receiver (on return) stops the reader at its next batch.
        let events = rx.into_iter().flat_map(|batch| batch.decoded(&name));
        replay_events(file, est, events, out, started)
    })
}

/// The streaming replay of the events of `file` ([`replay_streaming`]).
fn replay_events(
    file: &Path,
    mut est: Estimator,
    events: impl Iterator<Item = Decoded>,
    out: &mut Output,
    started: Instant,
) -> Result<Option<Replayed>> {
    let mut writer = None;
    // Once the metadata came (before any sample).
    let mut rows: Option<Rows> = None;
    let mut last: Option<(i64, u8)> = None;
    let mut samples = 0usize;
    let mut complete = false;
    for item in events {
        let s = match item {
            Decoded::Sample(s) => s,
            Decoded::Metadata(m) => {
                refuse_dyno_run(file, &est, &m)?;
                let path = (out.run_out)(&m.run_id)?;
                if out.format == Format::Mcap {
                    writer = Some(LogWriter::create(path, &m, WriteOptions::default())?);
                }
                rows = Some(Rows::new(out.format, out.table.as_deref_mut(), &m, 0));
                if let Some(rows) = rows.as_mut() {
                    rows.untrained = est.untrained_excitation(&m);
                }
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
        let Some(rows) = rows.as_mut() else {
            return Ok(None); // the decoder passes the metadata first
        };
        if last.is_none() {
            rows.t0_ns = key.0;
        }
        last = Some(key);
        samples += 1;
        if est.push(s).is_err() {
            return Ok(None);
        }
        take_estimates(&mut est, writer.as_mut(), Some(&s), rows)?;
    }
    let Some(mut rows) = rows else {
        return Ok(None);
    };
    if !complete || est.finish().is_err() {
        return Ok(None);
    }
    check_topics(file, &est)?;
    take_estimates(&mut est, writer.as_mut(), None, &mut rows)?;
    if let Some(w) = writer {
        w.finish()?;
    }
    Ok(Some(rows.replayed(file, est.counters(), samples, started)))
}

/// Fails a run that lacked a sensor its model reads: its pressure was NaN
/// throughout, and the replay said `final NaN` with exit status 0 (the
/// bindings refuse such a log upfront, naming the topics).
fn check_topics(file: &Path, est: &Estimator) -> Result<()> {
    match est.missing_topics_reason() {
        Some(reason) => anyhow::bail!("{}: {reason}", file.display()),
        None => Ok(()),
    }
}

/// Replays `file` read whole: the samples sorted by `(t_ns, topic rank)`,
/// skipped messages and ignored topics reported.
fn replay_whole(
    file: &Path,
    model: &Model,
    cfg: &EstimatorConfig,
    out: &mut Output,
    started: Instant,
) -> Result<Replayed> {
    let log = read_log(file)?;
    for problem in &log.problems {
        tracing::warn!(file = %file.display(), "{problem}");
    }
    let mut est = model.estimator(cfg, &file.display().to_string())?;
    refuse_dyno_run(file, &est, &log.metadata)?;
    let path = (out.run_out)(&log.metadata.run_id)?;
    let mut rows = Rows::new(
        out.format,
        out.table.as_deref_mut(),
        &log.metadata,
        t0(&log),
    );
    rows.untrained = est.untrained_excitation(&log.metadata);
    let mut writer = match out.format {
        Format::Mcap => Some(LogWriter::create(
            &path,
            &log.metadata,
            WriteOptions::default(),
        )?),
        _ => None,
    };
    for s in log.samples_in_order() {
        est.push(s).with_context(|| format!("{}", file.display()))?;
        take_estimates(&mut est, writer.as_mut(), Some(&s), &mut rows)?;
    }
    est.finish()
        .with_context(|| format!("{}", file.display()))?;
    check_topics(file, &est)?;
    take_estimates(&mut est, writer.as_mut(), None, &mut rows)?;
    if let Some(w) = writer {
        w.finish()?;
    }
    Ok(rows.replayed(file, est.counters(), log.sample_count(), started))
}

/// After a sample (`Some`, written to the MCAP output first) or at the end
/// (`None`): passes the estimator's new estimates to `rows` and, with an
/// MCAP output, into the log after the sample.
fn take_estimates<W: Write + Seek>(
    est: &mut Estimator,
    writer: Option<&mut LogWriter<W>>,
    sample: Option<&Sample>,
    rows: &mut Rows,
) -> Result<()> {
    let Some(w) = writer else {
        for e in est.drain() {
            rows.push(e)?;
        }
        return Ok(());
    };
    if let Some(s) = sample {
        w.write_sample(s)?;
    }
    for e in est.drain() {
        w.write_json(topic::ESTIMATE, ESTIMATE_SCHEMA_JSON, e.t_ns, &e)?;
        rows.push(e)?;
    }
    Ok(())
}

/// What the summary keeps of a run's estimates (their rows are written as
/// they come): their count, the last one, and the sums of the RMSE against
/// the label over the ticks with a finite 1 s average.
#[derive(Debug, Clone, Copy, Default)]
struct Tally {
    ticks: usize,
    last: Option<Estimate>,
    sq_inst: f64,
    sq_avg: f64,
    scored: usize,
}

/// A run's estimates on their way out: a table row each (CSV, JSONL, into
/// `part`) and a [`Tally`].
struct Rows<'p> {
    format: Format,
    part: Option<&'p mut Part>,
    run_id: String,
    asset_id: String,
    label_bar: Option<f64>,
    /// The run's first sample, ns (`t_s` counts from it).
    t0_ns: i64,
    tally: Tally,
    line: String,
    /// See [`Replayed::untrained`].
    untrained: Option<String>,
}

impl<'p> Rows<'p> {
    fn new(format: Format, part: Option<&'p mut Part>, m: &RunMetadata, t0_ns: i64) -> Self {
        Rows {
            format,
            part,
            run_id: m.run_id.clone(),
            asset_id: m.asset_id.clone(),
            label_bar: m.charge_pressure_bar,
            t0_ns,
            tally: Tally::default(),
            line: String::new(),
            untrained: None,
        }
    }

    fn push(&mut self, e: Estimate) -> Result<()> {
        let t = &mut self.tally;
        t.ticks += 1;
        t.last = Some(e);
        if let Some(label) = self.label_bar {
            if e.pressure_avg_bar.is_finite() && e.pressure_bar.is_finite() {
                t.sq_inst += (e.pressure_bar - label).powi(2);
                t.sq_avg += (e.pressure_avg_bar - label).powi(2);
                t.scored += 1;
            }
        }
        let Some(part) = self.part.as_deref_mut() else {
            return Ok(());
        };
        let line = &mut self.line;
        line.clear();
        let t_s = (e.t_ns - self.t0_ns) as f64 * 1e-9;
        if self.format == Format::Csv {
            let _ = write!(line, "{},{},{t_s:.3}", self.run_id, self.asset_id);
            push_num(line, e.pressure_bar);
            push_num(line, e.pressure_avg_bar);
            push_num(line, e.pressure_lo_bar);
            push_num(line, e.pressure_hi_bar);
            push_num(line, e.expected_bar);
            let _ = write!(line, ",{}", e.health);
            push_num(line, e.velocity_mps);
            push_num(line, e.force_model_n);
            push_num(line, e.oil_temp_c);
            push_num(line, self.label_bar.unwrap_or(f64::NAN));
        } else {
            let mut v = serde_json::to_value(e)?;
            let obj = v.as_object_mut().expect("an Estimate is an object");
            obj.remove("t_ns");
            obj.insert("run_id".into(), self.run_id.clone().into());
            obj.insert("asset_id".into(), self.asset_id.clone().into());
            obj.insert("t_s".into(), ((t_s * 1e3).round() / 1e3).into());
            if let Some(label) = self.label_bar {
                obj.insert("label_bar".into(), label.into());
            }
            *line = serde_json::to_string(&v)?;
        }
        line.push('\n');
        part.w
            .write_all(line.as_bytes())
            .with_context(|| format!("writing {}", part.what))
    }

    fn replayed(
        self,
        file: &Path,
        counters: EstimatorCounters,
        samples: usize,
        started: Instant,
    ) -> Replayed {
        Replayed {
            file: file.to_path_buf(),
            run_id: self.run_id,
            label_bar: self.label_bar,
            tally: self.tally,
            counters,
            samples,
            seconds: started.elapsed().as_secs_f64(),
            untrained: self.untrained,
        }
    }
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

/// RMSE of the instantaneous and the 1 s average pressure against the label,
/// over ticks with a finite 1 s average; `None` without a label or ticks.
fn rmse(r: &Replayed) -> Option<(f64, f64, usize)> {
    r.label_bar?;
    let Tally {
        sq_inst,
        sq_avg,
        scored: n,
        ..
    } = r.tally;
    (n > 0).then(|| ((sq_inst / n as f64).sqrt(), (sq_avg / n as f64).sqrt(), n))
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
    } else if o.why_prior_kept().is_some() {
        line.push_str(
            " (none read: the estimate kept its prior; a failed window is a reversal too weak \
             to read, `observer.min_reversal_accel_mps2`, a gap or a poor fit)",
        );
    }
    Some(line)
}

fn print_summary(runs: &[Replayed], wall_s: f64, out: &Path, pattern: bool) {
    crate::outln!(
        "{:<28} {:>9} {:>8} {:>8} {:>11} {:>11} {:>8} {:>9}",
        "run",
        "label",
        "ticks",
        "final 1s",
        "RMSE inst",
        "RMSE 1 s",
        "health",
        "speed"
    );
    let mut data_s = 0.0;
    for r in runs {
        let last = r.tally.last;
        let dur_s = r.tally.ticks as f64 * 0.02;
        data_s += dur_s;
        let (inst, avg) = rmse(r).map_or(("n/a".into(), "n/a".into()), |(i, a, _)| {
            (format!("{i:.3}"), format!("{a:.3}"))
        });
        crate::outln!(
            "{:<28} {:>9} {:>8} {:>8} {:>11} {:>11} {:>8} {:>8.0}x",
            r.run_id,
            r.label_bar.map_or("-".into(), |l| format!("{l:.2}")),
            r.tally.ticks,
            last.map_or("-".into(), |e| if e.pressure_avg_bar.is_finite() {
                format!("{:.2}", e.pressure_avg_bar)
            } else {
                "n/a".into() // no usable tick in the run's last second
            }),
            inst,
            avg,
            last.map_or("-".into(), |e| e.health.to_string()),
            dur_s / r.seconds.max(1e-9),
        );
        let c = r.counters;
        if c.late_dropped + c.clock_jumps + c.missing_samples + c.timestamp_outliers > 0 {
            crate::outln!(
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
            crate::outln!("  {}: {line}", r.file.display());
        }
        if let Some(why) = &r.untrained {
            crate::outln!("  {}: {why}", r.file.display());
        }
        if let Some(road) = c.road {
            crate::outln!(
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
    crate::outln!(
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

    /// Runs `replay` with the CSV rows going to a part of their own; what
    /// it returned, and the part's rows.
    fn with_rows<T>(replay: impl FnOnce(&mut Output) -> T) -> (T, Vec<String>) {
        let dir = tempfile::tempdir().unwrap();
        let mut part = Part::beside(&dir.path().join("rows.csv")).unwrap();
        let no_mcap = |_: &str| Ok(PathBuf::new());
        let res = replay(&mut Output {
            format: Format::Csv,
            run_out: &no_mcap,
            table: Some(&mut part),
        });
        let path = part.done(true).unwrap().expect("a part keeps its file");
        let rows = std::fs::read_to_string(&path).unwrap();
        (res, rows.lines().map(str::to_owned).collect())
    }

    #[test]
    fn a_table_is_staged_beside_a_file_not_a_pipe() {
        let dir = tempfile::tempdir().unwrap();
        let fifo = dir.path().join("pipe.csv");
        assert!(std::process::Command::new("mkfifo")
            .arg(&fifo)
            .status()
            .unwrap()
            .success());
        assert!(staged_table(&fifo).unwrap().is_none());
        for out in [dir.path().join("new.csv"), dir.path().join("old.csv")] {
            if out.ends_with("old.csv") {
                std::fs::write(&out, b"kept").unwrap();
            }
            let staged = staged_table(&out).unwrap().unwrap();
            assert_eq!(staged.parent(), Some(dir.path()));
            let name = staged.file_name().unwrap().to_string_lossy().into_owned();
            assert!(
                name.starts_with(".replay-")
                    && Path::new(&name).extension().is_some_and(|e| e == "part"),
                "{name}"
            );
            drop(staged);
        }
        // dropped unpersisted: nothing left beside, the old output as it was
        let mut names: Vec<_> = std::fs::read_dir(dir.path())
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        names.sort();
        assert_eq!(names, ["old.csv", "pipe.csv"]);
        assert_eq!(std::fs::read(dir.path().join("old.csv")).unwrap(), b"kept");
    }

    #[test]
    fn the_output_may_be_a_pipe() {
        let dir = tempfile::tempdir().unwrap();
        let fifo = dir.path().join("est.csv");
        let made = std::process::Command::new("mkfifo").arg(&fifo).status();
        assert!(made.unwrap().success(), "mkfifo");
        let reader = {
            let fifo = fifo.clone();
            std::thread::spawn(move || std::fs::read_to_string(fifo).unwrap())
        };
        let mut part = Part::output(&fifo, &fifo, Format::Csv).unwrap();
        part.w.write_all(b"r1,unit-a,0.020,12\n").unwrap();
        assert!(part.done(true).unwrap().is_none());
        let header = FIELDS.join(",");
        assert_eq!(
            reader.join().unwrap(),
            format!("{header}\nr1,unit-a,0.020,12\n")
        );
    }

    #[test]
    fn a_failed_runs_rows_are_dropped_from_the_output_and_from_a_part() {
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("est.csv");
        let row = b"r1,unit-a,0.020,12\n";
        for ok in [true, false] {
            let mut part = Part::output(&out, &out, Format::Csv).unwrap();
            part.w.write_all(row).unwrap();
            assert!(part.done(ok).unwrap().is_none());
            let text = std::fs::read_to_string(&out).unwrap();
            let header = format!("{}\n", FIELDS.join(","));
            let rows = if ok {
                std::str::from_utf8(row).unwrap()
            } else {
                ""
            };
            assert_eq!(text, header + rows, "ok: {ok}");
            let mut part = Part::beside(&out).unwrap();
            part.w.write_all(row).unwrap();
            match part.done(ok).unwrap() {
                Some(path) => assert_eq!(std::fs::read(&path).unwrap(), row),
                None => assert!(!ok, "a run that succeeded keeps its rows"),
            }
        }
        // The parts are gone once dropped: only the output is left.
        let left: Vec<_> = std::fs::read_dir(dir.path()).unwrap().collect();
        assert_eq!(left.len(), 1);
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
        let t = Instant::now();
        let (streamed, streamed_rows) = with_rows(|out| {
            replay_streaming(&in_order, &b, &cfg, out, t, false)
                .unwrap()
                .expect("a clean file in order streams")
        });
        for pipelined in [false, true] {
            assert!(
                with_rows(
                    |out| replay_streaming(&shuffled, &b, &cfg, out, t, pipelined)
                        .unwrap()
                        .is_none()
                )
                .0,
                "a file out of order must not stream"
            );
        }
        // Read and decoded on a second thread: the same rows.
        let (pipelined, pipelined_rows) = with_rows(|out| {
            replay_streaming(&in_order, &b, &cfg, out, t, true)
                .unwrap()
                .expect("a clean file in order streams, pipelined too")
        });
        assert_eq!(pipelined_rows, streamed_rows);
        assert_eq!(pipelined.samples, streamed.samples);
        assert_eq!(pipelined.counters, streamed.counters);
        let (whole, whole_rows) =
            with_rows(|out| replay_file(&shuffled, &b, &cfg, out, true).unwrap());
        let (whole_in_order, whole_in_order_rows) =
            with_rows(|out| replay_whole(&in_order, &b, &cfg, out, t).unwrap());

        assert!(streamed.tally.ticks > 1000, "{}", streamed.tally.ticks);
        assert_eq!(streamed_rows.len(), streamed.tally.ticks);
        assert_eq!(streamed_rows, whole_rows);
        assert_eq!(streamed_rows, whole_in_order_rows);
        assert_eq!(whole_in_order.tally.ticks, streamed.tally.ticks);
        assert_eq!(streamed.samples, samples.len());
        assert_eq!(whole.samples, samples.len());
        assert_eq!(streamed.label_bar, Some(7.0));
        assert_eq!(streamed.run_id, "r1");
        // run, asset, t_s from the first sample (the first tick ends 20 ms in), …, the label
        assert!(
            streamed_rows[0].starts_with("r1,unit-a,0.020,"),
            "{}",
            streamed_rows[0]
        );
        assert!(streamed_rows[0].ends_with(",7"), "{}", streamed_rows[0]);
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
        let t = Instant::now();
        let mut replayed = Vec::new();
        for pipelined in [false, true] {
            let (gave_way, rows_before) = with_rows(|out| {
                replay_streaming(&path, &b, &cfg, out, t, pipelined)
                    .unwrap()
                    .is_none()
            });
            assert!(
                gave_way,
                "a message that does not parse must give way (pipelined: {pipelined})"
            );
            assert!(rows_before.len() > 100, "it gives way half-way");
            replayed.push(with_rows(|out| {
                replay_file(&path, &b, &cfg, out, pipelined).unwrap()
            }));
        }
        // The whole-file path skips the one message and keeps every other;
        // the rows the streaming path wrote before it gave way are dropped.
        let (whole, whole_rows) = with_rows(|out| replay_whole(&path, &b, &cfg, out, t).unwrap());
        assert_eq!(replayed[0].0.samples, samples.len());
        assert!(whole.tally.ticks > 1000);
        for (r, rows) in &replayed {
            assert_eq!(rows, &whole_rows);
            assert_eq!(r.tally.ticks, rows.len());
        }
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
        let t = Instant::now();
        for pipelined in [false, true] {
            assert!(
                with_rows(|out| replay_streaming(&cut, &b, &cfg, out, t, pipelined)
                    .unwrap()
                    .is_none())
                .0
            );
            let (res, _) = with_rows(|out| replay_file(&cut, &b, &cfg, out, pipelined));
            let err = res.err().expect("a truncated file is an error, as before");
            assert!(format!("{err:#}").contains("cut.mcap"), "{err:#}");
        }
    }
}
