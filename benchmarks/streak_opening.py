"""How much of a scene's true rain survives the line opening that ``rain_head.field_streaks``
applies to the predicted rain (``imaging/streaks.py``, ``line_opening``): per scene folder,
the share of the rain layer's sum kept by the opening along the rain's own estimated
direction, for lines of 2 h + 1 pixels. Streaks shorter than the line, drops and the
second direction of two-direction rain are what it removes. The rain layers are the
simulator's (``rain/``), read for this diagnosis only.

    python benchmarks/streak_opening.py SCENE [SCENE ...] [--halves 1,2,3] [--views 8]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch

from rainyscape.dataparsers.images import read_rgb
from rainyscape.imaging.angles import residual_streak_angle
from rainyscape.imaging.streaks import line_opening


def kept_shares(rain: torch.Tensor, halves: list[int]) -> list[float]:
    """Share of ``rain`` (1, 3, H, W) kept by the opening along its own direction, per half length."""
    angle, _ = residual_streak_angle(rain)
    return [float(line_opening(rain, angle, h).sum() / rain.sum().clamp_min(1e-12)) for h in halves]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scenes", nargs="+", type=Path)
    parser.add_argument("--halves", default="1,2,3")
    parser.add_argument("--views", type=int, default=8)
    args = parser.parse_args()
    halves = [int(h) for h in args.halves.split(",")]
    print("| scene | size | " + " | ".join(f"kept, line of {2 * h + 1} px" for h in halves) + " |")
    print("|---|---|" + "---|" * len(halves))
    for scene in args.scenes:
        files = sorted((scene / "rain").iterdir())[: args.views]
        shares, size = [], ""
        for f in files:
            rain = torch.from_numpy(read_rgb(f)).float().div(255).permute(2, 0, 1)[None]
            size = f"{rain.shape[-1]} x {rain.shape[-2]}"
            shares.append(kept_shares(rain, halves))
        mean = torch.tensor(shares).mean(0).tolist()
        print(f"| {scene.name} | {size} | " + " | ".join(f"{m:.2f}" for m in mean) + " |")


if __name__ == "__main__":
    main()
