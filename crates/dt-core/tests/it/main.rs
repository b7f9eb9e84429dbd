//! dt-core integration tests (one binary, modules per area).

mod log_writer;
