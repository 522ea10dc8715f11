"""Synthetic 2-D rain streaks over textured backgrounds, with known angles.

Image-space stand-ins for the simulator's rain, cheap enough for unit tests and for the
angle-estimation benchmark: anti-aliased line segments of one orientation, and a smooth
random texture whose edges run in every direction (the "scene detail" the orientation
histogram must see past).
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor


def textured_background(size: int, generator: torch.Generator, contrast: float = 0.3,
                        blur: float = 1.5) -> Tensor:
    """(1, 1, size, size) smooth random texture in [0.25, 0.25 + contrast]."""
    noise = torch.rand(1, 1, size, size, generator=generator)
    radius = max(1, int(math.ceil(3 * blur)))
    taps = torch.exp(-torch.arange(-radius, radius + 1.0) ** 2 / (2 * blur ** 2))
    taps = taps / taps.sum()
    kernel = (taps[:, None] * taps[None])[None, None]
    smooth = F.conv2d(F.pad(noise, (radius,) * 4, mode="reflect"), kernel)
    smooth = (smooth - smooth.min()) / (smooth.max() - smooth.min()).clamp_min(1e-12)
    return 0.25 + contrast * smooth


def streak_layer(size: int, angle_deg: float, count: int, generator: torch.Generator,
                 length: float = 14.0, width: float = 1.0, brightness: float = 0.5) -> Tensor:
    """(1, 1, size, size) additive rain of ``count`` streaks running along ``angle_deg``.

    Angles are measured from the image +x axis towards +y (downwards): 90 is vertical rain.
    Each streak is a segment of ``length`` pixels with a Gaussian cross-section of std
    ``width`` pixels; overlapping streaks take the maximum.
    """
    a = math.radians(angle_deg)
    along_dir = torch.tensor([math.cos(a), math.sin(a)])
    across_dir = torch.tensor([-math.sin(a), math.cos(a)])
    centres = torch.rand(count, 2, generator=generator) * size
    ys, xs = torch.meshgrid(torch.arange(size) + 0.5, torch.arange(size) + 0.5, indexing="ij")
    offsets = torch.stack([xs, ys], -1).reshape(-1, 1, 2) - centres[None]  # (P, count, 2)
    along, across = offsets @ along_dir, offsets @ across_dir
    ends = torch.clamp(length / 2 + 0.5 - along.abs(), 0.0, 1.0)  # soft, anti-aliased tips
    value = torch.exp(-across ** 2 / (2 * width ** 2)) * ends
    return brightness * value.amax(1).reshape(1, 1, size, size)
