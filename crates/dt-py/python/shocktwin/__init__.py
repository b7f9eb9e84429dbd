"""shocktwin: digital twin of an automotive shock absorber (Python bindings).

The native module ``shocktwin._native`` is private; everything public is
re-exported here.
"""

from shocktwin._native import __version__

__all__ = ["__version__"]
