"""The embedded demo scene: generated once by the simulator and cached.

The cache lives in ``$RAINYSCAPE_CACHE`` (or ``~/.cache/rainyscape``) under a folder named
by the simulator version, so a simulator change regenerates it. Generation writes into a
temporary folder that is renamed into place only when complete: an interrupted run never
leaves a broken cache.
"""

from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path

from rainyscape.formats.cache import cache_root
from rainyscape.synth.simulate import SIM_VERSION, generate

# The medium-rain crossroad at 128 px, 3 x 6 views: rainyscape-3dgs trains on it in about
# 5 minutes on 2 cores (docs/benchmarks.md, "Demo runs").
DEMO_PRESET = "crossroad"
DEMO_SIZE = {"rows": 3, "cols": 6, "width": 128, "height": 128}


def demo_path() -> Path:
    return cache_root() / f"demo-scene-{DEMO_PRESET}-v{SIM_VERSION}"


def ensure_demo_scene(verbose: bool = True) -> Path:
    """Path of the cached demo scene, generating it first if needed."""
    final = demo_path()
    if (final / "scene.json").is_file():
        return final
    final.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{final.name}-", dir=final.parent))
    try:
        if verbose:
            print(f"generating the demo scene into {final} (once) ...", flush=True)
        generate(tmp, DEMO_PRESET, force=True, **DEMO_SIZE)
        if final.exists():  # a stale, incomplete folder (or another process won the race)
            if (final / "scene.json").is_file():
                return final
            shutil.rmtree(final)
        os.replace(tmp, final)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
    return final
