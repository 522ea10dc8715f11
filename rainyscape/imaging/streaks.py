"""Streak-shaped structure in an image: means and openings along a line of a given direction.

A rain streak is thin and long. Averaged along its own direction it keeps its level; scene
detail, whose edges run every way, averages down unless it happens to run the same way.
Pure functions on tensors.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from functools import reduce

import torch
import torch.nn.functional as F
from torch import Tensor

from rainyscape.imaging.colour import FLAT
from rainyscape.imaging.gradients import grayscale


def line_samples(images: Tensor, angle: Tensor, half_length: int) -> Iterator[Tensor]:
    """The (B, C, h, w) ``images`` shifted by t = -``half_length`` .. ``half_length`` pixels
    along the line at ``angle`` (B,) radians (from the image +x axis towards +y), sampled
    bilinearly, the border repeated beyond the image: one image per t."""
    b, _, h, w = images.shape
    ys, xs = torch.meshgrid(torch.arange(h, dtype=images.dtype, device=images.device),
                            torch.arange(w, dtype=images.dtype, device=images.device), indexing="ij")
    dx = torch.cos(angle).to(images)[:, None, None]
    dy = torch.sin(angle).to(images)[:, None, None]
    for t in range(-half_length, half_length + 1):
        # pixel centre x -> (2 x + 1) / w - 1 (align_corners=False)
        gx = (2 * (xs + t * dx) + 1) / w - 1
        gy = (2 * (ys + t * dy) + 1) / h - 1
        yield F.grid_sample(images, torch.stack([gx, gy], -1), mode="bilinear",
                            padding_mode="border", align_corners=False)


def line_mean(images: Tensor, angle: Tensor, half_length: int) -> Tensor:
    """The mean of (B, C, h, w) ``images`` over the 2 ``half_length`` + 1 points one pixel
    apart on the line through each pixel at ``angle`` (B,) radians."""
    return reduce(torch.add, line_samples(images, angle, half_length)) / (2 * half_length + 1)


def line_opening(images: Tensor, angle: Tensor, half_length: int) -> Tensor:
    """Morphological opening of (B, C, h, w) ``images`` by a line of 2 ``half_length`` + 1
    points at ``angle`` (B,) radians: the minimum along the line (erosion), then the maximum
    along it (dilation). What is at least that long in that direction keeps its level; dots,
    blobs and lines in other directions are removed. Never above ``images``: the bilinear
    samples of a line a little off the direction spread it onto its neighbours, which are
    cut back to their own level."""
    eroded = reduce(torch.minimum, line_samples(images, angle, half_length))
    return torch.minimum(reduce(torch.maximum, line_samples(eroded, angle, half_length)), images)


def across_opening(images: Tensor, angle: Tensor, half_length: int, directions: int = 3) -> Tensor:
    """What of (B, C, h, w) ``images`` runs at least 2 ``half_length`` + 1 pixels in some
    direction across ``angle`` (B,) radians: the largest of the :func:`line_opening` of
    ``directions`` lines spread evenly between ``angle`` and ``angle`` + pi (both excluded).
    A streak along ``angle`` and a dot shorter than the line are removed; an edge that runs
    across, and a blob wider than the line, keep their level."""
    step = math.pi / (directions + 1)
    return reduce(torch.maximum, (line_opening(images, angle + k * step, half_length)
                                  for k in range(1, directions + 1)))


def across_ridge(images: Tensor, angle: Tensor, half_width: int) -> Tensor:
    """How far each pixel of (B, C, h, w) ``images`` stands above both of its neighbours
    ``k`` pixels away across ``angle`` (B,) radians, at the best ``k`` in 1 .. ``half_width``
    (never below 0). Over a flat background, every pixel of a streak along ``angle`` up to
    ``half_width`` pixels wide stands out by the streak's level (the middle of one up to
    2 ``half_width`` - 1 wide); an edge along it (a step) has one side as bright as itself
    and does not stand out."""
    n = half_width
    samples = list(line_samples(images, angle + math.pi / 2, n))  # t = -n .. n
    best = reduce(torch.maximum, (images - torch.maximum(samples[n - k], samples[n + k])
                                  for k in range(1, n + 1)))
    return best.clamp_min(0)


EDGE_SIDES = ("either", "one")


def darker_partner(images: Tensor, angle: Tensor, half_width: int, sides: str = "either") -> Tensor:
    """How far the darkest of each pixel's neighbours up to ``half_width`` pixels away across
    ``angle`` (B,) radians lies below 0 in (B, C, h, w) ``images`` (never below 0). On a
    residual I - B it is the dark side of an edge the fit blurs, too bright next to a bright
    side fitted too dark; a streak over a background the fit has right has none.

    ``sides="one"``: how much further below 0 the darkest neighbour on one side lies than the
    darkest on the other. A blurred edge has its dark partner on one side only; a streak the
    fit holds in part, spread wider and fainter, leaves partners on both sides, and has none."""
    samples = list(line_samples(images, angle + math.pi / 2, half_width))
    if sides == "one":
        below = [(-reduce(torch.minimum, half)).clamp_min(0)
                 for half in (samples[:half_width], samples[half_width + 1:])]
        return (below[0] - below[1]).abs()
    del samples[half_width]  # the pixel itself
    return (-reduce(torch.minimum, samples)).clamp_min(0)


def edge_weights(residual: Tensor, angle: Tensor, half_width: int, share: float, sides: str = "either") -> Tensor:
    """(B, 1, h, w) weights of residual images I - B (B, C, h, w): 1 where the
    :func:`darker_partner` (on ``sides``) of their channel mean up to ``half_width`` pixels
    across ``angle`` (B,) lies less than ``share`` times the pixel's own residual below 0,
    falling to 0 at twice that: 0 on the bright side of an edge the fit blurs, 1 on a streak
    over a fitted background."""
    level = residual.mean(1, keepdim=True)
    partner = darker_partner(level, angle, half_width, sides)
    return (2.0 - partner / (share * level.clamp_min(FLAT))).clamp(0, 1)


def streak_strength(images: Tensor, angle: Tensor, tilts: Tensor, half_length: int, half_width: int) -> Tensor:
    """How far each pixel of (B, C, h, w) ``images`` (their luma) stands out as part of a bright
    streak that runs within ``tilts`` (radians, offsets tried) of ``angle`` (B,): the largest over
    the tilts of the :func:`line_opening` along it of the :func:`across_ridge` across it,
    (B, 1, h, w). A streak at least 2 ``half_length`` + 1 pixels long and up to ``half_width``
    wide scores its level over its background; a blob wider than that, an edge, a dot and a
    line that runs across score 0."""
    luma = grayscale(images)  # single-channel images unchanged
    return reduce(torch.maximum, (line_opening(across_ridge(luma, angle + t, half_width), angle + t, half_length)
                                  for t in tilts.tolist()))
