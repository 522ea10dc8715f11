"""The fusions' per-view threshold rules side by side, on finished runs of scenes with clean
views (simulated, or real photos with simulated rain): for each run, the training views fused
by `rain-mask-fusion` (a run with a rain head) and `streak-fusion`, each under every rule of
``postprocess/fusion.py: THRESHOLD_RULES``, with the mask's coverage and the random-mask
control of the same coverage (seeded as evaluation seeds it); and, for reference, the fusion
under the true rain's pixels grown by one pixel (the simulator's rain layer, read for this
measurement only). PSNR against the clean views, averaged over the training views.

    python benchmarks/fusion_rules.py RUN_DIR [RUN_DIR ...] [--json OUT]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import torch

from rainyscape.eval.protocol import CONTROL_SEED, RAIN_PIXEL
from rainyscape.eval.views import view_images
from rainyscape.imaging.metrics import psnr
from rainyscape.postprocess.fusion import THRESHOLD_RULES, fuse, rain_mask
from rainyscape.postprocess.rain_mask_fusion import RainMaskFusion
from rainyscape.postprocess.streak_fusion import StreakFusion
from rainyscape.workflow import load_trained


def fusions(has_rain: bool) -> dict:
    out = {f"streak {rule}": StreakFusion(StreakFusion.Config(rule=rule)) for rule in THRESHOLD_RULES}
    if has_rain:
        out.update({f"rain-mask {rule}": RainMaskFusion(RainMaskFusion.Config(rule=rule)) for rule in THRESHOLD_RULES})
    return out


def run_rows(run_dir: Path) -> dict:
    """Mean over the run's training views of each fusion's PSNR, control PSNR and coverage."""
    pipeline, _ = load_trained(run_dir, device="cpu")
    scene = pipeline.scene
    if scene.clean_images is None or scene.rain_layers is None:
        raise SystemExit(f"{run_dir}: its scene has no clean views or rain layers")
    posts = fusions(pipeline.rain_head is not None)
    sums: dict[str, float] = {}
    views = list(scene.train_indices)
    with torch.no_grad():
        for i in views:
            v = view_images(pipeline, i)
            score = lambda x: float(psnr(x.clamp(0, 1)[None], v.clean[None]))  # noqa: E731
            row = {"input": score(v.rainy), "render": score(v.rendered),
                   "true mask": score(fuse(v.rendered, v.rainy, rain_mask(v.true_rain, RAIN_PIXEL, 1)))}
            for name, post in posts.items():
                control = post.control(v.rendered, v.rain, v.rainy, seed=CONTROL_SEED + i)
                row[name] = score(post(v.rendered, v.rain, v.rainy))
                row[f"{name} control"] = score(control.control)
                row[f"{name} coverage"] = control.coverage
            for k, x in row.items():
                sums[k] = sums.get(k, 0.0) + x
    return {k: x / len(views) for k, x in sums.items()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", type=Path, nargs="+")
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    torch.set_num_threads(1)
    results = {}
    for run in args.runs:
        results[str(run)] = rows = run_rows(run)
        print(run)
        for k, x in rows.items():
            print(f"  {k:32s} {x:8.3f}" if "coverage" in k else f"  {k:32s} {x:8.2f}")
    if args.json:
        args.json.write_text(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
