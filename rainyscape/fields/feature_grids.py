"""Explicit feature grids over [-1, 1]^3, sampled with ``grid_sample`` and resampled to grow.

- :class:`DenseGrid`: C channels at n^3 lattice points, trilinear interpolation.
- :class:`VMGrid`: TensoRF's vector-matrix factorisation. Feature r of mode m at (x, y, z)
  is plane_m[r](a, b) * line_m[r](c) for the axis pairs (x, y | z), (x, z | y), (y, z | x):
  3 R (n^2 + n) numbers stand for R features on an n^3 lattice.

Lattices are corner-aligned (``align_corners=True``): n points span [-1, 1] on each axis.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

# (plane axis a, plane axis b, line axis c) per mode
MODES = ((0, 1, 2), (0, 2, 1), (1, 2, 0))


def resample(grid: Tensor, resolution: int) -> Tensor:
    """Resample a (1, C, *spatial) lattice to ``resolution`` along every axis that is not 1
    (a line (1, C, n, 1) stays a line)."""
    size = tuple(resolution if s > 1 else 1 for s in grid.shape[2:])
    mode = "trilinear" if grid.dim() == 5 else "bilinear"
    return F.interpolate(grid, size=size, mode=mode, align_corners=True)


class DenseGrid(nn.Module):
    """``channels`` features on an n^3 lattice, stored (1, C, z, y, x) as grid_sample reads it."""

    def __init__(self, channels: int, resolution: int, init: float = 0.0):
        super().__init__()
        n = resolution
        self.grid = nn.Parameter(torch.full((1, channels, n, n, n), float(init)))

    @property
    def resolution(self) -> int:
        return self.grid.shape[-1]

    def forward(self, x: Tensor) -> Tensor:
        """Features (P, C) at points (P, 3) in [-1, 1]."""
        out = F.grid_sample(self.grid, x.view(1, -1, 1, 1, 3), align_corners=True)
        return out.view(self.grid.shape[1], -1).T

    def factors(self) -> list[nn.Parameter]:
        return [self.grid]


class VMGrid(nn.Module):
    """``components`` features per mode at ``resolution`` lattice points per axis."""

    def __init__(self, components: int, resolution: int, init_scale: float = 0.1):
        super().__init__()
        self.planes = nn.ParameterList(
            [nn.Parameter(init_scale * torch.randn(1, components, resolution, resolution)) for _ in MODES])
        self.lines = nn.ParameterList(
            [nn.Parameter(init_scale * torch.randn(1, components, resolution, 1)) for _ in MODES])

    @property
    def resolution(self) -> int:
        return self.planes[0].shape[-1]

    def forward(self, x: Tensor) -> Tensor:
        """All features (P, 3 R) at points (P, 3) in [-1, 1]."""
        out = []
        zeros = torch.zeros_like(x[:, :1])
        for (a, b, c), plane, line in zip(MODES, self.planes, self.lines):
            # grid_sample reads (x, y) = (width index, height index).
            p = F.grid_sample(plane, x[None, :, None, [a, b]], align_corners=True)
            l_ = F.grid_sample(line, torch.cat([zeros, x[:, c:c + 1]], -1)[None, :, None],
                               align_corners=True)
            out.append((p * l_)[0, :, :, 0])
        return torch.cat(out, 0).T

    def factors(self) -> list[nn.Parameter]:
        return [*self.planes, *self.lines]
