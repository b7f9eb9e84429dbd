//! A crank dyno's CSV export of a simulated run: the shape of file a test
//! engineer brings from their own dyno, for `shocktwin import` to read.
//!
//! One row per sample at about `rate_hz` (the dyno's logger stamps samples
//! on a 1 ms clock, so at 300 Hz the steps are 3, 3 and 4 ms), columns
//! `Timestamp` (ISO-8601, UTC, milliseconds), `Force [N]` (**compression
//! positive**, the opposite of SPEC §1), `Displacement [mm]` (**compression
//! positive, from full extension** of the stroke: `stroke/2 − y`) and
//! `Temperature [°C]` (the shock-body thermocouple, read at the row rate).
//! No accelerometers and no ambient thermocouple, as on most dynos. Two
//! preamble lines (test name, stroke) come before the header. The file is
//! named `<asset>_<charge in psi, one decimal>psi_<frequency>Hz_s<seed>.csv`: the
//! charge label travels in the file name, as dyno operators keep it.
//!
//! Simulated data: the same plant, sensors and seeds as the MCAP runs of
//! [`crate::run`], sampled on the export's schedule instead of SPEC §2's.

use std::io::Write as _;
use std::path::{Path, PathBuf};

use rayon::prelude::*;

use crate::run::{drive, prepare, CampaignSpec, RunSpec, RunSummary, T0_NS};
use crate::SimError;

/// Pounds per square inch in one bar.
pub const PSI_PER_BAR: f64 = 14.503_773_773_020_923;

/// The export's file name for `spec`.
#[must_use]
pub fn export_file_name(spec: &RunSpec) -> String {
    let repeat = if spec.repeat > 0 {
        format!("-r{}", spec.repeat)
    } else {
        String::new()
    };
    format!(
        "{}_{:.1}psi_{}Hz_s{}{repeat}.csv",
        spec.asset_id(),
        spec.charge_bar * PSI_PER_BAR,
        spec.frequency_hz,
        spec.seed
    )
}

/// Simulates `spec` into the dyno CSV export `out_path` at about `rate_hz`
/// (at most 1000 Hz: the logger's clock).
pub fn simulate_dyno_csv(
    spec: &RunSpec,
    params: &crate::PlantParams,
    rate_hz: f64,
    out_path: &Path,
) -> Result<RunSummary, SimError> {
    if !(rate_hz > 0.0 && rate_hz <= 1000.0) {
        return Err(SimError::InvalidSpec {
            field: "csv_rate_hz",
            value: rate_hz,
            reason: "must be in (0, 1000] Hz (the logger stamps on a 1 ms clock)",
        });
    }
    let io = |source: std::io::Error| SimError::Io {
        path: out_path.display().to_string(),
        source,
    };
    let file = std::fs::File::create(out_path).map_err(io)?;
    let mut w = std::io::BufWriter::new(file);
    writeln!(w, "Test,{} (simulated crank dyno; dt-sim)", spec.run_id()).map_err(io)?;
    writeln!(w, "Stroke [mm],{:.1}", spec.stroke_pp_m * 1e3).map_err(io)?;
    writeln!(w, "Timestamp,Force [N],Displacement [mm],Temperature [°C]").map_err(io)?;
    let half_stroke_mm = spec.stroke_pp_m * 1e3 / 2.0;
    let mut next_row: u64 = 0;
    let mut rows: u64 = 0;
    let mut failed: Option<std::io::Error> = None;
    let mut summary = drive(spec, params, |ms, _truth, sensors, summary| {
        // The stop rule reads the thermocouple once a second, as in a log.
        let shock = (ms % 1000 == 0).then(|| sensors.sample_temp_shock());
        if let Some(c) = shock {
            summary.final_shock_reading_c = c;
        }
        let due = (next_row as f64 * 1000.0 / rate_hz).round() as u64;
        if ms == due {
            next_row += 1;
            let t_ns = T0_NS + (ms as i64) * 1_000_000;
            let stamp = humantime::format_rfc3339_millis(
                std::time::UNIX_EPOCH + std::time::Duration::from_nanos(t_ns as u64),
            );
            let force = -sensors.sample_force();
            let displacement_mm = half_stroke_mm - sensors.sample_position() * 1e3;
            let temp = sensors.sample_temp_shock();
            if failed.is_none() {
                if let Err(e) = writeln!(w, "{stamp},{force:.1},{displacement_mm:.3},{temp:.2}") {
                    failed = Some(e);
                }
            }
            rows += 1;
        }
        Ok(shock)
    })?;
    if let Some(e) = failed {
        return Err(io(e));
    }
    w.flush().map_err(io)?;
    summary.messages = rows;
    summary.path = Some(out_path.to_path_buf());
    Ok(summary)
}

/// Every run of `spec` as a dyno CSV export into `out_dir`, in parallel;
/// `on_run` is called as each file is written.
pub fn simulate_dyno_csv_campaign(
    spec: &CampaignSpec,
    rate_hz: f64,
    out_dir: &Path,
    on_run: &(dyn Fn(&RunSummary) + Sync),
) -> Result<Vec<RunSummary>, SimError> {
    let (runs, params) = prepare(spec, out_dir)?;
    runs.par_iter()
        .map(|run| {
            let path: PathBuf = out_dir.join(export_file_name(run));
            let summary = simulate_dyno_csv(run, &params, rate_hz, &path)?;
            on_run(&summary);
            Ok(summary)
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn export_has_preamble_header_and_rows_at_the_rate() {
        let dir = tempfile::tempdir().unwrap();
        let mut spec = RunSpec::paper(7.0, 2.0, 3);
        spec.quick = true;
        let path = dir.path().join(export_file_name(&spec));
        let summary = simulate_dyno_csv(&spec, &spec.params(), 300.0, &path).unwrap();
        assert!(path
            .file_name()
            .unwrap()
            .to_str()
            .unwrap()
            .contains("101.5psi"));
        let text = std::fs::read_to_string(&path).unwrap();
        let lines: Vec<&str> = text.lines().collect();
        assert!(lines[2].starts_with("Timestamp,Force [N]"));
        assert_eq!(lines.len() as u64 - 3, summary.messages);
        // ~300 rows per second of the run.
        let per_s = summary.messages as f64 / summary.duration_s;
        assert!((per_s - 300.0).abs() < 2.0, "{per_s} rows/s");
        assert!(
            lines[3].starts_with("2023-11-14T22:13:20.000Z,"),
            "{}",
            lines[3]
        );
    }
}
