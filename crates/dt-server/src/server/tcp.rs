//! TCP ingest: each connection carries one MCAP byte stream, one run of one
//! asset (named by its `shocktwin.run` metadata), written incrementally by
//! any MCAP writer. A semaphore caps concurrent connections (others wait in
//! the accept backlog). When the run is processed and flushed the daemon
//! writes one JSON line (a [`super::ingest::RunReport`]) back and closes.
//! With TLS ([`super::security`]) each connection's handshake runs in its
//! own task, bounded by the idle timeout, and the same stream follows over
//! TLS; with a client CA a connection without a valid client certificate
//! fails its handshake and is counted, never decoded.

use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;

use futures_util::future::BoxFuture;
use tokio::io::{AsyncRead, AsyncReadExt, AsyncWrite, AsyncWriteExt};
use tokio::net::TcpListener;
use tokio::sync::Semaphore;

use super::sink::SourceKind;
use super::source::{Source, SourceContext};
use super::ServeError;

/// The TCP ingest listener.
#[derive(Debug)]
pub struct TcpSource {
    listener: TcpListener,
    max_connections: usize,
    idle: Duration,
    tls: Option<Arc<rustls::ServerConfig>>,
}

impl TcpSource {
    /// Serves `listener` with at most `max_connections` at once; a connection
    /// silent for `idle` is closed.
    #[must_use]
    pub fn new(listener: TcpListener, max_connections: usize, idle: Duration) -> Self {
        Self {
            listener,
            max_connections,
            idle,
            tls: None,
        }
    }

    /// Speaks TLS with `config` (none: plaintext).
    #[must_use]
    pub fn with_tls(mut self, config: Option<Arc<rustls::ServerConfig>>) -> Self {
        self.tls = config;
        self
    }
}

impl Source for TcpSource {
    fn name(&self) -> String {
        match self.listener.local_addr() {
            Ok(a) => format!("tcp {a}"),
            Err(_) => "tcp".to_owned(),
        }
    }

    fn run(self: Box<Self>, ctx: SourceContext) -> BoxFuture<'static, Result<(), ServeError>> {
        Box::pin(accept_loop(*self, ctx))
    }
}

async fn accept_loop(src: TcpSource, ctx: SourceContext) -> Result<(), ServeError> {
    let permits = Arc::new(Semaphore::new(src.max_connections));
    let mut backoff = Duration::from_millis(10);
    loop {
        let permit = tokio::select! {
            () = ctx.cancel.cancelled() => return Ok(()),
            p = Arc::clone(&permits).acquire_owned() => p.expect("the semaphore is never closed"),
        };
        let accepted = tokio::select! {
            () = ctx.cancel.cancelled() => return Ok(()),
            a = src.listener.accept() => a,
        };
        let (socket, peer) = match accepted {
            Ok(x) => {
                backoff = Duration::from_millis(10);
                x
            }
            Err(e) => {
                // E.g. out of file descriptors: wait, then retry.
                ctx.ingest.metrics().error("accept");
                tracing::warn!("accept failed: {e}; retrying in {backoff:?}");
                tokio::select! {
                    () = ctx.cancel.cancelled() => return Ok(()),
                    () = tokio::time::sleep(backoff) => {}
                }
                backoff = (backoff * 2).min(Duration::from_secs(1));
                continue;
            }
        };
        let m = ctx.ingest.metrics();
        m.connections.inc();
        m.connections_active.inc();
        let ingest = ctx.ingest.clone();
        let cancel = ctx.cancel.clone();
        let idle = src.idle;
        let tls = src.tls.clone();
        ctx.tracker.spawn(async move {
            match tls {
                None => serve_connection(&ingest, socket, peer, &cancel, idle).await,
                Some(config) => {
                    let acceptor = tokio_rustls::TlsAcceptor::from(config);
                    match tokio::time::timeout(idle, acceptor.accept(socket)).await {
                        Ok(Ok(stream)) => {
                            serve_connection(&ingest, stream, peer, &cancel, idle).await;
                        }
                        Ok(Err(e)) => {
                            ingest.metrics().error("tls_handshake");
                            tracing::warn!(%peer, "TLS handshake failed: {e}");
                        }
                        Err(_) => {
                            ingest.metrics().error("tls_handshake");
                            tracing::warn!(%peer, "TLS handshake timed out");
                        }
                    }
                }
            }
            ingest.metrics().connections_active.dec();
            drop(permit);
        });
    }
}

async fn serve_connection<S: AsyncRead + AsyncWrite + Unpin>(
    ingest: &super::ingest::Ingest,
    socket: S,
    peer: SocketAddr,
    cancel: &tokio_util::sync::CancellationToken,
    idle: Duration,
) {
    let (mut reader, mut writer) = tokio::io::split(socket);
    let report = ingest
        .ingest_stream(
            SourceKind::Tcp,
            format!("tcp {peer}"),
            &mut reader,
            cancel,
            Some(idle),
        )
        .await;
    let mut line = serde_json::to_vec(&report).unwrap_or_default();
    line.push(b'\n');
    // Best effort: the client may be gone already.
    let _ = writer.write_all(&line).await;
    let _ = writer.shutdown().await;
    // Lingering close: a client still sending (we stopped reading at an
    // error) would otherwise get a reset and lose the report line.
    let mut rest = reader.take(LINGER_MAX_BYTES);
    let _ = tokio::time::timeout(LINGER, tokio::io::copy(&mut rest, &mut tokio::io::sink())).await;
}

/// How long a closing connection's remaining input is read and discarded.
const LINGER: Duration = Duration::from_secs(2);
/// At most this much of it.
const LINGER_MAX_BYTES: u64 = 64 << 20;
