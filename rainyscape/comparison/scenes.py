"""Scenes of a benchmark: a folder, the embedded demo, or a simulator preset simulated once
into a cache folder (one per preset, size, camera array and simulator version).

A scene is first *planned* (:func:`plan_scene`: its label and, for presets, the exact size it
will be simulated at), so budgets can be checked before anything is simulated or trained,
then *resolved* (:func:`resolve_scene`) to a folder."""

from __future__ import annotations

import shutil
from dataclasses import dataclass
from pathlib import Path

from rainyscape.errors import ConfigError, DataError


@dataclass(frozen=True)
class ScenePlan:
    label: str  # the scene's name in the tables
    folder: str = ""  # an existing scene folder
    preset: str = ""  # or a simulator preset, simulated at the size below
    width: int = 0
    height: int = 0
    rows: int = 0
    cols: int = 0
    embedded: bool = False  # the embedded demo scene (synth/demo.py: DEMO_PRESET at DEMO_SIZE)
    mode: str = "static"  # presets: the simulator's rain mode (static: fixed in 3D; dynamic: moving)


def rain_suffix(mode: str) -> str:
    """What a preset's label and cache folder add for its rain mode ("" for static rain)."""
    return "" if mode == "static" else f"-{mode}"


def plan_scene(spec: str, width: int = 0, height: int = 0, rows: int = 0, cols: int = 0,
               mode: str = "static") -> ScenePlan:
    """The plan of a scene given as ``demo``, a simulator preset or a folder path. Sizes left
    at 0 are the preset's; a width without a height keeps the preset's aspect ratio. A preset
    in ``mode=dynamic`` rain is labelled ``PRESET-dynamic`` (a folder has its own rain)."""
    path = Path(spec).expanduser()
    if path.is_dir():
        return ScenePlan(path.name, folder=str(path.resolve()))
    from rainyscape.synth.presets import PRESETS

    if spec not in PRESETS:
        raise ConfigError(f"scene '{spec}' is neither a scene set, a folder nor a simulator preset "
                          f"({', '.join(PRESETS)})")
    p = PRESETS[spec]
    w = width or p.width
    h = height or (p.height if w == p.width else max(1, round(w * p.height / p.width)))
    embedded = spec == "demo" and not (width or height or rows or cols) and mode == "static"
    return ScenePlan(spec + rain_suffix(mode), preset=spec, width=w, height=h, rows=rows or p.rows,
                     cols=cols or p.cols, embedded=embedded, mode=mode)


def cache_folder(plan: ScenePlan, cache: Path) -> Path | None:
    """Where a planned preset scene is simulated under ``cache`` (None: not simulated there)."""
    if plan.folder or plan.embedded:
        return None
    from rainyscape.synth import SIM_VERSION

    return cache / (f"{plan.preset}-{plan.width}x{plan.height}-{plan.rows}x{plan.cols}"
                    f"{rain_suffix(plan.mode)}-v{SIM_VERSION}")


def resolve_scene(plan: ScenePlan, cache: Path) -> tuple[str, str]:
    """(label, folder) of a planned scene; presets are simulated once into ``cache``."""
    if plan.folder:
        return plan.label, plan.folder
    if plan.embedded:
        from rainyscape.synth.demo import ensure_demo_scene

        return plan.label, str(ensure_demo_scene())
    from rainyscape.synth import generate

    folder = cache_folder(plan, cache)
    if not (folder / "scene.json").is_file():
        print(f"simulating scene '{plan.preset}' ({plan.rows} x {plan.cols} views, {plan.width} x "
              f"{plan.height} px, {plan.mode} rain) into {folder} ...", flush=True)
        try:  # built beside the folder and moved in when complete
            generate(folder, plan.preset, rows=plan.rows, cols=plan.cols, width=plan.width, height=plan.height,
                     mode=plan.mode)
        except DataError:
            if not (folder / "scene.json").is_file():  # else another rs-bench simulated it meanwhile
                raise
    return plan.label, str(folder)
