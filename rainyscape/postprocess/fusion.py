"""Mask fusion, shared by the fusion post-processes: a mask of a training view's rain, and
the fused view that takes the render inside it and the input elsewhere (the input is exact
wherever it is dry and sharper than any render), with its random-mask control.

Inside the mask a pixel takes the render only where it is darker than the input
(``below_input``): the paper's model is I = B + R with R >= 0, so the clean scene is nowhere
brighter than the rainy photo; where the render is, it is wrong there (a detail it has not
fitted, or rain it kept), and the input is the closer of the two.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from rainyscape.components import FusionControl, PostProcess


def robust_threshold(values: Tensor, sigmas: float) -> float:
    """A level that separates a view's streaks from its dry pixels, from the view's own map
    (3, H, W) of rain-like values: the median of the per-pixel maximum over channels plus
    ``sigmas`` robust standard deviations (1.4826 x the median absolute deviation). Streaks
    are a minority of the pixels (2-20 % in light to heavy rain), so the median and its
    deviation describe the dry ones, whatever the map's overall level; a constant can sit
    above every streak (an empty mask)."""
    level = values.amax(0).flatten()
    median = level.median()
    spread = 1.4826 * (level - median).abs().median()
    return float(median + sigmas * spread.clamp_min(1e-6))


def otsu_threshold(values: Tensor, bins: int = 256) -> float:
    """The level that splits a view's map (C, H, W) of rain-like values into its two classes
    of largest between-class variance (Otsu, 1979), over the per-pixel maximum over channels
    binned on [0, its maximum]. It follows the rain's amount: faint false rain spread over a
    view (a rain head at full resolution puts some on most pixels) falls in the dry class,
    where median + deviations (:func:`robust_threshold`) sit just above the median and took
    half the view or more. It lies inside the values' range, so the mask is never empty
    unless the map is flat. Where faint rain is most of a view, Otsu splits it from the
    zeros instead (:func:`view_threshold`'s ``both``)."""
    level = values.amax(0).flatten().float().clamp_min(0.0)
    top = float(level.max())
    if top <= 0.0:
        return 0.0
    hist = torch.histc(level, bins, 0.0, top)
    centres = (torch.arange(bins, device=level.device, dtype=level.dtype) + 0.5) * (top / bins)
    p = hist / hist.sum()
    below = p.cumsum(0)  # share of pixels at or below each bin
    mean_below = (p * centres).cumsum(0)
    between = (mean_below[-1] * below - mean_below) ** 2 / (below * (1.0 - below)).clamp_min(1e-12)
    return float((int(between[:-1].argmax()) + 1) * top / bins)  # the upper edge of the lower class


THRESHOLD_RULES = ("both", "otsu", "deviations")


def view_threshold(values: Tensor, rule: str, sigmas: float) -> float:
    """A view's own threshold for ``values`` (C, H, W) under ``rule``: ``otsu``
    (:func:`otsu_threshold`), ``deviations`` (``sigmas`` robust deviations above the median,
    :func:`robust_threshold`), or ``both`` (the higher: a pixel must pass both). Each fails
    on a map the other reads right: where a head puts faint rain on most pixels and none on
    half, the median and its deviation are 0 and ``deviations`` takes every pixel with any
    rain; where the faint rain is most of the view and its own class, Otsu's split separates
    it from the zeros (the real Yard: 64 % of a view)."""
    if rule == "otsu":
        return otsu_threshold(values)
    if rule == "deviations":
        return robust_threshold(values, sigmas)
    return max(otsu_threshold(values), robust_threshold(values, sigmas))


def rain_mask(rain: Tensor, threshold: float, dilation: int) -> Tensor:
    """Binary mask (1, H, W): any channel of ``rain`` (3, H, W) above ``threshold``, grown by
    ``dilation`` pixels in every direction (a square structuring element), so the faint
    fringes of a streak go to the render as well."""
    mask = (rain.amax(0, keepdim=True) > threshold).to(rain.dtype)
    if dilation > 0:
        mask = F.max_pool2d(mask[None], 2 * dilation + 1, stride=1, padding=dilation)[0]
    return mask > 0


def fuse(rendered: Tensor, rainy: Tensor, mask: Tensor, below_input: bool = True) -> Tensor:
    """Rendered pixels inside ``mask`` (with ``below_input``, per channel the darker of the
    render and the input: rain only adds light), input pixels outside."""
    inside = torch.minimum(rendered, rainy) if below_input else rendered
    return torch.where(mask, inside, rainy)


def random_mask_like(mask: Tensor, seed: int) -> Tensor:
    """A boolean mask of ``mask``'s shape with exactly as many pixels set, placed uniformly at
    random (``torch.randperm`` with ``seed``: the same seed gives the same mask anywhere)."""
    n, k = mask.numel(), int(mask.sum())
    flat = torch.zeros(n, dtype=torch.bool)
    flat[torch.randperm(n, generator=torch.Generator().manual_seed(seed))[:k]] = True
    return flat.view(mask.shape).to(mask.device)


class MaskedFusion(PostProcess):
    """A fusion post-process: ``mask`` says where the view's rain is; the rest is shared.
    States :class:`rainyscape.components.MaskFusion` (coverage and random-mask control)."""

    below_input = True

    def mask(self, rendered: Tensor, rain: Tensor | None, rainy: Tensor) -> Tensor:
        raise NotImplementedError  # abstract

    def __call__(self, rendered: Tensor, rain: Tensor | None, rainy: Tensor) -> Tensor:
        return fuse(rendered, rainy, self.mask(rendered, rain, rainy), self.below_input)

    def control(self, rendered: Tensor, rain: Tensor | None, rainy: Tensor, seed: int) -> FusionControl:
        """The mask's coverage, and the fusion under a random mask of that coverage."""
        mask = self.mask(rendered, rain, rainy)
        control = fuse(rendered, rainy, random_mask_like(mask, seed), self.below_input)
        return FusionControl(float(mask.float().mean()), control.clamp(0, 1))
