# ---
# jupyter:
#   jupytext:
#     formats: py:percent
#     text_representation:
#       extension: .py
#       format_name: percent
#   kernelspec:
#     display_name: Python 3
#     language: python
#     name: python3
# ---

# %% [markdown]
# # shocktwin for analysts: a log, its features, a bundle, the estimate with its interval
#
# **Every number and figure in this notebook comes from simulated data**: the runs are
# made by `shocktwin simulate` (`dt-sim`, the project's dyno simulator), not measured on a
# real damper.
#
# The notebook makes its own data. It runs in a checkout of the shocktwin repository
# (it trains with the repository's `train` package; elsewhere set `SHOCKTWIN_ROOT` to
# one), with the `shocktwin` Python package and command line, and the training tools'
# packages: `make setup` puts them all in the repository's `.venv`; beside a wheel alone,
# `pip install -r requirements.txt` adds them (scipy, scikit-learn, skl2onnx, onnx …).
# About a minute on two cores with nothing else running (44.5 s measured in the sixty-eighth
# session); the road part (6) is its longest step (102 of 120 s in a helper's run at load 8):
#
# 1. simulate a small labelled campaign (4, 8 and 12 bar, 1 Hz, 60 s each) and one
#    held-out run at 10 bar, a charge the campaign does not have (and not the observer's
#    6 bar prior, which an estimate that never left it would match);
# 2. read the held-out log with `shocktwin.read_log`: topics, rates, metadata;
# 3. train the cheapest bundle that gives a 95 % interval: permutation 17, the charge
#    observer on the cheap suite (potentiometer, accelerometers, thermocouples; no
#    loadcell), with the project's own tools (`train.fit_physics`, `train.observer fit`,
#    `train.train`);
# 4. compute the bundle's features with `shocktwin.features` and run it with
#    `shocktwin.estimate` (the daemon's Rust code);
# 5. plot the estimate and its 95 % interval against the truth;
# 6. a vehicle on roads: fit a road calibration on simulated drives and read a held-out
#    drive with `shocktwin.road_blocks` (the road observer the daemon runs).
#
# Open it with `jupytext --to notebook docs/analyst.py -o /tmp/analyst.ipynb` (a copy out of
# the repository; or the jupytext plugin of
# Jupyter), or run it as a script. Environment variables: `SHOCKTWIN_BIN` (the CLI;
# default `target/release/shocktwin`, then `shocktwin` on `PATH`), `SHOCKTWIN_ROOT` (the
# repository, for `train/`; default: found from the working directory),
# `SHOCKTWIN_NOTEBOOK_OUT` (where data and the figure go; default a new temporary
# directory), `SHOCKTWIN_BUNDLE` (use this bundle instead of training one, e.g.
# `out/study/bundles/perm-18` after `make demo`).

# %%
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np

import shocktwin


def find_root() -> Path:
    """The repository (for `python -m train.…`): SHOCKTWIN_ROOT, or the first
    directory upwards from here that holds crates/dt-core and train/."""
    if os.environ.get("SHOCKTWIN_ROOT"):
        return Path(os.environ["SHOCKTWIN_ROOT"]).resolve()
    here = Path.cwd().resolve()
    for d in (here, *here.parents):
        if (d / "crates" / "dt-core").is_dir() and (d / "train").is_dir():
            return d
    raise RuntimeError("run this notebook inside the shocktwin repository, or set SHOCKTWIN_ROOT")


def find_bin(root: Path) -> Path:
    for candidate in (os.environ.get("SHOCKTWIN_BIN"), root / "target" / "release" / "shocktwin",
                      shutil.which("shocktwin")):
        if candidate and Path(candidate).is_file():
            return Path(candidate)
    raise RuntimeError("no shocktwin CLI: build it (cargo build --release -p dt-server) or set SHOCKTWIN_BIN")


def run(*args: object) -> str:
    """Runs a command from the repository root; its output if it succeeds, else its error."""
    proc = subprocess.run([str(a) for a in args], cwd=ROOT, capture_output=True, text=True)
    if proc.returncode != 0:
        raise RuntimeError(f"{' '.join(map(str, args[:3]))}… failed:\n{proc.stderr.strip()}")
    return proc.stdout


ROOT = find_root()
BIN = find_bin(ROOT)
OUT = Path(os.environ.get("SHOCKTWIN_NOTEBOOK_OUT") or tempfile.mkdtemp(prefix="shocktwin-analyst-"))
OUT.mkdir(parents=True, exist_ok=True)
print(f"shocktwin {shocktwin.__version__}; CLI {BIN}; output in {OUT}")

# %% [markdown]
# ## 1. Simulated data
#
# One MCAP log per run (SPEC §2). `--quick` stops each run after 60 s of excitation (plus
# 10 s at rest). The held-out run uses another seed (other sensor noise) and a charge
# the calibration never saw.

# %%
CAMPAIGN, HELD_OUT = OUT / "campaign", OUT / "held-out"
for d in (CAMPAIGN, HELD_OUT):
    shutil.rmtree(d, ignore_errors=True)
print(run(BIN, "simulate", "--quick", "--pressures", "4,8,12", "--frequencies", "1", "--out", CAMPAIGN).splitlines()[-1])
print(run(BIN, "simulate", "--quick", "--pressures", "10", "--frequencies", "1", "--seed", "7",
          "--out", HELD_OUT).splitlines()[-1])
(RUN,) = sorted(HELD_OUT.glob("*.mcap"))

# %% [markdown]
# ## 2. The log: metadata and topics
#
# `read_log` accepts any valid MCAP (SPEC §2). `metadata` is the `shocktwin.run` record
# (numbers already parsed), `label` the true charge when the log carries one, `problems`
# what the reader skipped.

# %%
log = shocktwin.read_log(RUN)
SIMULATED = str(log.metadata.get("simulated", "")).lower() == "true"
for key, value in sorted(log.metadata.items()):
    print(f"{key:>20}: {value}")
print(f"label {log.label} bar, problems {log.problems or 'none'}, unknown topics {log.unknown_topics or 'none'}")

print(f"\n{'topic':<22}{'messages':>9}{'rate Hz':>9}  fields")
for name in log.topics:
    data = log.topic(name)
    t = data["t_s"]
    rate = (len(t) - 1) / (t[-1] - t[0]) if len(t) > 1 else float("nan")
    fields = ", ".join(f"{k} [{np.nanmin(v):.3g}, {np.nanmax(v):.3g}]" for k, v in data.items() if k != "t_s")
    print(f"{name:<22}{len(t):>9}{rate:>9.1f}  {fields}")

# %% [markdown]
# ## 3. A bundle with an interval
#
# Every bundle reports `pressure_lo_bar`/`pressure_hi_bar` (SPEC §2a), two ways: a
# bundle that reads the charge observer (permutations 17–19) from the observer's own
# variance, which narrows as it reads the run; the others from one half-width sized on the
# runs `train.train` kept out (`twin.json` `interval`), around the 1 s average. Only the
# fixture bundles in `crates/dt-core/tests/fixtures`, older than either, leave them null.
# The observer needs a calibration of
# its measurement model on labelled runs (`train.observer fit`, on top of
# `train.fit_physics`), then `train.train` fits the network. On this three-run campaign
# that takes about 15–20 s; the study's permutation 18 on the ten-run quick campaign takes
# minutes, hence permutation 17 here and fewer training rows and epochs than the
# defaults (the network only maps the observer's state to the charge).

# %%
if os.environ.get("SHOCKTWIN_BUNDLE"):
    BUNDLE = Path(os.environ["SHOCKTWIN_BUNDLE"])
else:
    PHYSICS, BUNDLE = OUT / "physics.json", OUT / "perm-17"
    python = sys.executable
    run(python, "-m", "train.fit_physics", "--campaign", CAMPAIGN, "--out", PHYSICS)
    print(run(python, "-m", "train.observer", "fit", "--campaign", CAMPAIGN, "--physics", PHYSICS).strip())
    run(python, "-m", "train.train", "--campaign", CAMPAIGN, "--permutation", "17", "--physics", PHYSICS,
        "--out", BUNDLE, "--split", "none", "--per-run", "600", "--max-iter", "30")
bundle = shocktwin.Bundle(BUNDLE)
print(bundle)
print("groups:", bundle.groups, "| columns:", bundle.columns)
print("nominal", bundle.nominal_bar, "bar; health thresholds", bundle.health)

# %% [markdown]
# ## 4. Features and estimate
#
# `features` computes, per 50 Hz tick, exactly the columns the bundle's network reads,
# with the bundle's physics (the same Rust code as `shocktwin serve`); `estimate` runs the
# whole estimator (features, network, 1 s average, interval, health) over the log.

# %%
X, columns, t_feat = shocktwin.features(log, bundle, bundle.groups)
print(f"features: {X.shape[0]} ticks x {X.shape[1]} columns")
for j, name in enumerate(columns):
    col = X[:, j]
    print(f"  {name:<20} mean {np.nanmean(col):9.3f}  last {col[-1]:9.3f}  missing {np.isnan(col).sum()}")

est = shocktwin.estimate(log, bundle)
t = est["t_s"]
p, lo, hi = est["pressure_bar"], est["pressure_lo_bar"], est["pressure_hi_bar"]
has_interval = bool(np.isfinite(lo).any())
# the estimate is the network on these features (where they are all defined)
ok = np.isfinite(X).all(axis=1)
print(f"max |estimate - predict(features)| = {np.max(np.abs(bundle.predict(X[ok]) - p[ok])):.1e} bar")

# %% [markdown]
# How good is it? The truth is the run's label (the charge referred to 20 °C). Coverage is
# the share of ticks whose 95 % interval holds the true charge; it is only meaningful
# once the observer has seen enough reversals to leave its prior.

# %%
true_bar = log.label
final = slice(int(0.75 * len(t)), None)  # the last quarter of the run
rmse = float(np.sqrt(np.nanmean((p - true_bar) ** 2)))
# the interval is around the 1 s average (a bundle without the observer centres it there)
avg = est["pressure_avg_bar"]
print(f"true charge {true_bar} bar; 1 s average at the end {avg[-1]:.2f} bar; "
      f"RMSE of the 50 Hz estimate over the run {rmse:.2f} bar")
if has_interval:
    inside = (lo <= true_bar) & (true_bar <= hi)
    width = hi - lo
    print(f"95 % interval at the end [{lo[-1]:.2f}, {hi[-1]:.2f}] bar; "
          f"coverage over the last quarter {np.mean(inside[final]):.0%}, mean width {np.nanmean(width[final]):.2f} bar")
else:
    print("this bundle reports no interval (pressure_lo_bar/pressure_hi_bar are null)")
health, counts = np.unique(est["health"], return_counts=True)
print("health verdicts (ticks):", dict(zip(health.tolist(), counts.tolist())))

# %% [markdown]
# ## 5. The estimate against the truth

# %%
truth = log.topic("/truth/gas_pressure") if "/truth/gas_pressure" in log.topics else None
fig, ax = plt.subplots(figsize=(10, 4.8), constrained_layout=True)
if has_interval:
    ax.fill_between(t, lo, hi, color="tab:blue", alpha=0.2, linewidth=0, label="95 % interval")
ax.plot(t, p, color="tab:blue", linewidth=0.8, label="estimate (50 Hz)")
ax.plot(t, est["pressure_avg_bar"], color="navy", linewidth=1.4, label="estimate, 1 s average")
if true_bar is not None:
    ax.axhline(true_bar, color="tab:red", linewidth=1.6, label=f"true charge {true_bar:g} bar (label)")
if truth is not None:
    ax.plot(truth["t_s"], truth["static_bar"], color="tab:red", linestyle=":", linewidth=1.2,
            label="simulator: instantaneous static gas pressure")
ax.set(xlabel="time since the run's first message (s)", ylabel="charge pressure (bar gauge)",
       title=f"{log.metadata.get('run_id')}: permutation {bundle.permutation['id']} "
             f"({bundle.permutation['name']})")
ax.set_ylim(-1.0, 2.0 * max(true_bar or 0.0, float(np.nanmax(p))))  # the prior's band is wider
ax.legend(loc="upper right", fontsize=8)
ax.grid(alpha=0.3)
if SIMULATED:
    ax.text(0.01, 0.02, f"SIMULATED DATA ({log.metadata.get('simulator', 'dt-sim')}), not a measurement",
            transform=ax.transAxes, fontsize=10, fontweight="bold", color="darkred",
            bbox={"facecolor": "white", "edgecolor": "darkred", "alpha": 0.85})
FIGURE = OUT / "analyst-estimate.png"
fig.savefig(FIGURE, dpi=110)
print("saved", FIGURE)
plt.show()

# %% [markdown]
# The interval starts wide (the observer's prior, clipped by the axes) and narrows as
# velocity reversals accumulate; it does not shrink to zero, because it includes the
# systematic part the calibration cannot remove (the leave-one-run-out error and the
# unit-to-unit tolerance of the seal friction; see the README's section on the charge
# observer). As long as it straddles a health threshold (warn 9 bar, fault 5 bar), the
# verdict is `unknown` (SPEC §6a): with the cheap suite alone the twin does not claim more
# than the data support. A bundle without the observer (`SHOCKTWIN_BUNDLE=…` to try one)
# shows a band of one width around its 1 s average, sized on the runs its training kept
# out: it does not narrow as the run goes on.

# %% [markdown]
# ## 6. A vehicle on roads: the road observer
#
# The charge observer above reads a dyno's sine; a vehicle on roads is read by the road
# observer instead (dt-core `road`, the one `shocktwin serve` runs for an asset with a road
# calibration): the seal friction's flip in the body accelerometer, regressed over 10 s
# blocks of drive, into a recursive estimate with its 95 % interval. Its calibration is
# fitted on drives at known charges (`python -m train.road_observer fit`; here two quick
# simulated drive files, class C roads at 60 and 45 km/h, 0.5–12 bar, with the default mount
# parameters), and a unit's drive at a known charge after a service (its *baseline*, here a
# third drive file at 12 bar) narrows the interval to that unit's own seal.
# `shocktwin.road_blocks` runs the Rust observer over a log and returns every block it read.
# A calibration vouches only for strokes as fast as those it saw: a slower drive is not read
# (docs/history.md, "Nineteenth session" and "Twentieth session").

# %%
ROAD = OUT / "road"
shutil.rmtree(ROAD, ignore_errors=True)
for name, args in (("cal", ["--road", "60", "--seed", "1", "--pressures", "0.5,4,7,10,12"]),
                   ("cal", ["--road", "45", "--seed", "4", "--pressures", "0.5,4,7,10,12"]),
                   ("held-out", ["--road", "60", "--seed", "2", "--pressures", "2,12"]),
                   ("baseline", ["--road", "60", "--seed", "3", "--pressures", "12"])):
    run(BIN, "simulate", "--quick", *args, "--out", ROAD / name)
ROAD_PHYSICS, ROAD_CAL = ROAD / "physics.json", ROAD / "road.json"
ROAD_PHYSICS.write_text(json.dumps({**shocktwin.default_params(), "observer": shocktwin.default_observer_params()}))
print(run(sys.executable, "-m", "train.road_observer", "fit", "--campaign", ROAD / "cal", "--physics", ROAD_PHYSICS,
          "--out", ROAD_CAL).splitlines()[0])
(BASELINE,) = sorted((ROAD / "baseline").glob("*.mcap"))
road = {}
for path in sorted((ROAD / "held-out").glob("*.mcap")):
    drive = shocktwin.read_log(path)
    blocks = shocktwin.road_blocks(drive, ROAD_CAL.read_text(), baseline=BASELINE, baseline_bar=12.0)
    road[drive.label] = blocks
    print(f"{path.name}: true charge {drive.label:g} bar; {len(blocks['t_s'])} blocks read; final "
          f"{blocks['estimate_bar'][-1]:.2f} bar [{blocks['lo_bar'][-1]:.2f}, {blocks['hi_bar'][-1]:.2f}], "
          f"health {blocks['health'][-1]}")

# %%
fig, ax = plt.subplots(figsize=(10, 4.2), constrained_layout=True)
for (label, blocks), color in zip(sorted(road.items()), ("tab:red", "tab:blue")):
    ax.fill_between(blocks["t_s"], blocks["lo_bar"], blocks["hi_bar"], step="post", color=color, alpha=0.2,
                    linewidth=0)
    ax.step(blocks["t_s"], blocks["estimate_bar"], where="post", color=color, label=f"estimate, {label:g} bar drive")
    ax.plot(blocks["t_s"], blocks["reading_bar"], ".", color=color, alpha=0.6)
    ax.axhline(label, color=color, linestyle=":", linewidth=1.2)
ax.set(xlabel="time since the drive's first message (s): each block's end", ylabel="charge pressure (bar gauge)",
       title="The road observer on a held-out drive file, with the unit's 12 bar baseline (dots: one block each)")
ax.legend(loc="center right", fontsize=8)
ax.grid(alpha=0.3)
ax.text(0.01, 0.02, "SIMULATED DATA (dt-sim road drive files), not a measurement", transform=ax.transAxes,
        fontsize=10, fontweight="bold", color="darkred", bbox={"facecolor": "white", "edgecolor": "darkred", "alpha": 0.85})
ROAD_FIGURE = OUT / "analyst-road.png"
fig.savefig(ROAD_FIGURE, dpi=110)
print("saved", ROAD_FIGURE)
plt.show()
