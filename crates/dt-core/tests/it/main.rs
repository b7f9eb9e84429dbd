//! dt-core integration tests (one binary, modules per area).

mod bundle;
mod estimator;
mod fuzz_decode;
mod fuzz_driver;
mod log_conformance;
mod log_python;
mod log_reader;
mod log_writer;
