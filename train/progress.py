"""Progress bars for long work: shown on a terminal, quiet in CI logs and pipes."""

from __future__ import annotations

import os
import sys
from typing import Iterable, Iterator, TypeVar

from tqdm import tqdm  # type: ignore[import-untyped]

T = TypeVar("T")


def quiet() -> bool:
    """No bar when ``CI`` is set or stderr is not a terminal."""
    return bool(os.environ.get("CI")) or not sys.stderr.isatty()


def progress(items: Iterable[T], *, total: int | None = None, desc: str = "", unit: str = "it") -> Iterator[T]:
    """``items``, with a bar on the terminal (tqdm) while they are consumed."""
    return iter(tqdm(items, total=total, desc=desc, unit=unit, leave=False, disable=quiet()))
