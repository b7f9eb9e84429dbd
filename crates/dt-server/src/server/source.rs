//! Inputs behind one small [`Source`] interface. A source turns whatever it
//! reads into runs through [`Ingest`]: MCAP byte streams with
//! [`Ingest::ingest_stream`], sample streams from elsewhere (e.g. a message
//! bus partitioned by asset) with [`Ingest::open_run`] and
//! [`super::ingest::RunHandle`]. The estimator and the sinks do not know
//! which source fed them.

use std::collections::BTreeSet;
use std::sync::{Arc, Mutex, PoisonError};

use futures_util::future::BoxFuture;
use tokio_util::sync::CancellationToken;
use tokio_util::task::TaskTracker;

use super::ingest::Ingest;
use super::ServeError;

/// What a running source gets from the daemon.
#[derive(Debug, Clone)]
pub struct SourceContext {
    /// Where runs go.
    pub ingest: Ingest,
    /// Cancelled when the daemon starts shutting down: stop taking new work,
    /// end the runs in progress (their estimates so far are flushed).
    pub cancel: CancellationToken,
    /// Spawn per-connection tasks here; shutdown waits for all of them.
    pub tracker: TaskTracker,
    /// Say when the source takes work (see [`Source::says_started`]).
    pub started: Started,
}

/// The sources still starting, by name: `/readyz` is `503` until there is
/// none, so that a client who waits for it knows every source takes work
/// (e.g. a file renamed into the inbox is seen at once).
#[derive(Debug, Clone, Default)]
pub struct Starting(Arc<Mutex<BTreeSet<String>>>);

impl Starting {
    /// A source named `name` is starting until the handle's
    /// [`Started::signal`].
    pub fn enter(&self, name: &str) -> Started {
        self.0
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .insert(name.to_owned());
        Started {
            starting: Arc::clone(&self.0),
            name: Arc::from(name),
        }
    }

    /// The names of the sources still starting (empty: all take work).
    pub fn pending(&self) -> Vec<String> {
        let set = self.0.lock().unwrap_or_else(PoisonError::into_inner);
        set.iter().cloned().collect()
    }
}

/// One source's "I take work now"; signalled once (again is a no-op).
#[derive(Debug, Clone)]
pub struct Started {
    starting: Arc<Mutex<BTreeSet<String>>>,
    name: Arc<str>,
}

impl Started {
    /// The source takes work from now on.
    pub fn signal(&self) {
        self.starting
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .remove(self.name.as_ref());
    }
}

/// An input of the daemon.
pub trait Source: Send + 'static {
    /// Name for logs (`tcp 127.0.0.1:7410`, `inbox DIR`).
    fn name(&self) -> String;
    /// Whether the source signals [`SourceContext::started`] itself, once
    /// it takes work (the inbox, when its directory is watched). Otherwise
    /// (the default) it counts as started when spawned; either way the
    /// daemon signals it when `run` returns.
    fn says_started(&self) -> bool {
        false
    }
    /// Runs until `ctx.cancel` is cancelled (or a fatal error). Must return
    /// promptly after cancellation, once its runs are ended.
    fn run(self: Box<Self>, ctx: SourceContext) -> BoxFuture<'static, Result<(), ServeError>>;
}

#[cfg(test)]
mod tests {
    use super::Starting;

    #[test]
    fn a_source_is_pending_until_its_handle_signals() {
        let starting = Starting::default();
        let inbox = starting.enter("inbox in");
        let tcp = starting.enter("tcp 127.0.0.1:7410");
        assert_eq!(starting.pending(), ["inbox in", "tcp 127.0.0.1:7410"]);
        tcp.signal();
        assert_eq!(starting.pending(), ["inbox in"]);
        let again = inbox.clone();
        inbox.signal();
        again.signal();
        assert!(starting.pending().is_empty());
    }
}
