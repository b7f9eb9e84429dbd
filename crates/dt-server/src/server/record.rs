//! Records every run's estimates as MCAP (topic `/estimate`, SPEC §2),
//! written with `dt_core::log::LogWriter`, rotating by size or by span of
//! estimate time.
//!
//! Files are `<record_dir>/<asset_id>/<run_id>.<part>.mcap` (part 0, 1, …).
//! A file is written as `….mcap.part` and renamed when finished (on rotation,
//! at the end of its run, or at shutdown), so a `.mcap` file is always
//! complete. Names are deterministic: processing the same run again to its
//! end (an inbox file after a crash, a vehicle's retry) rewrites the same
//! files. Two things would lose a recording that way, and are kept apart as
//! `<run_id>~<seq>.<part>.mcap` ([`RunInfo::seq`]; `~` is in no run id)
//! with a warning: a copy of a run processed while another is being
//! recorded (both wrote one `.part` at once: a corrupt file), and a
//! processing that did not complete (failed, interrupted) whose last part's
//! name a finished recording already holds (a cut retry replaced the whole
//! run's recording).

use std::collections::HashMap;
use std::fs::File;
use std::io::{BufWriter, Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;

use dt_core::estimate::{Estimate, ESTIMATE_SCHEMA_JSON};
use dt_core::log::{topic, LogWriter, WriteOptions};

use super::config::RecordConfig;
use super::sink::{RunEnd, RunInfo, RunOutcome, Sink, SinkError};

/// A writer that knows how far it has written (for rotation by size).
#[derive(Debug)]
struct CountingWriter<W> {
    inner: W,
    pos: u64,
    /// Furthest position written, shared with the [`Recording`].
    len: Arc<AtomicU64>,
}

impl<W> CountingWriter<W> {
    fn advance(&mut self, pos: u64) {
        self.pos = pos;
        self.len.fetch_max(pos, Ordering::Relaxed);
    }
}

impl<W: Write> Write for CountingWriter<W> {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        let n = self.inner.write(buf)?;
        self.advance(self.pos + n as u64);
        Ok(n)
    }

    fn flush(&mut self) -> std::io::Result<()> {
        self.inner.flush()
    }
}

impl<W: Seek> Seek for CountingWriter<W> {
    fn seek(&mut self, to: SeekFrom) -> std::io::Result<u64> {
        let pos = self.inner.seek(to)?;
        self.advance(pos);
        Ok(pos)
    }
}

type Writer = LogWriter<CountingWriter<BufWriter<File>>>;

struct Recording {
    writer: Writer,
    part_path: PathBuf,
    final_path: PathBuf,
    /// The name kept apart ([`McapRecorder::aside_base`]), when the final
    /// one is another copy's.
    aside_path: PathBuf,
    /// The run (asset id, run id).
    run: (String, String),
    /// This copy's name apart from the run's own (`<run_id>~<seq>`), chosen
    /// at its first part and kept through its rotations.
    aside_base: String,
    /// Recorded apart from its first part: another copy was being recorded.
    apart: bool,
    part: u32,
    first_t_ns: i64,
    bytes: Arc<AtomicU64>,
}

/// The recording [`Sink`].
pub struct McapRecorder {
    dir: PathBuf,
    config: RecordConfig,
    open: HashMap<u64, Recording>,
}

impl std::fmt::Debug for McapRecorder {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("McapRecorder")
            .field("dir", &self.dir)
            .field("open_runs", &self.open.len())
            .finish_non_exhaustive()
    }
}

fn err(reason: String) -> SinkError {
    SinkError {
        sink: "record",
        reason,
    }
}

impl McapRecorder {
    /// Records under `dir` (created if needed).
    pub fn new(dir: &Path, config: RecordConfig) -> Result<Self, SinkError> {
        std::fs::create_dir_all(dir)
            .map_err(|e| err(format!("cannot create {}: {e}", dir.display())))?;
        Ok(Self {
            dir: dir.to_owned(),
            config,
            open: HashMap::new(),
        })
    }

    /// Path of part `part` of a run's recording.
    #[must_use]
    pub fn path_of(dir: &Path, asset_id: &str, run_id: &str, part: u32) -> PathBuf {
        dir.join(asset_id).join(format!("{run_id}.{part:04}.mcap"))
    }

    /// The base name under which a copy of a run is kept apart from the
    /// run's own recording (see the module's doc): `<run_id>~<seq>`, or with
    /// `-2`, `-3`, … when a copy of an earlier daemon's life (whose `seq`s
    /// start again at 1) holds it.
    fn aside_base(&self, run: &RunInfo) -> String {
        let taken = |base: &str| {
            let path = Self::path_of(&self.dir, &run.meta.asset_id, base, 0);
            path.exists() || path.with_extension("mcap.part").exists()
        };
        let base = format!("{}~{}", run.meta.run_id, run.seq);
        if !taken(&base) {
            return base;
        }
        // one more name than the directory holds files: one is free
        let files = std::fs::read_dir(self.dir.join(&run.meta.asset_id)).map_or(0, Iterator::count);
        (2..=files + 2)
            .map(|k| format!("{base}-{k}"))
            .find(|b| !taken(b))
            .unwrap_or(base)
    }

    /// Opens part `part` of `run`'s recording; `rotated`: the base name
    /// apart and whether the copy is recorded apart, from its part before.
    fn start(
        &self,
        run: &RunInfo,
        part: u32,
        first_t_ns: i64,
        rotated: Option<(String, bool)>,
    ) -> Result<Recording, SinkError> {
        let key = (run.meta.asset_id.clone(), run.meta.run_id.clone());
        let (aside_base, apart) = rotated.unwrap_or_else(|| {
            let apart = self.open.values().any(|r| r.run == key);
            (self.aside_base(run), apart)
        });
        let aside_path = Self::path_of(&self.dir, &run.meta.asset_id, &aside_base, part);
        let final_path = if apart {
            if part == 0 {
                tracing::warn!(
                    asset_id = %run.meta.asset_id,
                    run_id = %run.meta.run_id,
                    file = %aside_path.display(),
                    "another copy of this run is being recorded: this one is recorded apart"
                );
            }
            aside_path.clone()
        } else {
            Self::path_of(&self.dir, &run.meta.asset_id, &run.meta.run_id, part)
        };
        let part_path = final_path.with_extension("mcap.part");
        if let Some(parent) = final_path.parent() {
            std::fs::create_dir_all(parent)
                .map_err(|e| err(format!("cannot create {}: {e}", parent.display())))?;
        }
        let file = File::create(&part_path)
            .map_err(|e| err(format!("cannot create {}: {e}", part_path.display())))?;
        let bytes = Arc::new(AtomicU64::new(0));
        let counting = CountingWriter {
            inner: BufWriter::with_capacity(1 << 16, file),
            pos: 0,
            len: Arc::clone(&bytes),
        };
        let mut meta = run.meta.clone();
        meta.extra
            .insert("shocktwin.content".into(), "estimates".into());
        meta.extra
            .insert("shocktwin.recording_part".into(), part.to_string());
        meta.extra
            .insert("shocktwin.source".into(), run.source.clone());
        // Chunks small enough that rotation by size sees the bytes soon.
        let options = WriteOptions {
            compression: self.config.compression,
            chunk_size: Some((self.config.max_file_bytes / 4).clamp(4096, 256 << 10)),
        };
        let writer = LogWriter::new(counting, &meta, options)
            .map_err(|e| err(format!("{}: {e}", part_path.display())))?;
        Ok(Recording {
            writer,
            part_path,
            final_path,
            aside_path,
            run: key,
            aside_base,
            apart,
            part,
            first_t_ns,
            bytes,
        })
    }

    /// Finishes a part: renamed to its final name, or kept apart when that
    /// name holds a finished recording and this part is the last of a
    /// processing that did not complete (`whole` false).
    fn finish(rec: Recording, whole: bool) -> Result<PathBuf, SinkError> {
        let Recording {
            writer,
            part_path,
            mut final_path,
            aside_path,
            apart,
            ..
        } = rec;
        if !whole && !apart && final_path.exists() {
            tracing::warn!(
                file = %aside_path.display(),
                recorded = %final_path.display(),
                "a processing of an already recorded run did not complete: its estimates are \
                 kept apart, the run's recording as it was"
            );
            final_path = aside_path;
        }
        let counting = writer
            .finish()
            .map_err(|e| err(format!("{}: {e}", part_path.display())))?;
        let file = counting
            .inner
            .into_inner()
            .map_err(|e| err(format!("{}: {}", part_path.display(), e.error())))?;
        file.sync_all()
            .map_err(|e| err(format!("{}: {e}", part_path.display())))?;
        std::fs::rename(&part_path, &final_path).map_err(|e| {
            err(format!(
                "cannot rename {} to {}: {e}",
                part_path.display(),
                final_path.display()
            ))
        })?;
        tracing::debug!(file = %final_path.display(), "recording finished");
        Ok(final_path)
    }

    fn max_span_ns(&self) -> i64 {
        (self.config.max_file_s * 1e9) as i64
    }
}

impl Sink for McapRecorder {
    fn name(&self) -> &'static str {
        "record"
    }

    fn run_started(&mut self, _run: &RunInfo) -> Result<(), SinkError> {
        // The file is opened at the first estimate (a run may have none).
        Ok(())
    }

    fn estimates(&mut self, run: &RunInfo, batch: &[Estimate]) -> Result<(), SinkError> {
        for e in batch {
            let rotate = match self.open.get(&run.seq) {
                None => None,
                Some(r) => {
                    let over_size = r.writer_len() >= self.config.max_file_bytes;
                    let over_span = e.t_ns.saturating_sub(r.first_t_ns) >= self.max_span_ns();
                    (over_size || over_span).then_some(r.part + 1)
                }
            };
            if let Some(next) = rotate {
                let old = self.open.remove(&run.seq).expect("checked above");
                let rotated = (old.aside_base.clone(), old.apart);
                Self::finish(old, true)?; // a whole part
                self.open
                    .insert(run.seq, self.start(run, next, e.t_ns, Some(rotated))?);
            } else if !self.open.contains_key(&run.seq) {
                self.open.insert(run.seq, self.start(run, 0, e.t_ns, None)?);
            }
            let rec = self.open.get_mut(&run.seq).expect("opened above");
            rec.writer
                .write_json(topic::ESTIMATE, ESTIMATE_SCHEMA_JSON, e.t_ns, e)
                .map_err(|x| err(format!("{}: {x}", rec.part_path.display())))?;
        }
        Ok(())
    }

    fn run_ended(&mut self, run: &RunInfo, end: &RunEnd) -> Result<(), SinkError> {
        let whole = matches!(end.outcome, RunOutcome::Completed);
        match self.open.remove(&run.seq) {
            Some(rec) => Self::finish(rec, whole).map(|_| ()),
            None => Ok(()),
        }
    }

    fn close(&mut self) -> Result<(), SinkError> {
        let mut first = Ok(());
        for (_, rec) in self.open.drain() {
            if let Err(e) = Self::finish(rec, false) {
                if first.is_ok() {
                    first = Err(e);
                }
            }
        }
        first
    }
}

impl Recording {
    fn writer_len(&self) -> u64 {
        self.bytes.load(Ordering::Relaxed)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::server::config::AssetConfig;
    use crate::server::sink::SourceKind;
    use dt_core::estimate::Health;
    use dt_core::log::RunMetadata;

    fn run(seq: u64) -> RunInfo {
        RunInfo {
            seq,
            kind: SourceKind::Tcp,
            source: format!("tcp copy {seq}"),
            meta: RunMetadata {
                asset_id: "van-1".into(),
                run_id: "r1".into(),
                ..RunMetadata::default()
            },
            asset: AssetConfig::default(),
            started: std::time::SystemTime::now(),
        }
    }

    fn estimate(t_s: i64) -> Estimate {
        Estimate {
            t_ns: t_s * 1_000_000_000,
            pressure_bar: 7.0,
            pressure_avg_bar: 7.0,
            pressure_lo_bar: f64::NAN,
            pressure_hi_bar: f64::NAN,
            expected_bar: 12.0,
            health: Health::Unknown,
            velocity_mps: 0.0,
            force_model_n: 0.0,
            oil_temp_c: 20.0,
            unfloored_bar: f64::NAN,
            unfloored_half_bar: f64::NAN,
        }
    }

    fn names(dir: &Path) -> Vec<String> {
        let mut v: Vec<String> = std::fs::read_dir(dir.join("van-1"))
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        v.sort();
        v
    }

    /// The review: a copy recorded apart went back to the run's own name at
    /// its first rotation (the clash was looked for on the same part only),
    /// and a copy started while the first was on a later part overwrote the
    /// first's part 0.
    #[test]
    fn a_copy_recorded_apart_stays_apart_through_its_rotations() {
        let dir = tempfile::tempdir().unwrap();
        let config = RecordConfig {
            max_file_s: 10.0,
            ..RecordConfig::default()
        };
        let mut rec = McapRecorder::new(dir.path(), config).unwrap();
        let (a, b) = (run(1), run(2));
        let done = RunEnd {
            outcome: RunOutcome::Completed,
            observer: None,
            road: None,
        };
        // A on its part 1 when B starts; B then rotates to its part 1, 2.
        rec.estimates(&a, &[estimate(0), estimate(12)]).unwrap();
        rec.estimates(&b, &[estimate(0), estimate(12), estimate(24)])
            .unwrap();
        rec.run_ended(&b, &done).unwrap();
        rec.estimates(&a, &[estimate(25)]).unwrap();
        rec.run_ended(&a, &done).unwrap();
        assert_eq!(
            names(dir.path()),
            [
                "r1.0000.mcap",
                "r1.0001.mcap",
                "r1.0002.mcap",
                "r1~2.0000.mcap",
                "r1~2.0001.mcap",
                "r1~2.0002.mcap"
            ]
        );
        // a copy of a later life of the daemon (its seq 2 again) does not
        // overwrite the kept-apart one
        let mut rec = McapRecorder::new(dir.path(), RecordConfig::default()).unwrap();
        rec.estimates(&a, &[estimate(0)]).unwrap();
        rec.estimates(&b, &[estimate(0)]).unwrap();
        rec.close().unwrap();
        assert!(names(dir.path()).contains(&"r1~2-2.0000.mcap".to_owned()));
    }
}
