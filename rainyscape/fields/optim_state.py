"""Keep Adam's per-parameter moments in step with parameters that change shape."""

from __future__ import annotations

from typing import Callable

import torch
from torch import Tensor


@torch.no_grad()
def resize_adam_state(optimizer: torch.optim.Optimizer, param: Tensor,
                      resample: Callable[[Tensor], Tensor]) -> None:
    """After ``param.data`` was resampled by ``resample``, resample its moments the same way.

    Interpolating the moments keeps the effective step size of each region (a reset would
    make the next steps tiny or huge); the step count is kept for bias correction.
    """
    state = optimizer.state.get(param)
    if not state:
        return
    for key in ("exp_avg", "exp_avg_sq", "max_exp_avg_sq"):
        if key in state:
            state[key] = resample(state[key]).contiguous()
