"""How much a better mask could lift streak fusion: per finished run of a simulated scene,
the training views fused with streak fusion's mask and with masks that know the true rain
(the simulator's rain layers, read for this diagnosis only):

- ``streak``: streak fusion as shipped (``postprocess/streak_fusion.py``);
- ``true``: the true rain's pixels (any channel above 0.02), and grown by one pixel; the
  render fills them, so this is what the render's own error leaves at best;
- ``streak and true``: streak fusion's mask without its false pixels (what precision is worth);
- ``streak or true``: with the rain it misses added (what recall is worth);
- the mask's coverage, its precision (against the true rain grown by one pixel) and recall.

    python benchmarks/fusion_headroom.py RUN_DIR [RUN_DIR ...]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import torch

from rainyscape.workflow import load_trained
from rainyscape.eval.protocol import RAIN_PIXEL
from rainyscape.eval.views import render_image
from rainyscape.imaging.metrics import psnr
from rainyscape.postprocess.fusion import fuse, rain_mask
from rainyscape.postprocess.streak_fusion import StreakFusion


def view_rows(rendered: torch.Tensor, rainy: torch.Tensor, clean: torch.Tensor, rain: torch.Tensor) -> dict:
    """The fused views' PSNR (dB) and the streak mask's statistics for one view (3, H, W) each."""
    streak = StreakFusion().mask(rendered, None, rainy)
    true, grown = rain_mask(rain, RAIN_PIXEL, 0), rain_mask(rain, RAIN_PIXEL, 1)

    def fused(mask: torch.Tensor) -> float:
        return float(psnr(fuse(rendered, rainy, mask)[None], clean[None]))

    return {"input": float(psnr(rainy[None], clean[None])), "render": float(psnr(rendered[None], clean[None])),
            "streak": fused(streak), "true": fused(true), "true grown": fused(grown),
            "streak and true": fused(streak & grown), "streak or true": fused(streak | true),
            "coverage": float(streak.float().mean()), "true coverage": float(true.float().mean()),
            "precision": float((streak & grown).sum() / streak.sum().clamp_min(1)),
            "recall": float((streak & true).sum() / true.sum().clamp_min(1))}


def run_rows(run_dir: Path) -> tuple[str, dict]:
    pipeline, _ = load_trained(run_dir, device="cpu")
    scene = pipeline.scene
    if scene.clean_images is None or scene.rain_layers is None:
        raise SystemExit(f"{run_dir}: its scene has no clean images or rain layers (a simulated scene is needed)")
    rows = []
    for i in scene.train_indices:
        def image(t):
            return t[i].permute(2, 0, 1).float()
        rows.append(view_rows(render_image(pipeline, i).clamp(0, 1), image(scene.images) / 255,
                              image(scene.clean_images) / 255, image(scene.rain_layers)))
    return scene.name, {k: sum(r[k] for r in rows) / len(rows) for k in rows[0]}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+", type=Path)
    args = parser.parse_args()
    means = {}
    for run_dir in args.runs:
        name, means[name] = run_rows(run_dir)
        print(json.dumps({"scene": name, **{k: round(v, 3) for k, v in means[name].items()}}), flush=True)
    keys = next(iter(means.values())).keys()
    print("| | " + " | ".join(means) + " | mean |")
    print("|---|" + "---|" * (len(means) + 1))
    for k in keys:
        values = [m[k] for m in means.values()]
        print(f"| {k} | " + " | ".join(f"{v:.2f}" for v in values) + f" | {sum(values) / len(values):.2f} |")


if __name__ == "__main__":
    main()
