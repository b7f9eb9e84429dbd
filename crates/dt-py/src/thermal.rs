//! `shocktwin.ThermalModel`: the SPEC §3.2 oil/cylinder heat balance (RK4).

use dt_core::params::ThermalParams;
use dt_core::thermal::ThermalModel;
use numpy::PyArray1;
use pyo3::prelude::*;
use pyo3::types::PyDict;

use crate::convert::{to_numpy, to_vec, ArrayLike};
use crate::exceptions::CoreError;
use crate::gil::without_gil;

/// Two-node thermal model of the damper (SPEC §3.2, paper eqs. 2–3),
/// integrated with classical RK4, temperatures in °C.
///
/// Keyword-only parameters ``c_oil``, ``c_cyl`` (J/K), ``ha_in``, ``ha_out``
/// (W/K), ``eps_sigma_a`` (W/K⁴); each defaults to dt-core's prior
/// (``default_params()["thermal"]``). ``tc_gain`` and ``tc_lag_s`` (the shock
/// thermocouple's model: what it reads of the cylinder, and its lag) are
/// kept with them but do not enter the heat balance ``simulate`` integrates.
///
/// >>> import shocktwin
/// >>> model = shocktwin.ThermalModel(c_oil=500.0, c_cyl=700.0, ha_in=10.0, ha_out=2.5, eps_sigma_a=0.0)
/// >>> oil, cyl = model.simulate([0.0, 1.0], [500.0, 500.0], [20.0, 20.0], 20.0, 20.0)
/// >>> round(float(oil[1]), 3)  # 500 W into 500 J/K: about 1 K in 1 s
/// 20.99
#[pyclass(module = "shocktwin._native", name = "ThermalModel", frozen)]
pub(crate) struct PyThermalModel {
    model: ThermalModel,
}

#[pymethods]
impl PyThermalModel {
    #[new]
    // the defaults as Python shows them (`help`, `inspect.signature`), which
    // pyo3 writes as `...` for an expression; a test holds them to `params`
    #[pyo3(
        text_signature = "(*, c_oil=500.0, c_cyl=700.0, ha_in=10.0, ha_out=2.5, eps_sigma_a=2.3e-09, tc_gain=1.0, tc_lag_s=0.0)"
    )]
    #[pyo3(signature = (
        *,
        c_oil = ThermalParams::default().c_oil,
        c_cyl = ThermalParams::default().c_cyl,
        ha_in = ThermalParams::default().ha_in,
        ha_out = ThermalParams::default().ha_out,
        eps_sigma_a = ThermalParams::default().eps_sigma_a,
        tc_gain = ThermalParams::default().tc_gain,
        tc_lag_s = ThermalParams::default().tc_lag_s,
    ))]
    #[allow(clippy::too_many_arguments)]
    fn new(
        c_oil: f64,
        c_cyl: f64,
        ha_in: f64,
        ha_out: f64,
        eps_sigma_a: f64,
        tc_gain: f64,
        tc_lag_s: f64,
    ) -> PyResult<Self> {
        let params = ThermalParams {
            c_oil,
            c_cyl,
            ha_in,
            ha_out,
            eps_sigma_a,
            tc_gain,
            tc_lag_s,
        };
        params.validate().map_err(CoreError::from)?;
        Ok(Self {
            model: ThermalModel::new(params),
        })
    }

    /// Integrates over the non-decreasing grid ``t_s`` (s) from
    /// ``(oil0_c, cyl0_c)`` at ``t_s[0]``: one RK4 step per interval with the
    /// heat input ``power_w[i]`` (W) and ``ambient_c[i]`` (°C) held over
    /// ``[t_s[i], t_s[i+1]]``; an interval longer than 2 s in equal steps of
    /// at most 2 s (a coarser grid, e.g. one a minute, stays stable). Returns
    /// ``(oil_c, cyl_c)``, each as long as ``t_s`` and starting with the
    /// initial state. Raises ``PhysicsError`` when a temperature is not
    /// finite (naming the grid point), ``InputError`` for inputs of
    /// different lengths or times that go backwards.
    #[allow(clippy::type_complexity)]
    fn simulate<'py>(
        &self,
        py: Python<'py>,
        t_s: ArrayLike<'py>,
        power_w: ArrayLike<'py>,
        ambient_c: ArrayLike<'py>,
        oil0_c: f64,
        cyl0_c: f64,
    ) -> PyResult<(Bound<'py, PyArray1<f64>>, Bound<'py, PyArray1<f64>>)> {
        let (t_s, power_w, ambient_c) = (to_vec(&t_s), to_vec(&power_w), to_vec(&ambient_c));
        let model = self.model;
        let (oil, cyl) = without_gil(py, move || {
            model.simulate(&t_s, &power_w, &ambient_c, oil0_c, cyl0_c)
        })
        .map_err(CoreError::from)?;
        Ok((to_numpy(py, oil), to_numpy(py, cyl)))
    }

    /// The model's parameters as a dict (the ``thermal`` part of physics.json).
    #[getter]
    fn params<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        let p = self.model.params();
        let out = PyDict::new(py);
        out.set_item("c_oil", p.c_oil)?;
        out.set_item("c_cyl", p.c_cyl)?;
        out.set_item("ha_in", p.ha_in)?;
        out.set_item("ha_out", p.ha_out)?;
        out.set_item("eps_sigma_a", p.eps_sigma_a)?;
        out.set_item("tc_gain", p.tc_gain)?;
        out.set_item("tc_lag_s", p.tc_lag_s)?;
        Ok(out)
    }

    fn __repr__(&self) -> String {
        let p = self.model.params();
        format!(
            "ThermalModel(c_oil={:?}, c_cyl={:?}, ha_in={:?}, ha_out={:?}, eps_sigma_a={:?})",
            p.c_oil, p.c_cyl, p.ha_in, p.ha_out, p.eps_sigma_a
        )
    }
}
