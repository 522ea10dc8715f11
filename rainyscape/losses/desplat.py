"""DeSplat's loss (Wang et al., CVPR 2025): the render with the per-view distractor layer laid
over it, C = D + (1 - alpha_D) B, against the input, with DeSplat's two alpha regularisers.

    L = (1 - w) L1(C, I) + w (1 - SSIM(C, I))       w = 0.2 (3DGS's, DeSplat's)
      + lambda_static mean(1 - alpha_B)             the scene's render covers the view
      + lambda_distractor mean(alpha_D)             the distractor layer stays sparse

(lambda 0.01 each, DeSplat's ``alpha_bg_loss_lambda`` and ``alpha_2d_loss_lambda``; alpha_B
is the field's accumulated opacity). The layer comes from a head whose layer is named
``distractor`` (:class:`rainyscape.distractors.head.DistractorGaussians`).
"""

from __future__ import annotations

from dataclasses import dataclass

from torch import Tensor

from rainyscape.components import Loss, LossContext
from rainyscape.config.schema import bounded
from rainyscape.errors import ConfigError
from rainyscape.imaging.compositing import over, split_rgba
from rainyscape.imaging.metrics import ssim_map

LAYER = "distractor"


class DistractorComposite(Loss):
    """DeSplat: L1 + D-SSIM of the render under the distractor layer, plus alpha regularisers."""

    description = "DeSplat: 0.8 L1 + 0.2 D-SSIM of D + (1 - alpha_D) B vs the input, alpha regularisers"
    phases = ()  # every phase of the method
    needs = (LAYER,)

    @dataclass
    class Config:
        ssim_weight: float = bounded(0.2, 0.0, 1.0)
        static_alpha_weight: float = bounded(0.01, 0.0)  # lambda of mean(1 - alpha_B)
        distractor_alpha_weight: float = bounded(0.01, 0.0)  # lambda of mean(alpha_D)

    def __init__(self, config: "DistractorComposite.Config | None" = None):
        super().__init__(config or self.Config())
        if not 0.0 <= self.config.ssim_weight <= 1.0:
            raise ConfigError(f"desplat loss: ssim_weight must be in [0, 1], got {self.config.ssim_weight}")

    def __call__(self, ctx: LossContext) -> Tensor:
        c = self.config
        layer = ctx.layers[LAYER]
        pred = over(layer, ctx.rendered)
        l1 = (pred - ctx.target).abs().mean()
        loss = (1.0 - c.ssim_weight) * l1
        if c.ssim_weight > 0:
            loss = loss + c.ssim_weight * (1.0 - ssim_map(pred, ctx.target, padding="same").mean())
        alpha_d = split_rgba(layer)[1]
        loss = loss + c.distractor_alpha_weight * alpha_d.mean()
        acc = None if ctx.output is None else ctx.output.acc
        if acc is not None and c.static_alpha_weight > 0:
            loss = loss + c.static_alpha_weight * (1.0 - acc).mean()
        self.metrics = {"l1": float(l1.detach()), "distractor_alpha": float(alpha_d.detach().mean())}
        return loss
