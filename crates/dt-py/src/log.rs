//! `shocktwin.read_log` and `shocktwin.Log`: a whole run log as numpy columns.

use std::collections::BTreeMap;
use std::path::PathBuf;
use std::sync::Arc;

use dt_core::log::{read_log as core_read_log, topic, RunLog};
use pyo3::exceptions::PyKeyError;
use pyo3::prelude::*;
use pyo3::types::PyDict;

use crate::convert::{ns_to_seconds, to_numpy};
use crate::exceptions::CoreError;
use crate::gil::interruptible;

/// The SPEC §2 sensor topics in the order `Log.topics` lists them.
const TOPIC_ORDER: [&str; 7] = [
    topic::POSITION,
    topic::ACCELERATION,
    topic::FORCE,
    topic::TEMP_SHOCK,
    topic::TEMP_AMBIENT,
    topic::TRUTH_PRESSURE,
    topic::TRUTH_VELOCITY,
];

/// Reads a whole shocktwin run log (an MCAP file, SPEC §2); the GIL is
/// released while reading.
///
/// Raises ``LogError`` (a ``ValueError``) when the file is not valid MCAP
/// or not a valid shocktwin log, ``LogReadError`` (an ``OSError``) when it
/// cannot be read. Messages that cannot be decoded are skipped and listed in
/// ``Log.problems``.
///
/// >>> import shocktwin
/// >>> shocktwin.read_log("no/such/run.mcap")
/// Traceback (most recent call last):
/// ...
/// shocktwin.exceptions.LogReadError: no/such/run.mcap: No such file or directory (os error 2)
#[pyfunction]
pub(crate) fn read_log(py: Python<'_>, path: PathBuf) -> PyResult<PyLog> {
    let display = path.display().to_string();
    // for pickling: a worker process may run in another directory
    let source = std::path::absolute(&path).unwrap_or_else(|_| path.clone());
    let log = interruptible(py, move || core_read_log(&path))?.map_err(CoreError::from)?;
    Ok(PyLog {
        path: display,
        source,
        log: Arc::new(log),
    })
}

/// One run of one asset, read by ``read_log``. Immutable.
#[pyclass(module = "shocktwin._native", name = "Log", frozen)]
pub(crate) struct PyLog {
    path: String,
    /// The file, as an absolute path (what a pickle holds).
    source: PathBuf,
    log: Arc<RunLog>,
}

impl PyLog {
    /// The decoded run, shared with the feature pipeline without a copy.
    pub(crate) fn run_log(&self) -> Arc<RunLog> {
        Arc::clone(&self.log)
    }

    /// Time of the run's first message (any sensor topic), ns; 0 when empty.
    fn origin_ns(&self) -> i64 {
        self.log.t0_ns().unwrap_or(0)
    }

    fn len_of(&self, name: &str) -> Option<usize> {
        let log = &*self.log;
        Some(match name {
            topic::POSITION => log.position.len(),
            topic::ACCELERATION => log.acceleration.len(),
            topic::FORCE => log.force.len(),
            topic::TEMP_SHOCK => log.temp_shock.len(),
            topic::TEMP_AMBIENT => log.temp_ambient.len(),
            topic::TRUTH_PRESSURE => log.truth_pressure.len(),
            topic::TRUTH_VELOCITY => log.truth_velocity.len(),
            _ => return None,
        })
    }

    fn present_topics(&self) -> Vec<&'static str> {
        TOPIC_ORDER
            .into_iter()
            .filter(|t| self.len_of(t).is_some_and(|n| n > 0))
            .collect()
    }
}

/// `(t_ns, value)` columns as (times, values).
fn split2(rows: &[(i64, f64)]) -> (Vec<i64>, Vec<f64>) {
    rows.iter().copied().unzip()
}

#[pymethods]
impl PyLog {
    /// The file this run was read from.
    #[getter]
    fn path(&self) -> &str {
        &self.path
    }

    /// The ``shocktwin.run`` metadata: ``asset_id``, ``run_id`` (str);
    /// ``charge_pressure_bar``, ``frequency_hz``, ``stroke_pp_m`` (float)
    /// and ``excitation`` (str) when present; any other key as its str.
    #[getter]
    fn metadata<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        let m = &self.log.metadata;
        let out = PyDict::new(py);
        for (key, value) in &m.extra {
            out.set_item(key, value)?;
        }
        out.set_item("asset_id", &m.asset_id)?;
        out.set_item("run_id", &m.run_id)?;
        if let Some(v) = m.charge_pressure_bar {
            out.set_item("charge_pressure_bar", v)?;
        }
        if let Some(v) = &m.excitation {
            out.set_item("excitation", v)?;
        }
        if let Some(v) = m.frequency_hz {
            out.set_item("frequency_hz", v)?;
        }
        if let Some(v) = m.stroke_pp_m {
            out.set_item("stroke_pp_m", v)?;
        }
        Ok(out)
    }

    /// The label: true charge pressure, bar gauge at 20 °C, or ``None``.
    #[getter]
    fn label(&self) -> Option<f64> {
        self.log.metadata.charge_pressure_bar
    }

    /// The SPEC §2 topics that have at least one message, in SPEC order.
    #[getter]
    fn topics(&self) -> Vec<&'static str> {
        self.present_topics()
    }

    /// Non-fatal findings of the reader (skipped messages, ignored topics).
    #[getter]
    fn problems(&self) -> Vec<String> {
        self.log.problems.clone()
    }

    /// Message counts of topics this format does not know (not kept).
    #[getter]
    fn unknown_topics(&self) -> BTreeMap<String, u64> {
        self.log.unknown_topics.clone()
    }

    /// Time of the run's first message (``t_s == 0``), ns since the log's epoch.
    #[getter]
    fn t0_ns(&self) -> i64 {
        self.origin_ns()
    }

    /// One topic's samples as float64 arrays: ``"t_s"`` (seconds since the
    /// run's first message on any topic) and one array per field
    /// (``/acceleration``: ``a1_mps2``, ``a2_mps2``; ``/position``:
    /// ``position_m``; ...). A missing sample is NaN. Raises ``KeyError``
    /// for a topic the log does not have.
    fn topic<'py>(&self, py: Python<'py>, name: &str) -> PyResult<Bound<'py, PyDict>> {
        if !self.present_topics().contains(&name) {
            return Err(PyKeyError::new_err(format!(
                "{}: no topic {name:?}; it has {:?}",
                self.path,
                self.present_topics()
            )));
        }
        let origin = self.origin_ns();
        let log = &*self.log;
        let out = PyDict::new(py);
        let (t_ns, fields): (Vec<i64>, Vec<(&str, Vec<f64>)>) = if name == topic::ACCELERATION {
            let t = log.acceleration.iter().map(|r| r.0).collect();
            let a1 = log.acceleration.iter().map(|r| r.1).collect();
            let a2 = log.acceleration.iter().map(|r| r.2).collect();
            (t, vec![("a1_mps2", a1), ("a2_mps2", a2)])
        } else {
            let (rows, field) = match name {
                topic::POSITION => (&log.position, "position_m"),
                topic::FORCE => (&log.force, "force_n"),
                topic::TEMP_SHOCK => (&log.temp_shock, "temperature_c"),
                topic::TEMP_AMBIENT => (&log.temp_ambient, "temperature_c"),
                topic::TRUTH_VELOCITY => (&log.truth_velocity, "velocity_mps"),
                _ => (&log.truth_pressure, "static_bar"),
            };
            let (t, v) = split2(rows);
            (t, vec![(field, v)])
        };
        out.set_item("t_s", to_numpy(py, ns_to_seconds(&t_ns, origin)))?;
        for (field, values) in fields {
            out.set_item(field, to_numpy(py, values))?;
        }
        Ok(out)
    }

    /// Pickled as the file's absolute path: unpickling reads the file again
    /// (``read_log``), so a worker process (``multiprocessing``,
    /// ``concurrent.futures``, joblib) needs the same file, unchanged.
    fn __reduce__<'py>(&self, py: Python<'py>) -> PyResult<(Bound<'py, PyAny>, (PathBuf,))> {
        let read = py.import("shocktwin")?.getattr("read_log")?;
        Ok((read, (self.source.clone(),)))
    }

    fn __repr__(&self) -> String {
        let m = &self.log.metadata;
        format!(
            "<shocktwin.Log {} asset_id={:?} run_id={:?} topics={:?}>",
            self.path,
            m.asset_id,
            m.run_id,
            self.present_topics()
        )
    }
}
