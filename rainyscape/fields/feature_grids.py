"""Explicit feature grids over [-1, 1]^3, sampled with ``grid_sample`` and resampled to grow.

- :class:`DenseGrid`: C channels at nx * ny * nz lattice points, trilinear interpolation.
- :class:`VMGrid`: TensoRF's vector-matrix factorisation. Feature r of mode m at (x, y, z)
  is plane_m[r](a, b) * line_m[r](c) for the axis pairs (x, y | z), (x, z | y), (y, z | x):
  R (na nb + nc) numbers per mode stand for R features on the whole lattice.

Lattices are corner-aligned (``align_corners=True``): n points span [-1, 1] on an axis.
``sizes`` are lattice points per axis in (x, y, z) order.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

# (plane axis a, plane axis b, line axis c) per mode
MODES = ((0, 1, 2), (0, 2, 1), (1, 2, 0))


def resample(lattice: Tensor, size: tuple[int, ...]) -> Tensor:
    """Interpolate a (1, C, *spatial) lattice to ``size`` (spatial, in storage order)."""
    mode = "trilinear" if lattice.dim() == 5 else "bilinear"
    return F.interpolate(lattice, size=tuple(size), mode=mode, align_corners=True)


class DenseGrid(nn.Module):
    """``channels`` features per lattice point, stored (1, C, nz, ny, nx) as grid_sample reads it."""

    def __init__(self, channels: int, sizes: tuple[int, int, int], init: float = 0.0):
        super().__init__()
        nx, ny, nz = sizes
        self.grid = nn.Parameter(torch.full((1, channels, nz, ny, nx), float(init)))

    @property
    def channels(self) -> int:
        return self.grid.shape[1]

    def forward(self, x: Tensor) -> Tensor:
        """Features (P, C) at points (P, 3) in [-1, 1]."""
        out = F.grid_sample(self.grid, x.view(1, -1, 1, 1, 3), align_corners=True)
        return out.view(self.channels, -1).T

    def factors(self) -> list[nn.Parameter]:
        return [self.grid]

    @torch.no_grad()
    def resize(self, sizes: tuple[int, int, int]) -> list[tuple[nn.Parameter, nn.Parameter]]:
        """Resample to ``sizes`` with new Parameters (autograd fixes a leaf's shape); returns
        (old, new) pairs so optimisers can follow."""
        old = self.grid
        self.grid = nn.Parameter(resample(old.detach(), sizes[::-1]))
        return [(old, self.grid)]


class VMGrid(nn.Module):
    """``components`` features per mode (3 x components in all)."""

    def __init__(self, components: int, sizes: tuple[int, int, int], init_scale: float = 0.1):
        super().__init__()
        self.planes = nn.ParameterList(
            [nn.Parameter(init_scale * torch.randn(1, components, sizes[b], sizes[a])) for a, b, _ in MODES])
        self.lines = nn.ParameterList(
            [nn.Parameter(init_scale * torch.randn(1, components, sizes[c], 1)) for _, _, c in MODES])

    @property
    def channels(self) -> int:
        return 3 * self.planes[0].shape[1]

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

    @torch.no_grad()
    def resize(self, sizes: tuple[int, int, int]) -> list[tuple[nn.Parameter, nn.Parameter]]:
        """Resample to ``sizes`` with new Parameters; returns (old, new) pairs."""
        pairs = []
        for m, (a, b, c) in enumerate(MODES):
            for factors, size in ((self.planes, (sizes[b], sizes[a])), (self.lines, (sizes[c], 1))):
                old = factors[m]
                factors[m] = nn.Parameter(resample(old.detach(), size))
                pairs.append((old, factors[m]))
        return pairs
