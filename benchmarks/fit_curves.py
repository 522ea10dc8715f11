"""PSNR against training time of the fields on real photographs (clean captures).

Each run trains one method's CPU recipe (or N times its length, ``--length``) on a posed
capture's clean photos, read at the real set's size (rainyscape/comparison/captures.py), and
measures PSNR on every training and held-out view at a few points of the run; the time axis is
training time only (evaluation excluded), wall and CPU. Runs are separate processes, one after
another, so their timings compare.

    python benchmarks/fit_curves.py --capture ../shared/data/real/fern --methods 3dgs,nerf \\
        --lengths 1,4 --threads 2 --out benchmarks/results/fit-fern.json
    python benchmarks/fit_curves.py --plot benchmarks/results/fit-*.json --png docs/img/fit_curves.png

The first form prints one line per measurement and writes the curves; the second draws them.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

MARKS = (0.1, 0.25, 0.5, 0.75, 1.0)  # shares of the run at which every view is measured


def run_one(capture: str, method: str, length: float, threads: int, overrides: list[str]) -> dict:
    """Train and measure one run in this process."""
    import numpy as np
    import torch

    from rainyscape.comparison.captures import benchmark_downscale, parse_capture
    from rainyscape.cameras import Window
    from rainyscape.comparison.plan import fixed_length
    from rainyscape.config import method_config, with_run_length
    from rainyscape.engine.pipeline import build_pipeline
    from rainyscape.engine.trainer import Trainer
    from rainyscape.imaging.metrics import psnr

    torch.set_num_threads(threads)
    folder = Path(capture)
    factor = benchmark_downscale(folder)
    scene = parse_capture(folder, factor)
    cfg = method_config(method, [f"data={folder}", "profile=cpu", f"dataparser.downscale={factor}",
                                 "trainer.progress=false", "trainer.eval_every=0", *overrides])
    cfg = with_run_length(cfg, len(scene.train_indices), scene.train_pixels)
    steps = int(round(cfg.trainer.max_iters * length))
    cfg = method_config(method, [f"data={folder}", "profile=cpu", f"dataparser.downscale={factor}",
                                 "trainer.progress=false", "trainer.eval_every=0",
                                 *fixed_length(steps), *overrides])
    if cfg.field.name == "gaussians":  # as rs-train: points triangulated in the training views
        from rainyscape.process.scene_points import with_sparse_points

        scene = with_sparse_points(scene)
    pipe = build_pipeline(cfg, scene, torch.device("cpu"))
    work = Path("/tmp") / f"fit-curves-{method}-{time.time_ns()}"
    work.mkdir(parents=True)
    trainer = Trainer(pipe, work)

    def measure(views: list[int]) -> float:
        pipe.field.eval()
        with torch.no_grad():
            scores = []
            for v in views:
                cams = scene.cameras[[v]]
                rgb = pipe.field.render(cams, Window.full(cams)).rgb.clamp(0, 1)
                truth = scene.images[v].permute(2, 0, 1)[None].float() / 255
                scores.append(float(psnr(rgb, truth)))
        pipe.field.train()
        return float(np.mean(scores))

    marks = sorted({max(1, int(round(m * steps))) for m in MARKS})
    curve, wall, cpu = [], 0.0, 0.0
    while trainer.step < steps:
        w0, c0 = time.perf_counter(), time.process_time()
        trainer.train_step()
        wall += time.perf_counter() - w0
        cpu += time.process_time() - c0
        if trainer.step in marks:
            point = {"step": trainer.step, "wall_s": round(wall, 1), "cpu_s": round(cpu, 1),
                     "train_psnr": round(measure(scene.train_indices), 3),
                     "heldout_psnr": round(measure(scene.eval_indices), 3)}
            print(json.dumps({"method": method, "length": length, **point}), flush=True)
            curve.append(point)
    return {"capture": folder.name, "method": method, "length": length, "steps": steps,
            "threads": threads, "size": [scene.width, scene.height], "train_views": len(scene.train_indices),
            "overrides": overrides, "curve": curve}


def plot(files: list[str], png: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    runs = [r for f in files for r in json.loads(Path(f).read_text())["runs"]]
    captures = sorted({r["capture"] for r in runs})
    fig, axes = plt.subplots(1, len(captures), figsize=(5.5 * len(captures), 4), squeeze=False)
    for ax, capture in zip(axes[0], captures):
        for r in (r for r in runs if r["capture"] == capture):
            t = [p["wall_s"] / 60 for p in r["curve"]]
            label = f"{r['method']} x{r['length']:g}"
            line, = ax.plot(t, [p["train_psnr"] for p in r["curve"]], "-o", ms=3, label=f"{label} training views")
            ax.plot(t, [p["heldout_psnr"] for p in r["curve"]], "--", color=line.get_color(), label=f"{label} held out")
        ax.set_title(f"{capture} (clean photos, {runs[0]['threads']} threads)")
        ax.set_xlabel("training wall time (min)")
        ax.set_ylabel("PSNR (dB)")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(png, dpi=120)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--capture", help="a posed capture folder (LLFF, COLMAP, transforms.json)")
    ap.add_argument("--methods", default="3dgs,nerf")
    ap.add_argument("--lengths", default="1,4", help="multiples of each recipe's run length")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--out", help="results JSON")
    ap.add_argument("--one", nargs=2, metavar=("METHOD", "LENGTH"), help=argparse.SUPPRESS)
    ap.add_argument("--plot", nargs="*", help="results JSON files to draw")
    ap.add_argument("--png", default="docs/img/fit_curves.png")
    args, overrides = ap.parse_known_args()
    if args.plot:
        plot(args.plot, args.png)
        return
    if args.one:
        print("RESULT " + json.dumps(run_one(args.capture, args.one[0], float(args.one[1]), args.threads,
                                             overrides)), flush=True)
        return
    runs = []
    for method in args.methods.split(","):
        for length in args.lengths.split(","):
            cmd = [sys.executable, __file__, "--capture", args.capture, "--threads", str(args.threads),
                   "--one", method, length, *overrides]
            out = subprocess.run(cmd, capture_output=True, text=True)
            sys.stdout.write("".join(line + "\n" for line in out.stdout.splitlines() if not line.startswith("RESULT ")))
            if out.returncode:
                sys.exit(f"{method} x{length} failed:\n{out.stderr[-2000:]}")
            runs.append(json.loads(next(l for l in out.stdout.splitlines() if l.startswith("RESULT "))[7:]))
            Path(args.out).write_text(json.dumps({"command": " ".join(sys.argv), "runs": runs}, indent=1))


if __name__ == "__main__":
    main()
