"""Permutations that read the charge observer, held out with the observer calibrated per fold.

A network that reads the observer, held out on whole runs, must not read an observer calibrated on
those runs: one calibration made on every run of the campaign, shared between the folds, leaks
(in the fifty-fourth session, docs/history.md, it made 17 / 18 / 19 read 0.22 / 0.25 / 0.25 bar
held out on the full simulated campaign, against 0.47 / 0.46 / 0.38 calibrated per fold).
``FoldObservers`` calibrates the observer by ``python -m train.observer fit`` on each fold's
training runs alone; ``train.study`` holds out every permutation and suite that reads the observer
with it. The physics under the observer (Kalman, thermal and force) stays the given file's, as it
does for every permutation in the study. The observer's sd is then the fit's assumed unit
tolerance: the unit and transfer spreads that ``make study`` measures on other units are not
measured per fold. This command runs the study's held-out protocol for those permutations alone:

    python -m train.observer_folds --campaign DIR --physics physics.json --out DIR
        [--datasheet FILE] [--permutations 17,18,19] [--quick] [--folds K] [--seed 0] [--jobs 2]
        [--law-runs nominal|complete]

Writes ``DIR/observer_folds.json`` (per permutation its held-out scores and runs, per fold the
runs held out and the shape the fit took) and each fold's calibration under ``DIR/fold-K/``.
"""
from __future__ import annotations

import argparse
import json
import logging
import os
import shutil
from pathlib import Path
from typing import Any, Sequence

import shocktwin

from train import dataset
from train import observer as observer_tool
from train.campaign import load_campaign, main_wrapper, read_json

log = logging.getLogger("shocktwin.observer_folds")

#: The observer's datasheet values (not fitted): a fold's fit keeps the given observer's.
GEOMETRY = ("a_rod_m2", "v_gas_m3", "oil_expansion_m3_per_k")


def fold_physics(physics: dict[str, Any], runs: Sequence[Any], held: Sequence[int], work: Path,
                 datasheet: Path | None, jobs: int, fit_args: Sequence[str] = ()) -> dict[str, Any]:
    """``physics`` with its observer calibrated on the runs not in ``held`` (symbolic links to them
    in ``work/campaign``); the calibration is kept in ``work/physics.json``. Without a
    ``datasheet`` the fit takes the given observer's geometry (``a_rod_m2``, ``v_gas_m3``,
    ``oil_expansion_m3_per_k``, datasheet values, not fitted), so that only its runs differ.
    ``fit_args``: more options of ``observer fit``."""
    camp = work / "campaign"
    if camp.exists():  # a run before this one into the same --out: its links go
        shutil.rmtree(camp)
    camp.mkdir(parents=True)
    held_set = set(int(i) for i in held)
    for i, run in enumerate(runs):
        if i not in held_set:
            (camp / run.path.name).symlink_to(run.path.resolve())
    # the shared observer goes, and with it the records of what was measured on it (`fit.observer`,
    # `fit.observer_unit_spread`, ...): they describe another calibration than the fold's
    base = {k: v for k, v in physics.items() if k != "observer"}
    if "fit" in base:
        base["fit"] = {k: v for k, v in base["fit"].items() if not k.startswith("observer")}
    out = work / "physics.json"
    out.write_text(json.dumps(base, indent=2) + "\n")
    if datasheet is None and physics.get("observer"):
        geometry = {k: physics["observer"][k] for k in GEOMETRY if k in physics["observer"]}
        datasheet = work / "datasheet.json"
        datasheet.write_text(json.dumps(geometry, indent=2) + "\n")
    argv = ["fit", "--campaign", str(camp), "--physics", str(out), "--jobs", str(jobs), *fit_args]
    if datasheet is not None:
        argv += ["--datasheet", str(datasheet)]
    if observer_tool.main(argv) != 0:
        raise SystemExit(f"{camp}: the observer fit failed")
    return read_json(out)


class FoldObservers:
    """The campaign's tables with the observer calibrated on each fold's training runs alone
    (``fold_physics``), calibrated once per fold: a fold is named by its held-out runs.
    ``train.study.evaluate_permutation_set`` takes it for the permutations that read the
    observer; each fold's calibration is kept under ``work/fold-K`` (K in the order asked)."""

    def __init__(self, data: dataset.CampaignData, work: Path, datasheet: Path | None, jobs: int,
                 fit_args: Sequence[str] = ()) -> None:
        self.data, self.work, self.datasheet, self.jobs = data, work, datasheet, jobs
        self.fit_args = tuple(fit_args)
        self._folds: dict[tuple[int, ...], dataset.CampaignData] = {}

    def __call__(self, held: Sequence[int]) -> dataset.CampaignData:
        key = tuple(sorted(int(i) for i in held))
        if key not in self._folds:
            runs = self.data.campaign.runs
            log.info("calibrating the observer without %s", ", ".join(runs[i].path.name for i in key))
            phys = fold_physics(self.data.physics, runs, key, self.work / f"fold-{len(self._folds)}",
                                self.datasheet, self.jobs, self.fit_args)
            self._folds[key] = self.data.recalibrated(phys)
        return self._folds[key]

    def calibrations(self) -> list[dict[str, Any]]:
        """Per fold calibrated so far: the runs it held out and the shape its fit took."""
        runs = self.data.campaign.runs
        return [{"held_out": [runs[i].path.name for i in key], "calibration": shape(fold.physics)}
                for key, fold in self._folds.items()]


def shape(physics: dict[str, Any]) -> dict[str, Any]:
    """What a calibration made of the campaign's excitations."""
    o = physics["observer"]
    own = (o.get("excitations") or {}).get("own")
    fit = (physics.get("fit") or {}).get("observer") or {}
    return {"accel_clusters_mps2": o["accel_clusters_mps2"], "own": own, "held_sd_bar": o.get("held_sd_bar", 0.0),
            "cold_ref_c": o.get("cold_ref_c"), "max_residual_mps2": o.get("max_residual_mps2"),
            "common_gain": bool(fit.get("common_gain", False))}


def main(argv: Sequence[str] | None = None) -> int:
    from train import study  # which takes this module's FoldObservers

    p = argparse.ArgumentParser(prog="python -m train.observer_folds", description=__doc__.split("\n")[0])
    p.add_argument("--campaign", required=True, type=Path)
    p.add_argument("--physics", required=True, type=Path,
                   help="physics.json (its observer, if any, is recalibrated per fold; the rest is kept)")
    p.add_argument("--out", required=True, type=Path)
    p.add_argument("--datasheet", type=Path,
                   help="the damper's datasheet, as for `train.observer fit` (default: the observer's geometry)")
    p.add_argument("--permutations", default="17,18,19", help="permutations that read the observer")
    p.add_argument("--quick", action="store_true", help="the quick study's folds and training")
    p.add_argument("--folds", type=int, help="folds (default: the study's)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--jobs", type=int, default=min(2, os.cpu_count() or 1))
    p.add_argument("--law-runs", choices=("nominal", "complete"), default="complete",
                   help="each fold's `observer fit --law-runs`")
    args = p.parse_args(argv)

    campaign = load_campaign(args.campaign)
    campaign.require_labels()
    runs = campaign.runs
    physics = read_json(args.physics)
    cfg = study.settings(args.quick, args.seed, args.jobs)
    k = min(args.folds or cfg.folds, len(runs))
    if k < 2:
        raise SystemExit(f"{args.campaign}: {len(runs)} run(s): per-fold calibration needs at least two folds")
    perms = {q["id"]: q for q in shocktwin.extra_permutations()}
    wanted = [int(x) for x in args.permutations.split(",") if x.strip()]
    for pid in wanted:
        if pid not in perms or "observer" not in perms[pid]["groups"]:
            raise SystemExit(f"--permutations: {pid} is not a permutation that reads the observer")
    args.out.mkdir(parents=True, exist_ok=True)

    data = dataset.CampaignData(campaign, physics)
    folds = FoldObservers(data, args.out, args.datasheet, args.jobs, ["--law-runs", args.law_runs])
    rows, _ = study.evaluate_permutation_set(data, [dict(perms[pid], key=pid) for pid in wanted], cfg, folds=k,
                                             per_run=cfg.per_run, max_iter=cfg.max_iter, paper=False,
                                             in_sample=False, fold_observers=folds)
    result = {
        "note": "observer calibrated per fold on its training runs (simulated data when made from shocktwin simulate)",
        "campaign": str(args.campaign), "folds": folds.calibrations(),
        "permutations": {str(r["perm"]["id"]): {"held_out": r["held_out"], "held_out_runs": r["held_out_runs"]}
                         for r in rows},
    }
    (args.out / "observer_folds.json").write_text(json.dumps(result, indent=2) + "\n")
    for pid in wanted:
        s = result["permutations"][str(pid)]["held_out"]
        print(f"model {pid:>2}: held out with the observer calibrated per fold {s['rmse_bar']:.2f} bar "
              f"({s['rmse_avg_bar']:.2f} 1 s avg) over {s['n']} ticks")
    print(f"wrote {args.out / 'observer_folds.json'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main_wrapper(main)())
