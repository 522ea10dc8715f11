"""Keep an Adam optimiser in step with parameters that are replaced by resampled ones."""

from __future__ import annotations

from typing import Callable

import torch
from torch import Tensor, nn


@torch.no_grad()
def replace_adam_param(optimizer: torch.optim.Optimizer, old: nn.Parameter, new: nn.Parameter,
                       resample: Callable[[Tensor], Tensor]) -> None:
    """Put ``new`` where ``old`` was in ``optimizer`` and carry its moments over, resampled
    by ``resample`` (the map that made ``new`` from ``old``).

    Interpolating the moments keeps each region's effective step size (a reset would make
    the next steps tiny or huge); the step count is kept for bias correction.
    """
    for group in optimizer.param_groups:
        for i, p in enumerate(group["params"]):
            if p is old:
                group["params"][i] = new
    state = optimizer.state.pop(old, None)
    if state:
        for key in ("exp_avg", "exp_avg_sq", "max_exp_avg_sq"):
            if key in state:
                state[key] = resample(state[key]).contiguous()
        optimizer.state[new] = state
