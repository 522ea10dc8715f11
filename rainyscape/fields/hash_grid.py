"""Instant-NGP's multi-resolution hash encoding in plain PyTorch (no custom kernels).

Level l has a lattice of N_l = N_min * b^l points per unit axis (b so that the last level
has N_max), per axis in proportion to ``aspect``. Its T x F feature table is indexed
directly while the lattice fits in T entries and through the spatial hash
(x * 1) xor (y * 2654435761) xor (z * 805459861) mod T otherwise. A point's feature at a
level is the trilinear blend of its 8 lattice corners; the levels are concatenated. All
levels are looked up in one gather from one table holding every level's entries.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn

from rainyscape.fields.feature_grids import lookup

PRIMES = (1, 2654435761, 805459861)
CORNERS = torch.tensor([[(i >> 2) & 1, (i >> 1) & 1, i & 1] for i in range(8)])  # (8, 3) in (x, y, z)


class HashGrid(nn.Module):
    """Multi-resolution hash grid over [-1, 1]^3: (P, 3) -> (P, levels * features)."""

    def __init__(self, levels: int = 16, features: int = 2, log2_table: int = 19, base: int = 16,
                 finest: int = 2048, aspect: tuple[float, float, float] = (1.0, 1.0, 1.0)):
        super().__init__()
        self.levels, self.features = levels, features
        growth = math.exp((math.log(finest) - math.log(base)) / max(1, levels - 1))
        table = 2 ** log2_table
        res, sizes, dense = [], [], []
        for lvl in range(levels):
            n = base * growth ** lvl
            r = [max(2, int(math.ceil(n * a)) + 1) for a in aspect]  # lattice points per axis
            points = r[0] * r[1] * r[2]
            res.append(r)
            dense.append(points <= table)
            sizes.append(min(points, table))
        self.register_buffer("resolution", torch.tensor(res, dtype=torch.long), persistent=False)
        self.register_buffer("dense", torch.tensor(dense), persistent=False)
        self.register_buffer("table_size", torch.tensor(sizes, dtype=torch.long), persistent=False)
        self.register_buffer("offset", torch.cumsum(torch.tensor([0] + sizes[:-1]), 0), persistent=False)
        self.table = nn.Parameter(torch.empty(sum(sizes), features).uniform_(-1e-4, 1e-4))

    @property
    def channels(self) -> int:
        return self.levels * self.features

    def level_resolution(self) -> Tensor:
        """Lattice points along the longest axis per level (L,)."""
        return self.resolution.amax(-1)

    def forward(self, x: Tensor, active: int | None = None) -> Tensor:
        """Features (P, L * F) at points (P, 3) in [-1, 1]; levels past ``active`` are zeros."""
        levels = self.levels if active is None else max(1, min(active, self.levels))
        res = self.resolution[:levels]  # (L, 3)
        pos = (x.clamp(-1, 1)[:, None] + 1.0) * 0.5 * (res - 1)  # (P, L, 3)
        base = pos.floor().long().clamp_max(res - 2)
        frac = pos - base
        corner = base[:, :, None] + CORNERS.to(x.device)  # (P, L, 8, 3)
        dense_idx = corner[..., 0] + res[:, None, 0] * (corner[..., 1] + res[:, None, 1] * corner[..., 2])
        hashed = corner[..., 0] * PRIMES[0] ^ corner[..., 1] * PRIMES[1] ^ corner[..., 2] * PRIMES[2]
        idx = torch.where(self.dense[:levels, None], dense_idx, hashed) % self.table_size[:levels, None]
        idx = idx + self.offset[:levels, None]
        c = CORNERS.to(x.dtype).to(x.device)  # (8, 3)
        w = (frac[:, :, None] * c + (1 - frac[:, :, None]) * (1 - c)).prod(-1)  # (P, L, 8)
        feats = lookup(self.table, idx.reshape(-1, 8), w.reshape(-1, 8))  # (P L, F)
        out = feats.reshape(x.shape[0], -1)
        if levels < self.levels:
            out = torch.cat([out, out.new_zeros(x.shape[0], (self.levels - levels) * self.features)], -1)
        return out
