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
//! the call's end (a helper's trial, sixty-second session). The call's
//! thread gets a cancellation flag (`dt_core::cancel`), set when the wait
//! ends with the signal: a run's loop over its samples (or a log's over
//! its messages) stops within a few milliseconds and its incomplete result
//! is dropped. The calls that work on every core (rayon) have no such point
//! and run to their end.

use std::panic::{catch_unwind, resume_unwind, AssertUnwindSafe};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc::{sync_channel, RecvTimeoutError};
use std::sync::Arc;
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
/// and asks the computation to stop (see the module doc). A panic in `f` is a panic here (pyo3's
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
    let cancel = Arc::new(AtomicBool::new(false));
    let flag = Arc::clone(&cancel);
    std::thread::Builder::new()
        .name("shocktwin-call".into())
        // the caller's thread it ran on before had the main thread's 8 MiB
        .stack_size(8 << 20)
        .spawn(move || {
            let result = dt_core::cancel::with_flag(flag, || catch_unwind(AssertUnwindSafe(f)));
            // the caller may be gone (interrupted): nothing to tell
            let _ = tx.send(result);
        })
        .map_err(|e| PyRuntimeError::new_err(format!("could not start the call's thread: {e}")))?;
    loop {
        let (got, back) = py.allow_threads(move || (rx.recv_timeout(SIGNAL_POLL), rx));
        rx = back;
        match got {
            Ok(Ok(value)) => return Ok(value),
            Ok(Err(panic)) => resume_unwind(panic),
            Err(RecvTimeoutError::Timeout) => {
                if let Err(signal) = py.check_signals() {
                    // stop the computation: nobody will read its result
                    cancel.store(true, Ordering::Relaxed);
                    return Err(signal);
                }
            }
            Err(RecvTimeoutError::Disconnected) => {
                return Err(PyRuntimeError::new_err(
                    "the call's thread ended without a result",
                ))
            }
        }
    }
}
