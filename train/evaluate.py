"""Evaluation protocols (paper §5.4.2 and the held-out protocol) shared by the study.

- *paper*: the excited 50 Hz samples of all runs are split at random 75/25; the
  network is trained on the 75 % and scored on the 25 %. Neighbouring samples of
  one run (20 ms apart, nearly identical) fall on both sides: this leaks.
- *held-out runs*: whole runs are held out (grouped k-fold by run); every run is
  scored by a network that never saw it — what a deployed twin meets.
- *in-sample*: trained and scored on every sample. Not a protocol and not an
  information bound either: with a constant label per run, slowly varying inputs
  (temperatures) let it memorise runs. The study's bound is its *oracle*
  (``train.study``): the same network trained with a repeat take of the test
  conditions added (same rig and unit, new noise and room), scored on the test runs.

Training rows get *temperature-offset augmentation* (``shift_temperatures``): each
run's rows are dealt round-robin to four copies of the run, three of which see every
absolute temperature column shifted by one common offset drawn from N(0, 5 °C). A
deployed twin meets rooms and thermocouples other than the dyno's; without it a
network with the thermal group identifies the campaign's runs by their temperatures
(15 runs, one label each) instead of reading the physics. The row count is unchanged.

RMSE in bar over excited samples (rest periods are excluded, see
``train.dataset``), instantaneous and after a causal 1 s moving average of the
run's own estimates (the daemon's ``pressure_avg_bar``).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from train import dataset, model
from train.dataset import RunTable

AVG_TICKS = 50  # 1 s at 50 Hz
# Absolute temperatures (°C) that a common offset shifts; differences and rates are left alone.
TEMPERATURE_COLUMNS = ("temp_shock_c", "temp_ambient_c", "oil_temp_model_c", "cyl_temp_model_c")
TEMP_SHIFT_SD_C = 5.0
TEMP_SHIFT_COPIES = 3
AUGMENTATION = {"temperature_shift_sd_c": TEMP_SHIFT_SD_C, "shifted_copies": TEMP_SHIFT_COPIES,
                "columns": list(TEMPERATURE_COLUMNS)}


def moving_average(x: np.ndarray, n: int = AVG_TICKS) -> np.ndarray:
    """Causal mean over the last ``n`` values (fewer at the start)."""
    c = np.cumsum(np.concatenate([[0.0], x]))
    i = np.arange(1, len(x) + 1)
    lo = np.maximum(i - n, 0)
    return (c[i] - c[lo]) / (i - lo)


@dataclass
class Scores:
    rmse_bar: float
    rmse_avg_bar: float
    n: int

    def as_dict(self) -> dict[str, float]:
        return {"rmse_bar": self.rmse_bar, "rmse_avg_bar": self.rmse_avg_bar, "n": self.n}


def _rmse(err: np.ndarray) -> float:
    return float(np.sqrt(np.mean(err**2))) if len(err) else float("nan")


@dataclass
class RunPrediction:
    """Predictions of one run on its excited, finite ticks (in time order)."""

    table: RunTable
    idx: np.ndarray  # tick indices
    pred: np.ndarray

    def averaged(self) -> np.ndarray:
        return moving_average(self.pred)


def predict_run(trained: model.Trained, tab: RunTable, columns: Sequence[str], excited: np.ndarray) -> RunPrediction:
    x = tab.select(columns)
    sel = excited & np.all(np.isfinite(x), axis=1)
    idx = np.nonzero(sel)[0]
    pred = trained.predict(x[idx]) if len(idx) else np.empty(0)
    return RunPrediction(tab, idx, pred)


def _limit_threads() -> None:
    # Two processes on two cores train faster than one process with two BLAS threads.
    try:
        from threadpoolctl import threadpool_limits

        threadpool_limits(1)
    except ImportError:  # pragma: no cover - threadpoolctl ships with scikit-learn
        os.environ.setdefault("OMP_NUM_THREADS", "1")


def fit_job(x: np.ndarray, y: np.ndarray, columns: Sequence[str], seed: int, max_iter: int) -> model.Trained:
    _limit_threads()
    return model.fit(x, y, columns, seed=seed, max_iter=max_iter)


def held_out_folds(n_runs: int, k: int, seed: int) -> list[np.ndarray]:
    """Grouped k-fold over runs: each run is held out exactly once."""
    rng = np.random.default_rng(seed)
    order = rng.permutation(n_runs)
    return [np.sort(order[i::k]) for i in range(k)]


def score_runs(preds: Sequence[RunPrediction]) -> Scores:
    err = np.concatenate([p.pred - p.table.label_bar for p in preds]) if preds else np.empty(0)
    err_avg = np.concatenate([p.averaged() - p.table.label_bar for p in preds]) if preds else np.empty(0)
    return Scores(_rmse(err), _rmse(err_avg), len(err))


def per_run(preds: Sequence[RunPrediction]) -> list[dict[str, float | str]]:
    out = []
    for p in preds:
        out.append(
            {
                "run": p.table.run.name,
                "label_bar": p.table.label_bar,
                "rmse_bar": _rmse(p.pred - p.table.label_bar),
                "rmse_avg_bar": _rmse(p.averaged() - p.table.label_bar),
                "mean_bar": float(np.mean(p.pred)) if len(p.pred) else float("nan"),
            }
        )
    return out


def paper_split(tables: Sequence[RunTable], seed: int) -> list[np.ndarray]:
    """Per run, a boolean mask of the test ticks of the random 75/25 split."""
    rng = np.random.default_rng(seed)
    return [rng.random(len(t.t_s)) < 0.25 for t in tables]


def score_paper(
    trained: model.Trained, tables: Sequence[RunTable], columns: Sequence[str],
    excited: Sequence[np.ndarray], test_masks: Sequence[np.ndarray],
) -> Scores:
    """Scores on the test ticks. The 1 s average runs over the run's full series of
    estimates (train and test ticks alike, as a deployed average would) and is
    scored on the test ticks."""
    err, err_avg = [], []
    for tab, exc, test in zip(tables, excited, test_masks):
        p = predict_run(trained, tab, columns, exc)
        if not len(p.idx):
            continue
        is_test = test[p.idx]
        err.append(p.pred[is_test] - tab.label_bar)
        err_avg.append(p.averaged()[is_test] - tab.label_bar)
    e = np.concatenate(err) if err else np.empty(0)
    ea = np.concatenate(err_avg) if err_avg else np.empty(0)
    return Scores(_rmse(e), _rmse(ea), len(e))


def shift_temperatures(x: np.ndarray, columns: Sequence[str], rng: np.random.Generator,
                       sd_c: float = TEMP_SHIFT_SD_C, copies: int = TEMP_SHIFT_COPIES) -> np.ndarray:
    """One run's rows with temperature-offset augmentation (see the module doc): row j
    belongs to copy ``j mod (copies + 1)``; copy 0 is unchanged, copy c > 0 has every
    column of ``TEMPERATURE_COLUMNS`` shifted by its own offset ~ N(0, sd_c)."""
    idx = [i for i, c in enumerate(columns) if c in TEMPERATURE_COLUMNS]
    if not idx or copies == 0 or not len(x):
        return x
    offsets = np.concatenate([[0.0], rng.normal(0.0, sd_c, size=copies)])
    out = x.copy()
    out[:, idx] += offsets[np.arange(len(x)) % (copies + 1)][:, None]
    return out


def training_set(
    tables: Sequence[RunTable], columns: Sequence[str], excited: Sequence[np.ndarray],
    masks: Sequence[np.ndarray] | None, per_run: int, *, seed: int = 0, augment: bool = True,
) -> tuple[np.ndarray, np.ndarray]:
    """Training rows: excited, finite, inside ``masks`` (all when None); at most ``per_run``
    evenly spaced rows of each run, so that long slow runs do not outweigh short fast ones
    (a 1 Hz run lasts ~10x a 4 Hz run) and 50 Hz neighbours (nearly identical) are thinned.
    With ``augment``, temperature-offset augmentation (``shift_temperatures``, seeded by
    ``seed`` and the run's position)."""
    xs, ys = [], []
    for i, tab in enumerate(tables):
        x = tab.select(columns)
        sel = excited[i] & np.all(np.isfinite(x), axis=1)
        if masks is not None:
            sel &= masks[i]
        idx = np.nonzero(sel)[0]
        if len(idx) > per_run:
            idx = idx[np.linspace(0, len(idx) - 1, per_run).round().astype(int)]
        rows = x[idx]
        if augment:
            rows = shift_temperatures(rows, columns, np.random.default_rng([seed, i]))
        xs.append(rows)
        ys.append(np.full(len(idx), tab.label_bar))
    return np.concatenate(xs), np.concatenate(ys)


__all__ = [
    "Scores", "RunPrediction", "moving_average", "predict_run", "fit_job", "held_out_folds",
    "score_runs", "per_run", "paper_split", "score_paper", "training_set", "shift_temperatures",
    "TEMPERATURE_COLUMNS", "AUGMENTATION", "dataset",
]
