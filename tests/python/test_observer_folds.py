"""train.observer_folds: permutations that read the charge observer, held out with the observer
calibrated on each fold's training runs alone, as `train.study` holds them out (never a calibration
made on every run, which leaks)."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from train import observer_folds


def test_each_fold_calibrates_its_observer_on_its_training_runs_alone(
        calibrated_campaign: tuple[Path, Path], tmp_path: Path) -> None:
    campaign, fixture = calibrated_campaign
    # the shared calibration as `make study` leaves it: with a record of a spread measured on it
    params = json.loads(fixture.read_text())
    params.setdefault("fit", {})["observer_unit_spread"] = {"systematic_sd_bar": 1.4}
    # a datasheet's geometry other than the defaults, which each fold must keep
    params["observer"]["v_gas_m3"] = params["observer"]["v_gas_m3"] * 1.05
    physics = tmp_path / "physics.json"
    physics.write_text(json.dumps(params))
    shared = params["observer"]
    out = tmp_path / "folds"
    assert observer_folds.main(["--campaign", str(campaign), "--physics", str(physics), "--out", str(out),
                                "--quick", "--permutations", "17"]) == 0
    res = json.loads((out / "observer_folds.json").read_text())
    runs = sorted(p.name for p in campaign.glob("*.mcap"))
    held = [set(f["held_out"]) for f in res["folds"]]
    assert sorted(n for h in held for n in h) == runs  # every run held out once
    for f, h in enumerate(held):
        # the fold's observer was fitted on the other runs only, and is not the shared one
        assert {p.name for p in (out / f"fold-{f}" / "campaign").iterdir()} == set(runs) - h
        fold_physics = json.loads((out / f"fold-{f}" / "physics.json").read_text())
        assert "observer_unit_spread" not in fold_physics["fit"]  # the shared calibration's record
        own = fold_physics["observer"]
        assert own["step_per_bar_n"] != shared["step_per_bar_n"]
        # without --datasheet the fold keeps the given observer's geometry (datasheet values, not fitted)
        for k in observer_folds.GEOMETRY:
            assert own[k] == shared[k], k
        assert res["folds"][f]["calibration"]["accel_clusters_mps2"] == own["accel_clusters_mps2"]
    # run again into the same directory: the folds are made afresh
    assert observer_folds.main(["--campaign", str(campaign), "--physics", str(physics), "--out", str(out),
                                "--quick", "--permutations", "17"]) == 0
    assert json.loads((out / "observer_folds.json").read_text())["permutations"] == res["permutations"]
    scores = res["permutations"]["17"]
    assert {r["run"] for r in scores["held_out_runs"]} == set(runs)
    assert scores["held_out"]["n"] > 0
    # the observer alone (17), read by a fold that never saw the run, still carries information:
    # below what always answering the campaign's mean charge would score (the labels' spread)
    labels = [r["label_bar"] for r in scores["held_out_runs"]]
    assert scores["held_out"]["rmse_bar"] < float(np.std(labels))


def test_a_permutation_without_the_observer_is_refused_by_name(
        calibrated_campaign: tuple[Path, Path], tmp_path: Path) -> None:
    campaign, physics = calibrated_campaign
    with pytest.raises(SystemExit, match="12 is not a permutation that reads the observer"):
        observer_folds.main(["--campaign", str(campaign), "--physics", str(physics), "--out", str(tmp_path),
                             "--permutations", "12"])


def test_the_study_holds_out_only_what_reads_the_observer_on_the_folds_calibrations(
        calibrated_campaign: tuple[Path, Path]) -> None:
    """`train.study` asks the per-fold calibrations for the tables of each held-out fold of a
    permutation or suite that reads the observer, and only for those: the others, and the paper
    split and in-sample fit, read the campaign's tables."""
    import shocktwin

    from train import dataset, evaluate, study
    from train.campaign import load_campaign

    campaign, physics = calibrated_campaign
    data = dataset.CampaignData(load_campaign(campaign), json.loads(physics.read_text()))
    asked: list[tuple[int, ...]] = []

    def folds(held):  # the campaign's own tables, each fold's request recorded
        asked.append(tuple(sorted(int(i) for i in held)))
        return data

    cfg = study.settings(True, 0, 2)
    perms = [dict(p, key=p["id"]) for p in shocktwin.extra_permutations() if p["id"] == 17]
    perms += [dict(p, key=p["id"]) for p in shocktwin.permutations() if p["id"] == 3]
    rows, models = study.evaluate_permutation_set(data, perms, cfg, folds=3, per_run=200, max_iter=3, paper=True,
                                                  in_sample=True, fold_observers=folds)
    expected = [tuple(sorted(int(i) for i in held)) for held in evaluate.held_out_folds(10, 3, cfg.seed)]
    assert asked == expected, "once per fold, for the observer's permutation alone"
    assert set(models) == {17, 3}
    for row in rows:
        assert {r["run"] for r in row["held_out_runs"]} == {p.name for p in campaign.glob("*.mcap")}
        assert row["paper"]["n"] > 0 and row["in_sample"]["n"] > 0


def test_the_reports_note_names_each_folds_calibrated_excitations() -> None:
    """The study report's note under Table 2: each fold with the excitations its calibration kept
    (an excitation it dropped is one its observer skips), and the suites' folds only when searched."""
    from train import study

    folds = [{"held_out": ["p4.0-f2.0-s1.mcap", "p7.0-f4.0-s1.mcap"],
              "calibration": {"accel_clusters_mps2": [1.52, 6.07, 24.1, 0.0], "own": [False, False, True, False]}},
             {"held_out": ["p0.5-f2.0-s1.mcap"], "calibration": {"accel_clusters_mps2": [1.52, 0.0, 0.0, 0.0],
                                                                 "own": None}},
             {"held_out": ["p7.0-f2.0-s1.mcap"], "calibration": {"accel_clusters_mps2": [1.52, 6.07, 0.0, 0.0],
                                                                 "own": None, "common_gain": True}}]
    note = "\n".join(study.observer_folds_note(folds, suites=False))
    assert "suites' folds" not in note and "3 calibrations for Table 2's folds" in note
    assert "| p4.0-f2.0-s1, p7.0-f4.0-s1 | 1.5, 6.1, 24.1 *own* |" in note
    assert "| p0.5-f2.0-s1 | 1.5 |" in note
    assert "| p7.0-f2.0-s1 | 1.5, 6.1 (one gain for all) |" in note
    assert "Table 2's folds and the suites' folds" in "\n".join(study.observer_folds_note(folds, suites=True))
