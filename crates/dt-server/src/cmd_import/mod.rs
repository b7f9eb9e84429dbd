//! `shocktwin import`: tabular dyno exports (CSV) into shocktwin run logs
//! (SPEC §2), one MCAP per file.
//!
//! Per file: the header is found ([`table`]), every mapped cell parsed and
//! converted to SPEC units and conventions ([`map`]), the rows put on a
//! uniform grid and each topic resampled, anti-aliased, to its nominal rate
//! ([`resample`]) — each stretch between gaps on its own, the gaps left in
//! the log — then written with the `shocktwin.run` metadata (asset,
//! run, the charge label converted to bar gauge, the source file's name
//! and rate). A file that fails is reported (file, line, column) and the
//! others are still imported; the exit status is 1 if any failed. The log
//! is written to `<run_id>.mcap.part` and renamed when complete.

pub mod map;
pub mod resample;
pub mod table;

use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::process::ExitCode;

use anyhow::{bail, Context as _};
use dt_core::log::{is_valid_id, LogWriter, RunMetadata, Sample, WriteOptions};

use crate::cli::ImportArgs;
use map::{Charge, Mapping};

/// A step between rows longer than this many median steps is a gap the
/// import will not interpolate across: the stretches on either side are
/// resampled each on its own and written into one log with the gap in it
/// (the twin reads a gap in a stream as one).
const GAP_STEPS: f64 = 10.0;

/// Runs `shocktwin import`.
pub fn run(args: &ImportArgs) -> anyhow::Result<ExitCode> {
    let map = map::resolve(args)?;
    if map.run_id.is_some() && args.files.len() > 1 {
        bail!(
            "import: a run id names one run: give one file, or let each run take its file's name"
        );
    }
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("import: cannot create {}", args.out.display()))?;
    let bar = crate::progress::bar(args.files.len() as u64, "import");
    let mut written: BTreeMap<String, PathBuf> = BTreeMap::new();
    let (mut failed, mut skipped) = (0usize, 0u64);
    for file in &args.files {
        bar.set_message(file.display().to_string());
        match import_file(file, &map, args, &written) {
            Ok(done) => {
                bar.suspend(|| crate::outln!("{}", done.report));
                skipped += done.skipped;
                written.insert(done.run_id, file.clone());
            }
            Err(err) => {
                bar.suspend(|| eprintln!("shocktwin: import: {err:#}"));
                failed += 1;
            }
        }
        bar.inc(1);
    }
    bar.finish_and_clear();
    crate::outln!(
        "imported {} of {} files into {}{}",
        written.len(),
        args.files.len(),
        args.out.display(),
        if skipped > 0 {
            format!(" ({skipped} bad rows skipped)")
        } else {
            String::new()
        }
    );
    Ok(if failed == 0 {
        ExitCode::SUCCESS
    } else {
        ExitCode::FAILURE
    })
}

/// One file imported.
struct Imported {
    run_id: String,
    report: String,
    skipped: u64,
}

/// A topic's series at its output rate.
struct Series {
    topic: &'static str,
    rate: resample::GridRate,
    nominal_hz: u32,
    /// Time of sample 0 after the file's first row, s.
    start_s: f64,
    values: Vec<Vec<f64>>,
}

#[allow(clippy::too_many_lines)] // read, resample, write, then the report line by line
fn import_file(
    path: &Path,
    map: &Mapping,
    args: &ImportArgs,
    written: &BTreeMap<String, PathBuf>,
) -> anyhow::Result<Imported> {
    let file = path.display().to_string();
    let stem = path
        .file_stem()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_default();
    let metadata = metadata(path, &stem, map)?;
    if let Some(other) = written.get(&metadata.run_id) {
        bail!(
            "{file}: run id {:?} was already written from {} (give each file its own name, or import them separately with --run-id)",
            metadata.run_id,
            other.display()
        );
    }
    let mut table = table::read(path, map, args.skip_bad_rows)?;
    if table.t_ns.len() < 2 {
        bail!("{file}: fewer than two data rows: nothing to import");
    }
    // Elapsed times before 0 (a pre-trigger stretch): the log's clock
    // starts at 0, so the run is moved to start there, and the report says
    // so (it failed only when written, naming neither line nor column, and
    // left its `.part` behind).
    let shifted_ns = (table.t_ns[0] < 0).then(|| -table.t_ns[0]);
    if let Some(dt) = shifted_ns {
        for t in &mut table.t_ns {
            *t += dt;
        }
    }
    drop_glitches(map, &mut table);
    if table.t_ns.len() < 2 {
        bail!("{file}: fewer than two data rows left: nothing to import");
    }
    if let (Some(stroke), Some(position)) = (map.stroke_pp_m, &map.position) {
        // the position is the first value column (`Mapping::value_columns`)
        check_stroke(&file, &position.name, &table.values[0], stroke)?;
    }
    let Resampled {
        stretches,
        rate,
        mut samples,
        series,
        left_out,
    } = resample_stretches(&file, map, &table)?;

    let out = args.out.join(format!("{}.mcap", metadata.run_id));
    if !args.overwrite {
        check_replaces_the_same(&file, &out, &metadata)?;
    }
    let part = args.out.join(format!("{}.mcap.part", metadata.run_id));
    let t0 = table.t_ns[0];
    samples.sort_by_key(|s| (s.t_ns(), s.topic_rank()));
    let written = (|| -> anyhow::Result<()> {
        let mut writer = LogWriter::create(&part, &metadata, WriteOptions::default())
            .with_context(|| format!("{file}: writing {}", part.display()))?;
        for s in &samples {
            writer
                .write_sample(s)
                .with_context(|| format!("{file}: writing {}", part.display()))?;
        }
        writer
            .finish()
            .with_context(|| format!("{file}: writing {}", part.display()))?;
        std::fs::rename(&part, &out)
            .with_context(|| format!("{file}: renaming to {}", out.display()))
    })();
    if let Err(err) = written {
        // no half-written log is left behind
        let _ = std::fs::remove_file(&part);
        return Err(err);
    }

    let duration_s = (table.t_ns[table.t_ns.len() - 1] - t0) as f64 * 1e-9;
    let kept = table.t_ns.len();
    let mut report = if kept as u64 == table.rows {
        format!("{file} -> {}: {kept} rows", out.display())
    } else {
        format!(
            "{file} -> {}: {kept} rows (of {} read)",
            out.display(),
            table.rows
        )
    };
    let _ = write!(report, ", {duration_s:.1} s at {rate} Hz;");
    for s in &series {
        let _ = write!(report, " {} {} Hz", s.topic, s.rate);
        if s.rate.hz() < f64::from(s.nominal_hz) {
            let _ = write!(
                report,
                " (source slower than the nominal {} Hz: not upsampled)",
                s.nominal_hz
            );
        }
        report.push(',');
    }
    report.pop();
    if let Some(bar) = metadata.charge_pressure_bar {
        let label = metadata
            .extra
            .get("charge_label")
            .map_or("", String::as_str);
        let _ = write!(report, "; charge {label} = {bar:.3} bar");
    }
    if let Some(dt) = shifted_ns {
        let _ = write!(
            report,
            "\n  its times start at {:.6} s: moved by +{:.6} s to start at 0 (a log's clock does not go below 0)",
            -(dt as f64) * 1e-9,
            dt as f64 * 1e-9
        );
    }
    for line in &table.midnights {
        let _ = write!(
            report,
            "\n  the time of day crossed midnight at line {line}: read as the next day"
        );
    }
    if let Some((line, cells)) = &table.units_row {
        let _ = write!(
            report,
            "\n  line {line} read as a units row ({}): not data",
            cells.join(", ")
        );
    }
    for (column, n) in &table.error_values {
        let (lo, hi) = table::THERMOCOUPLE_RANGE_C;
        let _ = write!(
            report,
            "\n  column {column:?}: {n} cells outside {lo}..{hi} °C (a thermocouple's error \
             value) read as blank, the value above them holding"
        );
    }
    for (column, n) in &table.held {
        let _ = write!(
            report,
            "\n  column {column:?}: {n} blank cells read as the value above them (a channel \
             written less often than the rows)"
        );
    }
    for (reason, (n, first)) in &table.skipped {
        let _ = write!(
            report,
            "\n  skipped {n} rows: {reason} (first at line {first})"
        );
    }
    for w in stretches.windows(2) {
        let (a, b) = (w[0].end - 1, w[1].start);
        let _ = write!(
            report,
            "\n  gap of {:.3} s after line {} (more than {GAP_STEPS} median steps): not \
             interpolated, the log has none of it (each side resampled on its own: its first and \
             last few samples ring)",
            (table.t_ns[b] - table.t_ns[a]) as f64 * 1e-9,
            table.lines[a],
        );
    }
    for what in &left_out {
        let _ = write!(report, "\n  left out {what}");
    }
    for what in convention_warnings(&samples, map.stroke_pp_m) {
        let _ = write!(report, "\n  warning: {what}");
    }
    if rate.hz() < SLOWEST_PLAUSIBLE_ROWS_HZ {
        // a time column in ms read as seconds imported a 70 s run as 19 h at
        // 1 Hz without a word, and its replay wrote 3.5 M rows (a helper's trial)
        let _ = write!(
            report,
            "\n  warning: the rows come at {rate} Hz, {duration_s:.0} s in all: a dyno logs at \
             hundreds of rows a second. Is the time column in milliseconds or microseconds read \
             as seconds (`[time] format`, --time-format elapsed_ms; it was read as {})?",
            map.time_format.key()
        );
    }
    for (topic, what) in [
        (
            "/acceleration",
            "no accelerometers: the twin runs its position-only Kalman filter",
        ),
        ("/temperature/ambient", "no ambient thermocouple"),
        ("/force", "no loadcell force"),
    ] {
        if !series.iter().any(|s| s.topic == topic) {
            let _ = write!(report, "\n  note: {what}");
        }
    }
    Ok(Imported {
        run_id: metadata.run_id,
        report,
        skipped: table.skipped_rows(),
    })
}

fn metadata(path: &Path, stem: &str, map: &Mapping) -> anyhow::Result<RunMetadata> {
    let file = path.display().to_string();
    let Some(asset_id) = map.asset_id.clone() else {
        bail!("{file}: no asset id: give --asset-id or [run] asset_id");
    };
    if !is_valid_id(&asset_id) {
        bail!("asset id {asset_id:?}: must be {}", dt_core::log::ID_FORMAT);
    }
    let run_id = match &map.run_id {
        Some(id) => id.clone(),
        None => stem
            .chars()
            .map(|c| {
                if c.is_ascii_alphanumeric() || "._-".contains(c) {
                    c
                } else {
                    '_'
                }
            })
            .take(64)
            .collect(),
    };
    if !is_valid_id(&run_id) {
        bail!(
            "{file}: run id {run_id:?}: must be {}",
            dt_core::log::ID_FORMAT
        );
    }
    let (label, bar) = match &map.charge {
        Charge::None => (None, None),
        Charge::Label(label) => (Some(label.clone()), Some(map::charge_bar(label)?)),
        Charge::FromName => {
            let (label, bar) = map::charge_in_name(stem).with_context(|| {
                format!(
                    "{file}: charge \"from-name\": the file name has no <number> psi|bar|kPa|MPa"
                )
            })?;
            (Some(label), Some(bar))
        }
    };
    let mut meta = RunMetadata {
        asset_id,
        run_id,
        charge_pressure_bar: bar,
        frequency_hz: map.frequency_hz,
        stroke_pp_m: map.stroke_pp_m,
        ..RunMetadata::default()
    };
    meta.extra.extend(map.metadata.clone());
    if let Some(label) = label {
        meta.extra.insert("charge_label".into(), label);
    }
    let name = path
        .file_name()
        .map_or_else(String::new, |n| n.to_string_lossy().into_owned());
    meta.extra.insert("source_file".into(), name);
    let bytes = std::fs::read(path).with_context(|| format!("{}: reading", path.display()))?;
    let digest = sha2::Digest::finalize(<sha2::Sha256 as sha2::Digest>::new_with_prefix(&bytes));
    meta.extra.insert(SOURCE_SHA256.into(), hex(&digest));
    meta.extra.insert(
        "imported_by".into(),
        format!("shocktwin {}", env!("CARGO_PKG_VERSION")),
    );
    Ok(meta)
}

/// Below this correlation a pair of channels that physics ties together is
/// taken to disagree in sign (a stroked damper reads +0.96 and more).
const SIGN_CORRELATION: f64 = -0.5;

/// Sign and offset mistakes the data itself shows (a helper's trial: a
/// flipped position sign read a 12 bar unit as −17 bar, a flipped force
/// tripled the error, a missing `mid_stroke` moved the estimate; all imported
/// without a word):
/// - the relative acceleration `a1 − a2` against the position's second
///   derivative (SPEC §2: both extension positive, they agree in sign); when
///   they disagree and the body-end column `a2` is the one that follows the
///   stroke, the two columns are taken to be swapped (a helper's trial: a
///   swapped pair imported without a word, the rod accelerometer's check
///   reading the body's near-still column);
/// - the force against the velocity (positive in tension: a damper's force
///   follows the extension velocity);
/// - with a stated stroke, positions that never cross mid-stroke (0).
fn convention_warnings(samples: &[Sample], stroke_pp_m: Option<f64>) -> Vec<String> {
    let mut pos: Vec<(f64, f64)> = Vec::new();
    let (mut rel, mut rod, mut body) = (Vec::new(), Vec::new(), Vec::new());
    let mut force: Vec<(f64, f64)> = Vec::new();
    for s in samples {
        match *s {
            Sample::Position { t_ns, position_m } => pos.push((t_ns as f64 * 1e-9, position_m)),
            Sample::Acceleration {
                t_ns,
                a1_mps2,
                a2_mps2,
            } => {
                let t = t_ns as f64 * 1e-9;
                rel.push((t, a1_mps2 - a2_mps2));
                rod.push((t, a1_mps2));
                body.push((t, a2_mps2));
            }
            Sample::Force { t_ns, force_n } => force.push((t_ns as f64 * 1e-9, force_n)),
            _ => {}
        }
    }
    let mut out = Vec::new();
    if pos.len() < 5 {
        return out;
    }
    // central differences where both neighbours are one step away (no gap)
    let step = {
        let mut d: Vec<f64> = pos.windows(2).map(|w| w[1].0 - w[0].0).collect();
        d.sort_by(f64::total_cmp);
        d[d.len() / 2]
    };
    let mut vel = Vec::new();
    let mut second = Vec::new();
    for w in pos.windows(3) {
        let (h0, h1) = (w[1].0 - w[0].0, w[2].0 - w[1].0);
        if h0 < 1.5 * step && h1 < 1.5 * step {
            vel.push((w[1].0, (w[2].1 - w[0].1) / (h0 + h1)));
            second.push((w[1].0, (w[2].1 - 2.0 * w[1].1 + w[0].1) / (h0 * h1)));
        }
    }
    if let Some(r) = correlation_at(&second, &rel) {
        if r < SIGN_CORRELATION {
            let r1 = correlation_at(&second, &rod).unwrap_or(f64::NAN);
            let r2 = correlation_at(&second, &body).unwrap_or(f64::NAN);
            // a constant a1 column (no spread: NaN) does not follow the stroke either
            out.push(
                if r2 > -SIGN_CORRELATION && (r1.is_nan() || r1.abs() < -SIGN_CORRELATION) {
                    format!(
                        "the accelerometers look swapped: the body-end column (a2) follows the \
                     stroke (correlation {r2:.2} with the position's second derivative), the \
                     rod-end one (a1) does not ({r1:.2}); swap `[acceleration] a1` and `a2` \
                     (--a1, --a2)"
                    )
                } else {
                    format!(
                        "the relative acceleration (a1 − a2) and the position's second derivative \
                     disagree in sign (correlation {r:.2}): is the position's sign (`[position] \
                     positive`) or the accelerometers' flipped, or a1 and a2 swapped? SPEC §2 \
                     counts both positive in extension"
                    )
                },
            );
        }
    }
    if let Some(r) = correlation_at(&vel, &force) {
        if r < SIGN_CORRELATION {
            out.push(format!(
                "the force is against the velocity (correlation {r:.2}), not with it as a \
                 damper's is: is the force's sign (`[force] positive`) or the position's \
                 flipped? SPEC §2 counts the force positive in tension, the position in extension"
            ));
        }
    }
    if let Some(stroke) = stroke_pp_m {
        let (lo, hi) = pos
            .iter()
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), p| {
                (a.min(p.1), b.max(p.1))
            });
        if (lo > 0.0 || hi < 0.0) && hi - lo > 0.5 * stroke {
            out.push(format!(
                "the positions never cross mid-stroke ({:.1} to {:.1} mm for a {:.1} mm stroke): \
                 is `[position] mid_stroke` (--mid-stroke) missing?",
                lo * 1e3,
                hi * 1e3,
                stroke * 1e3
            ));
        }
    }
    out
}

/// Pearson's correlation of `a` with `b` linearly interpolated at `a`'s
/// times (both in time order); `None` with too little overlap or no spread.
fn correlation_at(a: &[(f64, f64)], b: &[(f64, f64)]) -> Option<f64> {
    if b.len() < 2 {
        return None;
    }
    let mut pairs = Vec::with_capacity(a.len());
    let mut j = 0;
    for &(t, x) in a {
        while j + 2 < b.len() && b[j + 1].0 < t {
            j += 1;
        }
        let (p, q) = (b[j], b[j + 1]);
        if t < p.0 || t > q.0 || q.0 - p.0 <= 0.0 {
            continue;
        }
        let y = p.1 + (q.1 - p.1) * (t - p.0) / (q.0 - p.0);
        if x.is_finite() && y.is_finite() {
            pairs.push((x, y));
        }
    }
    if pairs.len() < 20 {
        return None;
    }
    let n = pairs.len() as f64;
    let (mx, my) = pairs
        .iter()
        .fold((0.0, 0.0), |(a, b), p| (a + p.0 / n, b + p.1 / n));
    let (mut sxy, mut sxx, mut syy) = (0.0, 0.0, 0.0);
    for (x, y) in &pairs {
        sxy += (x - mx) * (y - my);
        sxx += (x - mx) * (x - mx);
        syy += (y - my) * (y - my);
    }
    (sxx > 0.0 && syy > 0.0).then(|| sxy / (sxx * syy).sqrt())
}

/// The metadata key of the source file's SHA-256 (hex): a log imported
/// again from the same bytes replaces the first, one from other bytes does
/// not (`--overwrite`).
const SOURCE_SHA256: &str = "source_sha256";

fn hex(bytes: &[u8]) -> String {
    bytes.iter().fold(String::new(), |mut s, b| {
        let _ = write!(s, "{b:02x}");
        s
    })
}

/// An earlier log at `out` is replaced only when it was imported from the
/// same bytes (a re-import, e.g. with a corrected map): a second day's
/// `run.csv` imported into the same directory replaced the first day's log
/// without a word (a helper trying the import as a test engineer).
fn check_replaces_the_same(file: &str, out: &Path, meta: &RunMetadata) -> anyhow::Result<()> {
    if !out.exists() {
        return Ok(());
    }
    let ours = meta.extra.get(SOURCE_SHA256);
    let theirs = dt_core::log::read_log(out)
        .ok()
        .map(|log| log.metadata.extra);
    let same = theirs
        .as_ref()
        .is_some_and(|m| m.get(SOURCE_SHA256).is_some_and(|h| Some(h) == ours));
    if same {
        return Ok(());
    }
    let from = theirs
        .as_ref()
        .and_then(|m| m.get("source_file"))
        .map_or_else(
            || "not by this import".to_owned(),
            |f| format!("from another {f}"),
        );
    bail!(
        "{file}: {} exists, imported {from}: give this file another run id (--run-id, or rename it), \
         import into another --out, or replace it with --overwrite",
        out.display()
    )
}

/// The table's stretches between gaps, each resampled on its own at one
/// grid rate (the longest stretch's).
struct Resampled {
    stretches: Vec<std::ops::Range<usize>>,
    rate: resample::GridRate,
    samples: Vec<Sample>,
    /// The first stretch's series (their rates; the report's).
    series: Vec<Series>,
    /// The stretches left out and why.
    left_out: Vec<String>,
}

fn resample_stretches(
    file: &str,
    map: &Mapping,
    table: &table::Table,
) -> anyhow::Result<Resampled> {
    let stretches = stretches(table);
    // One grid rate for every stretch: the longest one's (two rows or more:
    // the median step itself is no gap).
    let longest = stretches
        .iter()
        .max_by_key(|r| r.len())
        .cloned()
        .unwrap_or(0..table.t_ns.len());
    let rate = resample::grid_rate(&table.t_ns[longest]);
    let mut samples_out = Vec::new();
    let mut series = None;
    let mut left_out = Vec::new();
    for r in &stretches {
        let (first, last) = (table.lines[r.start], table.lines[r.end - 1]);
        if r.len() < 2 {
            left_out.push(format!("line {first}: one row between gaps"));
            continue;
        }
        let part = table.slice(r.clone());
        match resample_topics(map, &part, rate) {
            Ok(s) => {
                samples_out.extend(samples(&s, part.t_ns[0]));
                series.get_or_insert(s);
            }
            Err(e) if stretches.len() == 1 => return Err(e.context(file.to_owned())),
            Err(e) => left_out.push(format!("lines {first}-{last}: {e:#}")),
        }
    }
    let Some(series) = series else {
        bail!(
            "{file}: no stretch between its gaps could be resampled ({})",
            left_out.join("; ")
        );
    };
    Ok(Resampled {
        stretches,
        rate,
        samples: samples_out,
        series,
        left_out,
    })
}

/// Rows slower than this are warned of: the time column's unit is likely
/// wrong.
const SLOWEST_PLAUSIBLE_ROWS_HZ: f64 = 20.0;

/// Drops the rows whose position lies outside the column's range (between
/// its 0.1 % and 99.9 % points) by more than that range's span (at least
/// 5 mm): one bad row of a logger, which no stroke reaches. Kept, one
/// position sample of 999 in among 70,000 was smeared by the resampler over
/// 0.1 s of ±65 mm, and the run's estimate read 2,509 bar there and stayed
/// 4 bar off for the rest of the run (a helper's trial). The rows are
/// counted as skipped, by reason, in the import's report. A stroke's own
/// samples are never so far, however few a cycle has. (A thermocouple's
/// error values are read as blank cells instead: [`table::read`].)
/// Accelerations and forces are left as they are: a knock is a real spike.
fn drop_glitches(map: &Mapping, table: &mut table::Table) {
    const FLOOR_M: f64 = 0.005;
    if map.position.is_none() {
        return;
    }
    // the position is the first value column (`Mapping::value_columns`)
    let v = &table.values[0];
    let n = v.len();
    if n < 2 {
        return;
    }
    let mut sorted = v.clone();
    sorted.sort_by(f64::total_cmp);
    #[allow(
        clippy::cast_possible_truncation,
        clippy::cast_sign_loss,
        clippy::cast_precision_loss
    )]
    let at = |q: f64| sorted[((n - 1) as f64 * q).round() as usize];
    let (lo, hi) = (at(0.001), at(0.999));
    let reach = (hi - lo).max(FLOOR_M);
    let far: Vec<bool> = v
        .iter()
        .map(|&x| x < lo - reach || x > hi + reach)
        .collect();
    if far.iter().any(|&b| b) {
        let name = map.position.as_ref().map_or("", |c| c.name.as_str());
        table.drop_rows(
            &far,
            &format!(
                "column {name:?}: far outside the stroke the rest of the column spans (a glitch)"
            ),
        );
    }
}

/// The positions may span at most this many times the stated stroke: beyond
/// it the position's unit (or the stroke) is wrong.
const STROKE_SLACK: f64 = 1.25;

/// Refuses a position column whose range the stated stroke cannot hold
/// (`positions` in m, `stroke` peak to peak in m): read in inches, an 80 mm
/// stroke becomes 2 m and would replay without a word. The range is taken
/// between the 0.1 % and 99.9 % points (spikes in up to 0.1 % of the rows at
/// either end do not refuse a file);
/// a range well inside the stroke is not refused: a run may use part of it.
fn check_stroke(file: &str, column: &str, positions: &[f64], stroke: f64) -> anyhow::Result<()> {
    let mut sorted = positions.to_vec();
    sorted.sort_by(f64::total_cmp);
    let at = |q: f64| sorted[((sorted.len() - 1) as f64 * q).round() as usize];
    let (lo, hi) = (at(0.001), at(0.999));
    let span = hi - lo;
    if span > STROKE_SLACK * stroke {
        bail!(
            "{file}: column {column:?} spans {:.1} mm, more than the stroke of {:.1} mm \
             allows: is the position's unit (`[position] unit`, --position-unit) or the stroke \
             (`[run] stroke_pp_mm`, --stroke-pp-mm) wrong?",
            span * 1e3,
            stroke * 1e3
        );
    }
    Ok(())
}

/// The rows' stretches between gaps: steps longer than [`GAP_STEPS`]
/// median steps are not interpolated across (the table has two rows or more).
fn stretches(table: &table::Table) -> Vec<std::ops::Range<usize>> {
    let t = &table.t_ns;
    let mut steps: Vec<i64> = t.windows(2).map(|w| w[1] - w[0]).collect();
    let mid = steps.len() / 2;
    let median_ns = *steps.select_nth_unstable(mid).1 as f64;
    let mut out = Vec::new();
    let mut start = 0;
    for k in 1..t.len() {
        if (t[k] - t[k - 1]) as f64 > GAP_STEPS * median_ns {
            out.push(start..k);
            start = k;
        }
    }
    out.push(start..t.len());
    out
}

/// Each mapped topic of `table` (one stretch, two rows or more) on the grid
/// at `rate`, then at its nominal rate if the grid is faster. A stretch that
/// leaves no topic two samples is refused: two or three rows made a log of
/// one position message.
fn resample_topics(
    map: &Mapping,
    table: &table::Table,
    rate: resample::GridRate,
) -> anyhow::Result<Vec<Series>> {
    let topics: Vec<(&'static str, u32, usize)> = {
        let mut v = Vec::new();
        for (present, topic, nominal, width) in [
            (map.position.is_some(), "/position", 100, 1),
            (map.force.is_some(), "/force", 50, 1),
            (map.temp_shock.is_some(), "/temperature/shock", 1, 1),
            (map.temp_ambient.is_some(), "/temperature/ambient", 1, 1),
            (map.acceleration.is_some(), "/acceleration", 1000, 2),
        ] {
            if present {
                v.push((topic, nominal, width));
            }
        }
        v
    };
    let mut out = Vec::new();
    let mut column = 0;
    for (topic, nominal_hz, width) in topics {
        let mut values = Vec::with_capacity(width);
        let mut start_s = 0.0;
        for _ in 0..width {
            let grid = resample::to_grid(&table.t_ns, &table.values[column], rate);
            column += 1;
            values.push(if rate.faster_than(nominal_hz) {
                // the rate change num/den -> nominal, as integers
                let d = resample::downsample(&grid, rate.num, nominal_hz * rate.den)
                    .with_context(|| format!("topic {topic}"))?;
                start_s = -rate.time_s(d.lag_in_samples);
                d.values
            } else {
                grid
            });
        }
        let rate_out = if rate.faster_than(nominal_hz) {
            resample::GridRate::whole(nominal_hz)
        } else {
            rate
        };
        out.push(Series {
            topic,
            rate: rate_out,
            nominal_hz,
            start_s,
            values,
        });
    }
    if out.iter().all(|s| s.len() < 2) {
        let span_s = (table.t_ns[table.t_ns.len() - 1] - table.t_ns[0]) as f64 * 1e-9;
        let counts: Vec<String> = out
            .iter()
            .map(|s| format!("{} {} at {} Hz", s.topic, s.len(), s.rate))
            .collect();
        bail!(
            "{} rows over {span_s:.3} s give no topic two samples ({}): too short to import",
            table.t_ns.len(),
            counts.join(", ")
        );
    }
    Ok(out)
}

impl Series {
    /// Samples (of every column).
    fn len(&self) -> usize {
        self.values.iter().map(Vec::len).min().unwrap_or(0)
    }
}

fn samples(series: &[Series], t0_ns: i64) -> Vec<Sample> {
    let mut out = Vec::new();
    for s in series {
        let at = |j: usize| t0_ns + ((s.start_s + s.rate.time_s(j as f64)) * 1e9).round() as i64;
        for j in 0..s.len() {
            let t_ns = at(j);
            let v = s.values[0][j];
            out.push(match s.topic {
                "/position" => Sample::Position {
                    t_ns,
                    position_m: v,
                },
                "/force" => Sample::Force { t_ns, force_n: v },
                "/temperature/shock" => Sample::TempShock {
                    t_ns,
                    temperature_c: v,
                },
                "/temperature/ambient" => Sample::TempAmbient {
                    t_ns,
                    temperature_c: v,
                },
                _ => Sample::Acceleration {
                    t_ns,
                    a1_mps2: v,
                    a2_mps2: s.values[1][j],
                },
            });
        }
    }
    out
}
