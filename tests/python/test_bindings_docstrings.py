"""The examples in the public docstrings run (pydantic-core's test_docstrings.py,
polars' doctests). Native functions and classes are not found by doctest's
finder (their ``__module__`` is ``shocktwin._native``), so they are listed
explicitly from ``shocktwin.__all__``."""

from __future__ import annotations

import doctest
import inspect

import pytest

import shocktwin


def public_docstrings():
    seen = {"shocktwin": shocktwin.__doc__}
    for name in shocktwin.__all__:
        obj = getattr(shocktwin, name)
        if inspect.isclass(obj) or inspect.isroutine(obj):
            seen[f"shocktwin.{name}"] = obj.__doc__
        if inspect.isclass(obj):
            for attr, member in vars(obj).items():
                if not attr.startswith("_"):
                    seen[f"shocktwin.{name}.{attr}"] = getattr(member, "__doc__", None)
    return {k: v for k, v in seen.items() if v and ">>>" in v}


EXAMPLES = public_docstrings()


def test_the_main_entry_points_have_examples():
    for name in ["shocktwin", "KalmanFilter", "ThermalModel", "ForceModel", "features", "default_params", "read_log",
                 "Bundle", "estimate"]:
        assert any(k == name or k.endswith("." + name) for k in EXAMPLES), name


@pytest.mark.parametrize("name", sorted(EXAMPLES))
def test_docstring_examples_run(name):
    test = doctest.DocTestParser().get_doctest(EXAMPLES[name], {}, name, None, 0)
    assert test.examples, name
    runner = doctest.DocTestRunner(optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE)
    runner.run(test)
    result = runner.summarize(verbose=False)
    assert result.failed == 0, f"{name}: {result.failed} of {result.attempted} examples failed"


@pytest.mark.parametrize("cls", [shocktwin.KalmanFilter, shocktwin.ForceModel, shocktwin.ThermalModel])
def test_the_signatures_show_the_defaults(cls):
    """``help`` and ``inspect.signature`` show each parameter's default (pyo3 wrote ``...``
    for an expression), and they are the defaults the constructor uses."""
    shown = {n: p.default for n, p in inspect.signature(cls).parameters.items()}
    assert shown == cls().params
