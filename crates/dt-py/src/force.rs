//! `shocktwin.ForceModel`: the SPEC §3.3 nominal force model (eqs. 4–9).

use dt_core::force::{ForceBreakdown, ForceModel};
use dt_core::params::ForceParams;
use numpy::PyArray1;
use pyo3::prelude::*;
use pyo3::types::PyDict;

use crate::convert::{check_same_len, to_numpy, to_vec, ArrayLike};
use crate::exceptions::CoreError;
use crate::gil::without_gil;

/// The nominal force model of SPEC §3.3 (paper eqs. 4–9), vectorised.
///
/// Keyword-only parameters (SPEC names): ``k_leak_reb``, ``k_leak_com``,
/// ``f_preload_reb``, ``f_preload_com`` (N), ``k_spring_reb``,
/// ``k_spring_com`` (N·s/m), ``k_main_reb``, ``k_main_com``, ``k_tr``,
/// ``k_hys`` (N·s²/m), ``nu_40`` (cSt), ``beta`` (1/K), ``charge_bar``
/// (bar gauge at 20 °C), ``a_rod`` (m²), ``v_gas`` (m³). Each defaults to
/// dt-core's prior (``default_params()["force"]``).
///
/// >>> import shocktwin
/// >>> model = shocktwin.ForceModel(charge_bar=12.0, a_rod=3.14159e-4)
/// >>> model.force([0.0], [0.0], [0.0], [20.0]).round(1)  # at rest: 12 bar on a 20 mm rod
/// array([-377.])
/// >>> sorted(model.components([0.5], [0.0], [0.0], [40.0]))
/// ['force_n', 'gas_n', 'hysteresis_n', 'main_n', 'port_n', 'power_w']
#[pyclass(module = "shocktwin._native", name = "ForceModel", frozen)]
pub(crate) struct PyForceModel {
    model: ForceModel,
}

/// The four inputs of the model, copied out of their arrays.
struct Inputs {
    velocity: Vec<f64>,
    accel: Vec<f64>,
    position: Vec<f64>,
    oil_c: Vec<f64>,
}

impl Inputs {
    fn new(
        velocity: &ArrayLike<'_>,
        accel: &ArrayLike<'_>,
        position: &ArrayLike<'_>,
        oil_c: &ArrayLike<'_>,
    ) -> PyResult<Self> {
        let inputs = Self {
            velocity: to_vec(velocity),
            accel: to_vec(accel),
            position: to_vec(position),
            oil_c: to_vec(oil_c),
        };
        check_same_len(&[
            ("velocity", inputs.velocity.len()),
            ("accel", inputs.accel.len()),
            ("position", inputs.position.len()),
            ("oil_c", inputs.oil_c.len()),
        ])?;
        Ok(inputs)
    }

    fn breakdown(&self, model: &ForceModel, charge_bar: Option<f64>) -> Vec<ForceBreakdown> {
        let charge_bar = charge_bar.unwrap_or(model.params().charge_bar);
        (0..self.velocity.len())
            .map(|i| {
                model.force_at_charge(
                    self.velocity[i],
                    self.accel[i],
                    self.position[i],
                    self.oil_c[i],
                    charge_bar,
                )
            })
            .collect()
    }
}

#[pymethods]
impl PyForceModel {
    #[new]
    // the defaults as Python shows them (`help`, `inspect.signature`), which
    // pyo3 writes as `...` for an expression; a test holds them to `params`
    #[pyo3(
        text_signature = "(*, k_leak_reb=533.0, k_leak_com=270.0, f_preload_reb=600.0, f_preload_com=300.0, k_spring_reb=2000.0, k_spring_com=400.0, k_main_reb=670.0, k_main_com=150.0, k_tr=2.0, k_hys=2.0, nu_40=15.0, beta=0.02, charge_bar=12.0, a_rod=0.00031415926535897936, v_gas=0.0001)"
    )]
    #[pyo3(signature = (
        *,
        k_leak_reb = ForceParams::default().k_leak_reb,
        k_leak_com = ForceParams::default().k_leak_com,
        f_preload_reb = ForceParams::default().f_preload_reb,
        f_preload_com = ForceParams::default().f_preload_com,
        k_spring_reb = ForceParams::default().k_spring_reb,
        k_spring_com = ForceParams::default().k_spring_com,
        k_main_reb = ForceParams::default().k_main_reb,
        k_main_com = ForceParams::default().k_main_com,
        k_tr = ForceParams::default().k_tr,
        k_hys = ForceParams::default().k_hys,
        nu_40 = ForceParams::default().nu_40,
        beta = ForceParams::default().beta,
        charge_bar = ForceParams::default().charge_bar,
        a_rod = ForceParams::default().a_rod,
        v_gas = ForceParams::default().v_gas,
    ))]
    #[allow(clippy::too_many_arguments)] // one keyword argument per SPEC §3.3 parameter
    fn new(
        k_leak_reb: f64,
        k_leak_com: f64,
        f_preload_reb: f64,
        f_preload_com: f64,
        k_spring_reb: f64,
        k_spring_com: f64,
        k_main_reb: f64,
        k_main_com: f64,
        k_tr: f64,
        k_hys: f64,
        nu_40: f64,
        beta: f64,
        charge_bar: f64,
        a_rod: f64,
        v_gas: f64,
    ) -> PyResult<Self> {
        let params = ForceParams {
            k_leak_reb,
            k_leak_com,
            f_preload_reb,
            f_preload_com,
            k_spring_reb,
            k_spring_com,
            k_main_reb,
            k_main_com,
            k_tr,
            k_hys,
            nu_40,
            beta,
            charge_bar,
            a_rod,
            v_gas,
        };
        params.validate().map_err(CoreError::from)?;
        Ok(Self {
            model: ForceModel::new(params),
        })
    }

    /// Eq. 9: the axial force (N, positive in tension) at each sample of
    /// ``velocity`` (m/s), ``accel`` (relative acceleration, m/s²),
    /// ``position`` (extension, m) and ``oil_c`` (°C), for the nominal unit
    /// or, with ``charge_bar``, a unit charged to that pressure.
    #[pyo3(signature = (velocity, accel, position, oil_c, *, charge_bar = None))]
    fn force<'py>(
        &self,
        py: Python<'py>,
        velocity: ArrayLike<'py>,
        accel: ArrayLike<'py>,
        position: ArrayLike<'py>,
        oil_c: ArrayLike<'py>,
        charge_bar: Option<f64>,
    ) -> PyResult<Bound<'py, PyArray1<f64>>> {
        let inputs = Inputs::new(&velocity, &accel, &position, &oil_c)?;
        let model = self.model;
        let total = without_gil(py, move || {
            inputs
                .breakdown(&model, charge_bar)
                .iter()
                .map(|b| b.total_n)
                .collect()
        });
        Ok(to_numpy(py, total))
    }

    /// The terms of eq. 9, each signed as it enters the sum (N):
    /// ``force_n`` (the total), ``port_n`` (sign(v)·F_port), ``main_n``
    /// (sign(v)·F_main), ``hysteresis_n`` (-k_hys·accel), ``gas_n`` (-F_gas),
    /// and ``power_w``, the heat input (F_port + F_main)·|v| (W, ≥ 0).
    #[pyo3(signature = (velocity, accel, position, oil_c, *, charge_bar = None))]
    fn components<'py>(
        &self,
        py: Python<'py>,
        velocity: ArrayLike<'py>,
        accel: ArrayLike<'py>,
        position: ArrayLike<'py>,
        oil_c: ArrayLike<'py>,
        charge_bar: Option<f64>,
    ) -> PyResult<Bound<'py, PyDict>> {
        let inputs = Inputs::new(&velocity, &accel, &position, &oil_c)?;
        let model = self.model;
        let (parts, power) = without_gil(py, move || {
            let parts = inputs.breakdown(&model, charge_bar);
            let power: Vec<f64> = inputs
                .velocity
                .iter()
                .zip(&inputs.oil_c)
                .map(|(&v, &t)| model.dissipative_power_w(v, t))
                .collect();
            (parts, power)
        });
        let column = |f: fn(&ForceBreakdown) -> f64| to_numpy(py, parts.iter().map(f).collect());
        let out = PyDict::new(py);
        out.set_item("force_n", column(|b| b.total_n))?;
        out.set_item("port_n", column(|b| b.port_n))?;
        out.set_item("main_n", column(|b| b.main_n))?;
        out.set_item("hysteresis_n", column(|b| b.hys_n))?;
        out.set_item("gas_n", column(|b| b.gas_n))?;
        out.set_item("power_w", to_numpy(py, power))?;
        Ok(out)
    }

    /// The model's parameters as a dict (the ``force`` part of physics.json).
    #[getter]
    fn params<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        crate::params::force_dict(py, self.model.params())
    }

    fn __repr__(&self) -> String {
        format!("ForceModel({:?})", self.model.params())
    }
}
