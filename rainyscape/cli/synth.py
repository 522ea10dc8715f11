"""rs-synth: simulate a multi-view rainy scene with ground truth (the paper's Maya layout).

Usage:
  rs-synth preset=NAME out=DIR [key=value ...]
  rs-synth --list                 presets with their scene and rain strength

Writes rainy and clean images, depth, the true rain layer and cameras.csv into DIR and
prints the rainy-vs-clean PSNR / SSIM (the rain's strength) and the rain's coverage. Rain
options default to the preset's values (the base values are shown).

A non-empty DIR is refused unless force=true, which replaces every entry of a scene there
(images_rain/, images_wo_rain/, depth/, rain/, haze/, cameras.csv, scene.json) as a whole and
keeps the rest. The scene is built beside DIR and moved in when complete: a failed or
interrupted run leaves DIR as it was.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass

from rainyscape.cli import run_cli
from rainyscape.cli.args import SEED_MAX, Command, opt, parse, print_help
from rainyscape.synth.params import RainConfig
from rainyscape.synth.presets import PRESETS


@dataclass
class SynthArgs:
    preset: str = opt("demo", "simulator preset (rs-synth --list)", choices=tuple(PRESETS))
    out: str = opt("", "folder to write (required)")
    rows: int | None = opt(None, "camera rows (default: the preset's)", lo=1, hi=100)
    cols: int | None = opt(None, "camera columns (default: the preset's)", lo=1, hi=100)
    width: int | None = opt(None, "image width in pixels (default: the preset's)", lo=1, hi=8192)
    height: int | None = opt(None, "image height in pixels (default: the preset's, or square with width=)",
                             lo=1, hi=8192)
    mode: str = opt("static", "static: one rain field, like the paper's Maya data; dynamic: rain moves",
                    choices=("static", "dynamic"))
    trajectory: str = opt("sphere", "camera path", choices=("sphere", "video"))
    seed: int = opt(0, "random seed", lo=0, hi=SEED_MAX)
    workers: int | None = opt(None, "processes (default: 1 for small jobs, else every core)", lo=1, hi=256)
    force: bool = opt(False, "write into a non-empty folder, replacing every entry of a scene there as a "
                             "whole (the rest of the folder is kept)")


OOM_HINT = ("lower width= and height= or the views (rows=, cols=), or use fewer workers= (each holds "
            "the scene)")
COMMAND = Command("rs-synth", __doc__, SynthArgs, more=(("Rain options", RainConfig),), actions=("--list",),
                  oom_hint=OOM_HINT)


def print_presets() -> None:
    from rainyscape.synth.params import SIM_VERSION
    from rainyscape.synth.presets import PRESETS
    from rainyscape.synth.strength import MEASURED_VERSION, PRESET_STRENGTH

    current = MEASURED_VERSION == SIM_VERSION

    def column(name: str, width: int) -> str:
        s = PRESET_STRENGTH.get(name, {}).get(width) if current else None
        return f"{s[0]:5.1f} dB / {s[1]:.3f}" if s else "not measured"

    print(f"{'preset':<9}  {'scene':<9}  {'views':<11}  {'label':<6}  {'at 128 px':<16}  {'at 512 px':<16}  "
          "description (rainy vs clean PSNR / SSIM)")
    for p in PRESETS.values():
        views = f"{p.rows}x{p.cols} {p.width}px"
        print(f"{p.name:<9}  {p.scene:<9}  {views:<11}  {p.label_db:4.0f}dB  {column(p.name, 128):<16}  "
              f"{column(p.name, 512):<16}  {p.level}: {p.description}")


def main(argv: list[str]) -> int:
    from rainyscape.errors import ConfigError

    args = parse(argv, COMMAND)
    if args.help:
        return print_help(COMMAND)
    if "--list" in args.actions:
        print_presets()
        return 0
    values = dict(args.values)  # only what was given: the preset fills in the rest
    if "out" not in values:
        raise ConfigError("where to write? e.g. rs-synth preset=demo out=data/demo (rs-synth --list shows presets)")
    import json
    import time
    from pathlib import Path

    from rainyscape.synth import generate

    preset = values.pop("preset", "demo")
    out = values.pop("out")

    def progress(done: int, total: int) -> None:
        print(f"\r  rendering view {done}/{total}", end="" if done < total else "\n", flush=True)

    start = time.perf_counter()
    path = generate(out, preset, progress=progress, **values)
    info = json.loads((Path(path) / "scene.json").read_text())
    m = info["metrics"]
    print(f"wrote {info['rows'] * info['cols']} views ({info['width']}x{info['height']}, {info['mode']} rain, "
          f"{info['drops']} drops) to {path} in {time.perf_counter() - start:.1f} s")
    print(f"rainy vs clean: PSNR {m['psnr_rainy_vs_clean']:.2f} dB, SSIM {m['ssim_rainy_vs_clean']:.4f} "
          f"(per view: {min(v['psnr'] for v in m['per_view']):.2f} to {max(v['psnr'] for v in m['per_view']):.2f} dB)")
    print(f"rain streaks cover {100 * m['rain_coverage']:.1f} % of the pixels (alpha > 0.02); their per-image "
          f"mean is {100 * m['rain_mean_share']:.1f} % of their squared error")
    return 0


def entry() -> None:
    sys.exit(run_cli(main))


if __name__ == "__main__":
    entry()
