"""3DGS's photometric loss: (1 - w) L1 + w (1 - SSIM), w = 0.2.

With ``with_rain`` it compares B + R (render plus predicted rain) with the rainy input,
and ``render_l1`` adds (1 - w) L1(B, I): the loss the Gaussians get in the authors'
RainyScape-3DGS (0.8 [L1(B + R, I) + L1(B, I)] + 0.2 (1 - SSIM(B + R, I)); the method
config stops its gradient into R with ``detach = "rain"``).
"""

from __future__ import annotations

from dataclasses import dataclass

from torch import Tensor

from rainyscape.components import Loss, LossContext
from rainyscape.errors import ConfigError
from rainyscape.imaging.metrics import ssim_map
from rainyscape.losses.rain_losses import dry_weight


class L1SSIM(Loss):
    """(1 - w) L1 + w D-SSIM of the render (optionally render + rain) against the input."""

    description = "3DGS loss: 0.8 L1 + 0.2 D-SSIM vs the rainy input (optionally of B + R)"
    phases = ()  # every phase of the method
    spatial = True

    @dataclass
    class Config:
        ssim_weight: float = 0.2  # w: the D-SSIM share (3DGS's lambda_dssim)
        with_rain: bool = False  # compare B + R with I when a rain map is present
        render_l1: bool = False  # add (1 - w) L1(B, I) to the B + R terms (authors' 3DGS code)
        # 0: that L1(B, I) anchor everywhere (the authors'); s > 0: weighted exp(-(R / s)^2),
        # letting B go below I where rain is predicted (the two L1 terms cancel for
        # I - R < B < I, a dead band that keeps the rain in B)
        anchor_scale: float = 0.0
        # s > 0 (beyond the paper): every term weighted per pixel by exp(-(R / s)^2), R the
        # predicted rain (detached): where rain is predicted, the Gaussians are fitted by the
        # other views alone (rain-aware robust fitting; rain is view-inconsistent)
        rain_exclusion: float = 0.0

    def __init__(self, config: "L1SSIM.Config | None" = None):
        super().__init__(config or self.Config())
        if not 0.0 <= self.config.ssim_weight <= 1.0:
            raise ConfigError(f"l1-ssim: ssim_weight must be in [0, 1], got {self.config.ssim_weight}")

    def __call__(self, ctx: LossContext) -> Tensor:
        w = self.config.ssim_weight
        use_rain = self.config.with_rain and ctx.rain is not None
        pred = ctx.rendered + ctx.rain if use_rain else ctx.rendered
        keep = self.pixel_weights(ctx)
        l1 = _mean((pred - ctx.target).abs(), keep)
        loss = (1.0 - w) * l1
        self.metrics = {"l1": float(l1.detach())}
        if w > 0:
            s = _mean(ssim_map(pred, ctx.target, padding="same"), keep)
            loss = loss + w * (1.0 - s)
            self.metrics["ssim"] = float(s.detach())
        if use_rain and self.config.render_l1:
            anchor = (ctx.rendered - ctx.target).abs()
            if self.config.anchor_scale > 0:
                anchor = anchor * dry_weight(ctx.rain, self.config.anchor_scale)
            loss = loss + (1.0 - w) * _mean(anchor, keep)
        return loss

    def pixel_weights(self, ctx: LossContext) -> Tensor | None:
        """Per-pixel weights of every term (B, 1, h, w), or None: every pixel counts.
        With ``rain_exclusion`` they leave the predicted rain out (benchmarks/oracles puts the
        true rain's pixels here)."""
        exclusion = self.config.rain_exclusion if self.config.with_rain and ctx.rain is not None else 0.0
        return dry_weight(ctx.rain, exclusion) if exclusion > 0 else None


def _mean(values: Tensor, weights: Tensor | None) -> Tensor:
    """The mean of ``values``, each pixel weighted (weights sum to at most the pixel count, so
    left-out pixels lower the loss rather than lifting the others)."""
    return values.mean() if weights is None else (values * weights).mean()
