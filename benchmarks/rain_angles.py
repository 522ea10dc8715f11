"""Accuracy of the rain-angle estimation on synthetic streaks over textured backgrounds.

For every setting (derivative kernel, histogram smoothing passes, bins) and every streak
angle 0, 5, ..., 175 degrees, ``--seeds`` random 64 x 64 images are made with
:mod:`rainyscape.testing.streaks`; the table gives the mean and worst error of the estimated
streak direction and the share of estimates off by more than 3 degrees, plus the share of
two-direction mixtures (30 and 110 degrees) where K = 2 finds both within 3 degrees.

    python benchmarks/rain_angles.py [--seeds 10] [--contrast 0.3]
"""

from __future__ import annotations

import argparse
import math

import torch

from rainyscape.imaging.angles import angle_difference_deg, estimate_rain_angles, streak_angle
from rainyscape.testing.streaks import streak_layer, textured_background

SETTINGS = [  # (kernel, smoothing passes, bins)
    ("sobel", 0, 60), ("sobel", 2, 60), ("scharr", 0, 60), ("scharr", 1, 60), ("scharr", 2, 60),
    ("scharr", 2, 30), ("scharr", 2, 90),
]


def single_direction_errors(kernel: str, smoothing: int, bins: int, seeds: int, contrast: float) -> torch.Tensor:
    errors = []
    for seed in range(seeds):
        for angle in range(0, 180, 5):
            g = torch.Generator().manual_seed(seed * 1000 + angle)
            image = textured_background(64, g, contrast) + streak_layer(64, angle, 25, g)
            theta, _ = estimate_rain_angles(image, bins=bins, smoothing=smoothing, kernel=kernel)
            errors.append(angle_difference_deg(math.degrees(float(streak_angle(theta)[0, 0])), angle))
    return torch.tensor(errors)


def two_direction_success(kernel: str, smoothing: int, bins: int, seeds: int, contrast: float) -> float:
    hits = 0
    for seed in range(seeds):
        g = torch.Generator().manual_seed(seed)
        image = (textured_background(64, g, contrast) + streak_layer(64, 30, 20, g)
                 + streak_layer(64, 110, 20, g))
        theta, _ = estimate_rain_angles(image, bins=bins, k=2, smoothing=smoothing, kernel=kernel)
        found = sorted(torch.rad2deg(streak_angle(theta))[0].tolist())
        hits += angle_difference_deg(found[0], 30) <= 3 and angle_difference_deg(found[1], 110) <= 3
    return hits / seeds


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seeds", type=int, default=10)
    parser.add_argument("--contrast", type=float, default=0.3, help="background texture contrast")
    args = parser.parse_args()
    torch.set_num_threads(1)
    print("| kernel | smoothing | bins | mean error (deg) | max error | > 3 deg | K=2 both found |")
    print("|---|---|---|---|---|---|---|")
    for kernel, smoothing, bins in SETTINGS:
        e = single_direction_errors(kernel, smoothing, bins, args.seeds, args.contrast)
        two = two_direction_success(kernel, smoothing, bins, 3 * args.seeds, args.contrast)
        print(f"| {kernel} | {smoothing} | {bins} | {e.mean():.2f} | {e.max():.1f} | "
              f"{(e > 3).float().mean():.1%} | {two:.0%} |")


if __name__ == "__main__":
    main()
