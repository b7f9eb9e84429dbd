//! Bounds of the HTTPS API against clients that hold connections open.
//!
//! A helper trying the daemon as a gateway operator opened 377 TLS
//! connections to the API that finished their handshake and sent no
//! request: they were held for ever, until the daemon ran out of file
//! descriptors and its TCP ingest, inbox and API all failed (a vehicle's
//! report took 400 s). Now:
//! - at most `limits.max_http_connections` connections are held at once; one
//!   beyond them is closed as soon as it is accepted, before its TLS
//!   handshake (and said in the log, as the ingest's refusals are)
//!   ([`Bounded`]);
//! - after its TLS handshake a connection must send its first bytes within
//!   `limits.first_data_timeout_s` ([`FirstBytes`]), else it is closed;
//! - an HTTP/1 connection waiting for a request head (one sent in part, or
//!   none between two requests on a kept-alive connection) is closed after
//!   `limits.idle_timeout_s` (hyper's header-read timeout);
//! - an HTTP/2 connection's peer is pinged every `limits.idle_timeout_s` and
//!   dropped when it does not answer within `first_data_timeout_s`.
//!
//! The TLS handshake itself is bounded by axum-server (10 s). A client that
//! keeps its connections busy can still take the API's slots (not the
//! ingest's, nor the inbox's): `docs/security.md` says so.

use std::future::Future;
use std::io;
use std::pin::Pin;
use std::sync::Arc;
use std::task::{Context, Poll};
use std::time::Duration;

use axum_server::accept::Accept;
use hyper_util::rt::{TokioExecutor, TokioTimer};
use hyper_util::server::conn::auto::Builder;
use tokio::io::{AsyncRead, AsyncWrite, ReadBuf};
use tokio::net::TcpStream;
use tokio::sync::{OwnedSemaphorePermit, Semaphore};
use tokio::time::Sleep;

use super::config::Limits;

/// The request bounds of the list above, set on the server's builder.
pub fn bound_requests(builder: &mut Builder<TokioExecutor>, limits: &Limits) {
    let first = Duration::from_secs_f64(limits.first_data_timeout_s);
    builder
        .http1()
        .timer(TokioTimer::new())
        .header_read_timeout(Duration::from_secs_f64(limits.idle_timeout_s));
    builder
        .http2()
        .timer(TokioTimer::new())
        .keep_alive_interval(Duration::from_secs_f64(limits.idle_timeout_s))
        .keep_alive_timeout(first);
}

/// What is done with a connection that failed its TLS handshake (logged and
/// counted: the HTTPS API's were dropped without a word, so a server
/// certificate that had expired showed only at the clients; a helper's
/// trial).
pub type OnHandshakeError = Arc<dyn Fn(&io::Error) + Send + Sync>;

/// An acceptor around the TLS one: each connection takes one of a fixed
/// number of slots before its handshake (one for which none is free is
/// closed at once), holds it until it is dropped, and must bring its first
/// bytes within a deadline after the handshake ([`FirstBytes`]); a failed
/// handshake is handed to `on_error`.
#[derive(Clone)]
pub struct Bounded<A> {
    inner: A,
    slots: Arc<Semaphore>,
    max: usize,
    within: Duration,
    on_error: OnHandshakeError,
}

impl<A> std::fmt::Debug for Bounded<A> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Bounded")
            .field("max", &self.max)
            .field("within", &self.within)
            .finish_non_exhaustive()
    }
}

impl<A> Bounded<A> {
    /// `inner`'s connections, at most `max` at once, each closed unless it
    /// sends within `within` of its handshake.
    pub fn new(inner: A, max: usize, within: Duration, on_error: OnHandshakeError) -> Self {
        Self {
            inner,
            slots: Arc::new(Semaphore::new(max)),
            max,
            within,
            on_error,
        }
    }
}

impl<A, S> Accept<TcpStream, S> for Bounded<A>
where
    A: Accept<TcpStream, S>,
    A::Future: Send + 'static,
    A::Stream: Send + 'static,
    A::Service: Send + 'static,
{
    type Stream = FirstBytes<A::Stream>;
    type Service = A::Service;
    type Future = Pin<Box<dyn Future<Output = io::Result<(Self::Stream, Self::Service)>> + Send>>;

    fn accept(&self, stream: TcpStream, service: S) -> Self::Future {
        let Ok(slot) = Arc::clone(&self.slots).try_acquire_owned() else {
            let peer = stream
                .peer_addr()
                .map_or_else(|e| e.to_string(), |a| a.to_string());
            let reason = format!(
                "the API is serving its limit of {} connections (limits.max_http_connections)",
                self.max
            );
            tracing::warn!(%peer, "HTTPS connection closed: {reason}");
            return Box::pin(std::future::ready(Err(io::Error::other(reason))));
        };
        let accepted = self.inner.accept(stream, service);
        let within = self.within;
        let on_error = Arc::clone(&self.on_error);
        Box::pin(async move {
            match accepted.await {
                Ok((stream, service)) => Ok((FirstBytes::new(stream, within, slot), service)),
                Err(e) => {
                    on_error(&e);
                    Err(e)
                }
            }
        })
    }
}

/// A stream whose reads fail with `TimedOut` when its first bytes do not
/// come before its deadline (then it reads as the stream it wraps), and the
/// connection slot it holds until it is dropped.
pub struct FirstBytes<T> {
    inner: T,
    deadline: Option<Pin<Box<Sleep>>>,
    _slot: OwnedSemaphorePermit,
}

impl<T> FirstBytes<T> {
    /// `inner`, whose first bytes must come within `within`, holding `slot`.
    pub fn new(inner: T, within: Duration, slot: OwnedSemaphorePermit) -> Self {
        Self {
            inner,
            deadline: Some(Box::pin(tokio::time::sleep(within))),
            _slot: slot,
        }
    }
}

impl<T> std::fmt::Debug for FirstBytes<T> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("FirstBytes")
            .field("waiting", &self.deadline.is_some())
            .finish_non_exhaustive()
    }
}

impl<T: AsyncRead + Unpin> AsyncRead for FirstBytes<T> {
    fn poll_read(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &mut ReadBuf<'_>,
    ) -> Poll<io::Result<()>> {
        let before = buf.filled().len();
        let this = &mut *self;
        match Pin::new(&mut this.inner).poll_read(cx, buf) {
            Poll::Ready(Ok(())) if buf.filled().len() > before => {
                this.deadline = None;
                Poll::Ready(Ok(()))
            }
            Poll::Pending => {
                let late = this
                    .deadline
                    .as_mut()
                    .is_some_and(|deadline| deadline.as_mut().poll(cx).is_ready());
                if late {
                    Poll::Ready(Err(io::Error::new(
                        io::ErrorKind::TimedOut,
                        "nothing sent within limits.first_data_timeout_s of the TLS handshake",
                    )))
                } else {
                    Poll::Pending
                }
            }
            other @ Poll::Ready(_) => other,
        }
    }
}

impl<T: AsyncWrite + Unpin> AsyncWrite for FirstBytes<T> {
    fn poll_write(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &[u8],
    ) -> Poll<io::Result<usize>> {
        Pin::new(&mut self.inner).poll_write(cx, buf)
    }

    fn poll_flush(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Pin::new(&mut self.inner).poll_flush(cx)
    }

    fn poll_shutdown(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Pin::new(&mut self.inner).poll_shutdown(cx)
    }

    fn poll_write_vectored(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        bufs: &[io::IoSlice<'_>],
    ) -> Poll<io::Result<usize>> {
        Pin::new(&mut self.inner).poll_write_vectored(cx, bufs)
    }

    fn is_write_vectored(&self) -> bool {
        self.inner.is_write_vectored()
    }
}
