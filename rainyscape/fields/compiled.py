"""Importing the optional compiled modules that setup.py builds (the rasteriser, the vector-
matrix lookup, the grid field's first pass): each wrapper keeps the module, or None and why."""

from __future__ import annotations

import importlib
from types import ModuleType


def load(name: str) -> tuple[ModuleType | None, str]:
    """The module ``name`` and ''; or None and the import error's text (not built: no
    compiler at install time, or a stale install)."""
    try:
        return importlib.import_module(name), ""
    except ImportError as err:
        return None, str(err) or type(err).__name__
