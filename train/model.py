"""The network (paper §5.4): a feed-forward MLP, 4 hidden layers × 64, ReLU, one output
(the charge pressure in bar), trained with scikit-learn; exported to ONNX with
skl2onnx in double precision, and written with its input normalisation and the
physics into a model bundle (SPEC §5: ``twin.json`` + ``mlp.onnx``).
"""

from __future__ import annotations

import datetime as _dt
import hashlib
import json
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np
from sklearn.exceptions import ConvergenceWarning
from sklearn.neural_network import MLPRegressor

BUNDLE_FORMAT = "shocktwin-bundle/1"
HIDDEN = (64, 64, 64, 64)
ONNX_INPUT = "x"
ONNX_OUTPUT = "pressure_bar"
DEFAULT_HEALTH = {
    "warn_bar": 9.0,
    "fault_bar": 5.0,
    "hysteresis_bar": 0.5,
    "dwell_s": 3.0,
    "min_excitation_mps": 0.05,
}


@dataclass
class Trained:
    """A trained network with the normalisation of its inputs."""

    mlp: MLPRegressor
    mean: np.ndarray
    std: np.ndarray
    columns: list[str]

    def predict(self, x: np.ndarray) -> np.ndarray:
        return self.mlp.predict((x - self.mean) / self.std)


def fit(
    x: np.ndarray, y: np.ndarray, columns: Sequence[str], *, seed: int, max_iter: int = 80
) -> Trained:
    """Standardise the inputs and fit the 4×64 MLP (Adam, early stopping on 10 %)."""
    mean = x.mean(axis=0)
    std = x.std(axis=0)
    std[std < 1e-12] = 1.0
    mlp = MLPRegressor(
        hidden_layer_sizes=HIDDEN,
        activation="relu",
        solver="adam",
        alpha=1e-4,
        batch_size=256,
        learning_rate_init=1e-3,
        max_iter=max_iter,
        early_stopping=True,
        validation_fraction=0.1,
        n_iter_no_change=8,
        random_state=seed,
    )
    with warnings.catch_warnings():
        # The epoch budget is capped on purpose (2-core time budget); scikit-learn's
        # "not converged" warning for it is expected, not a fault.
        warnings.simplefilter("ignore", ConvergenceWarning)
        mlp.fit((x - mean) / std, y)
    return Trained(mlp=mlp, mean=mean, std=std, columns=list(columns))


def to_onnx(trained: Trained) -> bytes:
    """The MLP alone (normalised inputs → bar), float64, as ONNX bytes."""
    from skl2onnx import convert_sklearn
    from skl2onnx.common.data_types import DoubleTensorType

    onx = convert_sklearn(
        trained.mlp,
        initial_types=[(ONNX_INPUT, DoubleTensorType([None, len(trained.columns)]))],
        final_types=[(ONNX_OUTPUT, DoubleTensorType([None, 1]))],
        target_opset=13,
    )
    return onx.SerializeToString()


def write_bundle(
    out_dir: Path,
    trained: Trained,
    *,
    permutation: dict[str, Any],
    physics: dict[str, Any],
    nominal_bar: float,
    provenance: dict[str, Any],
    health: dict[str, float] | None = None,
) -> Path:
    """Write ``twin.json`` + ``mlp.onnx`` (SPEC §5) into ``out_dir``."""
    out_dir.mkdir(parents=True, exist_ok=True)
    onnx_bytes = to_onnx(trained)
    (out_dir / "mlp.onnx").write_bytes(onnx_bytes)
    twin = {
        "format": BUNDLE_FORMAT,
        "permutation": {
            "id": permutation["id"],
            "name": permutation["name"],
            "groups": list(permutation["groups"]),
            "columns": list(trained.columns),
        },
        "normalisation": {"mean": trained.mean.tolist(), "std": trained.std.tolist()},
        "physics": {k: physics[k] for k in ("kalman", "thermal", "force", "observer") if k in physics},
        "nominal_bar": nominal_bar,
        "health": dict(health or DEFAULT_HEALTH),
        "onnx": {
            "file": "mlp.onnx",
            "input": ONNX_INPUT,
            "output": ONNX_OUTPUT,
            "dtype": "float64",
            "sha256": hashlib.sha256(onnx_bytes).hexdigest(),
        },
        "provenance": {
            "created_utc": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
            "network": {"hidden": list(HIDDEN), "activation": "relu", "library": "scikit-learn"},
            **provenance,
        },
    }
    (out_dir / "twin.json").write_text(json.dumps(twin, indent=2) + "\n")
    return out_dir
