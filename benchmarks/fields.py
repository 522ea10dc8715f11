"""NeRF field benchmarks: training step time of both fields, and quality after a time budget.

    python benchmarks/fields.py speed [--grid-steps 300] [--mlp-steps 3]
    python benchmarks/fields.py quality --method nerf --minutes 5 [--iters N]
    python benchmarks/fields.py quality --method vanilla-nerf --minutes 5 15
    python benchmarks/fields.py ceiling --method 3dgs --data DIR --tag TAG [key=value ...]

Both run on the simulator's demo scene trained on its CLEAN images (the ceiling the rain
work aims at), or on --data DIR (a maya-csv scene with an images_wo_rain folder).

speed: one process, the paper's batch (4096 random rays per step) for both fields: nerf-mlp
with 64 + 64 samples (the vanilla-nerf config), and the grid field (the nerf config) over a
whole schedule of --grid-steps (it gets cheaper per step as empty space is carved and dearer
as it grows), reporting its mean and final-resolution step time and the ratio.

ceiling: trains any METHOD (nerf, 3dgs, ...) for its whole schedule on the CLEAN images of
--data and reports training wall time (evaluation excluded), steps per second, the field's
stats (Gaussian count, densification events, grid resolution) every --stats-every steps,
and PSNR / SSIM of all training and held-out views against the clean images; one JSON line
per run is appended to --out/ceiling.jsonl.

quality: trains METHOD until each of the --minutes marks of training wall time (evaluation
time excluded), evaluating held-out views (PSNR, SSIM vs clean) at each mark. --iters sets
the schedule length (default: the method's); a schedule that ends earlier ends the run.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import torch


def clean_demo_overrides(data: str) -> list[str]:
    return ["dataparser=maya-csv", "dataparser.images=images_wo_rain"] + ([f"data={data}"] if data else [])


def build(method: str, overrides: list[str], out: Path):
    from rainyscape import config
    from rainyscape.engine.pipeline import build_pipeline
    from rainyscape.engine.scene_loading import load_scene
    from rainyscape.engine.device import resolve_device
    from rainyscape.engine.run import scene_folder
    from rainyscape.engine.trainer import Trainer, seed_everything
    from rainyscape.workflow import complete_scene, with_scene

    cfg = with_scene(config.method_config(method, overrides))
    seed_everything(cfg.trainer.seed)
    scene = complete_scene(cfg, load_scene(cfg, scene_folder(cfg)))  # as rs-train
    cfg = config.with_run_length(cfg, len(scene.train_indices), scene.train_pixels)
    pipeline = build_pipeline(cfg, scene, resolve_device(cfg.trainer.device))
    out.mkdir(parents=True, exist_ok=True)
    return cfg, Trainer(pipeline, out)


def timed_steps(trainer, count: int) -> list[float]:
    times = []
    for _ in range(count):
        t0 = time.perf_counter()
        trainer.train_step()
        times.append(time.perf_counter() - t0)
    return times


@torch.no_grad()
def view_metrics(trainer, indices) -> tuple[float, float]:
    """Mean PSNR / SSIM of the renders of ``indices`` against the clean images (the images
    themselves when the scene was read from its clean folder)."""
    from rainyscape.eval.views import render_view
    from rainyscape.imaging.metrics import psnr, ssim

    scene, psnrs, ssims = trainer.scene, [], []
    reference = scene.clean_images if scene.clean_images is not None else scene.images
    for i in indices:
        rgb = render_view(trainer.pipeline, i).rgb.clamp(0, 1)
        clean = reference[i].to(trainer.device).permute(2, 0, 1)[None].float() / 255
        psnrs.append(float(psnr(rgb, clean)))
        ssims.append(float(ssim(rgb, clean)))
    return sum(psnrs) / len(psnrs), sum(ssims) / len(ssims)


def ceiling(args) -> dict:
    overrides = clean_demo_overrides(args.data) + [
        "trainer.progress=false", "trainer.eval_every=0", "trainer.checkpoint_every=0",
        *args.overrides]
    cfg, trainer = build(args.method, overrides, Path(args.out) / f"ceiling-{args.tag}")
    trained, trace = 0.0, []
    while trainer.step < cfg.trainer.max_iters:
        t0 = time.perf_counter()
        trainer.train_step()
        trained += time.perf_counter() - t0
        if trainer.step % args.stats_every == 0 or trainer.step == cfg.trainer.max_iters:
            trace.append({"step": trainer.step, "seconds": round(trained, 1), **trainer.pipeline.field.stats()})
    scene = trainer.scene
    train_psnr, train_ssim = view_metrics(trainer, scene.train_indices)
    held_psnr, held_ssim = view_metrics(trainer, scene.eval_indices) if scene.eval_indices else (None, None)
    result = {"tag": args.tag, "method": args.method, "overrides": list(args.overrides),
              "steps": trainer.step, "train_seconds": round(trained, 1),
              "steps_per_s": round(trainer.step / trained, 2), "threads": torch.get_num_threads(),
              "train_psnr": round(train_psnr, 2), "train_ssim": round(train_ssim, 4),
              "heldout_psnr": held_psnr and round(held_psnr, 2),
              "heldout_ssim": held_ssim and round(held_ssim, 4),
              "final_stats": trace[-1], "trace": trace}
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    with open(out / "ceiling.jsonl", "a") as fh:
        fh.write(json.dumps(result) + "\n")
    return result


@torch.no_grad()
def heldout_metrics(trainer) -> dict:
    from rainyscape.eval.views import render_view
    from rainyscape.imaging.metrics import psnr, ssim

    scene, psnrs, ssims = trainer.scene, [], []
    for i in scene.eval_indices:
        rgb = render_view(trainer.pipeline, i).rgb.clamp(0, 1)
        reference = scene.clean_images if scene.clean_images is not None else scene.images
        clean = reference[i].to(trainer.device).permute(2, 0, 1)[None].float() / 255
        psnrs.append(float(psnr(rgb, clean)))
        ssims.append(float(ssim(rgb, clean)))
    return {"heldout_psnr": sum(psnrs) / len(psnrs), "heldout_ssim": sum(ssims) / len(ssims),
            "views": len(psnrs)}


def speed(args) -> dict:
    from rainyscape.comparison.plan import fixed_length

    base = clean_demo_overrides(args.data) + ["phases.fit.patches=4096", "phases.fit.patch_size=1"]
    out = Path(args.out)
    _, grid = build("nerf", base + fixed_length(args.grid_steps), out / "speed-grid")
    grid_times = timed_steps(grid, args.grid_steps)
    tail = grid_times[-max(1, args.grid_steps // 5):]
    _, mlp = build("vanilla-nerf", base, out / "speed-mlp")
    mlp.train_step()  # the first step pays for allocations
    mlp_times = timed_steps(mlp, args.mlp_steps)
    mlp_step = sum(mlp_times) / len(mlp_times)
    result = {
        "rays_per_step": 4096, "threads": torch.get_num_threads(),
        "nerf_mlp_step_s": mlp_step,
        "grid_mean_step_s": sum(grid_times) / len(grid_times),
        "grid_final_step_s": sum(tail) / len(tail),
        "grid_final_resolution": grid.pipeline.field.resolution,
        "grid_occupied_fraction": grid.pipeline.field.occupancy.fraction(),
    }
    result["ratio_mean"] = mlp_step / result["grid_mean_step_s"]
    result["ratio_final"] = mlp_step / result["grid_final_step_s"]
    return result


def quality(args) -> dict:
    from rainyscape.comparison.plan import fixed_length

    overrides = clean_demo_overrides(args.data) + list(args.overrides)
    if args.iters:
        overrides += fixed_length(args.iters)  # the grid's rates decay over the run's length
    cfg, trainer = build(args.method, overrides, Path(args.out) / f"quality-{args.method}")
    marks = sorted(args.minutes)
    results, trained = [], 0.0
    for mark in marks:
        while trained < mark * 60 and trainer.step < cfg.trainer.max_iters:
            t0 = time.perf_counter()
            trainer.train_step()
            trained += time.perf_counter() - t0
        results.append({"minutes": mark, "train_seconds": round(trained, 1), "steps": trainer.step,
                        **heldout_metrics(trainer)})
        print(json.dumps(results[-1]), flush=True)
    return {"method": args.method, "max_iters": cfg.trainer.max_iters, "threads": torch.get_num_threads(),
            "results": results}


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="mode", required=True)
    sp = sub.add_parser("speed")
    sp.add_argument("--grid-steps", type=int, default=300)
    sp.add_argument("--mlp-steps", type=int, default=3)
    q = sub.add_parser("quality")
    q.add_argument("--method", default="nerf", choices=["nerf", "vanilla-nerf"])
    q.add_argument("--minutes", type=float, nargs="+", default=[5.0])
    q.add_argument("--iters", type=int, default=0, help="schedule length (0: the method's)")
    q.add_argument("overrides", nargs="*", help="extra key=value config overrides")
    c = sub.add_parser("ceiling")
    c.add_argument("--method", default="3dgs")
    c.add_argument("--tag", default="run")
    c.add_argument("--stats-every", type=int, default=100)
    c.add_argument("overrides", nargs="*", help="extra key=value config overrides")
    for p in (sp, q, c):
        p.add_argument("--data", default="", help="maya-csv scene with images_wo_rain (default: demo)")
        p.add_argument("--out", default="outputs/benchmarks/fields")
    args = parser.parse_args(argv)
    if args.mode == "ceiling":
        result = ceiling(args)
        print(json.dumps({k: v for k, v in result.items() if k != "trace"}), flush=True)
        return 0
    result = speed(args) if args.mode == "speed" else quality(args)
    print(json.dumps(result, indent=2))
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    name = "speed" if args.mode == "speed" else f"quality-{args.method}"
    (out / f"{name}.json").write_text(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
