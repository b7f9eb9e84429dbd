//! numpy in, numpy out: conversions shared by every binding.

use numpy::{AllowTypeChange, IntoPyArray, PyArray1, PyArrayLike1};
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;

/// Any 1-D array-like of numbers (a numpy array of any real dtype, a list,
/// a tuple), converted to float64 by numpy.
pub(crate) type ArrayLike<'py> = PyArrayLike1<'py, f64, AllowTypeChange>;

/// Copies a 1-D array-like into an owned vector (any strides).
pub(crate) fn to_vec(array: &ArrayLike<'_>) -> Vec<f64> {
    array.as_array().to_vec()
}

/// Checks that every named array has the length of the first one.
pub(crate) fn check_same_len(arrays: &[(&str, usize)]) -> PyResult<()> {
    let Some(&(first_name, first_len)) = arrays.first() else {
        return Ok(());
    };
    for &(name, len) in &arrays[1..] {
        if len != first_len {
            return Err(PyValueError::new_err(format!(
                "`{name}` has {len} elements but `{first_name}` has {first_len}; they must be equal"
            )));
        }
    }
    Ok(())
}

/// Moves a vector into a new float64 numpy array (no copy).
pub(crate) fn to_numpy(py: Python<'_>, values: Vec<f64>) -> Bound<'_, PyArray1<f64>> {
    values.into_pyarray(py)
}
