"""Plain photometric loss: the render against the (rainy) input, no rain model."""

from __future__ import annotations

from dataclasses import dataclass

import torch.nn.functional as F
from torch import Tensor

from rainyscape.components import Loss, LossContext
from rainyscape.config.schema import bounded
from rainyscape.losses.rain_losses import reconstruction_loss


class Photometric(Loss):
    """Mean squared error of the render against the input image (NeRF's loss)."""

    description = "mean squared error of the render vs the rainy input (NeRF's loss)"
    phases = ()  # every phase of the method

    @dataclass
    class Config:
        brighter: float = bounded(1.0, 0.0, 1.0)  # the weight of pixels brighter than the render

    def __init__(self, config: "Photometric.Config | None" = None):
        super().__init__(config or self.Config())

    def __call__(self, ctx: LossContext) -> Tensor:
        if self.config.brighter == 1.0:
            return F.mse_loss(ctx.rendered, ctx.target)  # nerf's loss, as it always was
        return reconstruction_loss(ctx.target - ctx.rendered, self.config.brighter)
