//! [`FleetStore`] on an embedded `SQLite` file (rusqlite, `SQLite` compiled
//! in). WAL journal with `synchronous = NORMAL`: a crash of the process at
//! any moment (`kill -9`) leaves the last committed transaction and a
//! consistent file. One connection writes (the store's writer thread), one
//! reads (the HTTP handlers); WAL lets them run at once.
//!
//! Schema migrations are a list applied in order inside one transaction;
//! `PRAGMA user_version` holds the version reached. A file from a newer
//! shocktwin is refused, not touched.

use std::path::{Path, PathBuf};
use std::sync::{Mutex, PoisonError};
use std::time::Duration;

use dt_core::charge::{other_excitations_from, ObserverCounters, UnitBaseline};
use dt_core::road::{RoadBaseline, RoadCounters};
use dt_core::trend::RunPoint;
use rusqlite::{params, Connection, OptionalExtension as _};

use crate::server::sink::{ObserverRead, RoadRead};

use super::{
    health_code, health_from_code, health_from_str, AssetBaseline, AssetState, FleetStore,
    HealthChange, HistoryPoint, PendingService, RunRecord, StoreError, StoreOp, StoredBaseline,
};

/// The schema version this build writes.
pub const SCHEMA_VERSION: i64 = 14;

/// Migration `i` takes the schema from version `i` to `i + 1`.
const MIGRATIONS: [&str; SCHEMA_VERSION as usize] = [
    r"
CREATE TABLE assets (
    id       INTEGER PRIMARY KEY,
    asset_id TEXT NOT NULL UNIQUE
);
CREATE TABLE runs (
    key            TEXT PRIMARY KEY,
    asset          INTEGER NOT NULL REFERENCES assets(id),
    run_id         TEXT NOT NULL,
    source         TEXT NOT NULL,
    start_ms       INTEGER NOT NULL,
    end_ms         INTEGER,
    ticks          INTEGER NOT NULL DEFAULT 0,
    status         TEXT NOT NULL,
    reason         TEXT,
    summary_t_ms   INTEGER,
    summary_bar    REAL,
    summary_sd_bar REAL
);
CREATE INDEX runs_by_asset ON runs(asset, start_ms);
CREATE TABLE samples (
    asset        INTEGER NOT NULL REFERENCES assets(id),
    t_ms         INTEGER NOT NULL,
    pressure_bar REAL,
    lo_bar       REAL,
    hi_bar       REAL,
    health       INTEGER NOT NULL,
    excited      INTEGER NOT NULL,
    PRIMARY KEY (asset, t_ms)
) WITHOUT ROWID;
CREATE TABLE health_changes (
    asset       INTEGER NOT NULL REFERENCES assets(id),
    t_ms        INTEGER NOT NULL,
    run_id      TEXT NOT NULL,
    from_health TEXT NOT NULL,
    to_health   TEXT NOT NULL
);
CREATE INDEX health_by_asset ON health_changes(asset, t_ms);
",
    r"
CREATE TABLE baselines (
    asset       INTEGER PRIMARY KEY REFERENCES assets(id),
    charge_bar  REAL NOT NULL,
    read_bar    REAL NOT NULL,
    read_sd_bar REAL NOT NULL,
    set_ms      INTEGER NOT NULL
);
",
    r"
CREATE TABLE services (
    asset      INTEGER PRIMARY KEY REFERENCES assets(id),
    charge_bar REAL NOT NULL,
    set_ms     INTEGER NOT NULL,
    refusal    TEXT
);
",
    // What the charge observer made of a run's reversals: its counters as
    // JSON (`dt_core::charge::ObserverCounters`), NULL without an observer.
    r"
ALTER TABLE runs ADD COLUMN observer TEXT;
",
    // A road asset's baseline (`dt_core::road::RoadBaseline`); an asset has
    // at most one row in `baselines` and `road_baselines` together.
    r"
CREATE TABLE road_baselines (
    asset      INTEGER PRIMARY KEY REFERENCES assets(id),
    charge_bar REAL NOT NULL,
    offset_n   REAL NOT NULL,
    blocks     INTEGER NOT NULL,
    set_ms     INTEGER NOT NULL
);
",
    // What the road observer made of a road asset's run: its counters as
    // JSON (`dt_core::road::RoadCounters`), NULL for other assets.
    r"
ALTER TABLE runs ADD COLUMN road TEXT;
",
    // The excitations an observer baseline was read at
    // (`dt_core::charge::UnitBaseline::accel_range_mps2`), NULL: unknown.
    r"
ALTER TABLE baselines ADD COLUMN accel_lo_mps2 REAL;
ALTER TABLE baselines ADD COLUMN accel_hi_mps2 REAL;
",
    // A unit's own damping law (`dt_core::charge::UnitBaseline::damping_law`)
    // as JSON, NULL: the calibration's.
    r"
ALTER TABLE baselines ADD COLUMN damping_law TEXT;
",
    // A second reading at another known charge
    // (`dt_core::charge::UnitBaseline::second`) as JSON, NULL: none.
    r"
ALTER TABLE baselines ADD COLUMN second TEXT;
",
    // How many runs the first reading averages
    // (`dt_core::charge::UnitBaseline::runs_averaged`); 1: one.
    r"
ALTER TABLE baselines ADD COLUMN runs_averaged REAL NOT NULL DEFAULT 1.0;
",
    // The stroke's ends apart at the reading
    // (`dt_core::charge::UnitBaseline::split_bar`), bar; NULL: not read.
    r"
ALTER TABLE baselines ADD COLUMN split_bar REAL;
",
    // Whether the run's log says it is simulated (its metadata's `simulated`
    // key): 1, 0, or NULL when it does not say.
    r"
ALTER TABLE runs ADD COLUMN simulated INTEGER;
",
    // The unit read at other excitations
    // (`dt_core::charge::UnitBaseline::other_excitations`): a JSON list of its
    // readings; NULL: none.
    r"
ALTER TABLE baselines ADD COLUMN other_excitations TEXT;
",
    // The gateway's wall-clock time (Unix ms) of the run's last write: the
    // asset's `last_update_unix_ms` after a restart (the data's own clock
    // before, which read "1107 d ago" for an old upload). NULL: not kept.
    r"
ALTER TABLE runs ADD COLUMN seen_ms INTEGER;
",
];

const ASSET: &str = "(SELECT id FROM assets WHERE asset_id = ?1)";

/// A baseline's JSON column `name` (`damping_law`, `second`; NULL: none); a
/// value this daemon cannot read is an error naming the column.
fn json_column<T: serde::de::DeserializeOwned>(
    r: &rusqlite::Row<'_>,
    i: usize,
    name: &str,
) -> rusqlite::Result<Option<T>> {
    r.get::<_, Option<String>>(i)?
        .map(|text| {
            serde_json::from_str(&text).map_err(|e| {
                rusqlite::Error::FromSqlConversionFailure(
                    i,
                    rusqlite::types::Type::Text,
                    format!("baselines.{name}: {e}").into(),
                )
            })
        })
        .transpose()
}

/// The embedded fleet store.
#[derive(Debug)]
pub struct SqliteStore {
    path: PathBuf,
    writer: Mutex<Connection>,
    reader: Mutex<Connection>,
}

/// Makes `asset_id` known to the store within `tx`.
fn know_asset(tx: &rusqlite::Transaction<'_>, asset_id: &str) -> rusqlite::Result<()> {
    tx.execute(
        "INSERT OR IGNORE INTO assets (asset_id) VALUES (?1)",
        [asset_id],
    )
    .map(drop)
}

/// Deletes `asset_id`'s row of `table` (`baselines`, `road_baselines` or
/// `services`) within `tx`.
fn forget(tx: &rusqlite::Transaction<'_>, table: &str, asset_id: &str) -> rusqlite::Result<()> {
    tx.execute(
        &format!("DELETE FROM {table} WHERE asset = {ASSET}"),
        [asset_id],
    )
    .map(drop)
}

/// Keeps `b` as `asset_id`'s baseline within `tx` (the asset made known;
/// a baseline of the other kind forgotten).
fn put_baseline(
    tx: &rusqlite::Transaction<'_>,
    asset_id: &str,
    b: &StoredBaseline,
) -> rusqlite::Result<()> {
    know_asset(tx, asset_id)?;
    forget_baseline(tx, asset_id)?;
    match b.baseline {
        AssetBaseline::Observer(u) => tx.execute(
            &format!(
                "INSERT INTO baselines (asset, charge_bar, read_bar, read_sd_bar, set_ms, \
                 accel_lo_mps2, accel_hi_mps2, damping_law, second, runs_averaged, split_bar, \
                 other_excitations) \
                 VALUES ({ASSET}, ?2, ?3, ?4, ?5, ?6, ?7, ?8, ?9, ?10, ?11, ?12)"
            ),
            params![
                asset_id,
                u.charge_bar,
                u.read_bar,
                u.read_sd_bar,
                b.set_ms,
                u.accel_range_mps2.map(|r| r[0]),
                u.accel_range_mps2.map(|r| r[1]),
                u.damping_law
                    .map(|l| serde_json::to_string(&l).expect("a law is plain numbers")),
                u.second
                    .map(|r| serde_json::to_string(&r).expect("a reading is plain numbers")),
                u.runs_averaged,
                u.split_bar,
                u.other_excitations.iter().any(Option::is_some).then(|| {
                    let list: Vec<_> = u.other_excitations.iter().flatten().collect();
                    serde_json::to_string(&list).expect("readings are plain numbers")
                }),
            ],
        )?,
        AssetBaseline::Road(r) => tx.execute(
            &format!(
                "INSERT INTO road_baselines (asset, charge_bar, offset_n, blocks, set_ms) \
                 VALUES ({ASSET}, ?2, ?3, ?4, ?5)"
            ),
            params![
                asset_id,
                r.charge_bar,
                r.offset_n,
                i64::try_from(r.blocks).unwrap_or(i64::MAX),
                b.set_ms
            ],
        )?,
    };
    Ok(())
}

/// Forgets `asset_id`'s baseline, of either kind, within `tx`.
fn forget_baseline(tx: &rusqlite::Transaction<'_>, asset_id: &str) -> rusqlite::Result<()> {
    forget(tx, "baselines", asset_id)?;
    forget(tx, "road_baselines", asset_id)
}

fn finite(v: f64) -> Option<f64> {
    v.is_finite().then_some(v)
}

impl SqliteStore {
    /// Opens (creating it and its directory if missing) and migrates the
    /// store at `path`. Runs left `running` by a daemon that died are marked
    /// `interrupted`.
    pub fn open(path: &Path) -> Result<Self, StoreError> {
        let open_err = |reason: String| StoreError::Open {
            path: path.to_path_buf(),
            reason,
        };
        if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
            std::fs::create_dir_all(dir)
                .map_err(|e| open_err(format!("cannot create {}: {e}", dir.display())))?;
        }
        let writer = Self::connect(path)?;
        let version: i64 = writer
            .query_row("PRAGMA user_version", [], |r| r.get(0))
            .map_err(|e| open_err(format!("not a readable SQLite database ({e})")))?;
        if version > SCHEMA_VERSION {
            return Err(StoreError::NewerSchema {
                path: path.to_path_buf(),
                found: version,
            });
        }
        if version == 0 {
            let tables: i64 = writer
                .query_row("SELECT count(*) FROM sqlite_master", [], |r| r.get(0))
                .map_err(|e| open_err(e.to_string()))?;
            if tables > 0 {
                return Err(open_err(
                    "an SQLite database of something else (tables, but no shocktwin schema version)"
                        .into(),
                ));
            }
        }
        let store = Self {
            path: path.to_path_buf(),
            reader: Mutex::new(Self::connect(path)?),
            writer: Mutex::new(writer),
        };
        store.migrate(version)?;
        store.with_writer(|c| {
            c.execute(
                "UPDATE runs SET status = 'interrupted', \
                 reason = 'the daemon stopped before the run ended' WHERE status = 'running'",
                [],
            )
        })?;
        Ok(store)
    }

    fn connect(path: &Path) -> Result<Connection, StoreError> {
        let err = |e: rusqlite::Error| StoreError::Open {
            path: path.to_path_buf(),
            reason: e.to_string(),
        };
        let c = Connection::open(path).map_err(err)?;
        c.busy_timeout(Duration::from_secs(5)).map_err(err)?;
        let mode: String = c
            .query_row("PRAGMA journal_mode = WAL", [], |r| r.get(0))
            .map_err(|e| StoreError::Open {
                path: path.to_path_buf(),
                reason: format!("not a readable SQLite database ({e})"),
            })?;
        if !mode.eq_ignore_ascii_case("wal") {
            return Err(StoreError::Open {
                path: path.to_path_buf(),
                reason: format!("cannot use the WAL journal (got `{mode}`)"),
            });
        }
        c.pragma_update(None, "synchronous", "NORMAL")
            .map_err(err)?;
        c.pragma_update(None, "foreign_keys", "ON").map_err(err)?;
        Ok(c)
    }

    fn migrate(&self, from: i64) -> Result<(), StoreError> {
        if from == SCHEMA_VERSION {
            return Ok(());
        }
        self.with_writer(|c| {
            let tx = c.transaction()?;
            for (i, sql) in MIGRATIONS.iter().enumerate().skip(from as usize) {
                tx.execute_batch(sql)?;
                tx.pragma_update(None, "user_version", i as i64 + 1)?;
            }
            tx.commit()
        })
    }

    fn sqlite_err(&self, source: rusqlite::Error) -> StoreError {
        StoreError::Sqlite {
            path: self.path.clone(),
            source,
        }
    }

    fn with_writer<R>(
        &self,
        f: impl FnOnce(&mut Connection) -> rusqlite::Result<R>,
    ) -> Result<R, StoreError> {
        let mut c = self.writer.lock().unwrap_or_else(PoisonError::into_inner);
        f(&mut c).map_err(|e| self.sqlite_err(e))
    }

    fn with_reader<R>(
        &self,
        f: impl FnOnce(&Connection) -> rusqlite::Result<R>,
    ) -> Result<R, StoreError> {
        let c = self.reader.lock().unwrap_or_else(PoisonError::into_inner);
        f(&c).map_err(|e| self.sqlite_err(e))
    }

    /// Applies `op` within `tx`; `now_ms`: the gateway's clock (a run's
    /// `seen_ms`).
    fn apply_one(
        tx: &rusqlite::Transaction<'_>,
        op: &StoreOp,
        now_ms: i64,
    ) -> rusqlite::Result<()> {
        let asset_id = op.asset_id();
        tx.prepare_cached("INSERT OR IGNORE INTO assets (asset_id) VALUES (?1)")?
            .execute([asset_id])?;
        match op {
            StoreOp::RunStarted {
                key,
                run_id,
                source,
                start_ms,
                simulated,
                ..
            } => {
                tx.prepare_cached(&format!(
                    "INSERT OR REPLACE INTO runs \
                     (key, asset, run_id, source, start_ms, status, simulated, seen_ms) \
                     VALUES (?2, {ASSET}, ?3, ?4, ?5, 'running', ?6, ?7)"
                ))?
                .execute(params![
                    asset_id, key, run_id, source, start_ms, simulated, now_ms
                ])?;
            }
            StoreOp::Sample { point: p, .. } => {
                tx.prepare_cached(&format!(
                    "INSERT OR REPLACE INTO samples \
                     (asset, t_ms, pressure_bar, lo_bar, hi_bar, health, excited) \
                     VALUES ({ASSET}, ?2, ?3, ?4, ?5, ?6, ?7)"
                ))?
                .execute(params![
                    asset_id,
                    p.t_ms,
                    p.pressure_bar.and_then(finite),
                    p.pressure_lo_bar.and_then(finite),
                    p.pressure_hi_bar.and_then(finite),
                    health_code(p.health),
                    p.excited
                ])?;
            }
            StoreOp::Health { change: c, .. } => {
                tx.prepare_cached(&format!(
                    "INSERT INTO health_changes (asset, t_ms, run_id, from_health, to_health) \
                     VALUES ({ASSET}, ?2, ?3, ?4, ?5)"
                ))?
                .execute(params![
                    asset_id,
                    c.t_ms,
                    c.run_id,
                    c.from.as_str(),
                    c.to.as_str()
                ])?;
            }
            StoreOp::RunProgress {
                key, end_ms, ticks, ..
            } => {
                tx.prepare_cached(
                    "UPDATE runs SET end_ms = ?2, ticks = ?3, seen_ms = ?4 \
                     WHERE key = ?1 AND status = 'running'",
                )?
                .execute(params![
                    key,
                    end_ms,
                    i64::try_from(*ticks).unwrap_or(i64::MAX),
                    now_ms
                ])?;
            }
            StoreOp::RunEnded {
                key,
                end_ms,
                ticks,
                status,
                reason,
                summary,
                observer,
                road,
                ..
            } => {
                tx.prepare_cached(
                    "UPDATE runs SET end_ms = ?2, ticks = ?3, status = ?4, reason = ?5, \
                     summary_t_ms = ?6, summary_bar = ?7, summary_sd_bar = ?8, observer = ?9, \
                     road = ?10, seen_ms = ?11 WHERE key = ?1",
                )?
                .execute(params![
                    key,
                    end_ms,
                    i64::try_from(*ticks).unwrap_or(i64::MAX),
                    status,
                    reason,
                    summary.map(|s| (s.t_unix_s * 1e3).round() as i64),
                    summary.map(|s| s.pressure_bar),
                    summary.map(|s| s.sd_bar),
                    observer.map(|o| serde_json::to_string(&o).unwrap_or_default()),
                    road.map(|r| serde_json::to_string(&r).unwrap_or_default()),
                    now_ms,
                ])?;
            }
        }
        Ok(())
    }
}

/// A run's observer counters as kept (`None`: no observer, or a value this
/// build cannot read, which the API then leaves out rather than fail).
fn observer_from(json: Option<String>) -> Option<ObserverRead> {
    json.and_then(|j| serde_json::from_str::<ObserverCounters>(&j).ok())
        .map(ObserverRead::from)
}

/// A run's road observer counters as kept (`None`: not a road asset's run,
/// or a value this build cannot read).
fn road_from(json: Option<String>) -> Option<RoadRead> {
    json.and_then(|j| serde_json::from_str::<RoadCounters>(&j).ok())
        .map(RoadRead::from)
}

fn point_from_row(r: &rusqlite::Row<'_>, at: usize) -> rusqlite::Result<HistoryPoint> {
    Ok(HistoryPoint {
        t_ms: r.get(at)?,
        pressure_bar: r.get(at + 1)?,
        pressure_lo_bar: r.get(at + 2)?,
        pressure_hi_bar: r.get(at + 3)?,
        health: health_from_code(r.get(at + 4)?),
        excited: r.get::<_, i64>(at + 5)? != 0,
    })
}

impl FleetStore for SqliteStore {
    fn describe(&self) -> String {
        format!("SQLite {}", self.path.display())
    }

    fn apply(&self, ops: &[StoreOp]) -> Result<(), StoreError> {
        if ops.is_empty() {
            return Ok(());
        }
        let now_ms = super::wall_now_ms();
        self.with_writer(|c| {
            let tx = c.transaction()?;
            for op in ops {
                Self::apply_one(&tx, op, now_ms)?;
            }
            tx.commit()
        })
    }

    fn asset_states(&self) -> Result<Vec<AssetState>, StoreError> {
        self.with_reader(|c| {
            let mut stmt = c.prepare(
                "SELECT a.asset_id, r.run_id, r.status, r.reason, \
                   (SELECT coalesce(sum(ticks), 0) FROM runs WHERE asset = a.id), \
                   s.t_ms, s.pressure_bar, s.lo_bar, s.hi_bar, s.health, s.excited, \
                   r.observer, r.road, r.simulated, a.shown_ms, \
                   (SELECT max(seen_ms) FROM runs WHERE asset = a.id) \
                 FROM (SELECT id, asset_id, \
                         (SELECT max(t_ms) FROM samples WHERE asset = assets.id AND t_ms <= ?1) \
                           AS shown_ms \
                       FROM assets) a \
                 LEFT JOIN runs r ON r.key = \
                   (SELECT key FROM runs WHERE asset = a.id \
                    ORDER BY coalesce(end_ms, start_ms) > ?1, \
                      coalesce(end_ms, start_ms) DESC, rowid DESC LIMIT 1) \
                 LEFT JOIN samples s ON s.asset = a.id AND s.t_ms = coalesce(a.shown_ms, \
                   (SELECT max(t_ms) FROM samples WHERE asset = a.id)) \
                 ORDER BY a.asset_id",
            )?;
            // What lies ahead of this gateway's clock is shown only when the
            // asset has nothing else, and never orders what an upload must
            // not be older than (`shown_ms`).
            let future_ms = super::wall_now_ms().saturating_add(super::FUTURE_SLACK_MS);
            let rows = stmt.query_map([future_ms], |r| {
                let t_ms: Option<i64> = r.get(5)?;
                Ok(AssetState {
                    asset_id: r.get(0)?,
                    run_id: r.get::<_, Option<String>>(1)?.unwrap_or_default(),
                    last_run_status: r
                        .get::<_, Option<String>>(2)?
                        .unwrap_or_else(|| "unknown".into()),
                    last_run_reason: r.get(3)?,
                    last_run_observer: observer_from(r.get(11)?),
                    last_run_road: road_from(r.get(12)?),
                    simulated: r.get(13)?,
                    ticks: r.get::<_, i64>(4)?.max(0) as u64,
                    shown_ms: r.get(14)?,
                    seen_ms: r.get(15)?,
                    last: if t_ms.is_some() {
                        Some(point_from_row(r, 5)?)
                    } else {
                        None
                    },
                })
            })?;
            rows.collect()
        })
    }

    fn history(
        &self,
        asset_id: &str,
        (since_ms, until_ms): (i64, i64),
        step_ms: i64,
        max_points: usize,
    ) -> Result<Option<Vec<HistoryPoint>>, StoreError> {
        let limit = i64::try_from(max_points).unwrap_or(i64::MAX - 1) + 1;
        let points = self.with_reader(|c| {
            let known = c
                .prepare_cached("SELECT id FROM assets WHERE asset_id = ?1")?
                .query_row([asset_id], |r| r.get::<_, i64>(0))
                .optional()?;
            let Some(id) = known else { return Ok(None) };
            let points = if step_ms <= 1000 {
                let mut stmt = c.prepare_cached(
                    "SELECT t_ms, pressure_bar, lo_bar, hi_bar, health, excited FROM samples \
                     WHERE asset = ?1 AND t_ms BETWEEN ?2 AND ?3 ORDER BY t_ms LIMIT ?4",
                )?;
                let rows = stmt.query_map(params![id, since_ms, until_ms, limit], |r| {
                    point_from_row(r, 0)
                })?;
                rows.collect::<rusqlite::Result<Vec<_>>>()?
            } else {
                let mut stmt = c.prepare_cached(
                    "SELECT (t_ms / ?4) * ?4 AS b, avg(pressure_bar), avg(lo_bar), avg(hi_bar), \
                       max(health), max(excited) FROM samples \
                     WHERE asset = ?1 AND t_ms BETWEEN ?2 AND ?3 GROUP BY b ORDER BY b LIMIT ?5",
                )?;
                let rows = stmt
                    .query_map(params![id, since_ms, until_ms, step_ms, limit], |r| {
                        point_from_row(r, 0)
                    })?;
                rows.collect::<rusqlite::Result<Vec<_>>>()?
            };
            Ok(Some(points))
        })?;
        if points.as_ref().is_some_and(|p| p.len() > max_points) {
            return Err(StoreError::Request(format!(
                "more than {max_points} points: raise step_s or narrow since/until"
            )));
        }
        Ok(points)
    }

    fn newest_ms(&self, asset_id: &str) -> Result<Option<i64>, StoreError> {
        self.with_reader(|c| {
            c.prepare_cached(&format!(
                "SELECT max(t_ms) FROM samples WHERE asset = {ASSET}"
            ))?
            .query_row([asset_id], |r| r.get(0))
        })
    }

    fn runs(&self, asset_id: &str, limit: usize) -> Result<Vec<RunRecord>, StoreError> {
        self.with_reader(|c| {
            let mut stmt = c.prepare_cached(&format!(
                "SELECT run_id, source, start_ms, end_ms, ticks, status, reason, \
                   summary_t_ms, summary_bar, summary_sd_bar, observer, road, simulated \
                 FROM runs WHERE asset = {ASSET} ORDER BY start_ms DESC LIMIT ?2"
            ))?;
            let limit = i64::try_from(limit).unwrap_or(i64::MAX);
            let rows = stmt.query_map(params![asset_id, limit], |r| {
                let summary = match (
                    r.get::<_, Option<i64>>(7)?,
                    r.get::<_, Option<f64>>(8)?,
                    r.get::<_, Option<f64>>(9)?,
                ) {
                    (Some(t_ms), Some(pressure_bar), Some(sd_bar)) => Some(RunPoint {
                        t_unix_s: t_ms as f64 / 1e3,
                        pressure_bar,
                        sd_bar,
                    }),
                    _ => None,
                };
                Ok(RunRecord {
                    run_id: r.get(0)?,
                    source: r.get(1)?,
                    start_ms: r.get(2)?,
                    end_ms: r.get(3)?,
                    ticks: r.get::<_, i64>(4)?.max(0) as u64,
                    status: r.get(5)?,
                    reason: r.get(6)?,
                    summary,
                    observer: observer_from(r.get(10)?),
                    road: road_from(r.get(11)?),
                    simulated: r.get(12)?,
                })
            })?;
            rows.collect()
        })
    }

    fn health_changes(
        &self,
        asset_id: &str,
        limit: usize,
    ) -> Result<Vec<HealthChange>, StoreError> {
        self.with_reader(|c| {
            let mut stmt = c.prepare_cached(&format!(
                "SELECT t_ms, run_id, from_health, to_health FROM health_changes \
                 WHERE asset = {ASSET} ORDER BY t_ms DESC LIMIT ?2"
            ))?;
            let limit = i64::try_from(limit).unwrap_or(i64::MAX);
            let rows = stmt.query_map(params![asset_id, limit], |r| {
                Ok(HealthChange {
                    t_ms: r.get(0)?,
                    run_id: r.get(1)?,
                    from: health_from_str(&r.get::<_, String>(2)?),
                    to: health_from_str(&r.get::<_, String>(3)?),
                })
            })?;
            rows.collect()
        })
    }

    fn set_baseline(
        &self,
        asset_id: &str,
        baseline: Option<&StoredBaseline>,
    ) -> Result<(), StoreError> {
        self.with_writer(|c| {
            let tx = c.transaction()?;
            match baseline {
                Some(b) => put_baseline(&tx, asset_id, b)?,
                None => forget_baseline(&tx, asset_id)?,
            }
            tx.commit()
        })
    }

    fn baselines(&self) -> Result<Vec<(String, StoredBaseline)>, StoreError> {
        self.with_reader(|c| {
            let mut stmt = c.prepare(
                "SELECT a.asset_id, b.charge_bar, b.read_bar, b.read_sd_bar, b.set_ms, \
                 b.accel_lo_mps2, b.accel_hi_mps2, b.damping_law, b.second, b.runs_averaged, \
                 b.split_bar, b.other_excitations \
                 FROM baselines b JOIN assets a ON a.id = b.asset",
            )?;
            let mut all = stmt
                .query_map([], |r| {
                    Ok((
                        r.get(0)?,
                        StoredBaseline {
                            baseline: AssetBaseline::Observer(UnitBaseline {
                                charge_bar: r.get(1)?,
                                read_bar: r.get(2)?,
                                read_sd_bar: r.get(3)?,
                                accel_range_mps2: match (r.get(5)?, r.get(6)?) {
                                    (Some(lo), Some(hi)) => Some([lo, hi]),
                                    _ => None,
                                },
                                damping_law: json_column(r, 7, "damping_law")?,
                                second: json_column(r, 8, "second")?,
                                runs_averaged: r.get(9)?,
                                split_bar: r.get(10)?,
                                other_excitations: other_excitations_from(
                                    json_column(r, 11, "other_excitations")?.unwrap_or_default(),
                                )
                                .map_err(|e| {
                                    rusqlite::Error::FromSqlConversionFailure(
                                        11,
                                        rusqlite::types::Type::Text,
                                        format!("baselines.{e}").into(),
                                    )
                                })?,
                            }),
                            set_ms: r.get(4)?,
                        },
                    ))
                })?
                .collect::<rusqlite::Result<Vec<(String, StoredBaseline)>>>()?;
            let mut stmt = c.prepare(
                "SELECT a.asset_id, b.charge_bar, b.offset_n, b.blocks, b.set_ms \
                 FROM road_baselines b JOIN assets a ON a.id = b.asset",
            )?;
            for row in stmt.query_map([], |r| {
                Ok((
                    r.get(0)?,
                    StoredBaseline {
                        baseline: AssetBaseline::Road(RoadBaseline {
                            charge_bar: r.get(1)?,
                            offset_n: r.get(2)?,
                            blocks: u64::try_from(r.get::<_, i64>(3)?).unwrap_or(0),
                        }),
                        set_ms: r.get(4)?,
                    },
                ))
            })? {
                all.push(row?);
            }
            all.sort_by(|a, b| a.0.cmp(&b.0));
            Ok(all)
        })
    }

    fn set_service(
        &self,
        asset_id: &str,
        service: Option<&PendingService>,
    ) -> Result<(), StoreError> {
        self.with_writer(|c| {
            let tx = c.transaction()?;
            match service {
                Some(s) => {
                    know_asset(&tx, asset_id)?;
                    tx.execute(
                        &format!(
                            "INSERT OR REPLACE INTO services (asset, charge_bar, set_ms, refusal) \
                             VALUES ({ASSET}, ?2, ?3, ?4)"
                        ),
                        params![asset_id, s.charge_bar, s.set_ms, s.refusal],
                    )?;
                }
                None => forget(&tx, "services", asset_id)?,
            }
            tx.commit()
        })
    }

    fn services(&self) -> Result<Vec<(String, PendingService)>, StoreError> {
        self.with_reader(|c| {
            let mut stmt = c.prepare(
                "SELECT a.asset_id, s.charge_bar, s.set_ms, s.refusal \
                 FROM services s JOIN assets a ON a.id = s.asset ORDER BY a.asset_id",
            )?;
            let rows = stmt.query_map([], |r| {
                Ok((
                    r.get(0)?,
                    PendingService {
                        charge_bar: r.get(1)?,
                        set_ms: r.get(2)?,
                        refusal: r.get(3)?,
                    },
                ))
            })?;
            rows.collect()
        })
    }

    fn complete_service(&self, asset_id: &str, b: &StoredBaseline) -> Result<(), StoreError> {
        self.with_writer(|c| {
            let tx = c.transaction()?;
            put_baseline(&tx, asset_id, b)?;
            forget(&tx, "services", asset_id)?;
            tx.commit()
        })
    }

    fn prune(&self, before_ms: i64) -> Result<usize, StoreError> {
        self.with_writer(|c| {
            let tx = c.transaction()?;
            let n = tx.execute("DELETE FROM samples WHERE t_ms < ?1", [before_ms])?
                + tx.execute("DELETE FROM health_changes WHERE t_ms < ?1", [before_ms])?;
            tx.commit()?;
            Ok(n)
        })
    }
}

#[cfg(test)]
mod tests {
    use dt_core::charge::{BaselineReading, DampingLaw, ExcitationBaseline};
    use dt_core::estimate::Health;

    use super::*;

    fn sample(t_ms: i64, p: f64) -> StoreOp {
        StoreOp::Sample {
            asset_id: "a1".into(),
            point: HistoryPoint {
                t_ms,
                pressure_bar: Some(p),
                pressure_lo_bar: Some(p - 1.0),
                pressure_hi_bar: None,
                health: if p < 5.0 { Health::Leak } else { Health::Ok },
                excited: true,
            },
        }
    }

    #[test]
    fn a_road_runs_block_counts_come_back_with_why_none_was_read() {
        let dir = tempfile::tempdir().unwrap();
        let store = SqliteStore::open(&dir.path().join("fleet.sqlite")).unwrap();
        let run = |key: &str, start_ms: i64, road: RoadCounters| {
            [
                StoreOp::RunStarted {
                    key: key.into(),
                    asset_id: "car-1".into(),
                    run_id: key.into(),
                    source: "test".into(),
                    start_ms,
                    simulated: None,
                },
                StoreOp::RunEnded {
                    key: key.into(),
                    asset_id: "car-1".into(),
                    end_ms: start_ms + 60_000,
                    ticks: 3000,
                    status: "completed".into(),
                    reason: None,
                    summary: None,
                    observer: None,
                    road: Some(road),
                },
            ]
        };
        let driven = RoadCounters {
            read: 40,
            settling: 2,
            ..RoadCounters::default()
        };
        let parked = RoadCounters {
            at_rest: 5,
            settling: 1,
            ..RoadCounters::default()
        };
        store.apply(&run("drive", 0, driven)).unwrap();
        store.apply(&run("parked", 100_000, parked)).unwrap();
        let runs = store.runs("car-1", 10).unwrap();
        let got: Vec<_> = runs.iter().map(|r| r.road.clone().unwrap()).collect();
        assert_eq!(got[1].counts, driven);
        assert_eq!(got[1].why_none, None);
        assert_eq!(got[0].counts, parked);
        let why = got[0].why_none.as_deref().unwrap();
        assert!(
            why.contains("none of 6 blocks") && why.contains("at rest"),
            "{why}"
        );
        // The asset's latest run is the parked one.
        assert_eq!(
            store.asset_states().unwrap()[0].last_run_road,
            Some(got[0].clone())
        );
    }

    /// An asset's last update after a restart is when the gateway last wrote
    /// one of its runs, on its own clock, as while it runs (the data's clock
    /// before: a 2023 upload read "1107 d ago"; a helper's trial); a store
    /// from before the column says nothing.
    #[test]
    fn the_last_update_is_kept_on_the_gateways_clock() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("fleet.sqlite");
        let started = |key: &str| StoreOp::RunStarted {
            key: key.into(),
            asset_id: "van-07".into(),
            run_id: key.into(),
            source: "test".into(),
            start_ms: 1_700_000_000_000, // 2023: the data's clock
            simulated: Some(true),
        };
        {
            let store = SqliteStore::open(&path).unwrap();
            let before = super::super::wall_now_ms();
            store.apply(&[started("d001")]).unwrap();
            let seen = store.asset_states().unwrap()[0].seen_ms.unwrap();
            assert!(
                (before..=super::super::wall_now_ms()).contains(&seen),
                "{seen}"
            );
        }
        // a run of schema 13 has none
        let c = Connection::open(&path).unwrap();
        c.execute("UPDATE runs SET seen_ms = NULL", []).unwrap();
        drop(c);
        let store = SqliteStore::open(&path).unwrap();
        assert_eq!(store.asset_states().unwrap()[0].seen_ms, None);
    }

    /// The live view shows as an asset's last run the one whose estimates
    /// reach furthest (a re-sent, truncated copy of a run is a backlog); at
    /// a restart the store chose the latest start, where the copy ties, and
    /// the asset turned from `completed` to `failed` (a helper's trial).
    #[test]
    fn the_last_run_is_the_one_that_reaches_furthest_as_the_live_view_has_it() {
        let dir = tempfile::tempdir().unwrap();
        let store = SqliteStore::open(&dir.path().join("fleet.sqlite")).unwrap();
        let run = |key: &str, end_ms: i64, status: &str| {
            [
                StoreOp::RunStarted {
                    key: key.into(),
                    asset_id: "van-ok".into(),
                    run_id: "d005".into(),
                    source: "test".into(),
                    start_ms: 1_000,
                    simulated: None,
                },
                StoreOp::RunEnded {
                    key: key.into(),
                    asset_id: "van-ok".into(),
                    end_ms,
                    ticks: 100,
                    status: status.into(),
                    reason: None,
                    summary: None,
                    observer: None,
                    road: None,
                },
            ]
        };
        store.apply(&run("whole", 71_000, "completed")).unwrap();
        store.apply(&run("cut", 30_000, "failed")).unwrap();
        assert_eq!(
            store.asset_states().unwrap()[0].last_run_status,
            "completed"
        );
        // a later run of the asset is its last, whatever its status
        store.apply(&run("next", 90_000, "failed")).unwrap();
        assert_eq!(store.asset_states().unwrap()[0].last_run_status, "failed");
    }

    #[test]
    fn writes_read_back_and_average_over_steps() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("sub/fleet.sqlite");
        let store = SqliteStore::open(&path).unwrap();
        let mut ops = vec![StoreOp::RunStarted {
            key: "k1".into(),
            asset_id: "a1".into(),
            run_id: "r1".into(),
            source: "test".into(),
            start_ms: 0,
            simulated: Some(true),
        }];
        ops.extend((0..10).map(|i| sample(i * 1000, 12.0 - f64::from(i as i32))));
        ops.push(StoreOp::RunEnded {
            key: "k1".into(),
            asset_id: "a1".into(),
            end_ms: 9000,
            ticks: 500,
            status: "completed".into(),
            reason: None,
            summary: Some(RunPoint {
                t_unix_s: 5.0,
                pressure_bar: 7.5,
                sd_bar: 0.5,
            }),
            observer: Some(ObserverCounters {
                detected: 40,
                uncalibrated: 38,
                skipped: 2,
                ..ObserverCounters::default()
            }),
            road: None,
        });
        store.apply(&ops).unwrap();
        let h = store.history("a1", (0, 9000), 1000, 100).unwrap().unwrap();
        assert_eq!(h.len(), 10);
        assert_eq!(h[3].pressure_bar, Some(9.0));
        assert_eq!(h[3].pressure_hi_bar, None);
        // 5 s steps: means of 12..8 and 7..3; the worst health of the bin.
        let h5 = store.history("a1", (0, 9000), 5000, 100).unwrap().unwrap();
        assert_eq!(h5.len(), 2);
        assert!((h5[0].pressure_bar.unwrap() - 10.0).abs() < 1e-12);
        assert_eq!(h5[1].health, Health::Leak);
        assert!(store
            .history("nobody", (0, 1), 1000, 100)
            .unwrap()
            .is_none());
        let runs = store.runs("a1", 10).unwrap();
        assert_eq!(runs.len(), 1);
        assert_eq!(runs[0].ticks, 500);
        assert!((runs[0].summary.unwrap().pressure_bar - 7.5).abs() < 1e-12);
        // The observer's counts come back, with the verdict they imply.
        let o = runs[0].observer.unwrap();
        assert_eq!((o.counts.detected, o.counts.uncalibrated), (40, 38));
        assert!(o.not_calibrated_here);
        assert_eq!(store.asset_states().unwrap()[0].last_run_observer, Some(o));
        assert_eq!(runs[0].road, None);
        // Whether the log said it is simulated comes back per run and for
        // the asset's latest run.
        assert_eq!(runs[0].simulated, Some(true));
        assert_eq!(store.asset_states().unwrap()[0].simulated, Some(true));
        assert_eq!(store.newest_ms("a1").unwrap(), Some(9000));
        assert_eq!(store.prune(5000).unwrap(), 5);
        drop(store);
        // Reopened: the same data, nothing migrated twice.
        let again = SqliteStore::open(&path).unwrap();
        assert_eq!(again.asset_states().unwrap()[0].ticks, 500);
    }

    #[test]
    fn a_version_1_file_is_migrated_and_keeps_baselines_across_reopens() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("fleet.sqlite");
        {
            // A store as the first schema left it, with one run.
            let c = Connection::open(&path).unwrap();
            c.execute_batch(MIGRATIONS[0]).unwrap();
            c.pragma_update(None, "user_version", 1).unwrap();
            c.execute_batch(
                "INSERT INTO assets (asset_id) VALUES ('a1'); \
                 INSERT INTO runs (key, asset, run_id, source, start_ms, status, ticks) \
                 VALUES ('k', 1, 'r', 's', 0, 'completed', 7);",
            )
            .unwrap();
        }
        let store = SqliteStore::open(&path).unwrap();
        assert_eq!(store.runs("a1", 5).unwrap()[0].ticks, 7);
        // A run from before the column: its log's word is unknown.
        assert_eq!(store.runs("a1", 5).unwrap()[0].simulated, None);
        assert!(store.baselines().unwrap().is_empty());
        let b = StoredBaseline {
            baseline: AssetBaseline::Observer(UnitBaseline {
                charge_bar: 12.0,
                read_bar: 10.84,
                read_sd_bar: 0.7,
                accel_range_mps2: Some([1.45, 1.61]),
                damping_law: None,
                second: None,
                runs_averaged: 1.0,
                split_bar: None,
                other_excitations: Default::default(),
            }),
            set_ms: 1_700_000_000_000,
        };
        // A unit read with its own damping law keeps it, to the bit.
        let mut law = DampingLaw {
            knots_mps: [-0.15, -0.09, -0.05, -0.025, 0.025, 0.05, 0.09, 0.15],
            width_mps: 0.008,
            beta_per_k: 0.030_255_147_720_118_9,
            ..DampingLaw::default()
        };
        law.viscous_nspm[0] = 2_512.123_456_789;
        law.dry_nspm[3] = -1.0e-7 / 3.0;
        let own = StoredBaseline {
            baseline: AssetBaseline::Observer(UnitBaseline {
                charge_bar: 12.0,
                read_bar: 11.33,
                read_sd_bar: 0.09,
                accel_range_mps2: Some([5.8, 6.4]),
                damping_law: Some(law),
                // and a second reading at another charge, to the bit
                second: Some(BaselineReading {
                    charge_bar: 4.0,
                    read_bar: 3.1 / 0.7,
                    read_sd_bar: 0.123_456_789,
                    runs_averaged: 7.0 / 3.0,
                }),
                // and the runs each reading averages
                runs_averaged: 2.0 / 0.7,
                // and the stroke's ends apart at the reading
                split_bar: Some(-1.0 / 3.0),
                // and a reading at another excitation, to the bit
                other_excitations: [
                    Some(ExcitationBaseline {
                        accel_range_mps2: [1.4, 1.6],
                        charge_bar: 12.0,
                        read_bar: 10.1 / 0.9,
                        read_sd_bar: 0.2 / 3.0,
                        runs_averaged: 1.0,
                        second: None,
                        split_bar: Some(0.1 / 0.7),
                    }),
                    None,
                    None,
                ],
            }),
            ..b
        };
        // An asset the store has never seen a run of can be given one too.
        store.set_baseline("new-van", Some(&b)).unwrap();
        store.set_baseline("own-law", Some(&own)).unwrap();
        store.set_baseline("a1", Some(&b)).unwrap();
        store.set_baseline("a1", None).unwrap();
        drop(store);
        let again = SqliteStore::open(&path).unwrap();
        let mut kept = again.baselines().unwrap();
        kept.sort_by(|x, y| x.0.cmp(&y.0));
        assert_eq!(
            kept,
            vec![("new-van".to_owned(), b), ("own-law".to_owned(), own)]
        );
        let version: i64 = Connection::open(&path)
            .unwrap()
            .query_row("PRAGMA user_version", [], |r| r.get(0))
            .unwrap();
        assert_eq!(version, SCHEMA_VERSION);
    }

    #[test]
    fn a_pending_service_survives_a_reopen_and_completes_into_a_baseline() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("fleet.sqlite");
        let store = SqliteStore::open(&path).unwrap();
        let svc = PendingService {
            charge_bar: 12.0,
            set_ms: 1_700_000_000_000,
            refusal: Some("run `r1`: no excited tick".into()),
        };
        store.set_service("van-1", Some(&svc)).unwrap();
        store.set_service("van-2", Some(&svc)).unwrap();
        store.set_service("van-2", None).unwrap();
        drop(store);
        let store = SqliteStore::open(&path).unwrap();
        assert_eq!(
            store.services().unwrap(),
            vec![("van-1".to_owned(), svc.clone())]
        );
        let b = StoredBaseline {
            baseline: AssetBaseline::Observer(UnitBaseline {
                charge_bar: 12.0,
                read_bar: 10.6,
                read_sd_bar: 0.4,
                accel_range_mps2: None,
                damping_law: None,
                second: None,
                runs_averaged: 1.0,
                split_bar: None,
                other_excitations: Default::default(),
            }),
            set_ms: 1_700_000_000_000,
        };
        store.complete_service("van-1", &b).unwrap();
        drop(store);
        let again = SqliteStore::open(&path).unwrap();
        assert!(again.services().unwrap().is_empty());
        assert_eq!(again.baselines().unwrap(), vec![("van-1".to_owned(), b)]);
        // A road asset's service completes into a road baseline, which
        // replaces the observer's: one baseline an asset.
        let road = StoredBaseline {
            baseline: AssetBaseline::Road(RoadBaseline {
                charge_bar: 11.5,
                offset_n: -3.25,
                blocks: 41,
            }),
            set_ms: 1_700_000_100_000,
        };
        again.set_service("van-1", Some(&svc)).unwrap();
        again.complete_service("van-1", &road).unwrap();
        again.complete_service("car-2", &road).unwrap();
        drop(again);
        let again = SqliteStore::open(&path).unwrap();
        assert_eq!(
            again.baselines().unwrap(),
            vec![("car-2".to_owned(), road), ("van-1".to_owned(), road)]
        );
        again.set_baseline("car-2", None).unwrap();
        again.set_baseline("van-1", Some(&b)).unwrap();
        assert_eq!(again.baselines().unwrap(), vec![("van-1".to_owned(), b)]);
    }

    #[test]
    fn a_run_left_running_is_interrupted_on_reopen() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("fleet.sqlite");
        SqliteStore::open(&path)
            .unwrap()
            .apply(&[StoreOp::RunStarted {
                key: "k".into(),
                asset_id: "a1".into(),
                run_id: "r".into(),
                source: "s".into(),
                start_ms: 1,
                simulated: Some(false),
            }])
            .unwrap();
        let runs = SqliteStore::open(&path).unwrap().runs("a1", 5).unwrap();
        assert_eq!(runs[0].status, "interrupted");
        assert_eq!(runs[0].simulated, Some(false));
    }

    #[test]
    fn foreign_newer_and_broken_files_are_refused_by_name() {
        let dir = tempfile::tempdir().unwrap();
        let newer = dir.path().join("newer.sqlite");
        drop(SqliteStore::open(&newer).unwrap());
        Connection::open(&newer)
            .unwrap()
            .pragma_update(None, "user_version", 99)
            .unwrap();
        let e = SqliteStore::open(&newer).unwrap_err().to_string();
        assert!(e.contains("newer.sqlite") && e.contains("99"), "{e}");

        let foreign = dir.path().join("foreign.sqlite");
        Connection::open(&foreign)
            .unwrap()
            .execute_batch("CREATE TABLE t (x)")
            .unwrap();
        let e = SqliteStore::open(&foreign).unwrap_err().to_string();
        assert!(
            e.contains("foreign.sqlite") && e.contains("something else"),
            "{e}"
        );

        let garbage = dir.path().join("garbage.sqlite");
        std::fs::write(&garbage, vec![0x5a_u8; 8192]).unwrap();
        let e = SqliteStore::open(&garbage).unwrap_err().to_string();
        assert!(
            e.contains("garbage.sqlite") && e.contains("not a readable"),
            "{e}"
        );
    }
}
