//! The inbox: a watched directory of MCAP files, each processed once as one
//! run, then moved to `done/` or to `failed/` (beside it,
//! `<name>.reason.txt` says why).
//!
//! Nothing is lost across a restart: a file is moved only after its estimates
//! are flushed by every sink, so a file still in the inbox at start (a crash,
//! a shutdown mid-file) is simply processed again; the recorder's file names
//! are deterministic, so that rewrites the same recordings. Nothing is done
//! twice either: a file whose run the fleet store already holds as completed
//! from this inbox name (the daemon stopped between the store's commit and
//! the move) is moved to `done/` without being processed again. A file
//! renamed over the one being read is not moved unread in its place: the move
//! checks that the path still holds the file read (device and inode), and
//! leaves a new one for the next pass.
//!
//! Only `*.mcap` files not starting with `.` are taken: write a file under
//! another name (e.g. `run.mcap.part`) and rename it when complete (any other
//! name than `*.part`, `*.tmp` or a hidden one is logged once as not taken,
//! as is a sub-directory); a file
//! renamed into the inbox is taken at once (the file-system event of the
//! rename says it is complete). A file written in place (a plain `scp`, an
//! upload that stalls) is taken only once it has settled: unchanged in size
//! and modification time for `inbox_settle_s` seconds (default 10), so that a
//! copy in progress is not processed half-written and lost to `failed/`; so is
//! a renamed file whose event was missed. The directory is rescanned on every
//! file-system event (`notify`) and every `inbox_rescan_s` seconds, in case an
//! event is missed. The source counts as started (`/readyz`) once the
//! directory is watched, or once it falls back to rescanning.

use std::collections::{HashMap, HashSet};
use std::ffi::OsString;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex, PoisonError};
use std::time::{Duration, Instant, SystemTime};

use futures_util::future::BoxFuture;
use tokio::sync::Notify;

use super::ingest::RunReport;
use super::sink::SourceKind;
use super::source::{Source, SourceContext};
use super::ServeError;

/// Sub-directory of processed files.
pub const DONE_DIR: &str = "done";
/// Sub-directory of files that could not be processed completely.
pub const FAILED_DIR: &str = "failed";

/// The inbox source.
#[derive(Debug)]
pub struct InboxSource {
    dir: PathBuf,
    rescan: Duration,
    settle: Duration,
}

impl InboxSource {
    /// Watches `dir` (created with `done/` and `failed/` if missing); takes
    /// a file once it has not changed for `settle`.
    pub fn new(dir: &Path, rescan: Duration, settle: Duration) -> Result<Self, ServeError> {
        // (a missing inbox is said where the daemon first makes it: its lock, `lock::hold`)
        for d in [dir.to_owned(), dir.join(DONE_DIR), dir.join(FAILED_DIR)] {
            std::fs::create_dir_all(&d).map_err(|source| ServeError::Io {
                path: d,
                error: source,
            })?;
        }
        Ok(Self {
            dir: dir.to_owned(),
            rescan,
            settle,
        })
    }
}

impl Source for InboxSource {
    fn name(&self) -> String {
        format!("inbox {}", self.dir.display())
    }

    fn says_started(&self) -> bool {
        true
    }

    fn run(self: Box<Self>, ctx: SourceContext) -> BoxFuture<'static, Result<(), ServeError>> {
        Box::pin(watch_loop(*self, ctx))
    }
}

/// What a listing of the inbox found.
#[derive(Debug, Default)]
struct Listing {
    /// `*.mcap` files, by name: the runs to take.
    files: Vec<PathBuf>,
    /// Names the inbox does not take and does not expect (neither `*.mcap`,
    /// nor hidden, nor a file being written under `*.part` or `*.tmp`, nor
    /// `done/` or `failed/`): said once each, so that a `run.MCAP.gz` or a
    /// sub-directory of runs dropped there is not waited on in silence.
    strangers: Vec<OsString>,
}

/// Lists `dir`.
fn pending_files(dir: &Path) -> std::io::Result<Listing> {
    let mut out = Listing::default();
    for entry in std::fs::read_dir(dir)? {
        let entry = entry?;
        let os_name = entry.file_name();
        let name = os_name.to_string_lossy();
        let ext = Path::new(name.as_ref())
            .extension()
            .map(|e| e.to_string_lossy().to_ascii_lowercase());
        if name.starts_with('.') {
            continue;
        }
        let is_file = entry.file_type()?.is_file();
        match ext.as_deref() {
            Some("mcap") if is_file => out.files.push(entry.path()),
            Some("part" | "tmp") if is_file => {}
            _ if !is_file && (name == DONE_DIR || name == FAILED_DIR) => {}
            _ => out.strangers.push(os_name),
        }
    }
    out.files.sort();
    Ok(out)
}

/// Says once for each name of `strangers` (until it leaves the inbox) that
/// it is not taken. `said` keeps the names said and still there.
fn say_strangers(dir: &Path, strangers: Vec<OsString>, said: &mut HashSet<OsString>) {
    let present: HashSet<&OsString> = strangers.iter().collect();
    said.retain(|n| present.contains(n));
    for name in strangers {
        if said.len() >= MAX_RENAMED || said.contains(&name) {
            continue;
        }
        let path = dir.join(&name);
        if path.is_dir() {
            tracing::warn!(
                path = %path.display(),
                "not taken: the inbox reads the *.mcap files at its top level, not sub-directories"
            );
        } else if Path::new(&name).extension().is_some_and(|e| {
            ["csv", "tsv", "txt"]
                .iter()
                .any(|t| e.eq_ignore_ascii_case(t))
        }) {
            tracing::warn!(
                path = %path.display(),
                "not taken: the inbox reads *.mcap files only; a dyno or logger's table \
                 becomes one with `shocktwin import` (see its --help)"
            );
        } else {
            tracing::warn!(
                path = %path.display(),
                "not taken: the inbox reads *.mcap files only (write under *.part or *.tmp \
                 and rename to *.mcap when complete)"
            );
        }
        said.insert(name);
    }
}

async fn watch_loop(src: InboxSource, ctx: SourceContext) -> Result<(), ServeError> {
    // A file-system event only wakes the loop; `Notify` keeps at most one
    // wake-up, so the watcher's thread can never queue without bound.
    let wake = Arc::new(Notify::new());
    let waker = Arc::clone(&wake);
    // Names of the files renamed into the inbox (complete by the convention
    // above), until the loop takes them; bounded, beyond it a file settles as
    // any other. By name: the watcher may report the directory's path in
    // another form (absolute) than the one it was given.
    let renamed: Arc<Mutex<HashSet<OsString>>> = Arc::default();
    let renamed_in = Arc::clone(&renamed);
    let watcher = notify::recommended_watcher(move |event: notify::Result<notify::Event>| {
        // Listing the directory opens it, which inotify reports as an access:
        // waking on those made the loop rescan forever (a core busy while idle).
        if let Ok(e) = &event {
            if e.kind.is_access() {
                return;
            }
            if let Some(name) = rename_target(e).and_then(Path::file_name) {
                let mut set = renamed_in.lock().unwrap_or_else(PoisonError::into_inner);
                if set.len() < MAX_RENAMED {
                    set.insert(name.to_owned());
                }
            }
        }
        waker.notify_one();
    })
    .and_then(|mut w| {
        notify::Watcher::watch(&mut w, &src.dir, notify::RecursiveMode::NonRecursive)?;
        Ok(w)
    });
    let _watcher = match watcher {
        Ok(w) => Some(w),
        Err(e) => {
            tracing::warn!(
                dir = %src.dir.display(),
                "no file-system events ({e}); rescanning every {:?}",
                src.rescan
            );
            None
        }
    };
    // Watched: a file renamed in from now on is seen at once (without
    // events, at the next rescan, where it settles first).
    ctx.started.signal();
    // Files that could not be moved are not retried until restart.
    let mut stuck: HashSet<PathBuf> = HashSet::new();
    // Files still changing: (size, modification time) when first seen so, and when.
    let mut unsettled: HashMap<PathBuf, ((u64, Option<SystemTime>), Instant)> = HashMap::new();
    // Names not taken that were said so (`say_strangers`).
    let mut strangers_said: HashSet<OsString> = HashSet::new();
    loop {
        // The names renamed in *before* the listing: only those can be judged
        // by it (a rename reported between the listing and now is kept for
        // the next pass, which its event wakes).
        let reported = renamed
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .clone();
        let files = match pending_files(&src.dir) {
            Ok(listing) => {
                say_strangers(&src.dir, listing.strangers, &mut strangers_said);
                listing.files
            }
            Err(e) => {
                ctx.ingest.metrics().error("inbox");
                tracing::error!(dir = %src.dir.display(), "cannot list the inbox: {e}");
                Vec::new()
            }
        };
        let complete = {
            let present: HashSet<&std::ffi::OsStr> =
                files.iter().filter_map(|p| p.file_name()).collect();
            forget_gone(
                &mut renamed.lock().unwrap_or_else(PoisonError::into_inner),
                &reported,
                &present,
            );
            reported
        };
        for path in files {
            if ctx.cancel.is_cancelled() {
                return Ok(());
            }
            let name = path.file_name().unwrap_or_default();
            if stuck.contains(&path)
                || !(complete.contains(name) || settled(&path, src.settle, &mut unsettled))
            {
                continue;
            }
            unsettled.remove(&path);
            renamed
                .lock()
                .unwrap_or_else(PoisonError::into_inner)
                .remove(name);
            if !process_file(&ctx, &src.dir, &path).await {
                stuck.insert(path);
            }
        }
        // A file waiting to settle is looked at again when it may have.
        let next = if unsettled.is_empty() {
            src.rescan
        } else {
            src.rescan
                .min(src.settle / 2)
                .max(Duration::from_millis(50))
        };
        tokio::select! {
            () = ctx.cancel.cancelled() => return Ok(()),
            () = wake.notified() => {}
            () = tokio::time::sleep(next) => {}
        }
    }
}

/// Forgets the names of `renamed` that were `reported` before a listing and
/// are not `present` in it (renamed in, then away). A name reported after the
/// listing is kept whatever the listing says: its file may have arrived just
/// after it (forgetting it made a renamed file wait to settle).
fn forget_gone(
    renamed: &mut HashSet<OsString>,
    reported: &HashSet<OsString>,
    present: &HashSet<&std::ffi::OsStr>,
) {
    renamed.retain(|n| present.contains(n.as_os_str()) || !reported.contains(n));
}

/// Paths renamed into the inbox remembered at most (a directory flooded with
/// renames falls back to the settle rule).
const MAX_RENAMED: usize = 4096;

/// The destination of a rename the event reports (`mv` within the file
/// system, the documented way to drop a complete file), if it is one.
fn rename_target(event: &notify::Event) -> Option<&Path> {
    use notify::event::{EventKind, ModifyKind, RenameMode};
    match event.kind {
        EventKind::Modify(ModifyKind::Name(RenameMode::To)) => event.paths.first(),
        EventKind::Modify(ModifyKind::Name(RenameMode::Both)) => event.paths.get(1),
        _ => None,
    }
    .map(PathBuf::as_path)
}

/// Whether `path` has settled: last modified at least `settle` ago, or
/// unchanged in size and modification time for `settle` (a clock that puts
/// its modification time in the future cannot hold it back for ever).
fn settled(
    path: &Path,
    settle: Duration,
    unsettled: &mut HashMap<PathBuf, ((u64, Option<SystemTime>), Instant)>,
) -> bool {
    let Ok(meta) = std::fs::metadata(path) else {
        unsettled.remove(path);
        return false;
    };
    let modified = meta.modified().ok();
    let quiet = modified
        .and_then(|m| SystemTime::now().duration_since(m).ok())
        .is_some_and(|age| age >= settle);
    let key = (meta.len(), modified);
    let steady = match unsettled.get(path) {
        Some((seen, since)) if *seen == key => since.elapsed() >= settle,
        _ => {
            unsettled.insert(path.to_owned(), (key, Instant::now()));
            false
        }
    };
    if quiet || steady {
        unsettled.remove(path);
        true
    } else {
        false
    }
}

/// Processes one file and moves it; false if it could not be moved.
async fn process_file(ctx: &SourceContext, dir: &Path, path: &Path) -> bool {
    let Some(name) = path.file_name().map(|n| n.to_string_lossy().into_owned()) else {
        return true;
    };
    let source = format!("inbox {name}");
    // The file read, to move only that one (not another renamed over it since).
    let mut read = None;
    let report = if completed_before_restart(ctx, path, &source).await {
        None
    } else {
        let report = match tokio::fs::File::open(path).await {
            Ok(file) => {
                read = file.metadata().await.ok().map(|m| file_id(&m));
                ctx.ingest
                    .ingest_stream(SourceKind::Inbox, source.clone(), file, &ctx.cancel, None)
                    .await
            }
            // Gone since the listing (someone else took it): nothing to do.
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return true,
            Err(e) => RunReport {
                status: "failed",
                kind: Some("io"),
                reason: Some(format!("{source}: cannot open: {e}")),
                asset_id: None,
                run_id: None,
                samples: 0,
                ticks: 0,
                flushed: true,
                skipped_messages: 0,
                first_skipped: None,
                dropped_samples: 0,
                clock_jumps: 0,
            },
        };
        if report.status == "interrupted" {
            // Shutdown mid-file: leave it for the next start.
            return true;
        }
        Some(report)
    };
    let m = ctx.ingest.metrics();
    let done = report.as_ref().is_none_or(RunReport::ok);
    if read.is_some() {
        match tokio::fs::metadata(path).await.ok().map(|m| file_id(&m)) {
            // Gone since it was read (someone else took it): nothing to move.
            None => return true,
            // Another file was renamed over it while it was read: that one
            // is new and waits for the next pass (its rename woke it).
            Some(now) if Some(now) != read => {
                tracing::warn!(file = %path.display(),
                    "replaced while it was read: the new file is left for the next pass");
                return true;
            }
            Some(_) => {}
        }
    }
    let moved = match &report {
        Some(report) if !report.ok() => {
            let to = free_path(&dir.join(FAILED_DIR), &name).await;
            let reason_path = to.with_file_name(format!(
                "{}.reason.txt",
                to.file_name().unwrap_or_default().to_string_lossy()
            ));
            let mut text = format!(
                "{}\nkind: {}\nsamples: {}\nestimates: {}\n",
                report.reason.as_deref().unwrap_or("failed"),
                report.kind.unwrap_or("unknown"),
                report.samples,
                report.ticks
            );
            if let Some(first) = &report.first_skipped {
                let _ = writeln!(
                    text,
                    "skipped messages: {} (the first: {first})",
                    report.skipped_messages
                );
            }
            match tokio::fs::write(&reason_path, text).await {
                Ok(()) => move_to(path, &to).await,
                Err(e) => Err(format!("cannot write {}: {e}", reason_path.display())),
            }
        }
        _ => move_to(path, &free_path(&dir.join(DONE_DIR), &name).await).await,
    };
    match moved {
        Ok(()) => {
            let to = if done { DONE_DIR } else { FAILED_DIR };
            super::metrics::Metrics::add(&m.files, to, 1);
            tracing::info!(file = %path.display(), to, "inbox file processed");
            true
        }
        Err(e) => {
            m.error("inbox");
            tracing::error!(file = %path.display(), "{e}; not retried until restart");
            false
        }
    }
}

/// Whether the fleet store holds the run in `path` as completed from this
/// inbox name: processed to completion, then the daemon stopped before the
/// move (`kill -9` in between), so its estimates are all stored. Only a store
/// can say so: without one the file's head is not read.
async fn completed_before_restart(ctx: &SourceContext, path: &Path, source: &str) -> bool {
    if !ctx.ingest.has_store() {
        return false;
    }
    let Some((asset_id, run_id)) = run_of(path).await else {
        return false;
    };
    let completed = ctx
        .ingest
        .completed_before(&asset_id, &run_id, source)
        .await;
    if completed {
        tracing::info!(file = %path.display(), asset = %asset_id, run = %run_id,
            "inbox file's run already processed to completion from this name (the store holds \
             it; a restart before the move, or the file dropped again): moved to done/, not redone");
    }
    completed
}

/// The `(asset_id, run_id)` of the log at `path`, from its `shocktwin.run`
/// metadata at the start of the file (the first MiB at most); `None` if it
/// cannot be read there.
async fn run_of(path: &Path) -> Option<(String, String)> {
    use tokio::io::AsyncReadExt;
    let mut file = tokio::fs::File::open(path).await.ok()?;
    let mut decoder = dt_core::log::LogDecoder::new(&path.display().to_string());
    let mut buf = vec![0u8; 64 * 1024];
    for _ in 0..16 {
        let n = file.read(&mut buf).await.ok()?;
        if n == 0 {
            return None;
        }
        decoder.feed(&buf[..n]);
        while let Some(event) = decoder.next_event() {
            match event {
                Ok(dt_core::log::LogEvent::Metadata(m)) => return Some((m.asset_id, m.run_id)),
                Ok(_) => return None, // a message before the metadata
                Err(e) if e.is_fatal() => return None,
                Err(_) => {}
            }
        }
    }
    None
}

/// What tells one file from another at the same path.
#[cfg(unix)]
fn file_id(m: &std::fs::Metadata) -> (u64, u64) {
    use std::os::unix::fs::MetadataExt as _;
    (m.dev(), m.ino())
}

/// What tells one file from another at the same path (the size and
/// modification time, where no inode number is at hand).
#[cfg(not(unix))]
fn file_id(m: &std::fs::Metadata) -> (u64, Option<SystemTime>) {
    (m.len(), m.modified().ok())
}

/// `dir/name`, or `dir/<stem>~<k>.<ext>` with the first `k` free when a
/// file of that name is there already: a file dropped again under a name
/// the inbox had processed replaced the earlier one in `done/` (its only
/// copy when the two differed).
async fn free_path(dir: &Path, name: &str) -> PathBuf {
    let first = dir.join(name);
    if !tokio::fs::try_exists(&first).await.unwrap_or(false) {
        return first;
    }
    let name = Path::new(name);
    let stem = name.file_stem().unwrap_or_default().to_string_lossy();
    let ext = name
        .extension()
        .map(|e| format!(".{}", e.to_string_lossy()))
        .unwrap_or_default();
    for k in 1.. {
        let candidate = dir.join(format!("{stem}~{k}{ext}"));
        if !tokio::fs::try_exists(&candidate).await.unwrap_or(false) {
            return candidate;
        }
    }
    unreachable!("an unbounded range ends only by returning")
}

/// Moves `from` to `to`, and dates it now: `done/` is cleaned by age
/// (`deploy/shocktwin.tmpfiles`), and a file copied in with its logger's
/// times kept (`rsync -a`, `scp -p`) would have gone on the next clean (a
/// review). A date that cannot be set is logged; the move stands.
async fn move_to(from: &Path, to: &Path) -> Result<(), String> {
    tokio::fs::rename(from, to)
        .await
        .map_err(|e| format!("cannot move {} to {}: {e}", from.display(), to.display()))?;
    let moved = to.to_owned();
    let dated = tokio::task::spawn_blocking(move || {
        std::fs::File::options()
            .write(true)
            .open(&moved)?
            .set_modified(std::time::SystemTime::now())
    })
    .await;
    if let Ok(Err(e)) = dated {
        tracing::warn!(file = %to.display(), "moved, but its modification time could not be set: {e}");
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn names(v: &[&str]) -> HashSet<OsString> {
        v.iter().map(OsString::from).collect()
    }

    #[test]
    fn a_rename_reported_after_the_listing_is_not_forgotten() {
        // The listing ran before `late.mcap` was renamed in; its event came
        // before the names were pruned: it must survive to the next pass.
        let mut renamed = names(&["gone.mcap", "here.mcap", "late.mcap"]);
        let reported = names(&["gone.mcap", "here.mcap"]);
        let listed = names(&["here.mcap"]);
        let present: HashSet<&std::ffi::OsStr> = listed.iter().map(OsString::as_os_str).collect();
        forget_gone(&mut renamed, &reported, &present);
        assert_eq!(renamed, names(&["here.mcap", "late.mcap"]));
    }

    #[test]
    fn files_not_taken_are_told_apart_and_said_once() {
        let dir = tempfile::tempdir().unwrap();
        for d in [DONE_DIR, FAILED_DIR, "more-runs"] {
            std::fs::create_dir(dir.path().join(d)).unwrap();
        }
        for f in [
            "b.mcap",
            "A.MCAP",
            "c.mcap.part",
            "d.tmp",
            ".e.mcap.x1y2",
            "run.mcap.gz",
            "run.csv",
        ] {
            std::fs::write(dir.path().join(f), b"").unwrap();
        }
        let listing = pending_files(dir.path()).unwrap();
        let files: Vec<_> = listing
            .files
            .iter()
            .map(|p| p.file_name().unwrap().to_owned())
            .collect();
        assert_eq!(files, [OsString::from("A.MCAP"), OsString::from("b.mcap")]);
        let strangers: HashSet<OsString> = listing.strangers.iter().cloned().collect();
        assert_eq!(strangers, names(&["more-runs", "run.mcap.gz", "run.csv"]));
        let mut said = HashSet::new();
        say_strangers(dir.path(), listing.strangers.clone(), &mut said);
        assert_eq!(said, strangers);
        // Said once: a name gone from the inbox is forgotten, and said again
        // if it comes back.
        say_strangers(dir.path(), vec![OsString::from("run.csv")], &mut said);
        assert_eq!(said, names(&["run.csv"]));
    }
}
