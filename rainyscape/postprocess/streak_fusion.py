"""Streak fusion (beyond the paper): the render where the input stands above it in streaks.

The residual I - B of a training view holds the rain the render left out and the detail it
missed. Rain streaks share one direction (the paper's rain-angle estimate, III-C, finds it
from this residual's gradient orientations); detail runs every way. A pixel goes to the
render where the residual stands out both on its own and averaged along the streak
direction (:func:`rainyscape.imaging.streaks.line_mean`), each above a threshold from the
view's own values (by default above both Otsu's level and ``sigmas`` robust deviations above
the median). It needs no rain head: any method's render can be fused, so a plain field's
fused view is the baseline a rain head's must beat.

Measured against the rain head's mask (docs/rain.md, "Streak fusion").
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from rainyscape.config.schema import bounded, check_choice, choice
from rainyscape.imaging.angles import residual_streak_angle
from rainyscape.imaging.streaks import line_mean
from rainyscape.postprocess.fusion import THRESHOLD_RULES, MaskedFusion, rain_mask, view_threshold


def streak_mask(rendered: Tensor, rainy: Tensor, sigmas: float, half_length: int, dilation: int,
                rule: str) -> Tensor:
    """(1, H, W) mask of the streaks by which ``rainy`` (3, H, W) stands above ``rendered``:
    the residual above its view's threshold (``rule``, :func:`view_threshold`), and its mean
    along the streak direction above that mean's. Empty where the residual has no gradient
    to find a direction from."""
    residual = rainy - rendered
    angle, valid = residual_streak_angle(residual[None])  # the AGR loss's histogram defaults
    if not bool(valid[0]):
        return torch.zeros_like(residual[:1], dtype=torch.bool)
    along = line_mean(residual.clamp_min(0)[None], angle, half_length)[0]
    return (rain_mask(residual, view_threshold(residual, rule, sigmas), dilation)
            & rain_mask(along, view_threshold(along, rule, sigmas), dilation))


class StreakFusion(MaskedFusion):
    """Keep rendered pixels where the input stands above the render in streaks."""

    description = "streak fusion: rendered where the input exceeds the render along the rain's direction"

    @dataclass
    class Config:
        # each view's thresholds (fusion.view_threshold): both (the higher of the next two),
        # otsu (fusion.otsu_threshold) or deviations (`sigmas` robust deviations above the
        # median, fusion.robust_threshold); measured: docs/rain.md, "The fusions' thresholds
        # from Otsu's rule and the deviations' together"
        rule: str = choice("both", THRESHOLD_RULES)
        sigmas: float = bounded(3.0, above=0.0, hi=100.0)  # of the deviations rule
        half_length: int = bounded(3, 1, 32)  # the line mean spans 2 half_length + 1 pixels
        dilation: int = bounded(1, 0, 64)  # grow the mask by this many pixels

    def __init__(self, config: "StreakFusion.Config | None" = None):
        super().__init__(config or self.Config())
        check_choice(self.config.rule, THRESHOLD_RULES, "postprocess rule")

    def mask(self, rendered: Tensor, rain: Tensor | None, rainy: Tensor) -> Tensor:
        c = self.config
        return streak_mask(rendered, rainy, c.sigmas, c.half_length, c.dilation, c.rule)
