"""`python -m train.demo_serve` refuses an output directory a demo already used.

Run again into the same `--out`, the demo's daemon opened the last demo's fleet store and inbox,
took the drives dropped in again as runs it had read, and the demo then waited ten minutes for a
service baseline that never came. It now stops at once and says why, before simulating anything.
"""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))
from train import demo_serve  # noqa: E402

sys.path.remove(str(ROOT))


def test_a_used_output_directory_is_refused_at_once(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "serve-demo"
    (out / "inbox").mkdir(parents=True)
    # A binary that does not exist: the refusal must come before anything is run.
    argv = ["--bin", str(tmp_path / "no-shocktwin"), "--bundle", str(tmp_path / "no-bundle"), "--out", str(out)]
    with pytest.raises(SystemExit) as stop:
        demo_serve.main(argv)
    assert stop.value.code == 2
    err = capsys.readouterr().err
    assert f"--out {out} is not empty" in err and "remove it" in err
    assert sorted(p.name for p in out.iterdir()) == ["inbox"], "nothing written into the refused directory"


def test_an_empty_output_directory_is_taken(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "serve-demo"
    out.mkdir()
    # Accepted: the demo goes on to find its CLI, which fails here on the missing binary.
    with pytest.raises(SystemExit) as stop:
        demo_serve.main(["--bin", str(tmp_path / "no-shocktwin"), "--bundle", str(tmp_path / "b"), "--out", str(out)])
    assert stop.value.code == 2
    err = capsys.readouterr().err
    assert "no shocktwin CLI at" in err and "no-shocktwin" in err and "is not empty" not in err, err
