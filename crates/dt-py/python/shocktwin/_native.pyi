"""Stubs of the private native module; import from ``shocktwin`` instead."""

from os import PathLike
from typing import Any, Sequence, final

import numpy as np
import numpy.typing as npt

__all__ = [
    "__version__",
    "KalmanFilter",
    "ThermalModel",
    "ForceModel",
    "default_params",
    "Log",
    "read_log",
    "features",
    "group_columns",
    "group_topics",
    "suite",
    "permutations",
    "extra_permutations",
    "charge_reversals",
    "road_blocks",
    "reversal_window",
    "reversal_windows",
    "twin_trace",
    "default_observer_params",
    "Bundle",
    "estimate",
    "GROUPS",
    "COLUMNS",
    "MLP_F32_PARITY_BAR",
    "SENSOR_COSTS_AUD",
]

__version__: str

_F64 = npt.NDArray[np.float64]
_ArrayLike = npt.ArrayLike
_Path = str | PathLike[str]

GROUPS: tuple[str, ...]
COLUMNS: tuple[str, ...]
MLP_F32_PARITY_BAR: float
SENSOR_COSTS_AUD: dict[str, int]

@final
class Log:
    """One run of one asset, read by ``read_log``. Immutable."""

    @property
    def path(self) -> str: ...
    @property
    def metadata(self) -> dict[str, str | float]: ...
    @property
    def label(self) -> float | None: ...
    @property
    def topics(self) -> list[str]: ...
    @property
    def problems(self) -> list[str]: ...
    @property
    def unknown_topics(self) -> dict[str, int]: ...
    @property
    def t0_ns(self) -> int: ...
    def topic(self, name: str) -> dict[str, _F64]: ...

def read_log(path: _Path) -> Log: ...

@final
class KalmanFilter:
    def __new__(
        cls, sigma_accel: float = ..., sigma_bias: float = ..., sigma_position: float = ...
    ) -> KalmanFilter: ...
    def run(self, t_acc: _ArrayLike, a_rel: _ArrayLike, t_pos: _ArrayLike, pos: _ArrayLike) -> dict[str, _F64]: ...
    @property
    def params(self) -> dict[str, float]: ...

@final
class ThermalModel:
    def __new__(
        cls,
        *,
        c_oil: float = ...,
        c_cyl: float = ...,
        ha_in: float = ...,
        ha_out: float = ...,
        eps_sigma_a: float = ...,
        tc_gain: float = ...,
        tc_lag_s: float = ...,
    ) -> ThermalModel: ...
    def simulate(
        self, t_s: _ArrayLike, power_w: _ArrayLike, ambient_c: _ArrayLike, oil0_c: float, cyl0_c: float
    ) -> tuple[_F64, _F64]: ...
    @property
    def params(self) -> dict[str, float]: ...

@final
class ForceModel:
    def __new__(
        cls,
        *,
        k_leak_reb: float = ...,
        k_leak_com: float = ...,
        f_preload_reb: float = ...,
        f_preload_com: float = ...,
        k_spring_reb: float = ...,
        k_spring_com: float = ...,
        k_main_reb: float = ...,
        k_main_com: float = ...,
        k_tr: float = ...,
        k_hys: float = ...,
        nu_40: float = ...,
        beta: float = ...,
        charge_bar: float = ...,
        a_rod: float = ...,
        v_gas: float = ...,
    ) -> ForceModel: ...
    def force(
        self,
        velocity: _ArrayLike,
        accel: _ArrayLike,
        position: _ArrayLike,
        oil_c: _ArrayLike,
        *,
        charge_bar: float | None = None,
    ) -> _F64: ...
    def components(
        self,
        velocity: _ArrayLike,
        accel: _ArrayLike,
        position: _ArrayLike,
        oil_c: _ArrayLike,
        *,
        charge_bar: float | None = None,
    ) -> dict[str, _F64]: ...
    @property
    def params(self) -> dict[str, float]: ...

def default_observer_params() -> dict[str, float]: ...
def default_params() -> dict[str, dict[str, float]]: ...
def features(
    log: Log | _Path,
    bundle_or_params: dict[str, Any] | Bundle | _Path,
    groups: Sequence[str] | None = None,
) -> tuple[npt.NDArray[np.float64], list[str], _F64]: ...
def charge_reversals(
    log: Log | _Path,
    bundle_or_params: dict[str, Any] | Bundle | _Path,
) -> dict[str, Any]: ...
def road_blocks(
    log: Log | _Path,
    calibration: str | _Path,
    baseline: Log | _Path | None = None,
    baseline_bar: float | None = None,
) -> dict[str, Any]: ...
def reversal_window(
    bundle_or_params: dict[str, Any] | Bundle | _Path,
    accel_mps2: float,
    oil_c: float,
    theta: Sequence[float],
    times: Sequence[float] | _F64,
) -> _F64: ...
def reversal_windows(
    bundle_or_params: dict[str, Any] | Bundle | _Path,
    accel_mps2: Sequence[float],
    oil_c: Sequence[float],
    theta: Sequence[Sequence[float]] | npt.NDArray[np.float64],
    times: Sequence[Sequence[float] | _F64],
) -> _F64: ...
def twin_trace(
    log: Log | _Path,
    bundle_or_params: dict[str, Any] | Bundle | _Path,
) -> dict[str, Any]: ...
def group_columns(name: str) -> list[str]: ...
def group_topics(name: str) -> list[str]: ...
def suite(groups: Sequence[str]) -> tuple[list[str], int]: ...
def permutations() -> list[dict[str, Any]]: ...
def extra_permutations() -> list[dict[str, Any]]: ...

@final
class Bundle:
    """A model bundle (SPEC §5), loaded and checked by dt-core. Immutable."""

    def __new__(cls, path: _Path) -> Bundle: ...
    def predict(self, x: _ArrayLike) -> _F64: ...
    def predict_f64(self, x: _ArrayLike) -> _F64: ...
    def predict_reference(self, x: _ArrayLike) -> _F64: ...
    @property
    def path(self) -> str: ...
    @property
    def columns(self) -> list[str]: ...
    @property
    def groups(self) -> list[str]: ...
    @property
    def permutation(self) -> dict[str, Any]: ...
    @property
    def physics(self) -> dict[str, dict[str, float]]: ...
    @property
    def nominal_bar(self) -> float: ...
    @property
    def health(self) -> dict[str, float]: ...
    @property
    def twin(self) -> dict[str, Any]: ...
    @property
    def backend(self) -> str: ...
    @property
    def precision(self) -> str: ...

def estimate(log: Log | _Path, bundle: Bundle | _Path, *,
             observer_baseline: dict[str, Any] | str | PathLike[str] | None = None) -> dict[str, npt.NDArray[Any]]: ...
