//! TCP ingest: each connection carries one MCAP byte stream, one run of one
//! asset (named by its `shocktwin.run` metadata), written incrementally by
//! any MCAP writer. A semaphore caps concurrent connections and a count per
//! IP address caps each peer's share; a connection beyond either is
//! answered `{"status":"refused",…}` at once and closed (a flood of silent
//! sockets cannot leave vehicles waiting in the backlog), and a connection
//! that sends nothing within `first_data_timeout_s` gives its slot back. When the run is processed and flushed the daemon
//! writes one JSON line (a [`super::ingest::RunReport`]) back and closes.
//! With TLS ([`super::security`]) each connection's handshake runs in its
//! own task, bounded by the idle timeout, and the same stream follows over
//! TLS; with a client CA a connection without a valid client certificate
//! fails its handshake and is counted, never decoded.

use std::collections::HashMap;
use std::net::{IpAddr, SocketAddr};
use std::sync::Arc;
use std::sync::Mutex;
use std::time::Duration;

use futures_util::future::BoxFuture;
use futures_util::StreamExt;
use tokio::io::{AsyncBufReadExt, AsyncRead, AsyncReadExt, AsyncWrite, AsyncWriteExt};
use tokio::net::TcpListener;
use tokio::sync::Semaphore;
use tokio_util::io::{ReaderStream, StreamReader};

use super::sink::SourceKind;
use super::source::{Source, SourceContext};
use super::ServeError;

/// The TCP ingest listener.
#[derive(Debug)]
pub struct TcpSource {
    listener: TcpListener,
    limits: ConnectionLimits,
    tls: Option<Arc<rustls::ServerConfig>>,
    rate: Option<Arc<PeerRate>>,
}

/// What one listener allows (from `[limits]`).
#[derive(Debug, Clone, Copy)]
pub struct ConnectionLimits {
    /// Connections served at once; more are refused at once.
    pub max_connections: usize,
    /// Connections served at once from one IP address.
    pub max_per_peer: usize,
    /// A connection must send its first bytes (or finish its TLS handshake) this soon.
    pub first_data: Duration,
    /// A connection silent for this long is closed.
    pub idle: Duration,
}

impl ConnectionLimits {
    /// The `[limits]` of the configuration.
    #[must_use]
    pub fn from_config(l: &super::config::Limits) -> Self {
        Self {
            max_connections: l.max_connections,
            max_per_peer: l.max_connections_per_peer,
            first_data: Duration::from_secs_f64(l.first_data_timeout_s),
            idle: Duration::from_secs_f64(l.idle_timeout_s),
        }
    }
}

impl TcpSource {
    /// Serves `listener` within `limits`.
    #[must_use]
    pub fn new(listener: TcpListener, limits: ConnectionLimits) -> Self {
        Self {
            listener,
            limits,
            tls: None,
            rate: None,
        }
    }

    /// Speaks TLS with `config` (none: plaintext).
    #[must_use]
    pub fn with_tls(mut self, config: Option<Arc<rustls::ServerConfig>>) -> Self {
        self.tls = config;
        self
    }

    /// Limits each peer's byte rate (see [`peer_rate`]; none: unlimited).
    #[must_use]
    pub fn with_rate(mut self, rate: Option<Arc<PeerRate>>) -> Self {
        self.rate = rate;
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

/// Connections per peer address; a slot gives its place back when dropped.
#[derive(Debug, Default)]
struct Peers(Mutex<HashMap<IpAddr, usize>>);

struct PeerSlot {
    peers: Arc<Peers>,
    ip: IpAddr,
}

impl Peers {
    fn take(self: &Arc<Self>, ip: IpAddr, max: usize) -> Option<PeerSlot> {
        let mut map = self
            .0
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        let n = map.entry(ip).or_insert(0);
        if *n >= max {
            return None;
        }
        *n += 1;
        Some(PeerSlot {
            peers: Arc::clone(self),
            ip,
        })
    }
}

impl Drop for PeerSlot {
    fn drop(&mut self) {
        let mut map = self
            .peers
            .0
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        if let Some(n) = map.get_mut(&self.ip) {
            *n -= 1;
            if *n == 0 {
                map.remove(&self.ip);
            }
        }
    }
}

/// Accepts every connection at once: one within the limits is served, one
/// beyond them is answered `refused` (one JSON line) and closed, so that a
/// flood never leaves good clients hanging in the backlog.
async fn accept_loop(src: TcpSource, ctx: SourceContext) -> Result<(), ServeError> {
    let limits = src.limits;
    let permits = Arc::new(Semaphore::new(limits.max_connections));
    let peers = Arc::new(Peers::default());
    let mut backoff = Duration::from_millis(10);
    loop {
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
        let slot = peers.take(peer.ip(), limits.max_per_peer);
        let permit = Arc::clone(&permits).try_acquire_owned().ok();
        let (Some(slot), Some(permit)) = (slot, permit) else {
            let (kind, reason) = if peers_full(&peers, peer.ip(), limits.max_per_peer) {
                (
                    "refused_per_peer",
                    format!(
                        "{} already has {} connections, the most one address may have; retry later",
                        peer.ip(),
                        limits.max_per_peer
                    ),
                )
            } else {
                (
                    "refused_max_connections",
                    format!(
                        "the daemon is serving its limit of {} connections; retry later",
                        limits.max_connections
                    ),
                )
            };
            m.error(kind);
            tracing::warn!(%peer, "connection refused: {reason}");
            ctx.tracker.spawn(refuse(socket, reason, src.tls.is_some()));
            continue;
        };
        m.connections_active.inc();
        let ingest = ctx.ingest.clone();
        let cancel = ctx.cancel.clone();
        let tls = src.tls.clone();
        let rate = src.rate.clone();
        ctx.tracker.spawn(async move {
            let link = Accepted {
                ingest: &ingest,
                peer,
                limits,
                cancel: &cancel,
                rate,
            };
            match tls {
                None => link.serve_plain(socket).await,
                Some(config) => link.serve_tls(socket, config).await,
            }
            // The slots first: once the gauge reads the connection gone, a
            // new one finds its slot free.
            drop(permit);
            drop(slot);
            ingest.metrics().connections_active.dec();
        });
    }
}

/// An accepted connection's context, for the ingest to serve it.
struct Accepted<'a> {
    ingest: &'a super::ingest::Ingest,
    peer: SocketAddr,
    limits: ConnectionLimits,
    cancel: &'a tokio_util::sync::CancellationToken,
    rate: Option<Arc<PeerRate>>,
}

impl Accepted<'_> {
    /// A plain connection, once it has sent something: silent connections
    /// do not hold a slot for the whole idle timeout.
    async fn serve_plain(self, socket: tokio::net::TcpStream) {
        let mut first = [0u8; 1];
        if tokio::time::timeout(self.limits.first_data, socket.peek(&mut first))
            .await
            .is_err()
        {
            self.ingest.metrics().error("first_data_timeout");
            tracing::warn!(peer = %self.peer, "closed: nothing sent within {:?}", self.limits.first_data);
        } else {
            let (peer, idle) = (self.peer, self.limits.idle);
            serve_connection(self.ingest, socket, peer, self.cancel, idle, self.rate).await;
        }
    }

    /// A TLS connection: its handshake, then its first bytes, each within
    /// `first_data` (a vehicle's certificate does not buy a silent slot for
    /// the whole idle timeout either).
    async fn serve_tls(self, socket: tokio::net::TcpStream, config: Arc<rustls::ServerConfig>) {
        let (peer, first_data) = (self.peer, self.limits.first_data);
        let acceptor = tokio_rustls::TlsAcceptor::from(config);
        match tokio::time::timeout(first_data, acceptor.accept(socket)).await {
            Ok(Ok(stream)) => {
                let mut stream = tokio::io::BufReader::new(stream);
                if tokio::time::timeout(first_data, stream.fill_buf())
                    .await
                    .is_err()
                {
                    self.ingest.metrics().error("first_data_timeout");
                    tracing::warn!(
                        %peer,
                        "closed: nothing sent within {first_data:?} of the TLS handshake"
                    );
                } else {
                    let idle = self.limits.idle;
                    serve_connection(self.ingest, stream, peer, self.cancel, idle, self.rate).await;
                }
            }
            Ok(Err(e)) => {
                self.ingest.metrics().error("tls_handshake");
                tracing::warn!(%peer, "TLS handshake failed: {e}");
            }
            Err(_) => {
                self.ingest.metrics().error("tls_handshake");
                tracing::warn!(%peer, "TLS handshake timed out");
            }
        }
    }
}

fn peers_full(peers: &Peers, ip: IpAddr, max: usize) -> bool {
    let map = peers
        .0
        .lock()
        .unwrap_or_else(std::sync::PoisonError::into_inner);
    map.get(&ip).is_some_and(|&n| n >= max)
}

/// Answers a connection beyond the limits with one `refused` line and closes
/// it. On a TLS listener it is closed without a line: a plain line reads to
/// the client as a broken handshake (`WRONG_VERSION_NUMBER`, a helper's
/// trial), and a handshake to say it would cost a refused flood the work the
/// limit saves.
async fn refuse(mut socket: tokio::net::TcpStream, reason: String, tls: bool) {
    if tls {
        return;
    }
    let line = serde_json::json!({ "status": "refused", "reason": reason }).to_string() + "\n";
    let _ = tokio::time::timeout(Duration::from_secs(2), async {
        let _ = socket.write_all(line.as_bytes()).await;
        let _ = socket.shutdown().await;
    })
    .await;
}

/// The per-peer byte rate of the ingest (`limits.max_ingest_bytes_per_s_per_peer`):
/// governor's keyed GCRA limiter, one cell per byte, one second of burst.
pub type PeerRate = governor::DefaultKeyedRateLimiter<std::net::IpAddr>;

/// The limiter for `bytes_per_s` (none for 0).
#[must_use]
pub fn peer_rate(bytes_per_s: u64) -> Option<Arc<PeerRate>> {
    let per_s = std::num::NonZeroU32::new(u32::try_from(bytes_per_s).ok()?)?;
    Some(Arc::new(governor::RateLimiter::keyed(
        governor::Quota::per_second(per_s),
    )))
}

async fn serve_connection<S: AsyncRead + AsyncWrite + Unpin>(
    ingest: &super::ingest::Ingest,
    socket: S,
    peer: SocketAddr,
    cancel: &tokio_util::sync::CancellationToken,
    idle: Duration,
    rate: Option<Arc<PeerRate>>,
) {
    let (mut reader, mut writer) = tokio::io::split(socket);
    let source = format!("tcp {peer}");
    let report = match rate {
        None => {
            ingest
                .ingest_stream(SourceKind::Tcp, source, &mut reader, cancel, Some(idle))
                .await
        }
        Some(rate) => {
            // Each chunk read waits for its bytes' tokens: a peer over its rate
            // is read more slowly (TCP pushes back on it), never cut off.
            let ip = peer.ip();
            let chunks = ReaderStream::with_capacity(&mut reader, RATE_CHUNK_BYTES as usize).then(
                move |chunk| {
                    let rate = Arc::clone(&rate);
                    async move {
                        if let Ok(bytes) = &chunk {
                            if let Some(n) = u32::try_from(bytes.len())
                                .ok()
                                .and_then(std::num::NonZeroU32::new)
                            {
                                // `n` ≤ RATE_CHUNK_BYTES ≤ the burst (validated).
                                let _ = rate.until_key_n_ready(&ip, n).await;
                            }
                        }
                        chunk
                    }
                },
            );
            let mut throttled = StreamReader::new(Box::pin(chunks));
            ingest
                .ingest_stream(SourceKind::Tcp, source, &mut throttled, cancel, Some(idle))
                .await
        }
    };
    let mut line = serde_json::to_vec(&report).unwrap_or_default();
    line.push(b'\n');
    // Best effort: the client may be gone already.
    let _ = writer.write_all(&line).await;
    let _ = writer.shutdown().await;
    // Lingering close: a client still sending (we stopped reading at an
    // error) would otherwise get a reset and lose the report line.
    discard_rest(reader).await;
}

/// Reads and drops what a client still sends after its stream was answered
/// or refused, at most [`LINGER_MAX_BYTES`] for at most [`LINGER`]: a client
/// still sending would otherwise get a reset (TCP, HTTP/1.1) or a reset
/// stream (HTTP/2) and lose the answer. No memory is kept.
pub(crate) async fn discard_rest<R: tokio::io::AsyncRead + Unpin>(reader: R) {
    let mut rest = reader.take(LINGER_MAX_BYTES);
    let _ = tokio::time::timeout(LINGER, tokio::io::copy(&mut rest, &mut tokio::io::sink())).await;
}

/// Bytes read at a time from a rate-limited connection (at most the burst of
/// the smallest useful rate, 4 KiB/s).
const RATE_CHUNK_BYTES: u32 = 4096;

/// How long a closing connection's remaining input is read and discarded.
const LINGER: Duration = Duration::from_secs(2);
/// At most this much of it.
const LINGER_MAX_BYTES: u64 = 64 << 20;
