//! `shocktwin road --calibration ROAD.json FILE.mcap... [--out OUT.(csv|jsonl)]`:
//! reads the gas charge of each run driven on a road with dt-core's road
//! observer ([`dt_core::road`]), as the daemon would stream it, and prints
//! each run's final estimate, 95 % interval and health. `--baseline
//! RUN.mcap@BAR` first reads a drive of the same unit at a known charge
//! (after a service): its seal's offset is taken from it.
//!
//! - `.csv` / `.jsonl`: one row per block read, with `run_id`, `asset_id`,
//!   `t_s` (block end, s since the run's first message) and the block's
//!   reading, estimate, interval and health.
//!
//! When a log carries a label (`charge_pressure_bar`), the table adds the
//! error of the final estimate, whether the interval covers the label after
//! each block, and from which block on the health is the label's and stays.
//! An unreadable input is reported and skipped; the exit status is then 1.

use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Mutex;

use anyhow::{bail, Context, Result};
use dt_core::bundle::HealthConfig;
use dt_core::estimate::Health;
use dt_core::log::read_log;
use dt_core::road::{read_run_counted, RoadBlock, RoadCalibration, RoadCounters};

use crate::cli::RoadArgs;

/// One run read.
pub(crate) struct Read {
    run_id: String,
    asset_id: String,
    label_bar: Option<f64>,
    pub(crate) blocks: Vec<RoadBlock>,
    counters: RoadCounters,
}

pub(crate) fn read_one(path: &Path, cal: &RoadCalibration, health: HealthConfig) -> Result<Read> {
    let log = read_log(path).with_context(|| format!("reading {}", path.display()))?;
    let (blocks, counters) = read_run_counted(&log, cal, health)
        .with_context(|| format!("{}: road observer", path.display()))?;
    Ok(Read {
        run_id: log.metadata.run_id.clone(),
        asset_id: log.metadata.asset_id.clone(),
        label_bar: log.metadata.charge_pressure_bar,
        blocks,
        counters,
    })
}

fn expected(cfg: &HealthConfig, bar: f64) -> Health {
    if bar < cfg.fault_bar {
        Health::Leak
    } else if bar < cfg.warn_bar {
        Health::Low
    } else {
        Health::Ok
    }
}

/// `--baseline RUN.mcap@BAR`.
pub(crate) fn parse_baseline(spec: &str) -> Result<(PathBuf, f64)> {
    let Some((path, bar)) = spec.rsplit_once('@') else {
        bail!("--baseline {spec:?}: expected RUN.mcap@BAR");
    };
    let bar: f64 = bar
        .parse()
        .ok()
        .filter(|b: &f64| b.is_finite() && *b >= 0.0)
        .with_context(|| format!("--baseline {spec:?}: {bar:?} is not a charge in bar"))?;
    Ok((PathBuf::from(path), bar))
}

fn write_rows(out: &Path, runs: &[Read]) -> Result<()> {
    let csv = match out.extension().and_then(|e| e.to_str()) {
        Some("csv") => true,
        Some("jsonl") => false,
        _ => bail!("{}: output must end in .csv or .jsonl", out.display()),
    };
    let file = File::create(out).with_context(|| format!("creating {}", out.display()))?;
    let mut w = BufWriter::new(file);
    if csv {
        writeln!(w, "run_id,asset_id,t_s,alpha_n,alpha_sd_n,temp_c,stroke_rms_mps,reading_bar,reading_sd_bar,pressure_bar,pressure_lo_bar,pressure_hi_bar,health")?;
    }
    for r in runs {
        for b in &r.blocks {
            let (estimate, lo, hi) = reported(b);
            if csv {
                writeln!(
                    w,
                    "{},{},{},{},{},{},{},{},{},{},{},{},{}",
                    r.run_id,
                    r.asset_id,
                    b.t_s,
                    b.alpha_n,
                    b.alpha_sd_n,
                    b.temp_c,
                    b.stroke_rms_mps,
                    b.reading_bar,
                    b.reading_sd_bar,
                    estimate,
                    lo,
                    hi,
                    b.health.as_str()
                )?;
            } else {
                let row = serde_json::json!({
                    "run_id": r.run_id, "asset_id": r.asset_id, "t_s": b.t_s,
                    "alpha_n": b.alpha_n, "alpha_sd_n": b.alpha_sd_n, "temp_c": b.temp_c,
                    "stroke_rms_mps": b.stroke_rms_mps, "reading_bar": b.reading_bar,
                    "reading_sd_bar": b.reading_sd_bar, "pressure_bar": estimate,
                    "pressure_lo_bar": lo, "pressure_hi_bar": hi, "health": b.health,
                });
                writeln!(w, "{row}")?;
            }
        }
    }
    w.flush()?;
    Ok(())
}

/// A block's estimate and interval as `replay --road` and the daemon report
/// them: floored at ambient (0 bar gauge) when the interval reaches above
/// it (`dt_core::estimator::at_ambient_floor`; a helper's trial found
/// `shocktwin road` printing `[-1.02, 4.74]` where they gave 0). The block's
/// reading itself is not floored.
fn reported(b: &RoadBlock) -> (f64, f64, f64) {
    let [estimate, _, lo] =
        dt_core::estimator::at_ambient_floor([b.estimate_bar, b.estimate_bar, b.lo_bar], b.hi_bar);
    (estimate, lo, b.hi_bar)
}

/// The per-run table (Markdown) on stdout.
fn print_table(runs: &[Read], health: &HealthConfig, simulated: bool) {
    if simulated {
        crate::outln!("(calibrated on SIMULATED DATA)");
    }
    crate::outln!("| run | asset | charge, bar | blocks | estimate, bar | 95 % interval | health | error, bar | coverage | right from |");
    crate::outln!("| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |");
    for r in runs {
        let Some(last) = r.blocks.last() else {
            let why = r
                .counters
                .why_none()
                .unwrap_or_else(|| "no complete block: the run is shorter than one".into());
            crate::outln!(
                "| {} | {} | {} | 0 | — | — | unknown ({why}) | | | |",
                r.run_id,
                r.asset_id,
                r.label_bar.map_or("—".into(), |l| format!("{l}"))
            );
            continue;
        };
        let (label, err, cover, right) = match r.label_bar {
            Some(l) => {
                let want = expected(health, l);
                let covered = r
                    .blocks
                    .iter()
                    .filter(|b| b.lo_bar <= l && l <= b.hi_bar)
                    .count();
                let from = (0..r.blocks.len())
                    .find(|&i| r.blocks[i..].iter().all(|b| b.health == want))
                    .map_or("never".to_owned(), |i| format!("{:.0} s", r.blocks[i].t_s));
                (
                    format!("{l}"),
                    format!("{:+.2}", reported(last).0 - l),
                    format!("{:.0} %", 100.0 * covered as f64 / r.blocks.len() as f64),
                    format!("{from} (want {})", want.as_str()),
                )
            }
            None => ("—".into(), String::new(), String::new(), String::new()),
        };
        let (estimate, lo, hi) = reported(last);
        crate::outln!(
            "| {} | {} | {label} | {} | {estimate:.2} | [{lo:.2}, {hi:.2}] | {} | {err} | {cover} | {right} |",
            r.run_id,
            r.asset_id,
            r.blocks.len(),
            last.health.as_str()
        );
    }
}

/// Runs `shocktwin road`.
///
/// # Errors
/// The calibration or the baseline cannot be used, or the output cannot be
/// written (an unreadable input only sets the exit status).
///
/// # Panics
/// When a worker thread panicked.
pub fn run(args: &RoadArgs) -> Result<std::process::ExitCode> {
    let text = std::fs::read_to_string(&args.calibration)
        .with_context(|| format!("--calibration {}", args.calibration.display()))?;
    let mut cal = RoadCalibration::from_json(&args.calibration.display().to_string(), &text)
        .map_err(|e| anyhow::anyhow!("--calibration {e}"))?;
    let health = HealthConfig::default();
    if let Some(spec) = &args.baseline {
        let (path, bar) = parse_baseline(spec)?;
        let base = read_one(&path, &cal, health).with_context(|| format!("--baseline {spec}"))?;
        let b = cal
            .read_baseline(&base.blocks, bar)
            .map_err(|e| anyhow::anyhow!("--baseline {spec}: {e}"))?;
        cal = cal.apply(&b);
        eprintln!(
            "baseline {}: {} blocks at {bar} bar, the seal {:+.3} N from the calibration's; for the daemon:\n  \
             [assets.{}]\n  road = true\n  road_baseline = {{ charge_bar = {}, offset_n = {}, blocks = {} }}",
            path.display(),
            b.blocks,
            b.offset_n,
            base.asset_id,
            b.charge_bar,
            b.offset_n,
            b.blocks
        );
    }
    let jobs = args
        .jobs
        .unwrap_or_else(|| std::thread::available_parallelism().map_or(1, usize::from))
        .max(1);
    let next = AtomicUsize::new(0);
    let results: Mutex<Vec<(usize, Result<Read>)>> = Mutex::new(Vec::new());
    let bar = crate::progress::bar(args.files.len() as u64, "road");
    std::thread::scope(|scope| {
        for _ in 0..jobs.min(args.files.len()) {
            scope.spawn(|| loop {
                let i = next.fetch_add(1, Ordering::Relaxed);
                let Some(path) = args.files.get(i) else { break };
                let r = read_one(path, &cal, health);
                bar.inc(1);
                results.lock().expect("no worker panics").push((i, r));
            });
        }
    });
    bar.finish_and_clear();
    let mut results = results.into_inner().expect("no worker panics");
    results.sort_by_key(|(i, _)| *i);
    let mut failed = false;
    let mut runs = Vec::new();
    for (_, r) in results {
        match r {
            Ok(r) => runs.push(r),
            Err(e) => {
                eprintln!("shocktwin road: {e:#}");
                failed = true;
            }
        }
    }
    print_table(&runs, &health, cal.simulated);
    if let Some(out) = &args.out {
        write_rows(out, &runs)?;
        crate::outln!("wrote {} ({} runs)", out.display(), runs.len());
    }
    Ok(if failed {
        std::process::ExitCode::FAILURE
    } else {
        std::process::ExitCode::SUCCESS
    })
}
