"""shocktwin: digital twin of an automotive shock absorber (Python bindings).

The models are dt-core's (Rust); this package is a thin shell: numpy arrays
(float64) in and out, the GIL released during long calls. The native module
``shocktwin._native`` is private; everything public is re-exported here.

Times on the Python side are in seconds (float64); the core works in
integer nanoseconds, so times are rounded to the nanosecond on the way in.
"""

from shocktwin._native import ForceModel, KalmanFilter, ThermalModel, __version__, default_params
from shocktwin.exceptions import (
    BundleError,
    InputError,
    LogError,
    LogReadError,
    MissingTopicsError,
    ParamsError,
    PhysicsError,
    ShocktwinError,
)

__all__ = [
    "__version__",
    "KalmanFilter",
    "ThermalModel",
    "ForceModel",
    "default_params",
    "ShocktwinError",
    "LogError",
    "LogReadError",
    "MissingTopicsError",
    "ParamsError",
    "PhysicsError",
    "BundleError",
    "InputError",
]
