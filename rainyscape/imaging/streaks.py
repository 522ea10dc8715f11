"""Streak-shaped structure in an image: means along a line of a given direction.

A rain streak is thin and long. Averaged along its own direction it keeps its level; scene
detail, whose edges run every way, averages down unless it happens to run the same way.
Pure functions on tensors.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor


def line_mean(images: Tensor, angle: Tensor, half_length: int) -> Tensor:
    """The mean of (B, C, h, w) ``images`` over the 2 ``half_length`` + 1 points one pixel
    apart on the line through each pixel at ``angle`` (B,) radians (from the image +x axis
    towards +y), sampled bilinearly, the border repeated beyond the image."""
    b, _, h, w = images.shape
    ys, xs = torch.meshgrid(torch.arange(h, dtype=images.dtype, device=images.device),
                            torch.arange(w, dtype=images.dtype, device=images.device), indexing="ij")
    dx = torch.cos(angle).to(images)[:, None, None]
    dy = torch.sin(angle).to(images)[:, None, None]
    total = torch.zeros_like(images)
    for t in range(-half_length, half_length + 1):
        # pixel centre x -> (2 x + 1) / w - 1 (align_corners=False)
        gx = (2 * (xs + t * dx) + 1) / w - 1
        gy = (2 * (ys + t * dy) + 1) / h - 1
        total += F.grid_sample(images, torch.stack([gx, gy], -1), mode="bilinear",
                               padding_mode="border", align_corners=False)
    return total / (2 * half_length + 1)
