"""Occupancy grid for empty-space skipping: one bit per cell of the contracted cube [-2, 2]^3."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn


def cell_centers(resolution: int, device=None) -> Tensor:
    """Centres (r, r, r, 3) of the cells of [-2, 2]^3, indexed (x, y, z)."""
    c = (torch.arange(resolution, device=device, dtype=torch.float32) + 0.5) / resolution * 4.0 - 2.0
    return torch.stack(torch.meshgrid(c, c, c, indexing="ij"), -1)


def occupied_cells(alpha: Tensor, threshold: float, dilate: int = 1, strict: bool = False) -> Tensor:
    """Cells whose opacity, or a neighbour's within ``dilate`` cells, reaches ``threshold``
    (exceeds it, with ``strict``).

    The dilation keeps surfaces that fall between lattice points and lets density grow into
    neighbouring cells as the field sharpens.
    """
    occ = ((alpha > threshold) if strict else (alpha >= threshold)).float()[None, None]
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


class EmaOccupancy(nn.Module):
    """An occupancy grid over the grid cube [-1, 1]^3 kept as an EMA of opacities (nerfacc).

    Each cell holds the largest recent opacity of one marching step seen in it. An update
    evaluates ``opacity(points)`` at one random point in each chosen cell (every cell during
    the warm-up, then a random quarter of all cells and a quarter drawn from the occupied
    ones) and sets value = max(value * decay, new): a cell that empties fades out over a few
    updates instead of vanishing on one unlucky sample. After the warm-up a cell is occupied
    when its value is above min(threshold, mean value), or a neighbour's within ``dilate``
    cells is (one random point per cell misses a surface that only clips it, until the EMA has
    seen enough points); during the warm-up every cell stays occupied (a young field's
    density says little yet about where the surfaces will be).
    ``sizes`` are cells per axis (x, y, z).
    """

    def __init__(self, sizes: tuple[int, int, int]):
        super().__init__()
        self.sizes = tuple(int(s) for s in sizes)
        self.register_buffer("values", torch.zeros(self.sizes))
        self.register_buffer("occupied", torch.ones(self.sizes, dtype=torch.bool))

    @property
    def cells(self) -> int:
        return self.values.numel()

    def fraction(self) -> float:
        return float(self.occupied.float().mean())

    def _index(self, g: Tensor) -> Tensor:
        sizes = torch.tensor(self.sizes, device=g.device)
        idx = ((g + 1.0) * 0.5 * sizes).long()
        idx = torch.minimum(idx.clamp_min(0), sizes - 1)
        return (idx[..., 0] * self.sizes[1] + idx[..., 1]) * self.sizes[2] + idx[..., 2]

    def lookup(self, g: Tensor) -> Tensor:
        """Occupancy (...) of grid points (..., 3); points outside the cube are empty."""
        inside = (g.abs() <= 1.0).all(-1)
        return self.occupied.reshape(-1)[self._index(g)] & inside

    def cell_points(self, cells: Tensor, jitter: bool, generator: torch.Generator | None = None) -> Tensor:
        """A point (C, 3) in each of the flat cell indices: random inside it, or its centre."""
        nx, ny, nz = self.sizes
        ijk = torch.stack([cells // (ny * nz), (cells // nz) % ny, cells % nz], -1).float()
        off = (torch.rand(ijk.shape, device=cells.device, generator=generator) if jitter
               else torch.full_like(ijk, 0.5))
        sizes = torch.tensor(self.sizes, device=cells.device, dtype=torch.float32)
        return (ijk + off) / sizes * 2.0 - 1.0

    @torch.no_grad()
    def update(self, opacity, warmup: bool, threshold: float, decay: float,
               generator: torch.Generator | None = None, chunk: int = 1 << 18, dilate: int = 0) -> None:
        """One EMA update (see the class docstring); ``opacity(points (P, 3)) -> (P,)``."""
        n, device = self.cells, self.values.device
        if warmup:
            cells = torch.arange(n, device=device)
        else:
            uniform = torch.randint(n, (n // 4,), device=device, generator=generator)
            occ = self.occupied.reshape(-1).nonzero()[:, 0]
            pick = torch.randint(max(1, len(occ)), (n // 4,), device=device, generator=generator)
            cells = torch.cat([uniform, occ[pick]]) if len(occ) else uniform
        new = torch.cat([opacity(self.cell_points(part, True, generator)) for part in cells.split(chunk)])
        flat = self.values.reshape(-1)
        # max over duplicates drawn twice, then the EMA against the decayed old value
        best = torch.zeros_like(flat).scatter_reduce(0, cells, new.to(flat.dtype), "amax", include_self=False)
        seen = torch.zeros_like(flat, dtype=torch.bool)
        seen[cells] = True
        flat.copy_(torch.where(seen, torch.maximum(flat * decay, best), flat))
        if warmup:
            self.occupied.fill_(True)
        else:
            limit = min(threshold, float(flat.mean()))
            self.occupied.copy_(occupied_cells(self.values, limit, dilate, strict=True))
