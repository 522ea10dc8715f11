"""Batch sampling: which views and which windows of them a training step sees."""

from __future__ import annotations

import torch
from torch import Tensor

from rainyscape.cameras import Window

# A batch of whole images holds at most this many pixels (as one 64 x 64 patch), and at least
# one image: a phase written for single rays (patches=1024, patch_size=1) set to whole images
# (patch_size=0) would otherwise ask for 1024 whole images a step (over 20 GB on a 48 px scene).
MAX_WHOLE_IMAGE_PIXELS = 64 * 64


def whole_images(size: int, width: int, height: int) -> bool:
    """Whether windows of ``size`` are whole images (``size`` 0 or at least the image)."""
    return size <= 0 or (size >= width and size >= height)


def batch_count(count: int, size: int, width: int, height: int) -> int:
    """Windows per batch: ``count``, except that a batch of whole images keeps within
    :data:`MAX_WHOLE_IMAGE_PIXELS` (one image at least)."""
    if not whole_images(size, width, height):
        return count
    return max(1, min(count, MAX_WHOLE_IMAGE_PIXELS // max(1, width * height)))


def sample_windows(pool: Tensor, count: int, size: int, width: int, height: int,
                   generator: torch.Generator) -> tuple[Tensor, Window]:
    """``count`` random views from ``pool`` and a random ``size`` x ``size`` window in each.

    ``size`` 0 (or larger than the image) gives whole images.
    """
    pick = torch.randint(len(pool), (count,), generator=generator)
    view_ids = pool[pick]
    if whole_images(size, width, height):
        zeros = torch.zeros(count, dtype=torch.long)
        return view_ids, Window(zeros, zeros.clone(), width, height)
    w, h = min(size, width), min(size, height)
    x0 = torch.randint(width - w + 1, (count,), generator=generator)
    y0 = torch.randint(height - h + 1, (count,), generator=generator)
    return view_ids, Window(x0, y0, w, h)


def gather_pixels(images: Tensor, view_ids: Tensor, window: Window) -> Tensor:
    """Cut windows out of uint8 images (N, H, W, 3) -> float (B, 3, h, w) in [0, 1]."""
    return window.table_values(images, view_ids).float() / 255.0
