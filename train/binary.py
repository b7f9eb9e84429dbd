"""Where the ``shocktwin`` CLI is, for the scripts that run it (the study's generalisation
sets, the demo's daemon)."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

#: The workspace's release build, found from this package (not from the working directory).
REPO_BIN = Path(__file__).resolve().parents[1] / "target" / "release" / "shocktwin"


def find_shocktwin(given: str | os.PathLike[str] | None = None) -> Path:
    """The CLI: ``given`` (a path, or a name on ``PATH``), else ``$SHOCKTWIN_BIN``, else this
    workspace's ``target/release/shocktwin``, else ``shocktwin`` on ``PATH``.

    Raises ``FileNotFoundError`` naming what was tried: a script that needs the CLI late
    (the study's generalisation sets come after every permutation is trained) checks at its
    start, not after an hour's work."""
    explicit = given if given is not None else os.environ.get("SHOCKTWIN_BIN")
    if explicit:
        name = str(explicit)
        found = name if Path(name).is_file() else shutil.which(name)
        if found:
            return Path(found).resolve()
        where = "--shocktwin/--bin" if given is not None else "$SHOCKTWIN_BIN"
        raise FileNotFoundError(f"no shocktwin CLI at {name!r} ({where})")
    if REPO_BIN.is_file():
        return REPO_BIN
    on_path = shutil.which("shocktwin")
    if on_path:
        return Path(on_path).resolve()
    raise FileNotFoundError(f"no shocktwin CLI (tried {REPO_BIN} and shocktwin on PATH): build it with "
                            "`cargo build --release -p dt-server`, or give its path")
