//! One daemon per fleet store, inbox and recording directory.
//!
//! Two `shocktwin serve` on the same inbox each took every file dropped in
//! it (every run processed twice, stored twice, each recording's rename
//! racing the other's; a helper's trial: a service unit and a manual start).
//! At start the daemon holds an exclusive advisory lock (`flock`, through
//! [`std::fs::File::try_lock`]) on a file for each place it writes: beside
//! the store (`fleet.sqlite.lock`), and in the inbox and the recording
//! directory (`.shocktwin-serve.lock`, hidden, so the inbox passes over it).
//! A second daemon on any of them refuses to start and names the place and
//! the process that holds it. The kernel releases the locks when the process
//! ends, `kill -9` included; a lock file left behind holds nothing.

use std::fs::{File, OpenOptions, TryLockError};
use std::io::{Read as _, Seek as _, Write as _};
use std::path::{Path, PathBuf};

use super::{Config, ServeError};

/// The lock file's name in the inbox and the recording directory.
pub const LOCK_NAME: &str = ".shocktwin-serve.lock";

/// The locks a daemon holds while it runs (released when dropped).
#[derive(Debug)]
pub struct Held {
    _files: Vec<File>,
}

/// Takes the lock of every place `config` writes: the store, the inbox and
/// the recording directory (each created if missing, as the daemon would).
///
/// # Errors
/// [`ServeError::Locked`] when another process holds one (named);
/// [`ServeError::Io`] when a lock file cannot be created.
pub fn hold(config: &Config) -> Result<Held, ServeError> {
    let mut places: Vec<(&'static str, PathBuf)> = Vec::new();
    if let Some(dir) = &config.server.inbox {
        places.push(("inbox", dir.join(LOCK_NAME)));
    }
    if let Some(db) = &config.store.path {
        let mut name = db.file_name().unwrap_or_default().to_os_string();
        name.push(".lock");
        places.push(("fleet store", db.with_file_name(name)));
    }
    if let Some(dir) = &config.server.record_dir {
        places.push(("recording directory", dir.join(LOCK_NAME)));
    }
    let files = places
        .into_iter()
        .map(|(what, path)| lock(what, &path))
        .collect::<Result<_, _>>()?;
    Ok(Held { _files: files })
}

fn lock(what: &'static str, path: &Path) -> Result<File, ServeError> {
    let io = |error| ServeError::Io {
        path: path.to_path_buf(),
        error,
    };
    if let Some(parent) = path.parent().filter(|p| !p.as_os_str().is_empty()) {
        if !parent.exists() {
            // a mistyped inbox was created without a word (the inbox's own
            // warning came after this had made it), and files dropped into
            // the real one were never taken
            tracing::warn!(dir = %parent.display(), "the {what}'s directory did not exist: created it");
        }
        std::fs::create_dir_all(parent).map_err(io)?;
    }
    let mut file = OpenOptions::new()
        .read(true)
        .write(true)
        .create(true)
        .truncate(false)
        .open(path)
        .map_err(io)?;
    match file.try_lock() {
        Ok(()) => {}
        Err(TryLockError::WouldBlock) => {
            let mut holder = String::new();
            // best effort: the holder wrote its pid when it took the lock
            let _ = file.read_to_string(&mut holder);
            return Err(ServeError::Locked {
                what,
                path: path.to_path_buf(),
                holder: holder.trim().to_owned(),
            });
        }
        Err(TryLockError::Error(error)) => return Err(io(error)),
    }
    file.set_len(0).map_err(io)?;
    file.rewind().map_err(io)?;
    writeln!(file, "pid {}", std::process::id()).map_err(io)?;
    Ok(file)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_second_holder_is_refused_and_told_who_holds_it() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("inbox").join(LOCK_NAME);
        let first = lock("inbox", &path).unwrap();
        let err = lock("inbox", &path).unwrap_err().to_string();
        assert!(err.contains("another shocktwin serve"), "{err}");
        assert!(
            err.contains(&format!("pid {}", std::process::id())),
            "{err}"
        );
        assert!(err.contains(&path.display().to_string()), "{err}");
        drop(first);
        // released with its holder: the file left behind holds nothing
        lock("inbox", &path).unwrap();
    }
}
