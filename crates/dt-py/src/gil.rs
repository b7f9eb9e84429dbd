//! The one place where the bindings release the GIL.
//!
//! Every call into dt-core that can take longer than a few microseconds per
//! element (reading a log, running the filter, integrating the thermal
//! model, the feature pipeline) goes through [`without_gil`], as polars'
//! `enter_polars` does. Inputs are copied out of numpy arrays into owned
//! Rust values first, so nothing borrowed from Python is touched while other
//! Python threads run.

use pyo3::marker::Ungil;
use pyo3::Python;

/// Runs `f` with the GIL released and returns its result.
pub(crate) fn without_gil<T, F>(py: Python<'_>, f: F) -> T
where
    F: Ungil + FnOnce() -> T,
    T: Ungil,
{
    py.allow_threads(f)
}
