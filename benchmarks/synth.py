"""Simulator benchmark: rs-synth run times and the rain strength of every preset.

    python benchmarks/synth.py                 # everything below
    python benchmarks/synth.py --only timing   # the two timed runs
    python benchmarks/synth.py --only presets  # PSNR / SSIM of each preset at its default size

Timed runs go through the real command line (``rs-synth``, a fresh process: imports
included) and report wall time and CPU time (user + system of the child processes); on a
shared machine the CPU time is the steadier number.
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def run_synth(args: list[str]) -> tuple[float, float, dict]:
    """Run rs-synth in a fresh process: (wall s, CPU s, scene.json)."""
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "scene"
        before = resource.getrusage(resource.RUSAGE_CHILDREN)
        start = time.perf_counter()
        cmd = [sys.executable, "-m", "rainyscape.cli.synth", f"out={out}", *args]
        subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)
        wall = time.perf_counter() - start
        after = resource.getrusage(resource.RUSAGE_CHILDREN)
        cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
        return wall, cpu, json.loads((out / "scene.json").read_text())


def timing() -> None:
    print("| command | views | wall s | CPU s | workers |")
    print("|---|---|---|---|---|")
    for args in (["preset=demo"], ["preset=street", "rows=5", "cols=10", "width=512", "height=512"]):
        wall, cpu, info = run_synth(args)
        views = f"{info['rows'] * info['cols']} x {info['width']}x{info['height']}"
        print(f"| rs-synth {' '.join(args)} | {views} | {wall:.1f} | {cpu:.1f} | {info['workers']} |", flush=True)


def presets() -> None:
    from rainyscape.synth.presets import PRESETS

    print("| preset | scene | rain | views | PSNR dB (min-max) | SSIM |")
    print("|---|---|---|---|---|---|")
    table = {}
    for name, p in PRESETS.items():
        _, _, info = run_synth([f"preset={name}"])
        m = info["metrics"]
        per = [v["psnr"] for v in m["per_view"]]
        r = info["rain"]
        rain = f"density {r['density']:g}/m^3, wind {r['wind_deg']:g} deg"
        if r["mix"] > 0:
            rain += f" + {r['wind2_deg']:g} deg ({r['mix']:.0%})"
        print(f"| {name} | {p.scene} | {rain} | {info['rows']}x{info['cols']} @ {info['width']} px | "
              f"{m['psnr_rainy_vs_clean']:.2f} ({min(per):.1f}-{max(per):.1f}) | {m['ssim_rainy_vs_clean']:.3f} |",
              flush=True)
        table[name] = (round(m["psnr_rainy_vs_clean"], 2), round(m["ssim_rainy_vs_clean"], 3))
    print(f"\nsimulator_version {info['simulator_version']}: PRESET_STRENGTH = {table}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", choices=["timing", "presets"])
    a = ap.parse_args()
    if a.only in (None, "timing"):
        timing()
    if a.only in (None, "presets"):
        presets()


if __name__ == "__main__":
    main()
