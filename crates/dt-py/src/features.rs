//! `shocktwin.features` and the input-group tables of SPEC §4 (groups,
//! columns, topics, sensors and their costs, the paper's permutations).

use std::path::PathBuf;

use dt_core::bundle::Bundle;
use dt_core::features::{
    compute_features, compute_reversals, compute_twin, paper_permutations, paper_rmse_bar,
    suite_cost_aud, suite_sensors, Group, Permutation, Sensor, COLUMNS,
};
use dt_core::params::PhysicsParams;
use numpy::ndarray::Array2;
use numpy::{IntoPyArray, PyArray1, PyArray2};
use pyo3::exceptions::PyTypeError;
use pyo3::prelude::*;
use pyo3::types::{PyDict, PyString};

use crate::bundle::PyBundle;
use crate::convert::{ns_to_seconds, to_numpy};
use crate::exceptions::{input_error, CoreError};
use crate::gil::{interruptible, without_gil};
use crate::log::{read_log, PyLog};
use crate::params::{physics_from_dict, physics_from_file};

fn groups_from_names(names: &[String]) -> PyResult<Vec<Group>> {
    names
        .iter()
        .map(|n| Group::from_name(n).map_err(|e| CoreError::from(e).into()))
        .collect()
}

fn group(name: &str) -> PyResult<Group> {
    Group::from_name(name).map_err(|e| CoreError::from(e).into())
}

/// Physics parameters (and, from a bundle, its groups) from a dict (the
/// physics.json structure), a path to a physics.json file, or a model bundle
/// directory (loaded and checked by dt-core, network included).
fn physics_from(obj: &Bound<'_, PyAny>) -> PyResult<(PhysicsParams, Option<Vec<Group>>)> {
    if obj.is_instance_of::<PyDict>() {
        return Ok((physics_from_dict("parameters", obj)?, None));
    }
    if let Ok(bundle) = obj.downcast::<PyBundle>() {
        let bundle = bundle.get().inner();
        return Ok((*bundle.physics(), Some(bundle.groups.clone())));
    }
    if obj.is_instance_of::<PyString>() || obj.hasattr("__fspath__")? {
        let path: PathBuf = obj.extract()?;
        if path.is_dir() {
            let bundle =
                without_gil(obj.py(), move || Bundle::load(&path)).map_err(CoreError::from)?;
            return Ok((*bundle.physics(), Some(bundle.groups)));
        }
        return Ok((physics_from_file(&path)?, None));
    }
    Err(PyTypeError::new_err(format!(
        "bundle_or_params: expected a dict of physics parameters, a shocktwin.Bundle or a path, got {}",
        obj.get_type().name()?
    )))
}

/// The 50 Hz feature table of a run (SPEC §4), computed by the same
/// pipeline the streaming estimator runs; the GIL is released meanwhile.
///
/// ``log`` is a ``Log`` (from ``read_log``) or a path to a run log.
/// ``bundle_or_params`` is a dict of the physics.json structure
/// (``{"kalman": {...}, "thermal": {...}, "force": {...}}``; other top-level
/// keys are ignored), a path to a physics.json, a ``Bundle`` or a model
/// bundle directory (SPEC §5; loaded and checked in full). ``groups`` is a list of input
/// group names (see ``GROUPS``); with a bundle it may be left out (``None``)
/// for the bundle's own permutation.
///
/// Returns ``(X, columns, t_s)``: ``X`` float64 of shape
/// ``(n_ticks, len(columns))``, the columns of ``groups`` in the order
/// given (see ``group_columns``), and the tick times, seconds since the
/// run's first message (20 ms apart). Raises ``MissingTopicsError``
/// (its ``.topics`` lists them) when the log lacks a topic a group needs.
///
/// >>> import shocktwin
/// >>> shocktwin.group_columns("mechanical")
/// ['force_model_n', 'force_damping_model_n', 'force_gas_model_n']
#[pyfunction]
#[pyo3(signature = (log, bundle_or_params, groups = None))]
#[allow(clippy::type_complexity)]
pub(crate) fn features<'py>(
    py: Python<'py>,
    log: &Bound<'py, PyAny>,
    bundle_or_params: &Bound<'py, PyAny>,
    groups: Option<Vec<String>>,
) -> PyResult<(
    Bound<'py, PyArray2<f64>>,
    Vec<String>,
    Bound<'py, PyArray1<f64>>,
)> {
    let (params, bundle_groups) = physics_from(bundle_or_params)?;
    let groups = match (groups, bundle_groups) {
        (Some(names), _) => groups_from_names(&names)?,
        (None, Some(groups)) => groups,
        (None, None) => {
            return Err(PyTypeError::new_err(
                "features: `groups` is required unless `bundle_or_params` is a model bundle",
            ))
        }
    };
    let run = run_from(py, log)?;
    let table = interruptible(py, move || compute_features(&run, &params, &groups))?
        .map_err(CoreError::from)?;
    let shape = (table.n_rows(), table.columns.len());
    let x = Array2::from_shape_vec(shape, table.values)
        .expect("dt-core returns n_rows × n_columns values");
    let t_s = ns_to_seconds(&table.t_ns, table.t_origin_ns);
    Ok((x.into_pyarray(py), table.columns, to_numpy(py, t_s)))
}

/// The gas-charge observer's fitted reversals over a run, one entry per
/// fitted velocity reversal (for calibrating the observer's measurement
/// model and for analysis); the GIL is released meanwhile.
///
/// ``log`` and ``bundle_or_params`` as in ``features``; the physics'
/// ``observer`` section (or its defaults) configures the fit. Returns a dict
/// of float64 arrays: ``t_s`` (reversal time, s since the run's first
/// message), ``accel_mps2`` (velocity slope across it), ``spacing_s`` (time
/// since the previous reversal the detector saw, NaN for the first),
/// ``extension_m``,
/// ``gas_temp_c``, ``alpha_n`` (fitted friction amplitude), ``damping_ext_nspm``,
/// ``damping_comp_nspm``, ``shift_s``, ``residual_mps2``, ``alpha_sd_n`` (the
/// window fit's own sd of ``alpha_n``), ``samples``,
/// ``a_n``, ``b_n_per_bar`` (the measurement model ``alpha = a + b p``) and
/// ``used`` (1.0 when the update took it), plus the counts ``detected``,
/// ``skipped``, ``rejected``, ``spared`` (not fitted: the evidence was
/// enough, ``observer.fit_gain_floor``) and ``uncalibrated`` (at an excitation
/// the calibration does not cover, so not read), and ``rod_accel_scale`` (the
/// run's accelerometer scale against the potentiometer, NaN before enough
/// reversals: ``observer.rod_accel_scale``) and ``ends_split_bar`` (the
/// stroke's ends apart at the end of the run, ``m₊ − m₋`` in bar, NaN without
/// ``observer.stroke_ends`` or before each end has read a reversal: what a
/// baseline records as ``split_bar``). Raises ``MissingTopicsError`` when the log lacks
/// a topic the observer needs.
#[pyfunction]
pub(crate) fn charge_reversals<'py>(
    py: Python<'py>,
    log: &Bound<'py, PyAny>,
    bundle_or_params: &Bound<'py, PyAny>,
) -> PyResult<Bound<'py, PyDict>> {
    let (params, _) = physics_from(bundle_or_params)?;
    let run = run_from(py, log)?;
    let origin = run
        .samples_sorted()
        .first()
        .map_or(0, dt_core::log::Sample::t_ns);
    let dt_core::features::RunReversals {
        reversals: revs,
        counters,
        rod_accel_scale: rod_scale,
        ends_split_bar,
    } = interruptible(py, move || compute_reversals(&run, &params))?.map_err(CoreError::from)?;
    let out = PyDict::new(py);
    let col = |f: &dyn Fn(&dt_core::charge::Reversal) -> f64| -> Vec<f64> {
        revs.iter().map(f).collect()
    };
    out.set_item(
        "t_s",
        to_numpy(py, col(&|r| (r.t_ns - origin) as f64 * 1e-9)),
    )?;
    out.set_item("accel_mps2", to_numpy(py, col(&|r| r.accel_mps2)))?;
    out.set_item("spacing_s", to_numpy(py, col(&|r| r.spacing_s)))?;
    out.set_item("extension_m", to_numpy(py, col(&|r| r.extension_m)))?;
    out.set_item("gas_temp_c", to_numpy(py, col(&|r| r.gas_temp_c)))?;
    out.set_item("alpha_n", to_numpy(py, col(&|r| r.alpha_n)))?;
    out.set_item(
        "damping_ext_nspm",
        to_numpy(py, col(&|r| r.damping_ext_nspm)),
    )?;
    out.set_item(
        "damping_comp_nspm",
        to_numpy(py, col(&|r| r.damping_comp_nspm)),
    )?;
    out.set_item("shift_s", to_numpy(py, col(&|r| r.shift_s)))?;
    out.set_item("residual_mps2", to_numpy(py, col(&|r| r.residual_mps2)))?;
    out.set_item("alpha_sd_n", to_numpy(py, col(&|r| r.alpha_sd_n)))?;
    out.set_item("samples", to_numpy(py, col(&|r| r.samples as f64)))?;
    out.set_item("a_n", to_numpy(py, col(&|r| r.a_n)))?;
    out.set_item("b_n_per_bar", to_numpy(py, col(&|r| r.b_n_per_bar)))?;
    out.set_item("used", to_numpy(py, col(&|r| f64::from(u8::from(r.used)))))?;
    out.set_item("detected", counters.detected)?;
    out.set_item("skipped", counters.skipped)?;
    out.set_item("rejected", counters.rejected)?;
    out.set_item("spared", counters.spared)?;
    out.set_item("uncalibrated", counters.uncalibrated)?;
    out.set_item("rod_accel_scale", rod_scale.unwrap_or(f64::NAN))?;
    out.set_item("ends_split_bar", ends_split_bar.unwrap_or(f64::NAN))?;
    Ok(out)
}

/// The charge observer's window model of one reversal: the modelled body
/// acceleration ``a2`` (m/s², float64 array) at ``times`` (s from the
/// reversal) for a reversal with velocity slope ``accel_mps2`` and the oil at
/// ``oil_c`` (°C), with the scaled parameters ``theta = [alpha N, c_ext,
/// c_comp, shift ms, c0 m/s²]`` (``c_ext``, ``c_comp`` in kN·s/m with the
/// linear law, the calibrated ``damping_law``'s scales otherwise). The
/// physics' ``observer`` section (or its defaults) gives the mount, filter
/// and law. What the observer fits to every window; for calibrating the
/// damping law on the windows and for references.
#[pyfunction]
pub(crate) fn reversal_window<'py>(
    py: Python<'py>,
    bundle_or_params: &Bound<'py, PyAny>,
    accel_mps2: f64,
    oil_c: f64,
    theta: [f64; 5],
    times: Vec<f64>,
) -> PyResult<Bound<'py, PyArray1<f64>>> {
    let (params, _) = physics_from(bundle_or_params)?;
    let obs = params.observer.unwrap_or_default();
    let a2 = without_gil(py, move || {
        dt_core::charge::reversal_window_a2(&obs, accel_mps2, oil_c, theta, &times)
    });
    Ok(to_numpy(py, a2))
}

/// The window model of many reversals at once: ``reversal_window`` for
/// window `i` of ``accel_mps2[i]``, ``oil_c[i]``, ``theta[i]`` and
/// ``times[i]``, the windows' modelled ``a2`` end to end in their order (one
/// float64 array, ``sum(len(t) for t in times)`` long). The parameters are
/// read once, and the windows are simulated on every core with the GIL
/// released (rayon); each is the same computation as ``reversal_window``'s,
/// so the result is the same bits. For the damping law's fit, which asks for
/// every window at every step of its finite-difference Jacobian.
#[pyfunction]
pub(crate) fn reversal_windows<'py>(
    py: Python<'py>,
    bundle_or_params: &Bound<'py, PyAny>,
    accel_mps2: Vec<f64>,
    oil_c: Vec<f64>,
    theta: Vec<[f64; 5]>,
    times: Vec<Vec<f64>>,
) -> PyResult<Bound<'py, PyArray1<f64>>> {
    use rayon::prelude::*;

    let n = accel_mps2.len();
    for (name, len) in [
        ("oil_c", oil_c.len()),
        ("theta", theta.len()),
        ("times", times.len()),
    ] {
        if len != n {
            return Err(input_error(format!(
                "reversal_windows: `{name}` has {len} windows, `accel_mps2` {n}"
            )));
        }
    }
    let (params, _) = physics_from(bundle_or_params)?;
    let obs = params.observer.unwrap_or_default();
    let a2 = without_gil(py, move || {
        let per: Vec<Vec<f64>> = (0..n)
            .into_par_iter()
            .map(|i| {
                dt_core::charge::reversal_window_a2(
                    &obs,
                    accel_mps2[i],
                    oil_c[i],
                    theta[i],
                    &times[i],
                )
            })
            .collect();
        per.concat()
    });
    Ok(to_numpy(py, a2))
}

/// The twin's state at every 50 Hz tick of a run, from every sensor topic
/// the log has: the *reduced models* where sensors are missing (the
/// position-only Kalman filter without ``/acceleration``; the first shock
/// temperature as ambient without ``/temperature/ambient``), as the streaming
/// pipeline runs them. For calibrating the physics on a campaign without the
/// full suite; the GIL is released meanwhile.
///
/// ``log`` and ``bundle_or_params`` as in ``features`` (a bundle's groups
/// are ignored). Returns a dict: ``t_s`` (tick times, s since the run's first
/// message), ``force_n`` (loadcell boxcar, NaN without ``/force``),
/// ``position_m``, ``velocity_mps``, ``accel_mps2`` (the Kalman position,
/// velocity and bias-corrected acceleration — the position-only filter's
/// acceleration without accelerometers), ``force_model_n``,
/// ``oil_temp_model_c``, ``cyl_temp_model_c``, ``heat_rate_model_w``,
/// ``velocity_rms_mps`` (float64 arrays) and ``position_only`` (bool).
#[pyfunction]
pub(crate) fn twin_trace<'py>(
    py: Python<'py>,
    log: &Bound<'py, PyAny>,
    bundle_or_params: &Bound<'py, PyAny>,
) -> PyResult<Bound<'py, PyDict>> {
    let (params, _) = physics_from(bundle_or_params)?;
    let run = run_from(py, log)?;
    let table = interruptible(py, move || compute_twin(&run, &params))?.map_err(CoreError::from)?;
    let out = PyDict::new(py);
    let tw = |f: &dyn Fn(&dt_core::features::TwinState) -> f64| -> Vec<f64> {
        table.twin.iter().map(f).collect()
    };
    out.set_item(
        "t_s",
        to_numpy(py, ns_to_seconds(&table.t_ns, table.t_origin_ns)),
    )?;
    out.set_item(
        "force_n",
        to_numpy(py, table.column("force_n").unwrap_or_default()),
    )?;
    out.set_item("position_m", to_numpy(py, tw(&|t| t.position_m)))?;
    out.set_item("velocity_mps", to_numpy(py, tw(&|t| t.velocity_mps)))?;
    out.set_item("accel_mps2", to_numpy(py, tw(&|t| t.accel_mps2)))?;
    out.set_item("force_model_n", to_numpy(py, tw(&|t| t.force_model_n)))?;
    out.set_item("oil_temp_model_c", to_numpy(py, tw(&|t| t.oil_temp_c)))?;
    out.set_item("cyl_temp_model_c", to_numpy(py, tw(&|t| t.cyl_temp_c)))?;
    out.set_item("heat_rate_model_w", to_numpy(py, tw(&|t| t.heat_rate_w)))?;
    out.set_item(
        "velocity_rms_mps",
        to_numpy(py, tw(&|t| t.velocity_rms_1s_mps)),
    )?;
    out.set_item(
        "position_only",
        table.twin.first().is_some_and(|t| t.position_only),
    )?;
    Ok(out)
}

fn run_from(
    py: Python<'_>,
    log: &Bound<'_, PyAny>,
) -> PyResult<std::sync::Arc<dt_core::log::RunLog>> {
    if let Ok(log) = log.downcast::<PyLog>() {
        Ok(log.get().run_log())
    } else if log.is_instance_of::<PyString>() || log.hasattr("__fspath__")? {
        Ok(read_log(py, log.extract()?)?.run_log())
    } else {
        Err(PyTypeError::new_err(format!(
            "log: expected a shocktwin.Log or a path, got {}",
            log.get_type().name()?
        )))
    }
}

/// The feature columns of one input group, in order.
///
/// >>> import shocktwin
/// >>> shocktwin.group_columns("velocity")
/// ['velocity_mps']
#[pyfunction]
pub(crate) fn group_columns(name: &str) -> PyResult<Vec<&'static str>> {
    Ok(group(name)?.columns().to_vec())
}

/// The log topics one input group needs (SPEC §4).
///
/// >>> import shocktwin
/// >>> shocktwin.group_topics("velocity")
/// ['/position', '/acceleration']
#[pyfunction]
pub(crate) fn group_topics(name: &str) -> PyResult<Vec<&'static str>> {
    Ok(group(name)?.required_topics().to_vec())
}

/// The sensors a set of input groups needs, and their cost (AUD, paper
/// Table 3), as ``(sensors, cost_aud)``.
///
/// >>> import shocktwin
/// >>> shocktwin.suite(["position", "acceleration", "velocity", "mechanical", "thermal"])
/// (['potentiometer', 'accelerometers', 'thermocouples'], 297)
#[pyfunction]
pub(crate) fn suite(groups: Vec<String>) -> PyResult<(Vec<&'static str>, u32)> {
    let groups = groups_from_names(&groups)?;
    let sensors = suite_sensors(&groups)
        .into_iter()
        .map(Sensor::name)
        .collect();
    Ok((sensors, suite_cost_aud(&groups)))
}

/// The paper's 13 input permutations (SPEC §4) as a fresh list of dicts:
/// ``id``, ``name``, ``groups``, ``columns``, ``sensors``, ``cost_aud`` and
/// ``paper_rmse_bar``. They are data: any list of groups is a permutation.
#[pyfunction]
pub(crate) fn permutations(py: Python<'_>) -> PyResult<Vec<Bound<'_, PyDict>>> {
    permutation_dicts(py, paper_permutations())
}

/// Our input permutations beyond the paper's (ids 14–16: its hybrids with
/// the causal-window groups ``signature`` and ``residual``; 17–19: the
/// charge observer alone and beside the thermomechanical hybrids), as a
/// fresh list of dicts like ``permutations()`` (``paper_rmse_bar`` is
/// ``None``).
///
/// >>> import shocktwin
/// >>> [(p["id"], p["cost_aud"]) for p in shocktwin.extra_permutations()]
/// [(14, 297), (15, 4292), (16, 4292), (17, 297), (18, 297), (19, 4292)]
#[pyfunction]
pub(crate) fn extra_permutations(py: Python<'_>) -> PyResult<Vec<Bound<'_, PyDict>>> {
    permutation_dicts(py, dt_core::features::extra_permutations())
}

fn permutation_dicts<'py>(
    py: Python<'py>,
    perms: &[Permutation],
) -> PyResult<Vec<Bound<'py, PyDict>>> {
    perms
        .iter()
        .map(|p| {
            let d = PyDict::new(py);
            d.set_item("id", p.id)?;
            d.set_item("name", p.name.as_ref())?;
            d.set_item(
                "groups",
                p.groups.iter().map(|g| g.name()).collect::<Vec<_>>(),
            )?;
            d.set_item("columns", p.columns())?;
            let sensors: Vec<&str> = suite_sensors(&p.groups)
                .into_iter()
                .map(Sensor::name)
                .collect();
            d.set_item("sensors", sensors)?;
            d.set_item("cost_aud", p.cost_aud())?;
            d.set_item("paper_rmse_bar", paper_rmse_bar(p.id))?;
            Ok(d)
        })
        .collect()
}

/// Adds the constant tables to the module: `GROUPS`, `COLUMNS`,
/// `SENSOR_COSTS_AUD`.
pub(crate) fn add_constants(m: &Bound<'_, PyModule>) -> PyResult<()> {
    let py = m.py();
    let groups: Vec<&str> = Group::ALL.iter().map(|g| g.name()).collect();
    m.add("GROUPS", pyo3::types::PyTuple::new(py, groups)?)?;
    m.add("COLUMNS", pyo3::types::PyTuple::new(py, COLUMNS)?)?;
    let costs = PyDict::new(py);
    for s in Sensor::ALL {
        costs.set_item(s.name(), s.cost_aud())?;
    }
    m.add("SENSOR_COSTS_AUD", costs)?;
    Ok(())
}

/// The road observer (dt-core ``road``) over a recorded run, as the daemon
/// would stream it: ``log`` a ``shocktwin.Log`` or a path, ``calibration``
/// the JSON text of ``python -m train.road_observer fit``'s output or a path
/// to that file (text starting with ``{`` is JSON). Returns a
/// dict of float64 arrays, one entry per block read: ``t_s`` (block end, s
/// since the run's first message), ``alpha_n``, ``alpha_sd_n``,
/// ``residual_mps2``, ``temp_c``, ``stroke_rms_mps``, ``reading_bar``,
/// ``reading_sd_bar``, ``estimate_bar``, ``lo_bar``, ``hi_bar``; and
/// ``health`` (a list of str). ``baseline`` (a path or Log, and its charge
/// ``baseline_bar``): the unit's drive at a known charge, read first.
/// Raises ``MissingTopicsError`` when the log lacks a topic it needs,
/// ``ParamsReadError`` (an ``OSError``) for a calibration file it cannot
/// read, ``ParamsError`` for a calibration it cannot use and ``InputError``
/// for a baseline without its charge (or the reverse) or a baseline drive
/// it cannot read.
#[pyfunction]
#[pyo3(signature = (log, calibration, baseline=None, baseline_bar=None))]
pub(crate) fn road_blocks<'py>(
    py: Python<'py>,
    log: &Bound<'py, PyAny>,
    calibration: &Bound<'py, PyAny>,
    baseline: Option<&Bound<'py, PyAny>>,
    baseline_bar: Option<f64>,
) -> PyResult<Bound<'py, PyDict>> {
    use dt_core::road::{read_run, RoadCalibration};
    // JSON text, or a path to it: every other argument takes a path, and a
    // path given here was "not JSON: expected value at line 1 column 1"
    let text: Option<String> = calibration
        .extract::<String>()
        .ok()
        .filter(|t| t.trim_start().starts_with('{'));
    let (name, json) = if let Some(json) = text {
        ("calibration".to_owned(), json)
    } else {
        let path: PathBuf = calibration.extract().map_err(|_| {
            PyTypeError::new_err(format!(
                "calibration: expected JSON text or a path, got {}",
                calibration
                    .get_type()
                    .name()
                    .map_or_else(|_| "?".into(), |n| n.to_string())
            ))
        })?;
        let json = std::fs::read_to_string(&path).map_err(|e| {
            crate::exceptions::io_error(&format!("calibration {}", path.display()), &e)
        })?;
        (format!("calibration {}", path.display()), json)
    };
    let mut cal =
        RoadCalibration::from_json(&name, &json).map_err(crate::exceptions::params_error)?;
    let health = dt_core::bundle::HealthConfig::default();
    if baseline.is_none() && baseline_bar.is_some() {
        // it was ignored without a word (a helper's trial)
        return Err(crate::exceptions::input_error(
            "baseline_bar given without baseline (the drive at that known charge)".into(),
        ));
    }
    if let Some(base) = baseline {
        let bar = baseline_bar.ok_or_else(|| {
            crate::exceptions::input_error("baseline given without baseline_bar".into())
        })?;
        let run = run_from(py, base)?;
        let c = cal.clone();
        let blocks =
            interruptible(py, move || read_run(&run, &c, health))?.map_err(CoreError::from)?;
        cal = cal
            .with_baseline(&blocks, bar)
            .map_err(crate::exceptions::input_error)?;
    }
    let run = run_from(py, log)?;
    let blocks =
        interruptible(py, move || read_run(&run, &cal, health))?.map_err(CoreError::from)?;
    let out = PyDict::new(py);
    let col = |f: &dyn Fn(&dt_core::road::RoadBlock) -> f64| -> Vec<f64> {
        blocks.iter().map(f).collect()
    };
    out.set_item("t_s", to_numpy(py, col(&|b| b.t_s)))?;
    out.set_item("alpha_n", to_numpy(py, col(&|b| b.alpha_n)))?;
    out.set_item("alpha_sd_n", to_numpy(py, col(&|b| b.alpha_sd_n)))?;
    out.set_item("residual_mps2", to_numpy(py, col(&|b| b.residual_mps2)))?;
    out.set_item("temp_c", to_numpy(py, col(&|b| b.temp_c)))?;
    out.set_item("stroke_rms_mps", to_numpy(py, col(&|b| b.stroke_rms_mps)))?;
    out.set_item("reading_bar", to_numpy(py, col(&|b| b.reading_bar)))?;
    out.set_item("reading_sd_bar", to_numpy(py, col(&|b| b.reading_sd_bar)))?;
    out.set_item("estimate_bar", to_numpy(py, col(&|b| b.estimate_bar)))?;
    out.set_item("lo_bar", to_numpy(py, col(&|b| b.lo_bar)))?;
    out.set_item("hi_bar", to_numpy(py, col(&|b| b.hi_bar)))?;
    let health: Vec<&str> = blocks.iter().map(|b| b.health.as_str()).collect();
    out.set_item("health", health)?;
    Ok(out)
}
