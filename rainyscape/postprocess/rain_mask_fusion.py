"""Rain-mask fusion (paper IV-C, "post-processing with predicted rain").

Where the rain head's predicted rain stands out, keep the rendered (de-rained) pixel;
elsewhere keep the input pixel (:mod:`rainyscape.postprocess.fusion`). Only possible on
training views: held-out views have no input image. ``below_input`` (the default, beyond the
paper) takes the render only where it is darker than the input; ``false`` is the paper's.
"""

from __future__ import annotations

from dataclasses import dataclass

from torch import Tensor

from rainyscape.config.schema import bounded, check_choice, choice
from rainyscape.errors import ConfigError
from rainyscape.postprocess.fusion import THRESHOLD_RULES, MaskedFusion, rain_mask, view_threshold


class RainMaskFusion(MaskedFusion):
    """Keep rendered pixels where rain is predicted and input pixels elsewhere."""

    description = "rain-mask fusion: rendered where the predicted rain stands out, input elsewhere"
    needs_rain = True

    @dataclass
    class Config:
        # rain level (grey levels in [0, 1]) that counts as rain; 0: per view, from the view's
        # predicted rain by `rule` (fusion.view_threshold): both (the higher of the next two),
        # otsu (fusion.otsu_threshold) or deviations (`sigmas` robust deviations above its
        # median, fusion.robust_threshold); measured: docs/rain.md, "The fusions' thresholds
        # from Otsu's rule and the deviations' together"
        threshold: float = bounded(0.0, 0.0, 1.0)
        rule: str = choice("both", THRESHOLD_RULES)
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
        check_choice(self.config.rule, THRESHOLD_RULES, "postprocess rule")
        self.below_input = self.config.below_input

    def mask(self, rendered: Tensor, rain: Tensor, rainy: Tensor) -> Tensor:
        c = self.config
        threshold = c.threshold if c.threshold > 0 else view_threshold(rain, c.rule, c.sigmas)
        return rain_mask(rain, threshold, c.dilation)
