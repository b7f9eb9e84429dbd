//! Inputs behind one small [`Source`] interface. A source turns whatever it
//! reads into runs through [`Ingest`]: MCAP byte streams with
//! [`Ingest::ingest_stream`], sample streams from elsewhere (e.g. a message
//! bus partitioned by asset) with [`Ingest::open_run`] and
//! [`super::ingest::RunHandle`]. The estimator and the sinks do not know
//! which source fed them.

use std::collections::BTreeMap;
use std::sync::{Arc, Mutex, PoisonError, Weak};
use std::time::{Duration, Instant};

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

/// The sources still starting: `/readyz` is `503` until there is none, so
/// that a client who waits for it knows every source takes work (e.g. a file
/// renamed into the inbox is seen at once).
#[derive(Debug, Clone, Default)]
pub struct Starting(Arc<Mutex<Pending>>);

#[derive(Debug, Default)]
struct Pending {
    next_id: u64,
    /// Each starting source's name, and what keeps it (see [`Started::note`]).
    names: BTreeMap<u64, (String, Option<String>)>,
    /// Sources that stopped with an error while the daemon ran, and why.
    stopped: Vec<(String, String)>,
    /// Sources that took work and cannot for now (a lost connection):
    /// their name, why, and since when ([`Trouble`]).
    troubled: BTreeMap<u64, (String, String, Instant)>,
}

/// How long a source's trouble lasts before `/readyz` says it: a server's
/// restart or a lame-duck handover is a blip that should not take the whole
/// daemon (its TCP ingest, inbox and dashboard still work) out of a load
/// balancer's rotation (a review).
pub const TROUBLE_GRACE: Duration = Duration::from_secs(10);

impl Starting {
    /// A source named `name` is starting until its handle is signalled.
    pub fn enter(&self, name: &str) -> Started {
        let mut pending = self.0.lock().unwrap_or_else(PoisonError::into_inner);
        let id = pending.next_id;
        pending.next_id += 1;
        pending.names.insert(id, (name.to_owned(), None));
        Started(Some(Arc::new(Handle {
            starting: Arc::clone(&self.0),
            id,
            name: name.to_owned(),
        })))
    }

    /// The sources still starting (none: all take work), each as its name
    /// and, after it in parentheses, what keeps it when it said
    /// ([`Started::note`]).
    pub fn pending(&self) -> Vec<String> {
        let pending = self.0.lock().unwrap_or_else(PoisonError::into_inner);
        pending
            .names
            .values()
            .map(|(name, note)| match note {
                Some(note) => format!("{name} ({note})"),
                None => name.clone(),
            })
            .collect()
    }

    /// Source `name` stopped with an error (`why`) while the daemon ran: it
    /// takes no more work, and `/readyz` says so (a helper's trial: a source
    /// that gave up counted as started, and the daemon said ready).
    pub fn stopped(&self, name: &str, why: &str) {
        let mut pending = self.0.lock().unwrap_or_else(PoisonError::into_inner);
        pending.stopped.push((name.to_owned(), why.to_owned()));
    }

    /// The sources that stopped with an error, and why.
    pub fn failed(&self) -> Vec<(String, String)> {
        let pending = self.0.lock().unwrap_or_else(PoisonError::into_inner);
        pending.stopped.clone()
    }

    /// The sources that cannot take work for now (see [`Trouble`]) and
    /// have not for [`TROUBLE_GRACE`] or more, and why (with how long).
    #[must_use]
    pub fn troubled(&self) -> Vec<(String, String)> {
        self.troubled_for(TROUBLE_GRACE)
    }

    /// [`Self::troubled`] with another grace.
    fn troubled_for(&self, grace: Duration) -> Vec<(String, String)> {
        let pending = self.0.lock().unwrap_or_else(PoisonError::into_inner);
        pending
            .troubled
            .values()
            .filter(|(_, _, since)| since.elapsed() >= grace)
            .map(|(name, why, since)| {
                (
                    name.clone(),
                    format!("{why} ({} s)", since.elapsed().as_secs()),
                )
            })
            .collect()
    }
}

/// A source's "I take work now": signalled once (again is a no-op), and at
/// the latest when its last clone is dropped (the source returned, failed
/// or panicked). The default has nothing to signal (a source that does not
/// say, [`Source::says_started`]).
#[derive(Debug, Clone, Default)]
pub struct Started(Option<Arc<Handle>>);

#[derive(Debug)]
struct Handle {
    starting: Arc<Mutex<Pending>>,
    id: u64,
    name: String,
}

impl Handle {
    fn signal(&self) {
        let mut pending = self.starting.lock().unwrap_or_else(PoisonError::into_inner);
        pending.names.remove(&self.id);
    }

    fn note(&self, why: Option<String>) {
        let mut pending = self.starting.lock().unwrap_or_else(PoisonError::into_inner);
        if let Some((_, note)) = pending.names.get_mut(&self.id) {
            *note = why;
        }
    }
}

impl Drop for Handle {
    fn drop(&mut self) {
        let mut pending = self.starting.lock().unwrap_or_else(PoisonError::into_inner);
        pending.names.remove(&self.id);
        pending.troubled.remove(&self.id);
    }
}

/// Says, after a source has started, that it cannot take work for now and
/// why, or that it can again (a NATS part whose connection is lost:
/// `/readyz` said ready through a server's outage). Holds its source's
/// entry weakly: it outlives the source harmlessly (a client's event task).
#[derive(Debug, Clone, Default)]
pub struct Trouble(Option<Weak<Handle>>);

impl Trouble {
    /// Whether a daemon's source is behind it (`/readyz` says its trouble);
    /// not for a CLI's connection (`shocktwin publish`).
    #[must_use]
    pub fn is_said(&self) -> bool {
        self.0.is_some()
    }

    /// `Some(why)`: the source cannot take work for now; `None`: it can.
    pub fn set(&self, why: Option<String>) {
        let Some(handle) = self.0.as_ref().and_then(Weak::upgrade) else {
            return;
        };
        let mut pending = handle
            .starting
            .lock()
            .unwrap_or_else(PoisonError::into_inner);
        match why {
            Some(why) => {
                // since the trouble began: a new reason does not restart it
                let since = pending
                    .troubled
                    .get(&handle.id)
                    .map_or_else(Instant::now, |t| t.2);
                pending
                    .troubled
                    .insert(handle.id, (handle.name.clone(), why, since));
            }
            None => {
                pending.troubled.remove(&handle.id);
            }
        }
    }
}

impl Started {
    /// The source takes work from now on.
    pub fn signal(&self) {
        if let Some(handle) = &self.0 {
            handle.signal();
        }
    }

    /// What keeps the source from taking work, for `/readyz` (e.g. "no
    /// connection after 20 s"); `None` clears it. A no-op once signalled.
    pub fn note(&self, why: Option<String>) {
        if let Some(handle) = &self.0 {
            handle.note(why);
        }
    }

    /// The source's [`Trouble`] reporter.
    pub fn trouble(&self) -> Trouble {
        Trouble(self.0.as_ref().map(Arc::downgrade))
    }
}

/// An input of the daemon.
pub trait Source: Send + 'static {
    /// Name for logs (`tcp 127.0.0.1:7410`, `inbox DIR`).
    fn name(&self) -> String;
    /// Whether the source signals [`SourceContext::started`] itself, once
    /// it takes work (the inbox, once its directory is watched or, failing
    /// that, rescanned). Otherwise (the default) `/readyz` does not wait for
    /// it.
    fn says_started(&self) -> bool {
        false
    }
    /// Runs until `ctx.cancel` is cancelled (or a fatal error). Must return
    /// promptly after cancellation, once its runs are ended.
    fn run(self: Box<Self>, ctx: SourceContext) -> BoxFuture<'static, Result<(), ServeError>>;
}

#[cfg(test)]
mod tests {
    use super::{Started, Starting};
    use std::time::Duration;

    #[test]
    fn a_source_is_pending_until_its_handle_signals_or_goes() {
        let starting = Starting::default();
        let inbox = starting.enter("inbox in");
        let other = starting.enter("inbox in");
        let tcp = starting.enter("tcp 127.0.0.1:7410");
        assert_eq!(
            starting.pending(),
            ["inbox in", "inbox in", "tcp 127.0.0.1:7410"]
        );
        tcp.signal();
        tcp.signal();
        assert_eq!(starting.pending(), ["inbox in", "inbox in"]);
        // A source with the same name is another source.
        other.signal();
        assert_eq!(starting.pending(), ["inbox in"]);
        // What keeps a source is said beside its name, until cleared or signalled.
        inbox.note(Some("set-up failed: no JetStream".into()));
        assert_eq!(
            starting.pending(),
            ["inbox in (set-up failed: no JetStream)"]
        );
        inbox.note(None);
        assert_eq!(starting.pending(), ["inbox in"]);
        other.note(Some("after its signal".into()));
        assert_eq!(starting.pending(), ["inbox in"]);
        // Its clones go with the source's context: the last one signals.
        let clone = inbox.clone();
        drop(inbox);
        assert_eq!(starting.pending(), ["inbox in"]);
        drop(clone);
        assert!(starting.pending().is_empty());
        Started::default().signal();
    }

    #[test]
    fn a_started_source_in_trouble_is_said_until_it_recovers_or_goes() {
        let starting = Starting::default();
        let nats = starting.enter("nats worker w1");
        nats.signal();
        let trouble = nats.trouble();
        trouble.set(Some("connection lost".into()));
        // said only after the grace
        assert!(starting.troubled().is_empty());
        assert_eq!(
            starting.troubled_for(Duration::ZERO),
            [(
                "nats worker w1".to_owned(),
                "connection lost (0 s)".to_owned()
            )]
        );
        assert!(starting.pending().is_empty());
        trouble.set(None);
        assert!(starting.troubled_for(Duration::ZERO).is_empty());
        trouble.set(Some("connection lost".into()));
        // the source gone, its trouble goes with it, and a late report is a no-op
        drop(nats);
        assert!(starting.troubled_for(Duration::ZERO).is_empty());
        trouble.set(Some("after it".into()));
        assert!(starting.troubled_for(Duration::ZERO).is_empty());
        Started::default().trouble().set(Some("no-op".into()));
    }
}
