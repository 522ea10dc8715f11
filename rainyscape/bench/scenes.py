"""Scenes of a benchmark: a folder, the embedded demo, or a simulator preset simulated once
into a cache folder (one per preset, size and simulator version)."""

from __future__ import annotations

import shutil
from pathlib import Path

from rainyscape.errors import ConfigError


def resolve_scene(spec: str, cache: Path, width: int = 0, rows: int = 0, cols: int = 0) -> tuple[str, str]:
    """(label, folder) of a scene given as ``demo``, a simulator preset or a folder path.

    ``demo`` without size options is the embedded demo scene; presets are simulated once
    into ``cache`` (a folder per preset, size and simulator version)."""
    path = Path(spec).expanduser()
    if path.is_dir():
        return path.name, str(path.resolve())
    from rainyscape.synth.presets import PRESETS

    if spec not in PRESETS:
        raise ConfigError(f"scene '{spec}' is neither a folder nor a simulator preset "
                          f"({', '.join(PRESETS)})")
    if spec == "demo" and not (width or rows or cols):
        from rainyscape.synth.demo import ensure_demo_scene

        return "demo", str(ensure_demo_scene())
    from rainyscape.synth import SIM_VERSION, generate

    size = f"-{width or 'd'}x{rows or 'd'}x{cols or 'd'}" if (width or rows or cols) else ""
    folder = cache / f"{spec}{size}-v{SIM_VERSION}"
    if not (folder / "scene.json").is_file():
        print(f"simulating scene '{spec}' into {folder} ...", flush=True)
        tmp = folder.with_name(folder.name + ".partial")
        if tmp.exists():
            shutil.rmtree(tmp)
        generate(tmp, spec, rows=rows or None, cols=cols or None, width=width or None, force=True)
        tmp.rename(folder)
    return spec, str(folder)
