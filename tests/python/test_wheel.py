"""The analysts' path without Rust: `make wheel` builds an abi3 wheel into dist/;
it installs into a fresh virtual environment whose PATH has no cargo or rustc,
and the package's docstring examples run there against the installed copy."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
# The test dependencies of the docstring examples' runner, pinned as in requirements.txt.
RUNNER = [line.strip() for line in (ROOT / "requirements.txt").read_text().splitlines()
          if re.match(r"^(pytest|mcap|zstandard|lz4)==", line.strip())]


def test_the_wheel_installs_and_works_without_rust(tmp_path: Path) -> None:
    build = subprocess.run(["make", "-s", "wheel"], cwd=ROOT, capture_output=True, text=True, timeout=1800)
    assert build.returncode == 0, build.stdout[-2000:] + build.stderr[-4000:]
    wheels = sorted((ROOT / "dist").glob("shocktwin-*.whl"), key=lambda p: p.stat().st_mtime)
    assert wheels, "make wheel wrote no wheel into dist/"
    wheel = wheels[-1]
    assert re.fullmatch(r"shocktwin-[0-9.]+-cp39-abi3-(manylinux|linux)_[0-9a-z_]+\.whl", wheel.name), wheel.name

    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True, timeout=300)
    # No Rust toolchain on PATH: the wheel must not need one.
    path = [d for d in os.environ.get("PATH", "").split(os.pathsep)
            if d and not any((Path(d) / tool).exists() for tool in ("cargo", "rustc"))]
    env = {k: v for k, v in os.environ.items() if not k.startswith(("CARGO", "RUST", "VIRTUAL_ENV"))}
    env["PATH"] = os.pathsep.join([str(venv / "bin"), *path])
    assert shutil.which("cargo", path=env["PATH"]) is None and shutil.which("rustc", path=env["PATH"]) is None
    install = subprocess.run([str(venv / "bin" / "pip"), "install", "-q", str(wheel), *RUNNER],
                             env=env, cwd=tmp_path, capture_output=True, text=True, timeout=900)
    assert install.returncode == 0, install.stdout[-2000:] + install.stderr[-4000:]
    where = subprocess.run([str(venv / "bin" / "python"), "-c", "import shocktwin; print(shocktwin.__file__)"],
                           env=env, cwd=tmp_path, capture_output=True, text=True, timeout=120)
    assert Path(where.stdout.strip()).resolve().is_relative_to(venv.resolve()), where.stdout + where.stderr
    doctests = subprocess.run([str(venv / "bin" / "python"), "-m", "pytest", "-q", "-p", "no:cacheprovider",
                               str(ROOT / "tests" / "python" / "test_bindings_docstrings.py")],
                              env=env, cwd=tmp_path, capture_output=True, text=True, timeout=600)
    assert doctests.returncode == 0, doctests.stdout[-4000:] + doctests.stderr[-2000:]
