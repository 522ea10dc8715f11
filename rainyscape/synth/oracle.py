"""The clean scene itself as a "perfect 3D reconstruction": re-render a generated scene's views.

A simulated scene folder records everything that determines its clean images (preset, seed,
image size, camera array, trajectory; ``scene.json``). :func:`rerender_clean` rebuilds the
scene and the cameras from it and renders one clean view again, with any number of samples:
with the default it reproduces the stored ``images_wo_rain`` view (to 8-bit rounding), and
it is what an ideal 3D method would render at that view. Benchmarks use it for the "oracle
3D" row; tests use it to check the stored ground truth against renders with more samples.
"""

from __future__ import annotations

import json
from functools import lru_cache
from pathlib import Path

import numpy as np

from rainyscape.errors import DataError
from rainyscape.synth.params import SIM_VERSION
from rainyscape.synth.raycast import EDGE_FACTOR


@lru_cache(maxsize=4)
def _scene(folder: str, stamp: float):
    """Renderer and cameras of a scene folder (cached per folder and scene.json version)."""
    from rainyscape.synth.presets import PRESETS
    from rainyscape.synth.raycast import SceneRenderer
    from rainyscape.synth.rig import make_rig
    from rainyscape.synth.scenes import build_scene

    info = json.loads((Path(folder) / "scene.json").read_text())
    version = str(info.get("simulator_version"))
    if version != SIM_VERSION:
        raise DataError(f"{folder}: made by simulator version {version}, this is version {SIM_VERSION}; "
                        "its views cannot be re-rendered (generate the scene again)")
    preset = info["preset"]
    scene = info.get("scene") or PRESETS[preset].scene
    spec = build_scene(scene, int(info["seed"]))
    rig = make_rig(spec.rig, int(info["rows"]), int(info["cols"]), int(info["width"]), int(info["height"]),
                   info.get("trajectory", "sphere"))
    from rainyscape.synth.raycast import default_samples

    stored = (info.get("sampling") or {}).get("samples") or default_samples(int(info["width"]), int(info["height"]))
    return SceneRenderer(spec), rig.cameras(), int(info["seed"]), int(stored)


def rerender_clean(scene_dir: str | Path, view_index: int, samples: int | None = None,
                   edge_factor: int = EDGE_FACTOR, window: tuple[int, int, int, int] | None = None) -> np.ndarray:
    """Clean view ``view_index`` (0-based: 0 is ``001.png``) of a simulated scene, rendered
    again: (H, W, 3) float in [0, 1].

    ``samples``: the base grid is ``samples`` x ``samples`` prefiltered samples per pixel and
    edges get at least ``(edge_factor * samples)^2`` jittered ones; the default is the
    stored images' sampling (scene.json ``sampling``: 3 below 128 px, else 2), and doubling
    ``samples`` renders with 4x the samples.
    ``window=(x0, y0, x1, y1)`` renders a crop.
    """
    path = Path(scene_dir)
    meta = path / "scene.json"
    if not meta.is_file():
        raise DataError(f"{path}: no scene.json (not a simulated scene folder)")
    renderer, cameras, seed, stored = _scene(str(path.resolve()), meta.stat().st_mtime)
    if not 0 <= int(view_index) < len(cameras):
        raise DataError(f"{path}: view {view_index} out of range (the scene has {len(cameras)} views)")
    view = renderer.render(cameras, int(view_index), samples=stored if samples is None else int(samples),
                           edge_factor=int(edge_factor),
                           seed=seed, window=window)
    return view.rgb
