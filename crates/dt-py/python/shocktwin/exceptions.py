"""The exceptions raised by :mod:`shocktwin`.

Every error of the Rust core maps to exactly one class here (the mapping is
``crates/dt-py/src/exceptions.rs``). Each message is the core's message, which
names the file, topic, field or parameter at fault.

All derive from :class:`ShocktwinError`; each also derives from the builtin
exception a caller would expect (``ValueError`` for bad input, ``OSError`` for
a file that cannot be read, ``ArithmeticError`` for a numerical failure), so
``except ValueError`` keeps working.
"""

from __future__ import annotations

from typing import Sequence

__all__ = [
    "ShocktwinError",
    "LogError",
    "LogReadError",
    "MissingTopicsError",
    "ParamsError",
    "ParamsReadError",
    "ParamsNotFoundError",
    "PhysicsError",
    "BundleError",
    "BundleReadError",
    "BundleNotFoundError",
    "InputError",
]


class ShocktwinError(Exception):
    """Base class of every error raised by :mod:`shocktwin`."""


class LogError(ShocktwinError, ValueError):
    """A run log is not valid MCAP or not a valid shocktwin log (SPEC §2)."""


class LogReadError(ShocktwinError, OSError):
    """A run log could not be opened or read (the OS error is in the message)."""


class MissingTopicsError(LogError):
    """A log lacks topics that the requested input groups need.

    ``topics`` lists the missing topic names, e.g. ``["/force"]``.
    """

    topics: list[str]

    def __init__(self, message: str, topics: Sequence[str] = ()) -> None:
        super().__init__(message)
        self.topics = list(topics)


class ParamsError(ShocktwinError, ValueError):
    """A physics parameter is missing, unknown or out of its valid range."""


class ParamsReadError(ParamsError, OSError):
    """A parameter or calibration file (``physics.json``, a road calibration) could not
    be read (the OS error is in the message)."""


class ParamsNotFoundError(ParamsReadError, FileNotFoundError):
    """A parameter or calibration file is missing."""


class PhysicsError(ShocktwinError, ArithmeticError):
    """A model's numerical integration failed (non-finite state, bad inputs)."""


class BundleError(ShocktwinError, ValueError):
    """A model bundle is incomplete or inconsistent; the message names the
    file (``twin.json``, ``mlp.onnx``) and the part at fault."""


class BundleReadError(BundleError, OSError):
    """A file of a model bundle could not be read (the OS error is in the message)."""


class BundleNotFoundError(BundleReadError, FileNotFoundError):
    """A file of a model bundle (``twin.json``, the network it names) is missing."""


class InputError(ShocktwinError, ValueError):
    """An input array or argument is inconsistent (lengths differ, times not
    sorted, an unknown feature group)."""
