"""Occupancy grid for empty-space skipping: one bit per cell of the contracted cube [-2, 2]^3."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn


def cell_centers(resolution: int, device=None) -> Tensor:
    """Centres (r, r, r, 3) of the cells of [-2, 2]^3, indexed (x, y, z)."""
    c = (torch.arange(resolution, device=device, dtype=torch.float32) + 0.5) / resolution * 4.0 - 2.0
    return torch.stack(torch.meshgrid(c, c, c, indexing="ij"), -1)


def occupied_cells(alpha: Tensor, threshold: float, dilate: int = 1) -> Tensor:
    """Cells whose opacity, or a neighbour's within ``dilate`` cells, reaches ``threshold``.

    The dilation keeps surfaces that fall between lattice points and lets density grow into
    neighbouring cells as the field sharpens.
    """
    occ = (alpha >= threshold).float()[None, None]
    if dilate > 0:
        occ = F.max_pool3d(occ, 2 * dilate + 1, stride=1, padding=dilate)
    return occ[0, 0] > 0


class OccupancyGrid(nn.Module):
    """A boolean grid over the contracted cube; every cell occupied until the first update."""

    def __init__(self, resolution: int):
        super().__init__()
        self.register_buffer("occupied", torch.ones(resolution, resolution, resolution, dtype=torch.bool))

    @property
    def resolution(self) -> int:
        return self.occupied.shape[0]

    def lookup(self, contracted: Tensor) -> Tensor:
        """Occupancy (...) of contracted points (..., 3) in [-2, 2]."""
        r = self.resolution
        idx = ((contracted + 2.0) * (r / 4.0)).long().clamp(0, r - 1)
        flat = (idx[..., 0] * r + idx[..., 1]) * r + idx[..., 2]
        return self.occupied.reshape(-1)[flat]

    @torch.no_grad()
    def set(self, occupied: Tensor) -> None:
        self.occupied.copy_(occupied)

    def fraction(self) -> float:
        return float(self.occupied.float().mean())
