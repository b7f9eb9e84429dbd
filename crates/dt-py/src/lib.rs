//! `dt-py`: the `shocktwin._native` extension module, a thin shell over
//! dt-core (numpy in and out, the GIL released for long calls).
//!
//! The public Python API is re-exported by `python/shocktwin/__init__.py`;
//! the stubs are `python/shocktwin/_native.pyi`.

// The `///` comments of #[pyfunction]s and #[pymethods] are the Python
// docstrings (with doctests), not rustdoc.
#![allow(clippy::doc_markdown, clippy::doc_link_with_quotes)]
// pyo3 extracts every argument by value.
#![allow(clippy::needless_pass_by_value)]

mod bundle;
mod convert;
mod exceptions;
mod features;
mod force;
mod gil;
mod kalman;
mod log;
mod params;
mod thermal;

use pyo3::prelude::*;

/// The native module behind the `shocktwin` package.
#[pymodule]
fn _native(m: &Bound<'_, PyModule>) -> PyResult<()> {
    // NumPy's C API, imported now rather than by the first call that returns
    // an array: a Ctrl-C pending then (the call had run without the GIL)
    // made that import fail, and rust-numpy panicked (`PanicException`, which
    // `except KeyboardInterrupt` does not catch) instead of the interrupt.
    m.py().import("numpy")?;
    let _ = numpy::PyArray1::<f64>::zeros(m.py(), [0], false);
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    m.add_class::<kalman::PyKalmanFilter>()?;
    m.add_class::<thermal::PyThermalModel>()?;
    m.add_class::<force::PyForceModel>()?;
    m.add_function(wrap_pyfunction!(params::default_params, m)?)?;
    m.add_function(wrap_pyfunction!(params::default_observer_params, m)?)?;
    m.add_class::<log::PyLog>()?;
    m.add_function(wrap_pyfunction!(log::read_log, m)?)?;
    m.add_function(wrap_pyfunction!(features::features, m)?)?;
    m.add_function(wrap_pyfunction!(features::charge_reversals, m)?)?;
    m.add_function(wrap_pyfunction!(features::road_blocks, m)?)?;
    m.add_function(wrap_pyfunction!(features::reversal_window, m)?)?;
    m.add_function(wrap_pyfunction!(features::reversal_windows, m)?)?;
    m.add_function(wrap_pyfunction!(features::twin_trace, m)?)?;
    m.add_function(wrap_pyfunction!(features::group_columns, m)?)?;
    m.add_function(wrap_pyfunction!(features::group_topics, m)?)?;
    m.add_function(wrap_pyfunction!(features::suite, m)?)?;
    m.add_function(wrap_pyfunction!(features::permutations, m)?)?;
    m.add_function(wrap_pyfunction!(features::extra_permutations, m)?)?;
    m.add_class::<bundle::PyBundle>()?;
    m.add("MLP_F32_PARITY_BAR", dt_core::bundle::MLP_F32_PARITY_BAR)?;
    m.add_function(wrap_pyfunction!(bundle::estimate, m)?)?;
    features::add_constants(m)?;
    Ok(())
}
