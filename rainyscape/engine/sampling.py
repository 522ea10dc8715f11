"""Batch sampling: which views and which windows of them a training step sees."""

from __future__ import annotations

from dataclasses import replace

import torch
from torch import Tensor

from rainyscape.cameras import Window
from rainyscape.components import LossContext


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


def crop_batch(window: Window, ctx: LossContext, size: int, generator: torch.Generator
               ) -> tuple[Window, LossContext]:
    """A random ``size`` x ``size`` sub-window of each batch window, with the images of
    ``ctx`` (rendered, target, rain) cut to it; the window's offsets stay image-absolute."""
    w, h = min(size, window.width), min(size, window.height)
    count = len(window)
    dx = torch.randint(window.width - w + 1, (count,), generator=generator)
    dy = torch.randint(window.height - h + 1, (count,), generator=generator)
    local = Window(dx, dy, w, h)
    rain = None if ctx.rain is None else local.crop(ctx.rain)
    sub = Window(window.x0 + dx, window.y0 + dy, w, h)
    return sub, replace(ctx, rendered=local.crop(ctx.rendered), target=local.crop(ctx.target), rain=rain)
