"""Run folders: outputs/<scene>/<method>/<timestamp>/, never reused."""

from __future__ import annotations

import re
import time
from pathlib import Path


def _slug(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9._-]+", "-", text).strip("-") or "scene"


def new_run_dir(output_dir: str | Path, scene: str, method: str) -> Path:
    """Create a fresh run folder; a second run in the same second gets a suffix."""
    base = Path(output_dir) / _slug(scene) / _slug(method)
    base.mkdir(parents=True, exist_ok=True)
    stamp = time.strftime("%Y-%m-%d_%H%M%S")
    for i in range(1000):
        candidate = base / (stamp if i == 0 else f"{stamp}-{i}")
        try:
            candidate.mkdir()  # atomic: fails if another run took the name
            return candidate
        except FileExistsError:
            continue
    raise RuntimeError(f"could not create a new run folder under {base}")
