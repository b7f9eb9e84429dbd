"""The analysts' path: ``pip install ./crates/dt-py`` into a fresh virtual environment
gives a working ``shocktwin`` package (pyproject metadata, maturin build backend, the
pure-Python part and the native module together).

The build reuses the workspace's ``target/`` (``CARGO_TARGET_DIR``) so that CI pays for
the pip/maturin path, not for a second cold compile of the crate.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def test_pip_install_from_source_gives_a_working_package(tmp_path):
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True, timeout=300)
    bindir = venv / ("Scripts" if os.name == "nt" else "bin")
    env = dict(os.environ, CARGO_TARGET_DIR=str(ROOT / "target"))
    env.pop("VIRTUAL_ENV", None)
    install = subprocess.run(
        [str(bindir / "pip"), "install", "-q", str(ROOT / "crates" / "dt-py")],
        cwd=tmp_path, env=env, capture_output=True, text=True, timeout=1800,
    )
    assert install.returncode == 0, install.stdout[-2000:] + install.stderr[-4000:]
    log = ROOT / "crates" / "dt-core" / "tests" / "fixtures" / "python_mcap" / "zstd.mcap"  # Python-mcap-written
    probe = (
        "import json, sys, shocktwin\n"
        "print(json.dumps({'file': shocktwin.__file__, 'groups': list(shocktwin.GROUPS),\n"
        "                  'perms': len(shocktwin.permutations()), 'params': sorted(shocktwin.default_params()),\n"
        "                  'topics': sorted(shocktwin.read_log(sys.argv[1]).topics)}))\n"
    )
    run = subprocess.run([str(bindir / "python"), "-c", probe, str(log)], cwd=tmp_path, capture_output=True, text=True,
                         timeout=300)
    assert run.returncode == 0, run.stderr
    out = json.loads(run.stdout)
    assert Path(out["file"]).resolve().is_relative_to(venv.resolve()), out["file"]  # the installed copy
    assert out["groups"][:6] == ["force", "position", "acceleration", "velocity", "mechanical", "thermal"]
    assert out["perms"] == 13
    assert out["params"] == ["force", "kalman", "thermal"]
    assert "/position" in out["topics"]
