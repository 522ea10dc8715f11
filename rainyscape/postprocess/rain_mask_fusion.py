"""Rain-mask fusion (paper IV-C, "post-processing with predicted rain").

Where the predicted rain map says there is rain, keep the rendered (de-rained) pixel;
elsewhere the rainy input is already clean, so keep the input pixel, which is sharper than
any render. Only possible on training views: held-out views have no input image.

Beyond the paper (``below_input``, the default): inside the mask a pixel takes the render
only where it is darker than the input. The paper's model is I = B + R with R >= 0, so the
clean scene is nowhere brighter than the rainy photo; where the render is, it is wrong there
(a detail it has not fitted, or rain it kept), and the input is the closer of the two.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

from rainyscape.components import FusionControl, PostProcess
from rainyscape.config.schema import bounded
from rainyscape.errors import ConfigError


def robust_threshold(rain: Tensor, sigmas: float) -> float:
    """A rain level that separates a view's streaks from its dry pixels, from the view's own
    predicted rain (3, H, W): the median of the per-pixel rain plus ``sigmas`` robust standard
    deviations (1.4826 x the median absolute deviation). Streaks are a minority of the pixels
    (2-20 % in light to heavy rain), so the median and its deviation describe the dry ones,
    whatever the head's overall level; a constant can sit above every streak (an empty mask)."""
    level = rain.amax(0).flatten()
    median = level.median()
    spread = 1.4826 * (level - median).abs().median()
    return float(median + sigmas * spread.clamp_min(1e-6))


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


class RainMaskFusion(PostProcess):
    """Keep rendered pixels where rain is predicted and input pixels elsewhere."""

    description = "rain-mask fusion: rendered where the predicted rain stands out, input elsewhere"

    @dataclass
    class Config:
        # rain level (grey levels in [0, 1]) that counts as rain; 0: per view, `sigmas` robust
        # deviations above the median of the view's predicted rain (robust_threshold)
        threshold: float = bounded(0.0, 0.0, 1.0)
        sigmas: float = bounded(3.0, above=0.0, hi=100.0)
        dilation: int = bounded(1, 0, 64)  # grow the mask by this many pixels
        # inside the mask, the render only where it is darker than the input (I = B + R,
        # R >= 0); false: the paper's fusion (measured: docs/rain.md, "Fusion below the input")
        below_input: bool = True

    def __init__(self, config: "RainMaskFusion.Config | None" = None):
        super().__init__(config or self.Config())
        if self.config.threshold < 0:
            raise ConfigError(f"postprocess threshold must be >= 0, got {self.config.threshold}")
        if self.config.dilation < 0:
            raise ConfigError(f"postprocess dilation must be >= 0, got {self.config.dilation}")

    def mask(self, rain: Tensor) -> Tensor:
        c = self.config
        threshold = c.threshold if c.threshold > 0 else robust_threshold(rain, c.sigmas)
        return rain_mask(rain, threshold, c.dilation)

    def __call__(self, rendered: Tensor, rain: Tensor, rainy: Tensor) -> Tensor:
        return fuse(rendered, rainy, self.mask(rain), self.config.below_input)

    def control(self, rendered: Tensor, rain: Tensor, rainy: Tensor, seed: int) -> FusionControl:
        """:class:`rainyscape.components.MaskFusion`: the mask's coverage, and the fusion under
        a random mask of that coverage."""
        mask = self.mask(rain)
        control = fuse(rendered, rainy, random_mask_like(mask, seed), self.config.below_input)
        return FusionControl(float(mask.float().mean()), control.clamp(0, 1))
