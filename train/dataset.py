"""Feature tables of a campaign for training and evaluation (SPEC §4).

Features always come from ``shocktwin.features`` — the Rust pipeline the daemon runs.
A model uses only the sensors of its suite (the pipeline is given only the topics its
groups need), so tables are computed once per distinct *sensor suite* (set of topics)
and shared by every permutation on that suite.

Rest periods: the paper's network sees every 50 Hz sample, but a damper at rest
carries no information about its gas charge beyond the static rod force. Samples are
used for training and scored only where the damper is excited: the causal RMS of the
full-suite Kalman velocity over the last second is at least ``EXCITED_MPS`` (the
daemon's health is ``unknown`` below it). The same samples are scored for every
suite, so suites are compared on equal terms. A run without accelerometers has no
full-suite velocity: its excitation is the twin's own measure, the 1 s RMS of the
position-only Kalman velocity (``shocktwin.twin_trace``), as the daemon computes it
for such a unit.
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np

import shocktwin

from train.campaign import Campaign, CampaignError, Run

#: The paper's six input groups (SPEC §4): the sensor-suite search spans these.
PAPER_GROUPS = ["force", "position", "acceleration", "velocity", "mechanical", "thermal"]
#: Every group the bindings know (the paper's six and any causal-window groups).
ALL_GROUPS = list(shocktwin.GROUPS)
EXCITED_MPS = 0.05
TICK_S = 0.02


@dataclass
class RunTable:
    """The 50 Hz feature table of one run for one sensor suite."""

    run: Run
    t_s: np.ndarray
    columns: list[str]
    x: np.ndarray  # [n, k]
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


def suite_topics(groups: Sequence[str]) -> frozenset[str]:
    return frozenset(t for g in groups for t in shocktwin.group_topics(g))


def groups_within(topics: frozenset[str]) -> list[str]:
    """Every group whose sensors are in ``topics`` (the columns that suite can give)."""
    return [g for g in ALL_GROUPS if set(shocktwin.group_topics(g)) <= topics]


def group_columns(groups: Sequence[str]) -> list[str]:
    return [c for g in groups for c in shocktwin.group_columns(g)]


def with_observer(
    within: Sequence[str], computed: tuple[np.ndarray, list[str], Any], shared: RunTable
) -> tuple[np.ndarray, list[str], Any]:
    """``shocktwin.features``' result for ``within`` from the run's table without the observer
    (``computed``) and the observer columns of another suite's table of the same run
    (``shared``), in ``within``'s column order (each group's columns together, in group order)."""
    x, columns, t_s = computed
    if not np.array_equal(np.asarray(t_s), shared.t_s):
        raise RuntimeError(f"{shared.run.name}: the tables' ticks differ: the observer's columns cannot be shared")
    cut = len(group_columns(within[: list(within).index("observer")]))
    names = shocktwin.group_columns("observer")
    obs = shared.x[:, [shared.columns.index(c) for c in names]]
    return np.hstack([x[:, :cut], obs, x[:, cut:]]), [*columns[:cut], *names, *columns[cut:]], t_s


@dataclass
class CampaignData:
    """A labelled campaign's feature tables, computed lazily per sensor suite."""

    campaign: Campaign
    physics: dict[str, Any]
    _tables: dict[tuple[frozenset[str], bool], list[RunTable]] = field(default_factory=dict)
    _excited: list[np.ndarray] | None = None

    def __post_init__(self) -> None:
        self.campaign.require_labels()

    def tables(self, groups: Sequence[str]) -> list[RunTable]:
        """Tables of every run for the suite of ``groups``; an error names runs lacking sensors."""
        topics = suite_topics(groups)
        # the charge observer is costly: computed only for suites that ask for it
        key = (topics, "observer" in groups)
        if key not in self._tables:
            lacking = [
                f"{r.name} lacks {', '.join(sorted(topics - set(r.log.topics)))}"
                for r in self.campaign.runs
                if not topics <= set(r.log.topics)
            ]
            if lacking:
                raise CampaignError(f"input groups {'+'.join(groups)}: " + "; ".join(lacking))
            within = [g for g in groups_within(topics) if g != "observer" or key[1]]
            shared = self._observer_from_suite_without_loadcell(topics, within) if key[1] else None
            # the bindings release the GIL: the runs' pipelines (the observer's window fits
            # above all) run side by side on every core, each run's table the same as alone
            runs = self.campaign.runs
            computing = [g for g in within if g != "observer"] if shared is not None else within
            with ThreadPoolExecutor(max_workers=max(1, min(len(runs), os.cpu_count() or 1))) as pool:
                computed = list(pool.map(lambda run: shocktwin.features(run.log, self.physics, computing), runs))
            if shared is not None:
                computed = [with_observer(within, c, s) for c, s in zip(computed, shared)]
            self._tables[key] = [
                RunTable(run, np.asarray(t_s), list(columns), x, float(run.label_bar))  # type: ignore[arg-type]
                for run, (x, columns, t_s) in zip(runs, computed)
            ]
        return self._tables[key]

    def _observer_from_suite_without_loadcell(
        self, topics: frozenset[str], within: Sequence[str]
    ) -> list[RunTable] | None:
        """For a suite with the loadcell and the observer: the same suite's tables without the
        loadcell, whose observer columns are this suite's (the observer reads the accelerometers,
        the potentiometer and the thermal model, never the loadcell: the window fits, the
        costliest part of a table, are then done once for both suites;
        ``test_the_observer_reads_no_loadcell``). None when there is nothing to share."""
        if "/force" not in topics:
            return None
        lean = [g for g in within if "/force" not in shocktwin.group_topics(g)]
        if "observer" not in lean or suite_topics(lean) != topics - {"/force"}:
            return None
        return self.tables(lean)

    def recalibrated(self, physics: dict[str, Any]) -> "CampaignData":
        """The same campaign under ``physics`` that differs from this one's in the observer alone
        (``train.observer_folds``): the excited ticks, which do not read the observer, are kept."""
        other = CampaignData(self.campaign, physics)
        other._excited = self.excited()
        return other

    def excited(self) -> list[np.ndarray]:
        """Per run, the excited ticks (full-suite Kalman velocity; see the module doc)."""
        if self._excited is None:
            if all("/acceleration" in r.log.topics for r in self.campaign.runs):
                tabs = self.tables(["velocity"])
                velocities = [t.select(["velocity_mps"])[:, 0] for t in tabs]
            else:  # the reduced model where a run lacks accelerometers (see the module doc)
                velocities = [
                    shocktwin.features(r.log, self.physics, ["velocity"])[0][:, 0]
                    if "/acceleration" in r.log.topics
                    else np.asarray(shocktwin.twin_trace(r.log, self.physics)["velocity_mps"])
                    for r in self.campaign.runs
                ]
            self._excited = [excitation(v) >= EXCITED_MPS for v in velocities]
        return self._excited

    def excited_for(self, tabs: Sequence[RunTable]) -> list[np.ndarray]:
        """The excited masks aligned to ``tabs`` (a suite's last tick may differ by one)."""
        out = []
        for tab, exc in zip(tabs, self.excited()):
            n = len(tab.t_s)
            out.append(exc[:n] if len(exc) >= n else np.concatenate([exc, np.zeros(n - len(exc), bool)]))
        return out
