//! dt-core integration tests (one binary, modules per area).

mod log_conformance;
mod log_python;
mod log_reader;
mod log_writer;
mod bundle;
mod estimator;
