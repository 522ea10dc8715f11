"""How much of a trained run's error on each view is the view's exposure.

For every view of a run it renders the field, scores it against the view's reference (the
clean image where the scene has one, else the photo) and again after the best per-channel
gain for that view alone (the ratio of the means: what a per-image exposure or white-balance
correction could recover at most, to first order). Prints one line per view and the means
per split; a phone's automatic exposure shows as gains away from 1 and a PSNR that rises
with them, a field that misses detail as neither.

  python benchmarks/view_gain.py RUN_DIR [--json OUT.json]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import torch

from rainyscape.workflow import load_trained
from rainyscape.eval.views import render_image
from rainyscape.imaging.metrics import psnr


def best_gain(render: torch.Tensor, reference: torch.Tensor) -> torch.Tensor:
    """Per-channel gains (3,) that match the render's channel means to the reference's, for
    images (3, H, W)."""
    return reference.mean((1, 2)) / render.mean((1, 2)).clamp_min(1e-6)


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("run_dir")
    parser.add_argument("--json", default="")
    args = parser.parse_args(argv)
    pipeline, _ = load_trained(Path(args.run_dir), device="cpu")
    scene = pipeline.scene
    references = scene.clean_images if scene.clean_images is not None else scene.images
    rows = []
    for split, indices in (("train", scene.train_indices), ("heldout", scene.eval_indices)):
        for i in indices:
            render = render_image(pipeline, i)
            reference = references[i].permute(2, 0, 1).float() / 255
            gain = best_gain(render, reference)
            corrected = (render * gain[:, None, None]).clamp(0, 1)
            rows.append({"view": scene.image_names[i], "split": split,
                         "psnr": round(float(psnr(render[None], reference[None])), 2),
                         "psnr_gain": round(float(psnr(corrected[None], reference[None])), 2),
                         "gain": [round(float(g), 3) for g in gain]})
            print(json.dumps(rows[-1]), flush=True)
    for split in ("train", "heldout"):
        part = [r for r in rows if r["split"] == split]
        if part:
            print(f"{split}: {len(part)} views, PSNR {sum(r['psnr'] for r in part) / len(part):.2f}, "
                  f"with each view's gain {sum(r['psnr_gain'] for r in part) / len(part):.2f}")
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
