"""Scene contraction: unbounded space -> a cube, so one grid covers near and far content.

Inside the unit cube points stay put; outside, x -> (2 - 1/|x|) x/|x| with the max norm
(the cube-shaped variant of mip-NeRF 360's contraction, which suits axis-aligned grids).
Everything maps into [-2, 2]^3; points at infinity land on its surface.
"""

from __future__ import annotations

import torch
from torch import Tensor


def contract(x: Tensor) -> Tensor:
    norm = x.abs().amax(-1, keepdim=True).clamp_min(1e-9)
    outside = (2.0 - 1.0 / norm) * x / norm
    return torch.where(norm <= 1.0, x, outside)


def contraction_stretch(contracted: Tensor) -> Tensor:
    """How much longer a world step is than its contracted image, at contracted points (..., 3).

    1 inside the unit cube; 1 / (2 - r)^2 at max norm r > 1 (the inverse derivative of
    r_world -> 2 - 1 / r_world along a radius).
    """
    r = contracted.abs().amax(-1).clamp(max=2.0 - 1e-3)
    return torch.where(r <= 1.0, torch.ones_like(r), 1.0 / (2.0 - r) ** 2)
