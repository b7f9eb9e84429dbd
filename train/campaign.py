"""Loading a campaign (a directory of run logs) for the training tools.

A campaign is a directory of ``*.mcap`` run files (SPEC §2); labels come from each
run's ``shocktwin.run`` metadata. One unreadable run is reported and skipped, never
fatal; a campaign with no usable run, or runs without labels where labels are
needed, is an error that names the runs.
"""

from __future__ import annotations

import hashlib
import json
import logging
import signal
import sys
import threading
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Sequence

import shocktwin

log = logging.getLogger("shocktwin.train")


class CampaignError(Exception):
    """A campaign cannot be used for the requested job; the message says why."""


@dataclass
class Run:
    """One readable run of a campaign."""

    path: Path
    log: Any  # shocktwin.Log
    run_id: str
    asset_id: str
    label_bar: float | None
    frequency_hz: float | None

    @property
    def name(self) -> str:
        return self.path.name


@dataclass
class Campaign:
    """The readable runs of a campaign directory, and the files that were skipped."""

    root: Path
    runs: list[Run]
    skipped: list[tuple[Path, str]] = field(default_factory=list)

    def digest(self) -> str:
        """SHA-256 over the run files' names and bytes (training provenance)."""
        h = hashlib.sha256()
        for run in sorted(self.runs, key=lambda r: r.name):
            h.update(run.name.encode())
            with open(run.path, "rb") as fh:
                for block in iter(lambda: fh.read(1 << 20), b""):
                    h.update(block)
        return h.hexdigest()

    def require_labels(self) -> None:
        missing = [r.name for r in self.runs if r.label_bar is None]
        if missing:
            raise CampaignError(
                f"{self.root}: runs without a charge_pressure_bar label: {', '.join(missing)}"
            )

    def nominal(self, nominal_bar: float, *, tol_bar: float = 0.05) -> list[Run]:
        """The runs at the nominal charge pressure (the calibration set, paper §5.2.3)."""
        self.require_labels()
        runs = [r for r in self.runs if abs(r.label_bar - nominal_bar) <= tol_bar]  # type: ignore[operator]
        if not runs:
            charges = ", ".join(f"{c:g}" for c in sorted({float(r.label_bar) for r in self.runs}))  # type: ignore[arg-type]
            labelled = ", ".join(f"{r.name} {r.label_bar:g} bar" for r in self.runs[:12])
            more = f" and {len(self.runs) - 12} more" if len(self.runs) > 12 else ""
            raise CampaignError(
                f"{self.root}: no nominal runs at {nominal_bar:g} bar (±{tol_bar:g}); the charges present are "
                f"{charges} bar: give the nominal one with --nominal-bar or --nominal "
                f"(the runs are labelled: {labelled}{more})"
            )
        return runs

    @property
    def simulated(self) -> bool:
        """Whether every run says it was simulated (``simulated = true`` in its metadata)."""
        return all(str(r.log.metadata.get("simulated", "")).lower() == "true" for r in self.runs)


def _meta_float(meta: dict[str, Any], key: str) -> float | None:
    value = meta.get(key)
    if value is None or value == "":
        return None
    return float(value)


def read_run(path: Path) -> Run:
    """One run log with its metadata's labels (raises ``shocktwin.LogError``/``OSError``)."""
    lg = shocktwin.read_log(str(path))
    meta = lg.metadata
    return Run(path=path, log=lg, run_id=str(meta.get("run_id", path.stem)), asset_id=str(meta.get("asset_id", "")),
               label_bar=_meta_float(meta, "charge_pressure_bar"), frequency_hz=_meta_float(meta, "frequency_hz"))


def load_campaign(root: str | Path) -> Campaign:
    """Read every ``*.mcap`` in ``root``; unreadable runs are reported and skipped."""
    root = Path(root)
    if not root.is_dir():
        raise CampaignError(f"{root}: campaign directory not found")
    files = sorted(root.glob("*.mcap"))
    if not files:
        raise CampaignError(f"{root}: no *.mcap run files")
    runs: list[Run] = []
    skipped: list[tuple[Path, str]] = []
    for path in files:
        try:
            runs.append(read_run(path))
        except (shocktwin.LogError, OSError) as err:
            log.warning("skipping unreadable run %s: %s", path.name, err)
            skipped.append((path, str(err)))
    if not runs:
        raise CampaignError(f"{root}: none of the {len(files)} run files could be read")
    return Campaign(root=root, runs=runs, skipped=skipped)


def require_topics(runs: Sequence[Run], topics: Sequence[str], what: str) -> None:
    """Error naming every run that lacks one of ``topics`` (needed for ``what``)."""
    lacking = []
    for run in runs:
        missing = [t for t in topics if t not in run.log.topics]
        if missing:
            lacking.append(f"{run.name} lacks {', '.join(missing)}")
        # an empty topic is as good as a missing one
    if lacking:
        raise CampaignError(f"{what}: " + "; ".join(lacking))


def read_json(path: Path | str) -> Any:
    """The JSON document in ``path``; a file that is not JSON is an error naming it and where."""
    path = Path(path)
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError as err:
        raise ValueError(f"{path}: not JSON ({err.msg} at line {err.lineno}, column {err.colno})") from None


def _terminated(signum: int, _frame: Any) -> None:
    raise SystemExit(128 + signum)


def main_wrapper(main: Callable[[Sequence[str] | None], int]) -> Callable[[Sequence[str] | None], int]:
    """Run a CLI ``main``: exit 0 on success, non-zero with a one-line reason on stderr."""

    def wrapped(argv: Sequence[str] | None = None) -> int:
        logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
        # `kill` or a timeout ends the run as Ctrl-C does, through every `finally` and
        # temporary directory's clean-up (a killed study left its observer folds in /tmp)
        if threading.current_thread() is threading.main_thread():
            signal.signal(signal.SIGTERM, _terminated)
        try:
            return main(argv)
        except (CampaignError, shocktwin.ShocktwinError, OSError, ValueError) as err:
            print(f"{Path(sys.argv[0]).stem}: {err}", file=sys.stderr)
            return 1

    return wrapped
