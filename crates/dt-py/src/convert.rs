//! numpy in, numpy out: conversions shared by every binding.

use std::ops::Deref;

use numpy::{AllowTypeChange, IntoPyArray, PyArray1, PyArrayLike1, PyArrayLike2};
use pyo3::exceptions::{PyTypeError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::PyTuple;

use crate::exceptions::input_error;

/// Any 1-D array-like of numbers (a numpy array of any real dtype, a list,
/// a tuple), converted to float64 by numpy. Anything else is a `TypeError`
/// that says what was given: numpy's own says only that an `ndarray` "cannot
/// be converted to `PyArray<T, D>`" (the seventieth session's analyst).
pub(crate) struct ArrayLike<'py>(PyArrayLike1<'py, f64, AllowTypeChange>);

/// Any 2-D array-like of numbers (rows of samples), converted to float64;
/// anything else is a `TypeError` that says what was given, as [`ArrayLike`].
pub(crate) struct ArrayLike2<'py>(PyArrayLike2<'py, f64, AllowTypeChange>);

impl<'py> Deref for ArrayLike<'py> {
    type Target = PyArrayLike1<'py, f64, AllowTypeChange>;
    fn deref(&self) -> &Self::Target {
        &self.0
    }
}

impl<'py> Deref for ArrayLike2<'py> {
    type Target = PyArrayLike2<'py, f64, AllowTypeChange>;
    fn deref(&self) -> &Self::Target {
        &self.0
    }
}

impl<'py> FromPyObject<'py> for ArrayLike<'py> {
    fn extract_bound(ob: &Bound<'py, PyAny>) -> PyResult<Self> {
        ob.extract().map(Self).map_err(|e| what_was_given(ob, 1, e))
    }
}

impl<'py> FromPyObject<'py> for ArrayLike2<'py> {
    fn extract_bound(ob: &Bound<'py, PyAny>) -> PyResult<Self> {
        ob.extract().map(Self).map_err(|e| what_was_given(ob, 2, e))
    }
}

/// The error for `ob`, which did not convert to a float64 array of `ndim`
/// dimensions with error `err`: a `TypeError` saying its shape or its dtype,
/// and what to pass instead (pyo3 prefixes the argument's name). `err`
/// itself when it is not a type or value error (an interrupt, memory), or
/// when numpy cannot even say.
fn what_was_given(ob: &Bound<'_, PyAny>, ndim: usize, err: PyErr) -> PyErr {
    let py = ob.py();
    if !(err.is_instance_of::<PyTypeError>(py) || err.is_instance_of::<PyValueError>(py)) {
        return err;
    }
    described(ob, ndim).unwrap_or(err)
}

fn described(ob: &Bound<'_, PyAny>, ndim: usize) -> Option<PyErr> {
    let numpy = ob.py().import("numpy").ok()?;
    let array = numpy.call_method1("asarray", (ob,)).ok()?;
    let shape: Vec<usize> = array.getattr("shape").ok()?.extract().ok()?;
    let shape_text = PyTuple::new(ob.py(), &shape).ok()?.repr().ok()?.to_string();
    let wanted = if ndim == 1 {
        "a 1-D array of numbers (one value per sample)"
    } else {
        "a 2-D array of numbers (one row per sample, one column per feature)"
    };
    let dtype = array.getattr("dtype").ok()?;
    let numeric = "biuf".contains(&*dtype.getattr("kind").ok()?.extract::<String>().ok()?);
    let message = if shape.len() == ndim || !numeric {
        let kind = if shape.is_empty() {
            format!("a `{}`", ob.get_type().name().ok()?)
        } else {
            format!("an array of dtype `{}`", dtype.str().ok()?)
        };
        format!("expected {wanted}, got {kind}, which is not a real number type")
    } else {
        let hint = match (ndim, shape.len()) {
            (1, 0) => ": pass a single sample as a list of one value",
            (2, 1) => ": pass one sample as one row, e.g. `x.reshape(1, -1)`",
            _ => "",
        };
        format!(
            "expected {wanted}, got a {}-D value of shape {shape_text}{hint}",
            shape.len()
        )
    };
    Some(PyTypeError::new_err(message))
}

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
            return Err(input_error(format!(
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

/// Nanoseconds per second.
const NS_PER_S: f64 = 1.0e9;

/// Converts a time axis in seconds (Python) to the core's nanoseconds,
/// rounding to the nearest nanosecond. A non-finite or out-of-range time is
/// an error naming the input and index.
pub(crate) fn seconds_to_ns(name: &str, t_s: &[f64]) -> PyResult<Vec<i64>> {
    // ±2^62 ns ≈ ±146 years: far inside i64 and exactly representable bounds.
    const LIMIT_NS: f64 = 4.611_686_018_427_388e18;
    t_s.iter()
        .enumerate()
        .map(|(i, &t)| {
            let t_ns = (t * NS_PER_S).round();
            if t_ns.is_finite() && t_ns.abs() < LIMIT_NS {
                Ok(t_ns as i64)
            } else {
                Err(input_error(format!(
                    "`{name}`[{i}] = {t} s is not a finite time within ±146 years"
                )))
            }
        })
        .collect()
}

/// Converts nanoseconds relative to `origin_ns` to seconds.
pub(crate) fn ns_to_seconds(t_ns: &[i64], origin_ns: i64) -> Vec<f64> {
    t_ns.iter()
        .map(|&t| (t - origin_ns) as f64 / NS_PER_S)
        .collect()
}
