"""The hand-written stubs match the native module (mypy.stubtest), and a
typed user of the package type-checks."""

from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path


def run(args: list[str], cwd: Path | None = None) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", *args], capture_output=True, text=True, cwd=cwd)


def test_stubtest_native_module():
    result = run(["mypy.stubtest", "shocktwin._native"])
    assert result.returncode == 0, result.stdout + result.stderr


def test_package_is_typed_and_a_user_type_checks(tmp_path: Path):
    user = tmp_path / "user.py"
    user.write_text(
        textwrap.dedent(
            """
            import numpy as np
            import shocktwin

            kf = shocktwin.KalmanFilter(0.2, 0.005, 1e-3)
            out: dict[str, np.ndarray] = kf.run([0.0], [0.0], [0.0], [0.0])
            oil, cyl = shocktwin.ThermalModel(c_oil=500.0).simulate([0.0, 1.0], [0.0, 0.0], [20.0, 20.0], 20.0, 20.0)
            f = shocktwin.ForceModel(charge_bar=10.0).force([0.1], [0.0], [0.0], [20.0], charge_bar=4.0)
            cols: list[str] = shocktwin.group_columns("thermal")
            label: float | None = shocktwin.read_log("x.mcap").label
            bundle = shocktwin.Bundle("bundle")
            p: np.ndarray = bundle.predict(np.zeros((2, len(bundle.columns))))
            nominal: float = bundle.nominal_bar
            est: dict[str, np.ndarray] = shocktwin.estimate("x.mcap", bundle)
            x, columns, t_s = shocktwin.features("x.mcap", bundle)
            try:
                pass
            except shocktwin.MissingTopicsError as err:
                missing: list[str] = err.topics
            """
        )
    )
    bad = tmp_path / "bad.py"
    bad.write_text(
        "import shocktwin\nshocktwin.ThermalModel(500.0)\nx: str = shocktwin.read_log('x').label\n"
        "y: str = shocktwin.Bundle('b').nominal_bar\n"
    )
    ok = run(["mypy", "--strict", "--no-incremental", str(user)], cwd=tmp_path)
    assert ok.returncode == 0, ok.stdout + ok.stderr
    # and the stubs are strict enough to catch misuse (so the check above can fail)
    wrong = run(["mypy", "--no-incremental", str(bad)], cwd=tmp_path)
    assert wrong.returncode == 1, wrong.stdout
    assert "Too many positional arguments" in wrong.stdout
    assert 'incompatible type "float | None"' in wrong.stdout or "Incompatible types" in wrong.stdout
    assert wrong.stdout.count("Incompatible types in assignment") == 2, wrong.stdout
