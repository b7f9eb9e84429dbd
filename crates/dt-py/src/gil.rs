//! The one place where the bindings release the GIL.
//!
//! Every call into dt-core that can take longer than a few microseconds per
//! element (reading a log, running the filter, integrating the thermal
//! model, the feature pipeline) goes through [`without_gil`], as polars'
//! `enter_polars` does. Inputs are copied out of numpy arrays into owned
//! Rust values first, so nothing borrowed from Python is touched while other
//! Python threads run.
//!
//! A call that can take seconds or minutes on a long run (reading a log,
//! the feature pipeline, the observer's reversals, an estimate, the road
//! observer) goes through [`interruptible`] instead: Ctrl-C in a notebook
//! raises `KeyboardInterrupt` within [`SIGNAL_POLL`], where it waited for
//! the call's end (a helper's trial, sixty-second session). dt-core has no
//! cancellation points, so the interrupted computation runs to its end on
//! its own thread and its result is dropped.

use std::panic::{catch_unwind, resume_unwind, AssertUnwindSafe};
use std::sync::mpsc::{sync_channel, RecvTimeoutError};
use std::time::Duration;

use pyo3::exceptions::PyRuntimeError;
use pyo3::marker::Ungil;
use pyo3::{PyResult, Python};

/// How often a waiting [`interruptible`] call looks for a signal.
pub(crate) const SIGNAL_POLL: Duration = Duration::from_millis(50);

/// Runs `f` with the GIL released and returns its result.
pub(crate) fn without_gil<T, F>(py: Python<'_>, f: F) -> T
where
    F: Ungil + FnOnce() -> T,
    T: Ungil,
{
    py.allow_threads(f)
}

/// Runs `f` on a thread of its own, the GIL released, and returns its
/// result; a signal meanwhile (Ctrl-C) returns its Python exception at once
/// (see the module doc). A panic in `f` is a panic here (pyo3's
/// `PanicException`).
///
/// # Errors
/// The signal handler's exception, or the thread could not be started.
pub(crate) fn interruptible<T, F>(py: Python<'_>, f: F) -> PyResult<T>
where
    F: FnOnce() -> T + Send + 'static,
    T: Send + 'static,
{
    let (tx, mut rx) = sync_channel(1);
    std::thread::Builder::new()
        .name("shocktwin-call".into())
        // the caller's thread it ran on before had the main thread's 8 MiB
        .stack_size(8 << 20)
        .spawn(move || {
            // the caller may be gone (interrupted): nothing to tell
            let _ = tx.send(catch_unwind(AssertUnwindSafe(f)));
        })
        .map_err(|e| PyRuntimeError::new_err(format!("could not start the call's thread: {e}")))?;
    loop {
        let (got, back) = py.allow_threads(move || (rx.recv_timeout(SIGNAL_POLL), rx));
        rx = back;
        match got {
            Ok(Ok(value)) => return Ok(value),
            Ok(Err(panic)) => resume_unwind(panic),
            Err(RecvTimeoutError::Timeout) => py.check_signals()?,
            Err(RecvTimeoutError::Disconnected) => {
                return Err(PyRuntimeError::new_err(
                    "the call's thread ended without a result",
                ))
            }
        }
    }
}
