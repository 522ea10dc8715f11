"""Plain photometric loss: the render against the (rainy) input, no rain model."""

from __future__ import annotations

import torch.nn.functional as F
from torch import Tensor

from rainyscape.components import Loss, LossContext


class Photometric(Loss):
    """Mean squared error of the render against the input image (NeRF's loss)."""

    description = "mean squared error of the render vs the rainy input (NeRF's loss)"
    phases = ()  # every phase of the method

    def __call__(self, ctx: LossContext) -> Tensor:
        return F.mse_loss(ctx.rendered, ctx.target)
