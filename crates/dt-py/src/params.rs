//! Physics parameters between Python and dt-core: `default_params()`, the
//! `physics.json` structure as a dict, and dicts as parameters.
//!
//! The dict form is exactly the JSON form of `dt_core::params::PhysicsParams`
//! (`{"kalman": {...}, "thermal": {...}, "force": {...}}`, SPEC names), so
//! a `physics.json` loaded with `json.load` can be passed as it is.

use std::path::Path;

use dt_core::params::{ForceParams, PhysicsParams};
use pyo3::exceptions::PyTypeError;
use pyo3::prelude::*;
use pyo3::types::{PyBool, PyDict, PyList, PyString, PyTuple};
use serde_json::{Map, Number, Value};

use crate::exceptions::CoreError;

/// The SPEC §3 parameter priors of dt-core, as a fresh dict
/// ``{"kalman": {...}, "thermal": {...}, "force": {...}}`` (the
/// physics.json structure that ``features`` takes).
///
/// >>> import shocktwin
/// >>> params = shocktwin.default_params()
/// >>> sorted(params), params["force"]["charge_bar"]
/// (['force', 'kalman', 'thermal'], 12.0)
/// >>> shocktwin.ForceModel(**params["force"]).params == params["force"]
/// True
#[pyfunction]
pub(crate) fn default_params(py: Python<'_>) -> PyResult<Bound<'_, PyDict>> {
    physics_dict(py, &PhysicsParams::default())
}

/// The gas-charge observer's default parameters (the ``observer`` section of
/// a physics.json, SPEC §3 v2): the documented rig, an ADXL345-class filter,
/// the datasheet geometry of the simulated damper and an uncalibrated
/// measurement model (``step_per_bar_n`` 0: the observer keeps its prior).
/// ``python -m train.observer fit`` calibrates it.
#[pyfunction]
pub(crate) fn default_observer_params(py: Python<'_>) -> PyResult<Bound<'_, PyDict>> {
    to_dict(py, &dt_core::charge::ObserverParams::default())
}

/// `params` as the physics.json dict.
pub(crate) fn physics_dict<'py>(
    py: Python<'py>,
    params: &PhysicsParams,
) -> PyResult<Bound<'py, PyDict>> {
    to_dict(py, params)
}

/// The `force` part of the physics.json dict.
pub(crate) fn force_dict<'py>(
    py: Python<'py>,
    params: &ForceParams,
) -> PyResult<Bound<'py, PyDict>> {
    to_dict(py, params)
}

fn to_dict<'py, T: serde::Serialize>(py: Python<'py>, value: &T) -> PyResult<Bound<'py, PyDict>> {
    let value = serde_json::to_value(value).map_err(|err| CoreError::params("parameters", &err))?;
    Ok(json_to_py(py, &value)?.downcast_into::<PyDict>()?)
}

/// Parses and validates physics parameters from a dict of the physics.json
/// structure; `what` names the source in errors.
pub(crate) fn physics_from_dict(what: &str, obj: &Bound<'_, PyAny>) -> PyResult<PhysicsParams> {
    physics_from_value(what, py_to_json(obj, what)?)
}

/// Reads and validates the physics parameters of a physics.json file.
pub(crate) fn physics_from_file(path: &Path) -> PyResult<PhysicsParams> {
    let what = path.display().to_string();
    let text = std::fs::read_to_string(path).map_err(|source| CoreError::Io {
        file: what.clone(),
        source,
    })?;
    let value: Value = serde_json::from_str(&text).map_err(|err| CoreError::params(&what, &err))?;
    physics_from_value(&what, value)
}

/// The `kalman`, `thermal`, `force` and optional `observer` parts of a physics.json value (other
/// top-level keys, such as `format` or `fit`, are ignored; inside each part
/// every SPEC parameter is required and no other is allowed), validated.
fn physics_from_value(what: &str, value: Value) -> PyResult<PhysicsParams> {
    let Value::Object(mut map) = value else {
        return Err(CoreError::Params(format!("{what}: expected a JSON object / dict")).into());
    };
    let parts: Map<String, Value> = ["kalman", "thermal", "force", "observer"]
        .into_iter()
        .filter_map(|k| map.remove(k).map(|v| (k.to_owned(), v)))
        .collect();
    // serde_path_to_error: a wrong value deep in the observer's damping law
    // is named by its path (`observer.damping_law.dry_nspm`), not only its type.
    let params: PhysicsParams = serde_path_to_error::deserialize(Value::Object(parts))
        .map_err(|err| CoreError::params_at(what, &err))?;
    params.validate().map_err(CoreError::from)?;
    Ok(params)
}

pub(crate) fn json_to_py<'py>(py: Python<'py>, value: &Value) -> PyResult<Bound<'py, PyAny>> {
    Ok(match value {
        Value::Null => py.None().into_bound(py),
        Value::Bool(b) => PyBool::new(py, *b).to_owned().into_any(),
        Value::Number(n) => match (n.as_i64(), n.as_f64()) {
            (Some(i), _) => i.into_pyobject(py)?.into_any(),
            (None, Some(f)) => f.into_pyobject(py)?.into_any(),
            (None, None) => return Err(PyTypeError::new_err(format!("number {n} out of range"))),
        },
        Value::String(s) => PyString::new(py, s).into_any(),
        Value::Array(items) => {
            let items = items
                .iter()
                .map(|v| json_to_py(py, v))
                .collect::<PyResult<Vec<_>>>()?;
            PyList::new(py, items)?.into_any()
        }
        Value::Object(map) => {
            let dict = PyDict::new(py);
            for (k, v) in map {
                dict.set_item(k, json_to_py(py, v)?)?;
            }
            dict.into_any()
        }
    })
}

/// A Python value of JSON shape (dict with str keys, list/tuple, str, bool,
/// None, or anything `float()` accepts) as JSON; `at` is its path for errors.
pub(crate) fn py_to_json(obj: &Bound<'_, PyAny>, at: &str) -> PyResult<Value> {
    if obj.is_none() {
        return Ok(Value::Null);
    }
    if let Ok(b) = obj.downcast::<PyBool>() {
        return Ok(Value::Bool(b.is_true()));
    }
    if let Ok(dict) = obj.downcast::<PyDict>() {
        let mut map = Map::new();
        for (k, v) in dict.iter() {
            let key: String = k
                .extract()
                .map_err(|_| PyTypeError::new_err(format!("{at}: keys must be str, got {k:?}")))?;
            let value = py_to_json(&v, &format!("{at}.{key}"))?;
            map.insert(key, value);
        }
        return Ok(Value::Object(map));
    }
    if let Ok(s) = obj.downcast::<PyString>() {
        return Ok(Value::String(s.to_cow()?.into_owned()));
    }
    if obj.is_instance_of::<PyList>() || obj.is_instance_of::<PyTuple>() {
        return obj
            .try_iter()?
            .enumerate()
            .map(|(i, item)| py_to_json(&item?, &format!("{at}[{i}]")))
            .collect::<PyResult<Vec<_>>>()
            .map(Value::Array);
    }
    let x: f64 = obj.extract().map_err(|_| {
        PyTypeError::new_err(format!(
            "{at}: expected a number, str, list or dict, got {}",
            obj.get_type()
                .name()
                .map_or_else(|_| "?".into(), |n| n.to_string())
        ))
    })?;
    Number::from_f64(x)
        .map(Value::Number)
        .ok_or_else(|| CoreError::Params(format!("{at} = {x}: must be finite")).into())
}
