"""The analysts' notebook (``docs/analyst.py``, jupytext percent format) executes as
a notebook and makes its figure (issue 12, item 5).

jupytext converts it; nbclient runs it on an ipykernel ``python3`` kernel whose
kernelspec (written to a temporary ``JUPYTER_PATH``) starts this interpreter, i.e. the
project's .venv with the ``shocktwin`` package. The notebook simulates its own data
with the CLI (``target/release/shocktwin`` or ``SHOCKTWIN_BIN``, built when missing),
trains a small observer bundle with ``train/``, fits a road calibration and reads a held-out
drive with the road observer, and writes its figures to ``SHOCKTWIN_NOTEBOOK_OUT`` (under a minute on
two cores).
"""

from __future__ import annotations

import json
import os
import re
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
NOTEBOOK = ROOT / "docs" / "analyst.py"
CELL_TIMEOUT_S = 150  # the longest cells train the bundle and fit the road calibration (~20–35 s alone)


@pytest.fixture(scope="module")
def executed(shocktwin_bin: Path, tmp_path_factory: pytest.TempPathFactory):
    """(the executed notebook, its output directory)."""
    import jupytext  # requirements.txt: jupytext, nbclient, ipykernel (a missing one fails, not skips)
    from nbclient import NotebookClient

    tmp = tmp_path_factory.mktemp("analyst")
    kernel_dir = tmp / "jupyter" / "kernels" / "python3"
    kernel_dir.mkdir(parents=True)
    (kernel_dir / "kernel.json").write_text(json.dumps({
        "argv": [sys.executable, "-m", "ipykernel_launcher", "-f", "{connection_file}"],
        "display_name": "Python 3 (shocktwin .venv)",
        "language": "python",
    }))
    out = tmp / "out"
    env = {
        "JUPYTER_PATH": str(tmp / "jupyter"),
        "IPYTHONDIR": str(tmp / "ipython"),
        "SHOCKTWIN_NOTEBOOK_OUT": str(out),
        "SHOCKTWIN_BIN": str(shocktwin_bin),
        "SHOCKTWIN_ROOT": str(ROOT),
    }
    saved = {k: os.environ.get(k) for k in (*env, "MPLBACKEND", "SHOCKTWIN_BUNDLE")}
    os.environ.update(env)
    os.environ.pop("MPLBACKEND", None)  # the kernel's inline backend, as in Jupyter
    os.environ.pop("SHOCKTWIN_BUNDLE", None)  # the notebook trains its own bundle
    try:
        nb = jupytext.read(NOTEBOOK)
        assert nb.metadata["kernelspec"]["name"] == "python3"
        NotebookClient(
            nb, kernel_name="python3", timeout=CELL_TIMEOUT_S,
            resources={"metadata": {"path": str(ROOT / "docs")}},
        ).execute()
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
    return nb, out


def stdout(nb) -> str:
    return "".join(
        o.get("text", "") for c in nb.cells if c.cell_type == "code" for o in c.get("outputs", [])
        if o.get("output_type") == "stream"
    )


def test_the_notebook_makes_its_figure(executed):
    nb, out = executed
    figure = out / "analyst-estimate.png"
    assert figure.is_file() and figure.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    import matplotlib.image

    height, width, _ = matplotlib.image.imread(figure).shape
    assert width > 800 and height > 400
    shown = [o for c in nb.cells if c.cell_type == "code" for o in c.get("outputs", [])
             if "image/png" in o.get("data", {})]
    assert len(shown) == 2, "the estimate and road figures are displayed in the notebook"
    road = out / "analyst-road.png"
    assert road.is_file() and road.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_the_notebook_shows_the_interval_against_the_truth_of_simulated_data(executed):
    nb, _ = executed
    text = stdout(nb)
    assert "simulated: true" in text  # the log's metadata, printed by the notebook
    assert "/truth/gas_pressure" in text
    # a bundle with the charge observer: an interval, and the truth inside it at the end
    assert "95 % interval at the end [" in text, text[-2000:]
    line = next(s for s in text.splitlines() if s.startswith("95 % interval at the end"))
    lo, hi = (float(v) for v in line.split("[", 1)[1].split("]", 1)[0].split(","))
    assert lo < 10.0 < hi, line  # the held-out run's charge (the observer's prior is 6)
    # the estimate is the network on the features the notebook computed
    parity = next(s for s in text.splitlines() if s.startswith("max |estimate - predict(features)| = "))
    assert float(parity.split("= ", 1)[1].split()[0]) < 1e-9, parity


def test_the_notebook_reads_a_held_out_drive_with_the_road_observer(executed):
    """Section 6: a road calibration fitted in the notebook, and `shocktwin.road_blocks` with the
    unit's baseline reads the held-out drive file's 2 and 12 bar runs: the truth inside each
    final interval, and the 2 bar run `leak`, the 12 bar run `ok` (SPEC §6a)."""
    nb, _ = executed
    text = stdout(nb)
    assert "road observer: alpha = " in text, text[-2000:]
    finals = {}
    for line in text.splitlines():
        m = re.match(r"p[\d.]+-roadC60-s2\.mcap: true charge ([\d.]+) bar; (\d+) blocks read; final "
                     r"([-\d.]+) bar \[([-\d.]+), ([-\d.]+)\], health (\w+)", line)
        if m:
            finals[float(m[1])] = (int(m[2]), float(m[4]), float(m[5]), m[6])
    assert set(finals) == {2.0, 12.0}, text[-2000:]
    for charge, (blocks, lo, hi, health) in finals.items():
        assert blocks >= 3 and lo < charge < hi, (charge, finals)
    assert finals[2.0][3] == "leak" and finals[12.0][3] == "ok", finals
