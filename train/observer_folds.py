"""Permutations that read the charge observer, held out with the observer calibrated per fold.

The study's held-out column (``train.study``) shares one observer calibration, made on every run
of the campaign, between its folds: for the permutations that read the observer (17–19) it leaks.
Here each fold's observer is calibrated by ``python -m train.observer fit`` on that fold's training
runs alone; the rest is the study's (its folds, seeds, training rows, epochs and scoring; the
physics under the observer, Kalman, thermal and force, stays the given file's, as it does for every
permutation in the study). The observer's sd is then the fit's assumed unit tolerance: the unit and
transfer spreads that ``make study`` measures on other units are not measured per fold. In the
fifty-fourth session (docs/history.md) a script taking these steps read 17 / 18 / 19 at 0.47 /
0.46 / 0.38 bar on the full campaign, against 0.22 / 0.25 / 0.25 with the shared calibration; this
command itself was run there on the tests' quick campaign (simulated data).

    python -m train.observer_folds --campaign DIR --physics physics.json --out DIR
        [--datasheet FILE] [--permutations 17,18,19] [--quick] [--folds K] [--seed 0] [--jobs 2]

Writes ``DIR/observer_folds.json`` (per permutation its held-out scores and runs, per fold the
runs held out and the shape the fit took) and each fold's calibration under ``DIR/fold-K/``.
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
from pathlib import Path
from typing import Any, Sequence

import numpy as np

import shocktwin

from train import dataset, evaluate
from train import observer as observer_tool
from train.campaign import load_campaign, main_wrapper, read_json
from train.study import fit_many, settings


def fold_physics(physics: dict[str, Any], runs: Sequence[Any], held: Sequence[int], work: Path,
                 datasheet: Path | None, jobs: int) -> dict[str, Any]:
    """``physics`` with its observer calibrated on the runs not in ``held`` (symbolic links to them
    in ``work/campaign``); the calibration is kept in ``work/physics.json``."""
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
    argv = ["fit", "--campaign", str(camp), "--physics", str(out), "--jobs", str(jobs)]
    if datasheet is not None:
        argv += ["--datasheet", str(datasheet)]
    if observer_tool.main(argv) != 0:
        raise SystemExit(f"{camp}: the observer fit failed")
    return read_json(out)


def shape(physics: dict[str, Any]) -> dict[str, Any]:
    """What a calibration made of the campaign's excitations."""
    o = physics["observer"]
    own = (o.get("excitations") or {}).get("own")
    return {"accel_clusters_mps2": o["accel_clusters_mps2"], "own": own, "held_sd_bar": o.get("held_sd_bar", 0.0),
            "cold_ref_c": o.get("cold_ref_c"), "max_residual_mps2": o.get("max_residual_mps2")}


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m train.observer_folds", description=__doc__.split("\n")[0])
    p.add_argument("--campaign", required=True, type=Path)
    p.add_argument("--physics", required=True, type=Path,
                   help="physics.json (its observer, if any, is recalibrated per fold; the rest is kept)")
    p.add_argument("--out", required=True, type=Path)
    p.add_argument("--datasheet", type=Path, help="the damper's datasheet, as for `train.observer fit`")
    p.add_argument("--permutations", default="17,18,19", help="permutations that read the observer")
    p.add_argument("--quick", action="store_true", help="the quick study's folds and training")
    p.add_argument("--folds", type=int, help="folds (default: the study's)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--jobs", type=int, default=min(2, os.cpu_count() or 1))
    args = p.parse_args(argv)

    campaign = load_campaign(args.campaign)
    campaign.require_labels()
    runs = campaign.runs
    physics = read_json(args.physics)
    cfg = settings(args.quick, args.seed, args.jobs)
    k = min(args.folds or cfg.folds, len(runs))
    if k < 2:
        raise SystemExit(f"{args.campaign}: {len(runs)} run(s): per-fold calibration needs at least two folds")
    perms = {q["id"]: q for q in shocktwin.extra_permutations()}
    wanted = [int(x) for x in args.permutations.split(",") if x.strip()]
    for pid in wanted:
        if pid not in perms or "observer" not in perms[pid]["groups"]:
            raise SystemExit(f"--permutations: {pid} is not a permutation that reads the observer")
    folds = evaluate.held_out_folds(len(runs), k, cfg.seed)
    args.out.mkdir(parents=True, exist_ok=True)

    preds: dict[int, list[evaluate.RunPrediction]] = {pid: [] for pid in wanted}
    fold_rows = []
    for f, held in enumerate(folds):
        held_set = set(int(i) for i in held)
        phys = fold_physics(physics, runs, held, args.out / f"fold-{f}", args.datasheet, args.jobs)
        data = dataset.CampaignData(campaign, phys)
        tasks, prepared = [], []
        for pid in wanted:
            tabs = data.tables(perms[pid]["groups"])
            exc = data.excited_for(tabs)
            cols = dataset.group_columns(perms[pid]["groups"])
            masks = [np.full(len(t.t_s), i not in held_set) for i, t in enumerate(tabs)]
            x, y = evaluate.training_set(tabs, cols, exc, masks, cfg.per_run, seed=cfg.seed + f, augment=True)
            tasks.append((x, y, cols, cfg.seed + f))
            prepared.append((pid, tabs, exc, cols))
        for (pid, tabs, exc, cols), trained in zip(prepared, fit_many(cfg, tasks, cfg.max_iter)):
            preds[pid].extend(evaluate.predict_run(trained, tabs[i], cols, exc[i]) for i in held)
        fold_rows.append({"held_out": [runs[i].path.name for i in held], "calibration": shape(phys)})
        print(f"fold {f + 1}/{k}: held out {', '.join(runs[i].path.name for i in held)}")

    result = {
        "note": "observer calibrated per fold on its training runs (simulated data when made from shocktwin simulate)",
        "campaign": str(args.campaign), "folds": fold_rows,
        "permutations": {str(pid): {"held_out": evaluate.score_runs(preds[pid]).as_dict(),
                                    "held_out_runs": evaluate.per_run(preds[pid])} for pid in wanted},
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
