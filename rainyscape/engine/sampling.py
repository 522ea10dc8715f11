"""Batch sampling: which views and which windows of them a training step sees."""

from __future__ import annotations

import torch
from torch import Tensor

from rainyscape.cameras import Window


def sample_windows(pool: Tensor, count: int, size: int, width: int, height: int,
                   generator: torch.Generator) -> tuple[Tensor, Window]:
    """``count`` random views from ``pool`` and a random ``size`` x ``size`` window in each.

    ``size`` 0 (or larger than the image) gives whole images.
    """
    pick = torch.randint(len(pool), (count,), generator=generator)
    view_ids = pool[pick]
    if size <= 0 or (size >= width and size >= height):
        zeros = torch.zeros(count, dtype=torch.long)
        return view_ids, Window(zeros, zeros.clone(), width, height)
    w, h = min(size, width), min(size, height)
    x0 = torch.randint(width - w + 1, (count,), generator=generator)
    y0 = torch.randint(height - h + 1, (count,), generator=generator)
    return view_ids, Window(x0, y0, w, h)


def gather_pixels(images: Tensor, view_ids: Tensor, window: Window) -> Tensor:
    """Cut windows out of uint8 images (N, H, W, 3) -> float (B, 3, h, w) in [0, 1]."""
    xs, ys = window.pixel_grid(images.device)
    picked = images[view_ids.to(images.device)[:, None, None], ys, xs]  # (B, h, w, 3)
    return picked.permute(0, 3, 1, 2).float() / 255.0
