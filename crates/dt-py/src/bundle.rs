//! `shocktwin.Bundle` (a model bundle, SPEC §5) and `shocktwin.estimate`
//! (dt-core's streaming estimator over a whole log, SPEC §2 `/estimate`).

use std::path::PathBuf;
use std::sync::Arc;

use dt_core::bundle::{Bundle, BundleError};
use dt_core::error::PhysicsError;
use dt_core::estimator::{estimate_log, EstimatorConfig};
use dt_core::features::TopicSet;
use dt_core::log::RunLog;
use numpy::PyArray1;
use pyo3::exceptions::{PyRuntimeWarning, PyTypeError};
use pyo3::prelude::*;
use pyo3::types::{PyDict, PyString};

use crate::convert::{ns_to_seconds, to_numpy, ArrayLike2};
use crate::exceptions::{input_error, CoreError};
use crate::gil::{interruptible, without_gil};
use crate::log::{read_log, PyLog};
use crate::params::{json_to_py, physics_dict};

/// Loads a bundle directory with the GIL released.
pub(crate) fn load_bundle(py: Python<'_>, path: PathBuf) -> PyResult<Arc<Bundle>> {
    let bundle = without_gil(py, move || Bundle::load(&path)).map_err(CoreError::from)?;
    Ok(Arc::new(bundle))
}

/// A model bundle (SPEC §5): ``twin.json`` + ``mlp.onnx``, loaded and checked
/// by dt-core (the same code the daemon and ``shocktwin replay`` run).
///
/// ``Bundle(path)`` reads the directory ``path``. Every part is checked: the
/// format, the permutation's groups and their ordered columns, the
/// normalisation, the physics, the health thresholds, the network's input
/// and output names and ``onnx.sha256``. A part that is missing or does not
/// fit raises ``BundleError`` naming the file and the part
/// (``BundleNotFoundError``, also a ``FileNotFoundError``, for a missing
/// file). Immutable; cheap to share between threads.
///
/// >>> import shocktwin
/// >>> shocktwin.Bundle("no/such/bundle")
/// Traceback (most recent call last):
/// ...
/// shocktwin.exceptions.BundleNotFoundError: no/such/bundle/twin.json: No such file or directory (os error 2)
#[pyclass(module = "shocktwin._native", name = "Bundle", frozen)]
pub(crate) struct PyBundle {
    bundle: Arc<Bundle>,
    /// The directory's absolute path when the bundle was loaded (what it
    /// pickles as, whatever the working directory is by then).
    absolute: PathBuf,
}

impl PyBundle {
    /// The loaded bundle, shared without a copy.
    pub(crate) fn inner(&self) -> Arc<Bundle> {
        Arc::clone(&self.bundle)
    }

    /// Runs one of the bundle's prediction paths on the rows of `x`, checked
    /// against its width, with the GIL released.
    fn predict_with<'py>(
        &self,
        py: Python<'py>,
        x: &ArrayLike2<'py>,
        path: fn(&Bundle, &[f64]) -> Result<Vec<f64>, BundleError>,
    ) -> PyResult<Bound<'py, PyArray1<f64>>> {
        let rows = rows_of(&self.bundle, x)?;
        let bundle = self.inner();
        let out = without_gil(py, move || path(&bundle, &rows)).map_err(CoreError::from)?;
        Ok(to_numpy(py, out))
    }
}

/// Row-major values of a 2-D array of feature rows, checked against the
/// bundle's width.
fn rows_of(bundle: &Bundle, x: &ArrayLike2<'_>) -> PyResult<Vec<f64>> {
    let view = x.as_array();
    let k = bundle.n_inputs();
    if view.ncols() != k {
        return Err(input_error(format!(
            "`X` has {} columns but the bundle's permutation reads {k} ({})",
            view.ncols(),
            bundle.twin.permutation.columns.join(", ")
        )));
    }
    Ok(view.iter().copied().collect())
}

#[pymethods]
impl PyBundle {
    #[new]
    fn new(py: Python<'_>, path: PathBuf) -> PyResult<Self> {
        let absolute = std::path::absolute(&path).unwrap_or_else(|_| path.clone());
        Ok(Self {
            bundle: load_bundle(py, path)?,
            absolute,
        })
    }

    /// Charge pressure (bar) for raw, un-normalised feature rows ``X`` of
    /// shape ``(n, len(columns))`` (the columns of ``features`` for this
    /// bundle, in ``columns`` order): the bundle's normalisation, then the
    /// network (``backend``). A row with a NaN input gives NaN. Returns a
    /// float64 array of ``n`` values; the GIL is released meanwhile.
    fn predict<'py>(
        &self,
        py: Python<'py>,
        x: ArrayLike2<'py>,
    ) -> PyResult<Bound<'py, PyArray1<f64>>> {
        self.predict_with(py, &x, Bundle::predict)
    }

    /// ``predict`` in float64 throughout (the float64 dense path, or tract):
    /// what the float32 path is held to within ``MLP_F32_PARITY_BAR``.
    fn predict_f64<'py>(
        &self,
        py: Python<'py>,
        x: ArrayLike2<'py>,
    ) -> PyResult<Bound<'py, PyArray1<f64>>> {
        self.predict_with(py, &x, Bundle::predict_f64)
    }

    /// ``predict`` through tract-onnx's plan whatever ``backend`` is: the
    /// reference the dense path is checked against when the bundle loads.
    fn predict_reference<'py>(
        &self,
        py: Python<'py>,
        x: ArrayLike2<'py>,
    ) -> PyResult<Bound<'py, PyArray1<f64>>> {
        self.predict_with(py, &x, Bundle::predict_reference)
    }

    /// The bundle directory.
    #[getter]
    fn path(&self) -> String {
        self.bundle.dir.display().to_string()
    }

    /// The ordered feature columns the network reads.
    #[getter]
    fn columns(&self) -> Vec<String> {
        self.bundle.twin.permutation.columns.clone()
    }

    /// The permutation's input groups (SPEC §4 names).
    #[getter]
    fn groups(&self) -> Vec<String> {
        self.bundle.twin.permutation.groups.clone()
    }

    /// The permutation: ``{"id", "name", "groups", "columns"}`` (``id`` 0 for
    /// a custom suite).
    #[getter]
    fn permutation<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        let p = &self.bundle.twin.permutation;
        let d = PyDict::new(py);
        d.set_item("id", p.id)?;
        d.set_item("name", &p.name)?;
        d.set_item("groups", p.groups.clone())?;
        d.set_item("columns", p.columns.clone())?;
        Ok(d)
    }

    /// The physics parameters as the physics.json dict
    /// (``{"kalman": {...}, "thermal": {...}, "force": {...}}``).
    #[getter]
    fn physics<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        physics_dict(py, self.bundle.physics())
    }

    /// The asset model's nominal charge pressure (``expected_bar``), bar gauge.
    #[getter]
    fn nominal_bar(&self) -> f64 {
        self.bundle.twin.nominal_bar
    }

    /// Health thresholds (SPEC §6): ``warn_bar``, ``fault_bar``,
    /// ``hysteresis_bar``, ``dwell_s``, ``min_excitation_mps``.
    #[getter]
    fn health<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        let h = &self.bundle.twin.health;
        let d = PyDict::new(py);
        d.set_item("warn_bar", h.warn_bar)?;
        d.set_item("fault_bar", h.fault_bar)?;
        d.set_item("hysteresis_bar", h.hysteresis_bar)?;
        d.set_item("dwell_s", h.dwell_s)?;
        d.set_item("min_excitation_mps", h.min_excitation_mps)?;
        Ok(d)
    }

    /// The whole ``twin.json`` as read and checked (a fresh dict; provenance
    /// verbatim).
    #[getter]
    fn twin<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        let value = serde_json::to_value(&self.bundle.twin)
            .map_err(|e| PyTypeError::new_err(format!("twin.json: {e}")))?;
        json_to_py(py, &value)
    }

    /// Which evaluator runs the network: ``"dense"`` (an MLP read from the
    /// ONNX initializers, checked against tract at load) or ``"tract"``.
    #[getter]
    fn backend(&self) -> &'static str {
        self.bundle.backend()
    }

    /// The precision ``predict`` and ``estimate`` run the network in:
    /// ``"float32"`` (the dense path, within ``MLP_F32_PARITY_BAR`` of
    /// float64) or ``"float64"``.
    #[getter]
    fn precision(&self) -> &'static str {
        self.bundle.precision()
    }

    /// Pickled as the directory's absolute path when it was loaded:
    /// unpickling loads the bundle again, so a worker process
    /// (``multiprocessing``, ``concurrent.futures``, joblib) needs the same
    /// directory, unchanged. (Taken at pickling, a relative path named
    /// another directory after a ``chdir``: a helper's trial.)
    fn __reduce__<'py>(slf: &Bound<'py, Self>) -> (Bound<'py, pyo3::types::PyType>, (PathBuf,)) {
        (slf.get_type(), (slf.get().absolute.clone(),))
    }

    fn __repr__(&self) -> String {
        let p = &self.bundle.twin.permutation;
        format!(
            "<shocktwin.Bundle {} permutation={} ({:?}) columns={} backend={}>",
            self.bundle.dir.display(),
            p.id,
            p.name,
            p.columns.len(),
            self.bundle.backend()
        )
    }
}

/// A `Log` or a `Bundle` given as the object itself or as a path; paths are
/// resolved only after every argument's type has been checked.
enum Given<T> {
    Object(T),
    Path(PathBuf),
}

/// A `Log` or a path to a run log.
fn log_arg(log: &Bound<'_, PyAny>) -> PyResult<Given<Arc<RunLog>>> {
    if let Ok(log) = log.downcast::<PyLog>() {
        Ok(Given::Object(log.get().run_log()))
    } else if log.is_instance_of::<PyString>() || log.hasattr("__fspath__")? {
        Ok(Given::Path(log.extract()?))
    } else {
        Err(PyTypeError::new_err(format!(
            "log: expected a shocktwin.Log or a path, got {}",
            log.get_type().name()?
        )))
    }
}

/// A `Bundle` or a path to a bundle directory.
fn bundle_arg(bundle: &Bound<'_, PyAny>) -> PyResult<Given<Arc<Bundle>>> {
    if let Ok(b) = bundle.downcast::<PyBundle>() {
        Ok(Given::Object(b.get().inner()))
    } else if bundle.is_instance_of::<PyString>() || bundle.hasattr("__fspath__")? {
        Ok(Given::Path(bundle.extract()?))
    } else {
        Err(PyTypeError::new_err(format!(
            "bundle: expected a shocktwin.Bundle or a path, got {}",
            bundle.get_type().name()?
        )))
    }
}

/// Runs dt-core's streaming estimator (the daemon's and ``replay``'s code:
/// re-order window, 50 Hz pipeline, network, 1 s average, health state
/// machine) over a whole run log; the GIL is released meanwhile.
///
/// ``log`` is a ``Log`` or a path to a run log; ``bundle`` a ``Bundle`` or a
/// path to a bundle directory. The estimator is configured from the bundle
/// (its nominal pressure and health thresholds, a 100 ms re-order window, a
/// new segment after a 2 s gap). ``observer_baseline`` (a dict with
/// ``charge_bar``, ``read_bar``, ``read_sd_bar`` and optionally the unit's
/// own ``damping_law``, a ``second`` reading and ``runs_averaged``, as ``python -m train.observer baseline [--unit-law]``
/// writes under that key; the whole document it writes is taken too, as a
/// dict, as JSON text or as the path of that file) is this unit's
/// charge-observer baseline, for a bundle that reads the observer.
///
/// Returns a dict of equal-length arrays, one element per 50 Hz tick:
/// ``t_s`` (seconds since the run's first message), ``pressure_bar``,
/// ``pressure_avg_bar`` (1 s average), ``pressure_lo_bar`` and
/// ``pressure_hi_bar`` (central 95 % interval: NaN without the charge
/// observer and without the bundle's held-out interval, or while there is
/// no 1 s average for the latter), ``expected_bar``, ``velocity_mps``,
/// ``force_model_n``, ``oil_temp_c`` (float64, NaN where the estimator has
/// no value) and ``health`` (str: ``ok``, ``low``, ``leak``, ``unknown``).
/// Raises ``MissingTopicsError`` when the log lacks a topic the bundle's
/// groups need. Warns (``RuntimeWarning``) when the charge observer read
/// none of the run's reversals, saying why (the calibration does not cover
/// its excitation; reversals too weak, e.g. a 0.5 Hz sine, or too poor to
/// read): the estimate is then the observer's prior. Warns too when the
/// bundle, without the observer, records the excitations its network was
/// trained on and the log's ``excitation`` metadata is none of them (a road
/// run, a sine at another frequency): the estimate is an extrapolation.
///
/// >>> import shocktwin
/// >>> shocktwin.estimate("no/such/run.mcap", "no/such/bundle")
/// Traceback (most recent call last):
/// ...
/// shocktwin.exceptions.LogReadError: no/such/run.mcap: No such file or directory (os error 2)
#[pyfunction]
#[pyo3(signature = (log, bundle, *, observer_baseline = None))]
pub(crate) fn estimate<'py>(
    py: Python<'py>,
    log: &Bound<'py, PyAny>,
    bundle: &Bound<'py, PyAny>,
    observer_baseline: Option<&Bound<'py, PyAny>>,
) -> PyResult<Bound<'py, PyDict>> {
    let (log, bundle) = (log_arg(log)?, bundle_arg(bundle)?);
    let run = match log {
        Given::Object(run) => run,
        Given::Path(path) => read_log(py, path)?.run_log(),
    };
    let bundle = match bundle {
        Given::Object(bundle) => bundle,
        Given::Path(path) => load_bundle(py, path)?,
    };
    // A whole log that lacks a topic the bundle needs is an error here, as
    // in `features` (a live stream cannot know; it gives NaN pressures).
    let missing = TopicSet::from_log(&run).missing_for(&bundle.groups);
    if !missing.is_empty() {
        return Err(CoreError::from(PhysicsError::MissingTopics {
            run_id: run.metadata.run_id.clone(),
            missing: missing.into_iter().map(str::to_owned).collect(),
            groups: bundle.twin.permutation.groups.clone(),
        })
        .into());
    }
    let mut cfg = EstimatorConfig::from_bundle(&bundle);
    if let Some(obj) = observer_baseline {
        let what = "observer_baseline";
        if !bundle.groups.contains(&dt_core::features::Group::Observer) {
            return Err(CoreError::Params(format!(
                "{what}: the bundle does not read the charge observer (no `observer` group)"
            ))
            .into());
        }
        // as `train.observer baseline` writes it (nested) or bare, as the
        // daemon's API takes it; the error names the field (it said
        // "invalid physics parameters")
        // a dict, or the path of the file `train.observer baseline` wrote
        // (`road_blocks` took a path; this said "invalid type: string")
        let text = obj
            .extract::<String>()
            .ok()
            .filter(|t| t.trim_start().starts_with('{'));
        let (what, doc) = if let Some(text) = text {
            // JSON text, as `road_blocks` takes its calibration (a review)
            let doc = serde_json::from_str(&text)
                .map_err(|e| CoreError::Params(format!("{what}: not JSON: {e}")))?;
            (what.to_owned(), doc)
        } else if obj.is_instance_of::<pyo3::types::PyDict>() {
            (what.to_owned(), crate::params::py_to_json(obj, what)?)
        } else if let Ok(path) = obj.extract::<std::path::PathBuf>() {
            let file = format!("{what} {}", path.display());
            let text = std::fs::read_to_string(&path)
                .map_err(|e| crate::exceptions::io_error(&file, &e))?;
            let doc = serde_json::from_str(&text)
                .map_err(|e| CoreError::Params(format!("{file}: not JSON: {e}")))?;
            (file, doc)
        } else {
            (what.to_owned(), crate::params::py_to_json(obj, what)?)
        };
        let b = dt_core::charge::UnitBaseline::from_document(doc)
            .map_err(|e| CoreError::Params(format!("{what}: {e}")))?;
        cfg.observer_baseline = Some(b);
    }
    let untrained = bundle.untrained_excitation(&run.metadata);
    let origin_ns = run.t0_ns().unwrap_or(0);
    let (estimates, counters) =
        interruptible(py, move || estimate_log(bundle, cfg, &run))?.map_err(CoreError::from)?;
    if let Some(why) = counters.observer.why_prior_kept() {
        // `shocktwin replay` says so; a notebook got the prior without a word
        let msg = std::ffi::CString::new(format!("charge observer: {why}")).unwrap_or_default();
        PyErr::warn(py, &py.get_type::<PyRuntimeWarning>(), &msg, 1)?;
    }
    if let Some(why) = untrained {
        let msg = std::ffi::CString::new(why).unwrap_or_default();
        PyErr::warn(py, &py.get_type::<PyRuntimeWarning>(), &msg, 1)?;
    }
    let column = |f: fn(&dt_core::estimate::Estimate) -> f64| -> Vec<f64> {
        estimates.iter().map(f).collect()
    };
    let out = PyDict::new(py);
    let t_ns: Vec<i64> = estimates.iter().map(|e| e.t_ns).collect();
    out.set_item("t_s", to_numpy(py, ns_to_seconds(&t_ns, origin_ns)))?;
    out.set_item("pressure_bar", to_numpy(py, column(|e| e.pressure_bar)))?;
    out.set_item(
        "pressure_avg_bar",
        to_numpy(py, column(|e| e.pressure_avg_bar)),
    )?;
    out.set_item(
        "pressure_lo_bar",
        to_numpy(py, column(|e| e.pressure_lo_bar)),
    )?;
    out.set_item(
        "pressure_hi_bar",
        to_numpy(py, column(|e| e.pressure_hi_bar)),
    )?;
    out.set_item("expected_bar", to_numpy(py, column(|e| e.expected_bar)))?;
    let health: Vec<&str> = estimates.iter().map(|e| e.health.as_str()).collect();
    let numpy = py.import("numpy")?;
    out.set_item(
        "health",
        numpy.call_method1("asarray", (health, numpy.getattr("str_")?))?,
    )?;
    out.set_item("velocity_mps", to_numpy(py, column(|e| e.velocity_mps)))?;
    out.set_item("force_model_n", to_numpy(py, column(|e| e.force_model_n)))?;
    out.set_item("oil_temp_c", to_numpy(py, column(|e| e.oil_temp_c)))?;
    Ok(out)
}
