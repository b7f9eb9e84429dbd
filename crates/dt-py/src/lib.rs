//! `dt-py`: the `shocktwin._native` extension module; a thin shell over dt-core.
use pyo3::prelude::*;

/// The native module behind the `shocktwin` package.
#[pymodule]
fn _native(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    Ok(())
}
