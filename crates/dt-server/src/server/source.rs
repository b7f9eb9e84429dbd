//! Inputs behind one small [`Source`] interface. A source turns whatever it
//! reads into runs through [`Ingest`]: MCAP byte streams with
//! [`Ingest::ingest_stream`], sample streams from elsewhere (e.g. a message
//! bus partitioned by asset) with [`Ingest::open_run`] and
//! [`super::ingest::RunHandle`]. The estimator and the sinks do not know
//! which source fed them.

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
}

/// An input of the daemon.
pub trait Source: Send + 'static {
    /// Name for logs (`tcp 127.0.0.1:7410`, `inbox DIR`).
    fn name(&self) -> String;
    /// Runs until `ctx.cancel` is cancelled (or a fatal error). Must return
    /// promptly after cancellation, once its runs are ended.
    fn run(self: Box<Self>, ctx: SourceContext) -> BoxFuture<'static, Result<(), ServeError>>;
}
