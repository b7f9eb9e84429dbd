//! `dt-py`: the `shocktwin._native` extension module, a thin shell over
//! dt-core (numpy in and out, the GIL released for long calls).
//!
//! The public Python API is re-exported by `python/shocktwin/__init__.py`;
//! the stubs are `python/shocktwin/_native.pyi`.

mod convert;
mod exceptions;
mod force;
mod gil;
mod kalman;
mod params;
mod thermal;

use pyo3::prelude::*;

/// The native module behind the `shocktwin` package.
#[pymodule]
fn _native(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    m.add_class::<kalman::PyKalmanFilter>()?;
    m.add_class::<thermal::PyThermalModel>()?;
    m.add_class::<force::PyForceModel>()?;
    m.add_function(wrap_pyfunction!(params::default_params, m)?)?;
    Ok(())
}
