"""Feature tables of a campaign for training and evaluation (SPEC §4).

Features always come from ``shocktwin.features`` — the Rust pipeline the daemon runs.
Each run's table is computed once with every group its sensors allow; a permutation
then selects its columns, so the 13 (or 63) suites share one pass over the logs.

Rest periods: the paper's network sees every 50 Hz sample, but a damper at rest
carries no information about its gas charge beyond the static rod force. Samples are
used for training and scored for evaluation only when the twin's excitation measure
(velocity RMS over the last second, computed causally) is at least
``EXCITED_MPS``; the estimator reports ``unknown`` health below it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np

import shocktwin

from train.campaign import Campaign, CampaignError, Run

ALL_GROUPS = ["force", "position", "acceleration", "velocity", "mechanical", "thermal"]
EXCITED_MPS = 0.05
TICK_S = 0.02


@dataclass
class RunTable:
    """The 50 Hz feature table of one run (every available column)."""

    run: Run
    t_s: np.ndarray
    columns: list[str]
    x: np.ndarray  # [n, k] every available column
    excited: np.ndarray  # bool [n]
    label_bar: float

    def select(self, columns: Sequence[str]) -> np.ndarray:
        idx = [self.columns.index(c) for c in columns]
        return self.x[:, idx]


def excitation(velocity: np.ndarray, window: int = int(round(1.0 / TICK_S))) -> np.ndarray:
    """Causal RMS of velocity over the last ``window`` ticks (the twin's excitation measure)."""
    v2 = np.nan_to_num(velocity) ** 2
    c = np.cumsum(np.concatenate([[0.0], v2]))
    n = np.arange(1, len(v2) + 1)
    lo = np.maximum(n - window, 0)
    return np.sqrt((c[n] - c[lo]) / (n - lo))


def available_groups(run: Run) -> list[str]:
    topics = set(run.log.topics)
    return [g for g in ALL_GROUPS if set(shocktwin.group_topics(g)) <= topics]


def run_table(run: Run, physics: dict[str, Any], groups: Sequence[str] | None = None) -> RunTable:
    groups = list(groups) if groups is not None else available_groups(run)
    x, columns, t_s = shocktwin.features(run.log, physics, groups)
    if "velocity_mps" in columns:
        exc = excitation(x[:, columns.index("velocity_mps")]) >= EXCITED_MPS
    else:
        exc = np.ones(len(t_s), dtype=bool)
    if run.label_bar is None:
        raise CampaignError(f"{run.name}: no charge_pressure_bar label")
    return RunTable(run=run, t_s=np.asarray(t_s), columns=list(columns), x=x, excited=exc,
                    label_bar=float(run.label_bar))


def campaign_tables(campaign: Campaign, physics: dict[str, Any]) -> list[RunTable]:
    campaign.require_labels()
    return [run_table(run, physics) for run in campaign.runs]


def check_groups(tables: Sequence[RunTable], groups: Sequence[str]) -> list[str]:
    """The ordered feature columns of ``groups``; an error names runs lacking their sensors."""
    columns = [c for g in groups for c in shocktwin.group_columns(g)]
    lacking = []
    for tab in tables:
        missing = [c for c in columns if c not in tab.columns]
        if missing:
            topics = sorted({t for g in groups for t in shocktwin.group_topics(g)} - set(tab.run.log.topics))
            lacking.append(f"{tab.run.name} lacks {', '.join(topics) or ', '.join(missing)}")
    if lacking:
        raise CampaignError(f"groups {'+'.join(groups)}: " + "; ".join(lacking))
    return columns


def stack(
    tables: Sequence[RunTable], columns: Sequence[str], *, stride: int = 1, excited_only: bool = True
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """X, y, run index of the chosen columns over ``tables`` (every ``stride``-th excited tick)."""
    xs, ys, gs = [], [], []
    for i, tab in enumerate(tables):
        sel = tab.excited if excited_only else np.ones(len(tab.t_s), dtype=bool)
        x = tab.select(columns)
        sel = sel & np.all(np.isfinite(x), axis=1)
        idx = np.nonzero(sel)[0][::stride]
        xs.append(x[idx])
        ys.append(np.full(len(idx), tab.label_bar))
        gs.append(np.full(len(idx), i))
    return np.concatenate(xs), np.concatenate(ys), np.concatenate(gs)
