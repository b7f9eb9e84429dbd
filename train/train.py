"""Train the hybrid network for one permutation and write a model bundle (SPEC §5).

    python -m train.train --campaign DIR (--permutation N | --sensors LIST) --out BUNDLE_DIR [--physics physics.json]

The features come from the bindings (the daemon's pipeline). ``--split`` chooses what
part of the campaign is kept out of training to report metrics in the bundle's
provenance: ``runs`` (default) keeps whole runs out — what a deployed twin meets;
``paper`` splits the 50 Hz samples at random 75/25 (paper §5.4.2), which leaks
(neighbouring samples of one run fall on both sides); ``none`` trains on everything.
Without ``--physics`` the physics is calibrated on the campaign's nominal runs first.
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path
from typing import Any, Sequence

import numpy as np

import shocktwin

from train import dataset, evaluate, model
from train.campaign import Campaign, CampaignError, load_campaign, main_wrapper, read_json
from train.datasheet import parse_pressure_bar

log = logging.getLogger("shocktwin.train")

SPLITS = ("runs", "paper", "none")


def find_permutation(spec: str) -> dict[str, Any]:
    """A built-in permutation by id, or ``groups:a,b,c`` for a custom one."""
    if spec.startswith("groups:"):
        groups = [g for g in spec[len("groups:"):].split(",") if g]
        unknown = [g for g in groups if g not in dataset.ALL_GROUPS]
        if unknown or not groups:
            raise CampaignError(f"unknown input groups {unknown} (known: {', '.join(dataset.ALL_GROUPS)})")
        return {"id": 0, "name": "custom: " + "+".join(groups), "groups": groups}
    for perm in [*shocktwin.permutations(), *shocktwin.extra_permutations()]:
        if str(perm["id"]) == spec:
            return perm
    raise CampaignError(f"unknown permutation {spec!r} (built in: 1–13 paper, 14–16 causal, 17–19 observer, "
                        "or groups:a,b,…)")


# The project's models from best to worst held out (docs/study/report.md and the observer
# report): the first whose sensors a unit carries is the one `--sensors` trains.
# 19 and 18 add the charge observer to 13 and 12; 17 is the observer alone.
PREFERENCE = [19, 16, 13, 11, 15, 9, 18, 17, 12, 10, 14, 8, 7, 6, 5, 3, 2, 1, 4]


def permutation_for_sensors(spec: str, observer_ok: bool = True) -> dict[str, Any]:
    """The best built-in permutation whose sensors are all in ``spec`` (comma separated);
    without ``observer_ok`` (the physics has no calibrated charge observer) the best of those
    that do not read it."""
    known = list(shocktwin.SENSOR_COSTS_AUD)
    sensors = [s.strip() for s in spec.split(",") if s.strip()]
    if not sensors:
        raise CampaignError(f"--sensors {spec!r} names no sensor (known: {', '.join(known)})")
    unknown = [s for s in sensors if s not in known]
    if unknown:
        raise CampaignError(f"unknown sensors {', '.join(unknown)} in --sensors {spec!r} (known: {', '.join(known)})")
    perms = {p["id"]: p for p in [*shocktwin.permutations(), *shocktwin.extra_permutations()]}
    for pid in PREFERENCE:
        if set(perms[pid]["sensors"]) <= set(sensors) and (observer_ok or "observer" not in perms[pid]["groups"]):
            return perms[pid]
    raise CampaignError(f"no model uses only {', '.join(sensors)}")


def load_physics(path: Path | None, campaign: Campaign, nominal_bar: float) -> dict[str, Any]:
    if path is not None:
        physics = read_json(path)
        for part in ("kalman", "thermal", "force"):
            if part not in physics:
                raise CampaignError(f"{path}: no '{part}' parameters")
        return physics
    from train.fit_physics import calibrate

    log.info("no --physics given: calibrating on the nominal runs first")
    return calibrate(campaign, nominal_bar=nominal_bar)


def scaled_health(nominal_bar: float) -> dict[str, float]:
    """The paper's thresholds (warn 9, fault 5 bar for a 12 bar damper, SPEC §6) as
    fractions of the nominal charge: a 9 bar damper warns below 6.75 bar, not at its nominal."""
    scale = nominal_bar / 12.0
    return {**model.DEFAULT_HEALTH, "warn_bar": model.DEFAULT_HEALTH["warn_bar"] * scale,
            "fault_bar": model.DEFAULT_HEALTH["fault_bar"] * scale}


def split_runs(n_runs: int, seed: int, frac: float = 0.25) -> np.ndarray:
    """Indices of the runs held out (at least one)."""
    rng = np.random.default_rng(seed)
    k = max(1, int(round(frac * n_runs)))
    return np.sort(rng.choice(n_runs, size=k, replace=False))


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m train.train", description=__doc__.split("\n")[0])
    p.add_argument("--campaign", required=True, type=Path)
    which = p.add_mutually_exclusive_group(required=True)
    which.add_argument("--permutation", help="1–19, or groups:a,b,… for a custom suite")
    which.add_argument("--sensors", help="comma-separated sensors the unit carries (loadcell, potentiometer, "
                       "accelerometers, thermocouples): trains the project's best model for them")
    p.add_argument("--out", required=True, type=Path, help="bundle directory to write")
    p.add_argument("--physics", type=Path, help="physics.json from train.fit_physics")
    p.add_argument("--split", choices=SPLITS, default="runs")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--per-run", type=int, default=3000, help="training rows per run (evenly spaced excited ticks)")
    p.add_argument("--max-iter", type=int, default=80, help="training epochs at most (Adam, early stopping)")
    nominal = p.add_mutually_exclusive_group()
    nominal.add_argument("--nominal-bar", type=float,
                         help="nominal charge, bar gauge (default: the physics.json's, else 12)")
    nominal.add_argument("--nominal", help='nominal charge with a unit, e.g. "150 psi" (see train.fit_physics)')
    p.add_argument("--no-augment", action="store_true",
                   help="train without the temperature-offset augmentation (see train.evaluate)")
    p.add_argument("--no-residual", action="store_true",
                   help="a network reading the charge observer learns the charge itself, not what the "
                   "observer misses (see train.model)")
    args = p.parse_args(argv)

    campaign = load_campaign(args.campaign)
    campaign.require_labels()
    # by --sensors: chosen once the physics says whether the observer is calibrated; the
    # sensors' errors now, before any calibration
    perm = find_permutation(args.permutation) if args.permutation else None
    if perm is None:
        permutation_for_sensors(args.sensors)
    nominal_bar = args.nominal_bar
    if args.nominal is not None:
        try:
            nominal_bar = parse_pressure_bar(args.nominal)
        except ValueError as err:
            raise ValueError(f"--nominal: {err}") from None
    physics = load_physics(args.physics, campaign, 12.0 if nominal_bar is None else nominal_bar)
    calibrated_bar = float(physics.get("nominal_bar", 12.0))
    if nominal_bar is None or args.physics is None or abs(nominal_bar - calibrated_bar) <= 0.05:
        # the charge the physics was calibrated at (the bundle's expected_bar, SPEC §6)
        nominal_bar = calibrated_bar
    observer_ok = bool((physics.get("observer") or {}).get("step_per_bar_n"))
    if perm is None:
        perm = permutation_for_sensors(args.sensors, observer_ok)
        best = permutation_for_sensors(args.sensors)
        if best["id"] != perm["id"]:
            print(f"--sensors {args.sensors}: permutation {perm['id']} ({perm['name']}); permutation "
                  f"{best['id']} ({best['name']}) would read the charge observer too, which the physics "
                  f"{args.physics or '(calibrated now)'} has not calibrated (`python -m train.observer fit`)")
    if "observer" in perm["groups"] and not observer_ok:
        which = f"permutation {perm['id']}" if perm["id"] else f"the permutation {perm['name']!r}"
        raise CampaignError(f"{which} reads the charge observer, which the physics "
                            f"{args.physics or '(calibrated now)'} has not calibrated: run "
                            "`python -m train.observer fit --campaign DIR --physics physics.json` first")
    data = dataset.CampaignData(campaign, physics)
    tables = data.tables(perm["groups"])
    excited = data.excited_for(tables)
    columns = dataset.group_columns(perm["groups"])

    metrics: dict[str, Any] = {}
    held_out: list[Any] = []
    trained_on = [t.run for t in tables]
    if args.split == "runs":
        test_idx = set(split_runs(len(tables), args.seed).tolist())
        trained_on = [t.run for i, t in enumerate(tables) if i not in test_idx]
        masks = [np.full(len(t.t_s), i not in test_idx) for i, t in enumerate(tables)]
        x, y = evaluate.training_set(tables, columns, excited, masks, args.per_run, seed=args.seed,
                                      augment=not args.no_augment)
        trained = model.fit(x, y, columns, seed=args.seed, max_iter=args.max_iter,
                            residual=not args.no_residual)
        preds = [evaluate.predict_run(trained, tables[i], columns, excited[i]) for i in sorted(test_idx)]
        scores = evaluate.score_runs(preds)
        metrics = {"test_runs": [tables[i].run.name for i in sorted(test_idx)], **scores.as_dict()}
        held_out = [tables[i].run for i in sorted(test_idx)]
    elif args.split == "paper":
        test = evaluate.paper_split(tables, args.seed)
        x, y = evaluate.training_set(tables, columns, excited, [~m for m in test], args.per_run,
                                      seed=args.seed, augment=not args.no_augment)
        trained = model.fit(x, y, columns, seed=args.seed, max_iter=args.max_iter,
                            residual=not args.no_residual)
        metrics = evaluate.score_paper(trained, tables, columns, excited, test).as_dict()
    else:
        x, y = evaluate.training_set(tables, columns, excited, None, args.per_run, seed=args.seed,
                                      augment=not args.no_augment)
        trained = model.fit(x, y, columns, seed=args.seed, max_iter=args.max_iter,
                            residual=not args.no_residual)
    if metrics and "observer" in perm["groups"]:
        # the network did not see the test rows, but the observer and the physics were
        # calibrated on the whole campaign, test runs included
        metrics["caveat"] = ("optimistic: the physics and the charge observer were calibrated on every run, "
                             "the test runs too; `python -m train.observer_folds` (or the study) gives the "
                             "held-out figure with the observer calibrated per fold")

    model.write_bundle(
        args.out,
        trained,
        permutation=perm,
        physics=physics,
        nominal_bar=nominal_bar,
        health=scaled_health(nominal_bar),
        provenance={
            "campaign": campaign.root.name,
            "campaign_digest": campaign.digest(),
            "skipped_runs": [f"{path.name}: {reason}" for path, reason in campaign.skipped],
            "split": args.split,
            "seed": args.seed,
            "per_run": args.per_run,
            "max_iter": args.max_iter,
            "augmentation": None if args.no_augment else evaluate.AUGMENTATION,
            "trained_excitations": model.trained_excitations(trained_on),
            "metrics": metrics,
            "simulated_data": campaign.simulated,
        },
    )
    # The interval of a bundle without the observer (SPEC §2a; the observer gives its own): the
    # estimator's own 1 s average on the held-out runs, as it will be read
    interval = None
    if held_out and "observer" not in perm["groups"]:
        bundle = shocktwin.Bundle(args.out)
        errors = []
        for run in held_out:
            avg = np.asarray(shocktwin.estimate(run.log, bundle)["pressure_avg_bar"], dtype=float)
            errors.append(np.abs(avg[np.isfinite(avg)] - run.label_bar))
        interval = model.held_out_interval(np.concatenate(errors), [r.name for r in held_out])
        if interval:
            model.add_interval(args.out, interval)
    what = f"permutation {perm['id']} ({perm['name']}): {len(columns)} inputs"
    if "rmse_bar" in metrics:
        what += (f", test RMSE {metrics['rmse_bar']:.3f} bar instantaneous, "
                 f"{metrics['rmse_avg_bar']:.3f} bar 1 s average ({args.split} split, "
                 f"{'simulated' if campaign.simulated else 'dyno'} data)")
        if "caveat" in metrics:
            what += f"\n  {metrics['caveat']}"
    print(what)
    if interval:
        print(f"  95 % interval: the 1 s average ± {interval['half_width_bar']:.2f} bar, the 95th percentile of its "
              f"error on the {len(interval['runs'])} held-out run(s) ({interval['ticks']} ticks with an average)"
              + ("; optimistic: the physics was calibrated on this campaign's nominal runs, held-out ones among them"
                 if args.physics is None else ""))
    elif "observer" not in perm["groups"]:
        why = ("no held-out tick had a 1 s average (none excited)" if held_out else
               f"it is sized on held-out runs (--split runs); this is --split {args.split}")
        print(f"  no interval: the estimates' pressure_lo_bar/hi_bar stay null ({why})")
    print(f"wrote bundle {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main_wrapper(main)())
