"""shocktwin: digital twin of an automotive shock absorber (Python bindings).

The models are dt-core's (Rust); this package is a thin shell: numpy arrays
(float64) in and out, the GIL released during long calls. The native module
``shocktwin._native`` is private; everything public is re-exported here.

- ``read_log(path) -> Log``: a run log (SPEC §2) as numpy columns.
- ``KalmanFilter``, ``ThermalModel``, ``ForceModel``: the twin's models
  (SPEC §3.1–3.3); ``default_params()`` their priors as a physics.json dict.
- ``features(log, bundle_or_params, groups)``: the 50 Hz feature table
  (SPEC §4) that training and the streaming estimator share.
- ``charge_reversals(log, bundle_or_params)``: the gas-charge observer's
  per-reversal fits over a run (calibration and analysis).
- ``road_blocks(log, calibration, baseline=None, baseline_bar=None)``: the road
  observer (dt-core ``road``) over a run: each block's reading and the estimate,
  interval and health after it.
- ``reversal_window(bundle_or_params, accel_mps2, oil_c, theta, times)``: the
  observer's window model of one reversal (calibrating its damping law);
  ``reversal_windows(bundle_or_params, accel_mps2, oil_c, theta, times)``: many
  of them end to end, on every core.
- ``twin_trace(log, bundle_or_params)``: the twin's state per 50 Hz tick from
  whatever sensors the log has (the reduced models without accelerometers or
  ambient thermocouple; calibration on a reduced campaign).
- ``Bundle(path)``: a model bundle (SPEC §5), checked; ``Bundle.predict(X)``
  runs its network on raw feature rows (a plain MLP in float32, within
  ``MLP_F32_PARITY_BAR`` of the float64 ONNX graph; ``predict_f64`` in float64).
- ``estimate(log, bundle)``: the streaming estimator (the daemon's code) over
  a whole run: pressure, 1 s average and health per 50 Hz tick.
- ``GROUPS``, ``COLUMNS``, ``group_columns``, ``group_topics``, ``suite``,
  ``SENSOR_COSTS_AUD``, ``PERMUTATIONS`` / ``permutations()``: the input
  groups, sensor costs and the paper's 13 permutations, as data;
  ``extra_permutations()`` ours beyond them (14–19: 14–16 with the
  causal-window groups ``signature`` and ``residual``, 17–19 reading the
  charge observer, group ``observer``).

Times on the Python side are in seconds (float64); the core works in
integer nanoseconds, so input times are rounded to the nanosecond.
Errors are the classes of :mod:`shocktwin.exceptions`, all derived from
``ShocktwinError``.

>>> import shocktwin
>>> shocktwin.GROUPS[:6]  # the paper's six input groups
('force', 'position', 'acceleration', 'velocity', 'mechanical', 'thermal')
>>> [p["cost_aud"] for p in shocktwin.PERMUTATIONS if p["id"] in (12, 13)]
[297, 4292]
"""

from __future__ import annotations

from typing import Any

from shocktwin._native import (
    COLUMNS,
    Bundle,
    GROUPS,
    MLP_F32_PARITY_BAR,
    SENSOR_COSTS_AUD,
    ForceModel,
    KalmanFilter,
    Log,
    ThermalModel,
    __version__,
    charge_reversals,
    road_blocks,
    reversal_window,
    reversal_windows,
    twin_trace,
    default_params,
    default_observer_params,
    estimate,
    features,
    group_columns,
    group_topics,
    permutations,
    extra_permutations,
    read_log,
    suite,
)
from shocktwin.exceptions import (
    BundleError,
    BundleNotFoundError,
    BundleReadError,
    InputError,
    LogError,
    LogReadError,
    MissingTopicsError,
    ParamsError,
    ParamsNotFoundError,
    ParamsReadError,
    PhysicsError,
    ShocktwinError,
)

#: The paper's 13 input permutations (SPEC §4), as data: a tuple of dicts
#: with ``id``, ``name``, ``groups``, ``columns``, ``sensors``, ``cost_aud``,
#: ``paper_rmse_bar``. ``permutations()`` returns a fresh, mutable copy.
PERMUTATIONS: tuple[dict[str, Any], ...] = tuple(permutations())

__all__ = [
    "__version__",
    # run logs
    "read_log",
    "Log",
    # models
    "KalmanFilter",
    "ThermalModel",
    "ForceModel",
    "default_params",
    "default_observer_params",
    # features and suites
    "features",
    "charge_reversals",
    "road_blocks",
    "reversal_window",
    "reversal_windows",
    "twin_trace",
    "GROUPS",
    "COLUMNS",
    "group_columns",
    "group_topics",
    "suite",
    "SENSOR_COSTS_AUD",
    "PERMUTATIONS",
    "permutations",
    "extra_permutations",
    # model bundles and the estimator
    "Bundle",
    "MLP_F32_PARITY_BAR",
    "estimate",
    # errors
    "ShocktwinError",
    "LogError",
    "LogReadError",
    "MissingTopicsError",
    "ParamsError",
    "ParamsReadError",
    "ParamsNotFoundError",
    "PhysicsError",
    "BundleError",
    "BundleReadError",
    "BundleNotFoundError",
    "InputError",
]
