"""Where a trained `desplat` run put a simulated scene's transients: in its per-view
distractor layer, or in the scene's Gaussians.

For each training view of a run on a `scenes=distractors` scene it renders the static scene
(B) and the view's distractor layer (D, alpha_D), and reports, averaged over the views:
alpha_D on the transients' pixels (where the input differs from the clean view by more
than 0.05) and elsewhere; and the static render's depth on the transients relative to the
scene's true depth there (normalised by the same ratio on the other pixels): about 1 means
the scene's Gaussians painted the transient onto the surface behind it, well below 1 that
they built a floater in front of the camera. The clean views and depths are the
simulator's, which the scene loader keeps for evaluation (``SceneData.clean_images``,
``depths``); training never saw them. With ``--strip PNG`` it also
writes, for the first three views, input | clean | B | alpha_D | D + (1 - alpha_D) B.

  python benchmarks/distractor_layer.py RUN_DIR [--strip PNG]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import torch

from rainyscape.cameras import Window
from rainyscape.workflow import load_trained

TRANSIENT = 0.05  # |input - clean| above this in some channel: a transient's pixel


def view_layers(pipe, view: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Static render B (H, W, 3), its depth (H, W), and the layer's colour D (H, W, 3) and alpha (H, W)."""
    scene = pipe.scene
    zeros = torch.zeros(1, dtype=torch.long)
    window = Window(zeros, zeros.clone(), scene.width, scene.height)
    out = pipe.field.render(scene.cameras[[view]], window)
    layer = pipe.heads["rain_head"](torch.tensor([view]), window)[0].permute(1, 2, 0)
    return out.rgb[0].permute(1, 2, 0).clamp(0, 1), out.depth[0, 0], layer[..., :3], layer[..., 3]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", type=Path)
    parser.add_argument("--strip", type=Path)
    args = parser.parse_args()
    torch.set_num_threads(1)
    pipe, step = load_trained(args.run, device="cpu")
    pipe.field.eval()
    head = pipe.heads["rain_head"].eval()
    scene = pipe.scene
    if scene.clean_images is None or scene.depths is None:
        raise SystemExit(f"{args.run}: its scene has no clean views or depths (a simulated scene is needed)")
    rows, strip = [], []
    with torch.no_grad():
        for view in head.views:
            rainy, clean = (images[view].float() / 255 for images in (scene.images, scene.clean_images))
            true_depth = scene.depths[view]
            static, depth, colour, alpha = view_layers(pipe, view)
            transient = (rainy - clean).abs().amax(-1) > TRANSIENT
            ratio = depth / true_depth.clamp_min(1e-6)
            relative = ratio[transient] / ratio[~transient].median()
            rows.append([float(transient.float().mean()), float(alpha[transient].mean()),
                         float(alpha[~transient].mean()), float(relative.median()),
                         float((relative < 0.7).float().mean()), head.counts()[view]])
            if args.strip and len(strip) < 3:
                a = alpha[..., None].expand(-1, -1, 3)
                strip.append(torch.cat([rainy, clean, static, a, (colour + (1 - a) * static).clamp(0, 1)], 1))
    mean = np.array(rows).mean(0)
    print(f"{args.run} (step {step}, {len(rows)} training views)")
    print(f"  transients' pixels: {100 * mean[0]:.1f} %; distractor Gaussians per view: {mean[5]:.0f}")
    print(f"  alpha of the distractor layer: {mean[1]:.3f} on the transients, {mean[2]:.3f} elsewhere")
    print(f"  static depth / true depth on the transients (relative to elsewhere): median {mean[3]:.3f}, "
          f"{100 * mean[4]:.1f} % of the pixels below 0.7")
    if strip:
        iio.imwrite(args.strip, (torch.cat(strip, 0).numpy() * 255).round().astype(np.uint8))
        print(f"  strip: {args.strip}")


if __name__ == "__main__":
    main()
