//! numpy in, numpy out: conversions shared by every binding.

use numpy::{AllowTypeChange, IntoPyArray, PyArray1, PyArrayLike1};
use pyo3::prelude::*;

use crate::exceptions::input_error;

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
