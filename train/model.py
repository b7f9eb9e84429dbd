"""The network (paper §5.4): a feed-forward MLP, 4 hidden layers × 64, ReLU, one output
(the charge pressure in bar), trained with scikit-learn; exported to ONNX with
skl2onnx in double precision, and written with its input normalisation and the
physics into a model bundle (SPEC §5: ``twin.json`` + ``mlp.onnx``).

**The residual of the charge observer.** A network given the charge observer's estimate
(column ``observer_bar``, input group ``observer``) learns by default what the observer
misses: 62 units per hidden layer are trained on ``y − observer_bar`` from the other input
columns, and the observer's estimate is then carried through two more units per layer to
the output, exactly (``z = relu(z) − relu(−z)``; weights 1 and the column's ``std`` and
``mean``). The learned part reads neither of the observer's columns: from the estimate, or
from its standard deviation (which grows with the charge), a network learns to pull the
estimate onto the few charges the campaign was run at, which costs accuracy at every
other charge (docs/history.md, "Thirty-third session"). With the observer alone (permutation 17)
there is nothing else to read and the learned part is zero: the network answers the
observer's estimate. The bundle's network is still a plain 4 × 64 ReLU MLP from the
normalised inputs to the charge in bar, so every reader of a bundle (the estimator,
onnxruntime, tract) gets the sum without knowing; ``twin.json`` says what was learned in
``provenance.network.target``. ``fit(..., residual=False)`` (``train.train
--no-residual``) learns the charge itself, from every column.
"""

from __future__ import annotations

import copy
import datetime as _dt
import hashlib
import json
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterable, Sequence

import numpy as np
from sklearn.exceptions import ConvergenceWarning
from sklearn.neural_network import MLPRegressor

BUNDLE_FORMAT = "shocktwin-bundle/1"
HIDDEN = (64, 64, 64, 64)
# The column whose residual a network given it learns (module doc), the columns its learned
# part does not read (the observer's own), and the units per hidden layer that carry the
# column through to the output: two, relu(z) and relu(−z) (``with_passthrough``).
RESIDUAL_OF = "observer_bar"
NOT_READ_BY_RESIDUAL = ("observer_bar", "observer_sd_bar")
PASSTHROUGH_UNITS = 2
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
    # The input column whose residual the network learned (its value is added back inside
    # ``mlp``), or None when it learned the charge itself.
    residual_of: str | None = None

    def predict(self, x: np.ndarray) -> np.ndarray:
        return self.mlp.predict((x - self.mean) / self.std)


def fit(
    x: np.ndarray, y: np.ndarray, columns: Sequence[str], *, seed: int, max_iter: int = 80,
    residual: bool = True,
) -> Trained:
    """Standardise the inputs and fit the 4×64 MLP (Adam, early stopping on 10 %).

    With ``residual`` (the default) and the column ``RESIDUAL_OF`` among ``columns``, the
    network learns ``y − x[:, RESIDUAL_OF]`` from the columns not in ``NOT_READ_BY_RESIDUAL``
    and carries ``RESIDUAL_OF`` to its output (module doc); otherwise it learns ``y`` from
    every column."""
    columns = list(columns)
    mean = x.mean(axis=0)
    std = x.std(axis=0)
    std[std < 1e-12] = 1.0
    residual_of = RESIDUAL_OF if residual and RESIDUAL_OF in columns else None
    hidden = HIDDEN
    target = y
    if residual_of is not None:
        hidden = tuple(h - PASSTHROUGH_UNITS for h in HIDDEN)
        target = y - x[:, columns.index(residual_of)]
    mlp = MLPRegressor(
        hidden_layer_sizes=hidden,
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
    z = (x - mean) / std
    # A residual network reads none of the observer's columns (module doc). With nothing else
    # to read there is nothing to learn: its learned part is zero (the layers' shapes come
    # from one step on a single column of zeros).
    reads = np.array([residual_of is None or c not in NOT_READ_BY_RESIDUAL for c in columns])
    with warnings.catch_warnings():
        # The epoch budget is capped on purpose (2-core time budget); scikit-learn's
        # "not converged" warning for it is expected, not a fault.
        warnings.simplefilter("ignore", ConvergenceWarning)
        if reads.any():
            mlp.fit(z[:, reads], target)
        else:
            zeros = np.zeros((mlp.batch_size, 1))
            mlp.set_params(max_iter=1, early_stopping=False).fit(zeros, zeros[:, 0])
            mlp.coefs_ = [np.zeros_like(c) for c in mlp.coefs_]
            mlp.intercepts_ = [np.zeros_like(b) for b in mlp.intercepts_]
    if residual_of is not None:
        i = columns.index(residual_of)
        first = np.zeros((len(columns), mlp.coefs_[0].shape[1]))
        if reads.any():
            first[reads] = mlp.coefs_[0]
        mlp.coefs_[0] = first
        mlp.n_features_in_ = len(columns)
        mlp = with_passthrough(mlp, i, scale=float(std[i]), offset=float(mean[i]))
    return Trained(mlp=mlp, mean=mean, std=std, columns=columns, residual_of=residual_of)


def with_passthrough(mlp: MLPRegressor, column: int, *, scale: float, offset: float) -> MLPRegressor:
    """A copy of ``mlp`` (ReLU hidden layers, one output) that adds ``scale · z + offset`` to
    its output, ``z`` its normalised input ``column``: two more units per hidden layer carry
    ``relu(z)`` and ``relu(−z)`` through (identity weights, zero bias) and the output adds
    ``scale`` times their difference, which is ``z`` exactly."""
    out = copy.deepcopy(mlp)
    n = PASSTHROUGH_UNITS
    coefs, intercepts = [], []
    first = mlp.coefs_[0]
    w = np.zeros((first.shape[0], first.shape[1] + n))
    w[:, : first.shape[1]] = first
    w[column, -2], w[column, -1] = 1.0, -1.0
    coefs.append(w)
    intercepts.append(np.concatenate([mlp.intercepts_[0], np.zeros(n)]))
    for c, b in zip(mlp.coefs_[1:-1], mlp.intercepts_[1:-1]):
        w = np.zeros((c.shape[0] + n, c.shape[1] + n))
        w[: c.shape[0], : c.shape[1]] = c
        w[-2, -2] = w[-1, -1] = 1.0
        coefs.append(w)
        intercepts.append(np.concatenate([b, np.zeros(n)]))
    last = mlp.coefs_[-1]
    w = np.zeros((last.shape[0] + n, last.shape[1]))
    w[: last.shape[0]] = last
    w[-2, :], w[-1, :] = scale, -scale
    coefs.append(w)
    intercepts.append(mlp.intercepts_[-1] + offset)
    out.coefs_, out.intercepts_ = coefs, intercepts
    out.hidden_layer_sizes = tuple(c.shape[1] for c in coefs[:-1])
    return out


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


# How a held-out interval's errors were taken (``method`` in ``twin.json``'s ``interval``).
HELD_OUT = "held-out"  # train.train --split runs: the bundle itself on the runs it was not trained on
# train.study: the k folds' networks, each on the runs it was not trained on (every run once), for a
# bundle trained on all of them
CROSS_VALIDATED = "cross-validated"


def held_out_interval(errors: np.ndarray, runs: Sequence[str], level: float = 0.95,
                      method: str = HELD_OUT) -> dict[str, Any] | None:
    """The 95 % interval of a bundle without the charge observer (SPEC §2a; dt-core
    ``HeldOutInterval``) from ``errors``, the absolute errors of the 1 s average on the held-out
    ``runs``' ticks that have one: their ``⌈(n + 1) level⌉``-th smallest of ``n`` (the largest
    when ``n`` is too small). ``method`` says whose errors: ``HELD_OUT``, the bundle itself;
    ``CROSS_VALIDATED``, the study's fold networks, each written as a bundle and trained on fewer
    runs than the bundle (``train.study.cross_validated_interval``); both the estimator's own
    1 s average (``pressure_avg_bar``). An empirical percentile, not a coverage guarantee: a run's ticks err
    together, so it holds as far as the held-out runs are like the ones the bundle will read.
    ``None`` without an error."""
    err = np.sort(np.asarray(errors, dtype=float))
    err = err[np.isfinite(err)]
    if not len(err):
        return None
    k = min(len(err), int(np.ceil((len(err) + 1) * level))) - 1
    return {"half_width_bar": float(err[k]), "level": level, "runs": list(runs), "ticks": int(len(err)),
            "method": method}


def add_interval(bundle_dir: Path, interval: dict[str, Any]) -> None:
    """Writes ``interval`` into the bundle's ``twin.json`` (after its network has been run on the
    held-out runs to size it)."""
    path = bundle_dir / "twin.json"
    twin = json.loads(path.read_text())
    twin["interval"] = interval
    path.write_text(json.dumps(twin, indent=2) + "\n")


def trained_excitations(runs: Iterable[Any]) -> list[str]:
    """The distinct ``excitation`` metadata (SPEC §2) of the runs a network is trained on,
    sorted: the bundle's ``provenance.trained_excitations``, from which the estimator (dt-core
    ``Bundle::untrained_excitation``) says when a run's excitation is none of them."""
    return sorted({str(e).strip() for r in runs if (e := r.log.metadata.get("excitation"))})


# What a bundle's provenance must say (SPEC §5; dt-core ``bundle::PROVENANCE_KEYS``).
PROVENANCE_KEYS = ("campaign_digest", "split", "seed", "metrics")


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
    """Write ``twin.json`` + ``mlp.onnx`` (SPEC §5) into ``out_dir``. ``provenance`` must say
    ``PROVENANCE_KEYS`` (a value may be ``None`` where there is none): loading checks them."""
    missing = [k for k in PROVENANCE_KEYS if k not in provenance]
    if missing:
        raise ValueError(f"a bundle's provenance must say {', '.join(missing)} (SPEC §5)")
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
            "network": {
                "hidden": [c.shape[1] for c in trained.mlp.coefs_[:-1]],
                "activation": "relu",
                "library": "scikit-learn",
                "target": "charge_bar" if trained.residual_of is None else
                f"charge_bar - {trained.residual_of} (learned by {HIDDEN[0] - PASSTHROUGH_UNITS} units "
                f"per layer; {trained.residual_of} carried through {PASSTHROUGH_UNITS} more)",
            },
            **provenance,
        },
    }
    (out_dir / "twin.json").write_text(json.dumps(twin, indent=2) + "\n")
    return out_dir
