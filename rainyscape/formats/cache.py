"""The package's cache folder: what is computed once and reused across runs (the demo scene,
sparse points triangulated for scenes that ship none). Never inside a user's scene folder."""

from __future__ import annotations

import os
from pathlib import Path


def cache_root() -> Path:
    """``$RAINYSCAPE_CACHE``, else ``~/.cache/rainyscape``."""
    env = os.environ.get("RAINYSCAPE_CACHE", "").strip()
    return Path(env).expanduser() if env else Path.home() / ".cache" / "rainyscape"
