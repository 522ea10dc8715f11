"""Simulator benchmark: ground-truth accuracy, rain statistics of every preset, run times.

    python benchmarks/synth.py                  # everything below
    python benchmarks/synth.py --only gt        # clean views: stored sampling vs 4x samples, 2N -> N
    python benchmarks/synth.py --only presets   # every preset at 64/128/256/512 px (rs-synth runs)
    python benchmarks/synth.py --only timing    # the demo, one 50-view scene at 128 and at 512 px
    python benchmarks/synth.py --only presets --sizes 64,128 --presets yard,plaza
    python benchmarks/synth.py --only figure --yard /work/shared/data/yard   # docs/img/simulator_vs_yard.png

Preset and timed runs go through the real command line (``rs-synth``, a fresh process:
imports included) and report wall time and CPU time (user + system of the child processes);
on a shared machine the CPU time is the steadier number. The presets table ends with the
``PRESET_STRENGTH`` dict for ``rainyscape/synth/strength.py`` (128 and 512 px).
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

import numpy as np

SIZES = (64, 128, 256, 512)


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
    print("| command | views | wall s | CPU s | CPU s per view | workers |")
    print("|---|---|---|---|---|---|")
    runs = (["preset=demo"], ["preset=street", "width=128"], ["preset=street", "width=512"])
    for args in runs:
        wall, cpu, info = run_synth(args)
        n = info["rows"] * info["cols"]
        views = f"{n} x {info['width']}x{info['height']}"
        print(f"| rs-synth {' '.join(args)} | {views} | {wall:.1f} | {cpu:.1f} | {cpu / n:.2f} | {info['workers']} |",
              flush=True)


def presets(sizes: tuple[int, ...], names: list[str] | None) -> None:
    from rainyscape.synth.presets import PRESETS

    print("| preset | label dB | size px | views | PSNR dB (min-max) | SSIM | coverage % | mean share % | "
          "streaks / view | edge px % | wall s | CPU s |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    table: dict[str, dict[int, tuple[float, float]]] = {}
    version = None
    for name in names or list(PRESETS):
        p = PRESETS[name]
        for size in sizes:
            wall, cpu, info = run_synth([f"preset={name}", f"width={size}", f"height={size}"])
            version = info["simulator_version"]
            m = info["metrics"]
            per = [v["psnr"] for v in m["per_view"]]
            streaks = np.mean([v["streaks"] for v in m["per_view"]])
            print(f"| {name} | {p.label_db:g} | {size} | {info['rows']}x{info['cols']} | "
                  f"{m['psnr_rainy_vs_clean']:.2f} ({min(per):.1f}-{max(per):.1f}) | {m['ssim_rainy_vs_clean']:.3f} | "
                  f"{100 * m['rain_coverage']:.1f} | {100 * m['rain_mean_share']:.1f} | {streaks:.0f} | "
                  f"{100 * info['sampling']['edge_pixels']:.1f} | {wall:.0f} | {cpu:.0f} |", flush=True)
            table.setdefault(name, {})[size] = (round(m["psnr_rainy_vs_clean"], 2), round(m["ssim_rainy_vs_clean"], 3))
    stored = {k: {s: v[s] for s in (128, 512) if s in v} for k, v in table.items()}
    print(f"\nsimulator_version {version}: PRESET_STRENGTH = {stored}")


def _psnr(a: np.ndarray, b: np.ndarray) -> float:
    return float(-10 * np.log10(np.mean((np.asarray(a, np.float64) - np.asarray(b, np.float64)) ** 2)))


def _grey_rms(a: np.ndarray, b: np.ndarray) -> float:
    return float(255 * np.sqrt(np.mean((np.asarray(a, np.float64) - np.asarray(b, np.float64)) ** 2)))


def ground_truth(views: tuple[int, ...] = (7, 31)) -> None:
    """Clean-view accuracy on each preset's scene: the stored sampling (rounded to 8 bits, as
    written) against a render with 4x the samples, and 2N px area-averaged to N px against N
    px (grey levels RMS: the worst view). Views of 256 px and more are measured on a centred
    128 px crop (2N: 256 px)."""
    from rainyscape.synth.layout import to_uint8
    from rainyscape.synth.presets import PRESETS
    from rainyscape.synth.raycast import SceneRenderer
    from rainyscape.synth.rig import make_rig
    from rainyscape.synth.scenes import build_scene

    def window(size: int, crop: int = 128):
        if size <= crop:
            return None
        x0 = (size - crop) // 2
        return (x0, x0, x0 + crop, x0 + crop)

    print("| scene | size px | stored vs 4x samples: PSNR dB | grey levels RMS | 2N -> N vs N: PSNR dB | "
          "edge px % |")
    print("|---|---|---|---|---|---|")
    scenes = sorted({p.scene for p in PRESETS.values()})
    for scene in scenes:
        spec = build_scene(scene, 0)
        renderer = SceneRenderer(spec)
        for size in SIZES:
            cams = make_rig(spec.rig, 5, 10, size, size).cameras()
            a_psnr, a_rms, b_psnr, edges = [], [], [], []
            for v in views:
                win = window(size)
                stored = renderer.render(cams, v, window=win)
                finer = renderer.render(cams, v, samples=4, window=win)
                a_psnr.append(_psnr(to_uint8(stored.rgb) / 255.0, finer.rgb))
                a_rms.append(_grey_rms(to_uint8(stored.rgb) / 255.0, finer.rgb))
                edges.append(stored.edge_fraction)
                if size <= 256:  # 2N -> N (N = 64, 128, 256 px; 256 on a crop)
                    big_cams = make_rig(spec.rig, 5, 10, 2 * size, 2 * size).cameras()
                    big_win = None if win is None else tuple(2 * x for x in win)
                    big = renderer.render(big_cams, v, window=big_win).rgb
                    h, w = big.shape[:2]
                    down = big.reshape(h // 2, 2, w // 2, 2, 3).mean((1, 3))
                    b_psnr.append(_psnr(down, stored.rgb))
            b = f"{min(b_psnr):.1f}-{max(b_psnr):.1f}" if b_psnr else "-"
            crop = " (crop)" if window(size) else ""
            print(f"| {scene} | {size}{crop} | {min(a_psnr):.1f}-{max(a_psnr):.1f} | {max(a_rms):.2f} | {b} | "
                  f"{100 * np.mean(edges):.0f} |", flush=True)


FIGURE_VIEWS = (("crossroad", 12), ("street", 31), ("plaza", 22))
YARD_VIEWS = ("001.png", "020.png", "040.png")


def _resize(img: np.ndarray, size: int) -> np.ndarray:
    """Area-average (integer factor) or nearest-neighbour enlarge (integer factor) to ``size``."""
    h = img.shape[0]
    if h > size:
        k = h // size
        return img.reshape(size, k, size, k, -1).mean((1, 3))
    k = size // h
    return np.repeat(np.repeat(img, k, 0), k, 1)


def figure(yard: Path, out: Path, view: int = 384, crop: int = 94, zoom: int = 2) -> None:
    """Real rainy Yard views (the authors' release, 512 px) above simulated preset views at
    512 px (medium, wind 30 deg, heavy), shown at ``view`` px, and a row of ``crop`` px
    crops of each at ``zoom`` x."""
    import imageio.v3 as iio

    from rainyscape.synth import layout
    from rainyscape.synth.presets import PRESETS
    from rainyscape.synth.rain import render_rain
    from rainyscape.synth.simulate import Job, Simulation, rain_config

    real = [iio.imread(yard / "images_2" / name)[..., :3].astype(np.float64) for name in YARD_VIEWS]
    ours = []
    for name, k in FIGURE_VIEWS:
        p = PRESETS[name]
        sim = Simulation(Job(name, p.rows, p.cols, 512, 512, "static", "sphere", 0, rain_config(p.rain, {}), ""))
        clean = sim.render_clean(k)
        rain = render_rain(sim.drops, sim.cameras, k, clean.sub_depth, 0.0, sim.job.rain, sim.drop_rgb)
        ours.append(layout.to_uint8(rain.composite(clean.rgb)).astype(np.float64))
    # 384 px views: 512 -> 384 is not an integer factor; resample 512 -> 1536 -> 384 (x3, /4)
    def shrink(img):
        return _resize(np.repeat(np.repeat(img, 3, 0), 3, 1), view) if view != 512 else img

    gap = 8
    rows = []
    for group in (real, ours):
        tiles = [shrink(im) for im in group]
        rows.append(np.concatenate(sum(([t, np.full((view, gap, 3), 255.0)] for t in tiles), [])[:-1], 1))
    crops = []
    for im in real + ours:
        c = im[256 - crop // 2 + 64:256 + crop // 2 + 64, 256 - crop // 2:256 + crop // 2]
        crops.append(_resize(c, crop * zoom))
    width = rows[0].shape[1]
    strip = np.concatenate(sum(([c, np.full((crop * zoom, gap, 3), 255.0)] for c in crops), [])[:-1], 1)
    strip = _resize_width(strip, width)
    sep = np.full((gap, width, 3), 255.0)
    img = np.concatenate([rows[0], sep, rows[1], sep, strip], 0)
    out.parent.mkdir(parents=True, exist_ok=True)
    iio.imwrite(out, np.clip(np.round(img), 0, 255).astype(np.uint8))
    print(f"wrote {out} ({img.shape[1]}x{img.shape[0]})")


def _resize_width(strip: np.ndarray, width: int) -> np.ndarray:
    """Pad (white) or crop a strip to ``width`` columns."""
    if strip.shape[1] >= width:
        return strip[:, :width]
    pad = np.full((strip.shape[0], width - strip.shape[1], 3), 255.0)
    return np.concatenate([strip, pad], 1)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", choices=["gt", "timing", "presets", "figure"])
    ap.add_argument("--yard", default="/work/shared/data/yard", help="the real Yard scene (images_2/)")
    ap.add_argument("--figure", default="docs/img/simulator_vs_yard.png")
    ap.add_argument("--sizes", default=",".join(map(str, SIZES)), help="preset image sizes (px)")
    ap.add_argument("--presets", default="", help="comma-separated presets (default: all)")
    a = ap.parse_args()
    if a.only in (None, "gt"):
        ground_truth()
    if a.only in (None, "timing"):
        timing()
    if a.only in (None, "presets"):
        presets(tuple(int(s) for s in a.sizes.split(",")), [s for s in a.presets.split(",") if s] or None)
    if a.only == "figure" or (a.only is None and Path(a.yard).is_dir()):
        figure(Path(a.yard), Path(a.figure))


if __name__ == "__main__":
    main()
