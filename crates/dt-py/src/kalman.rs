//! `shocktwin.KalmanFilter`: the SPEC §3.1 velocity estimator (batch).

use dt_core::kalman::run_kalman;
use dt_core::params::KalmanParams;
use pyo3::prelude::*;
use pyo3::types::PyDict;

use crate::convert::{seconds_to_ns, to_numpy, to_vec, ArrayLike};
use crate::exceptions::CoreError;
use crate::gil::without_gil;

/// Kalman filter fusing the potentiometer with the accelerometer pair
/// (SPEC §3.1, paper eq. 1). State ``[y, dy/dt, b_a]``.
///
/// ``sigma_accel`` (m/s²), ``sigma_bias`` (m/s²/√s), ``sigma_position`` (m);
/// the defaults are dt-core's priors (``default_params()["kalman"]``).
///
/// >>> import numpy as np, shocktwin
/// >>> t_acc, t_pos = np.arange(1000) * 1e-3, np.arange(100) * 1e-2
/// >>> kf = shocktwin.KalmanFilter(sigma_accel=0.2, sigma_bias=0.005, sigma_position=1e-3)
/// >>> out = kf.run(t_acc, np.zeros(1000), t_pos, np.full(100, 0.01))  # at rest at +10 mm
/// >>> sorted(out)
/// ['bias_mps2', 'position_m', 't_s', 'velocity_mps']
/// >>> round(float(out["position_m"][-1]), 6), bool(abs(out["velocity_mps"][-1]) < 1e-3)
/// (0.01, True)
#[pyclass(module = "shocktwin._native", name = "KalmanFilter", frozen)]
pub(crate) struct PyKalmanFilter {
    params: KalmanParams,
}

#[pymethods]
impl PyKalmanFilter {
    #[new]
    // the defaults as Python shows them (`help`, `inspect.signature`), which
    // pyo3 writes as `...` for an expression; a test holds them to `params`
    #[pyo3(text_signature = "(sigma_accel=0.2, sigma_bias=0.005, sigma_position=0.001)")]
    #[pyo3(signature = (
        sigma_accel = KalmanParams::default().sigma_accel,
        sigma_bias = KalmanParams::default().sigma_bias,
        sigma_position = KalmanParams::default().sigma_position,
    ))]
    fn new(sigma_accel: f64, sigma_bias: f64, sigma_position: f64) -> PyResult<Self> {
        let params = KalmanParams {
            sigma_accel,
            sigma_bias,
            sigma_position,
        };
        params.validate().map_err(CoreError::from)?;
        Ok(Self { params })
    }

    /// Runs the filter over an accelerometer stream (``t_acc`` s, relative
    /// acceleration ``a_rel`` = a1 - a2, m/s²) and a potentiometer stream
    /// (``t_pos`` s, ``pos`` m), each sorted in time.
    ///
    /// Returns ``{"t_s", "position_m", "velocity_mps", "bias_mps2"}``: the
    /// state at each accelerometer sample time after every event at that
    /// time (NaN before the first position sample). Times are rounded to
    /// the nanosecond. A NaN sample counts as missing and is skipped.
    fn run<'py>(
        &self,
        py: Python<'py>,
        t_acc: ArrayLike<'py>,
        a_rel: ArrayLike<'py>,
        t_pos: ArrayLike<'py>,
        pos: ArrayLike<'py>,
    ) -> PyResult<Bound<'py, PyDict>> {
        let t_acc_s = to_vec(&t_acc);
        let t_acc_ns = seconds_to_ns("t_acc", &t_acc_s)?;
        let t_pos_ns = seconds_to_ns("t_pos", &to_vec(&t_pos))?;
        let (a_rel, pos) = (to_vec(&a_rel), to_vec(&pos));
        let params = self.params;
        let trace = without_gil(py, move || {
            run_kalman(params, &t_acc_ns, &a_rel, &t_pos_ns, &pos)
        })
        .map_err(CoreError::from)?;
        let out = PyDict::new(py);
        out.set_item("t_s", to_numpy(py, t_acc_s))?;
        out.set_item("position_m", to_numpy(py, trace.position_m))?;
        out.set_item("velocity_mps", to_numpy(py, trace.velocity_mps))?;
        out.set_item("bias_mps2", to_numpy(py, trace.bias_mps2))?;
        Ok(out)
    }

    /// The filter's parameters as a dict (the ``kalman`` part of physics.json).
    #[getter]
    fn params<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        let out = PyDict::new(py);
        out.set_item("sigma_accel", self.params.sigma_accel)?;
        out.set_item("sigma_bias", self.params.sigma_bias)?;
        out.set_item("sigma_position", self.params.sigma_position)?;
        Ok(out)
    }

    fn __repr__(&self) -> String {
        let p = &self.params;
        format!(
            "KalmanFilter(sigma_accel={:?}, sigma_bias={:?}, sigma_position={:?})",
            p.sigma_accel, p.sigma_bias, p.sigma_position
        )
    }
}
