//! `shocktwin replay --model BUNDLE FILE.mcap... --out OUT.(mcap|jsonl|csv)`:
//! runs logs through the streaming estimator as fast as the machine allows
//! (one worker per core, one run per worker at a time) and writes the
//! `/estimate` stream.
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
use std::io::{BufWriter, Write};
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
use dt_core::log::{read_log, topic, LogWriter, RunLog, WriteOptions};

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
    let several = args.files.len() > 1;
    let mcap_out = |run_id: &str| -> PathBuf {
        if several {
            let stem = args.out.with_extension("");
            PathBuf::from(format!("{}-{run_id}.mcap", stem.display()))
        } else {
            args.out.clone()
        }
    };

    let workers = args
        .jobs
        .unwrap_or_else(|| std::thread::available_parallelism().map_or(1, usize::from))
        .clamp(1, args.files.len());
    let next = AtomicUsize::new(0);
    let results: Mutex<Vec<(usize, Result<Replayed>)>> = Mutex::new(Vec::new());
    let started = Instant::now();
    let bar = crate::progress::bar(args.files.len() as u64, "replay");
    std::thread::scope(|scope| {
        for _ in 0..workers {
            scope.spawn(|| loop {
                let i = next.fetch_add(1, Ordering::Relaxed);
                let Some(file) = args.files.get(i) else { break };
                let res = replay_file(file, &bundle, cfg, format, &mcap_out);
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

fn replay_file(
    file: &Path,
    bundle: &Arc<Bundle>,
    cfg: EstimatorConfig,
    format: Format,
    mcap_out: &dyn Fn(&str) -> PathBuf,
) -> Result<Replayed> {
    let started = Instant::now();
    let log = read_log(file)?;
    for problem in &log.problems {
        tracing::warn!(file = %file.display(), "{problem}");
    }
    let mut est = Estimator::new(Arc::clone(bundle), cfg)
        .with_context(|| format!("{}: estimator", file.display()))?;
    let mut estimates = Vec::new();
    let samples = log.samples_sorted();
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
    for s in &samples {
        est.push(*s)
            .with_context(|| format!("{}", file.display()))?;
        if let Some(w) = writer.as_mut() {
            w.write_sample(s)?;
            for e in est.drain() {
                w.write_json(topic::ESTIMATE, ESTIMATE_SCHEMA_JSON, e.t_ns, &e)?;
                estimates.push(e);
            }
        } else {
            estimates.extend(est.drain());
        }
    }
    est.finish()
        .with_context(|| format!("{}", file.display()))?;
    for e in est.drain() {
        if let Some(w) = writer.as_mut() {
            w.write_json(topic::ESTIMATE, ESTIMATE_SCHEMA_JSON, e.t_ns, &e)?;
        }
        estimates.push(e);
    }
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
        samples: samples.len(),
        estimates,
        seconds: started.elapsed().as_secs_f64(),
    })
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

fn num(x: f64) -> String {
    if x.is_finite() {
        format!("{x}")
    } else {
        String::new()
    }
}

fn write_table(out: &Path, format: Format, runs: &[Replayed]) -> Result<()> {
    let file = File::create(out).with_context(|| format!("creating {}", out.display()))?;
    let mut w = BufWriter::new(file);
    if format == Format::Csv {
        writeln!(w, "{}", FIELDS.join(","))?;
    }
    let mut line = String::new();
    for r in runs {
        for e in &r.estimates {
            let t_s = (e.t_ns - r.t0_ns) as f64 * 1e-9;
            line.clear();
            if format == Format::Csv {
                let _ = write!(
                    line,
                    "{},{},{t_s:.3},{},{},{},{},{},{},{},{},{},{}",
                    r.run_id,
                    r.asset_id,
                    num(e.pressure_bar),
                    num(e.pressure_avg_bar),
                    num(e.pressure_lo_bar),
                    num(e.pressure_hi_bar),
                    num(e.expected_bar),
                    e.health,
                    num(e.velocity_mps),
                    num(e.force_model_n),
                    num(e.oil_temp_c),
                    r.label_bar.map_or(String::new(), num),
                );
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
