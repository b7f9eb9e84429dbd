//! dt-server integration tests (one binary): the `shocktwin serve` daemon
//! over real sockets on `127.0.0.1:0`, with the placeholder twin.

mod common;
mod serve_estimator;
mod serve_http;
mod serve_inbox;
mod serve_shutdown;
mod serve_tcp;
