//! dt-server integration tests (one binary): the `shocktwin serve` daemon
//! over real sockets on `127.0.0.1:0`, with the placeholder twin; fuzzing of
//! the configuration loader and of `shocktwin import`'s readers (`fuzz_*`).

mod common;
mod fuzz_config;
#[path = "../../../dt-core/tests/it/fuzz_driver.rs"]
mod fuzz_driver;
mod fuzz_import;
mod fuzz_nats;
mod serve_estimator;
mod serve_http;
mod serve_inbox;
mod serve_shutdown;
mod serve_tcp;
