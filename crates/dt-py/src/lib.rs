//! `dt-py`: the `shocktwin._native` extension module, a thin shell over
//! dt-core (numpy in and out, the GIL released for long calls).
//!
//! The public Python API is re-exported by `python/shocktwin/__init__.py`;
//! the stubs are `python/shocktwin/_native.pyi`.

mod convert;
mod exceptions;
mod gil;
mod kalman;

use pyo3::prelude::*;

/// The native module behind the `shocktwin` package.
#[pymodule]
fn _native(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    m.add_class::<kalman::PyKalmanFilter>()?;
    Ok(())
}
