"""The feature encodings a grid field can stand on: points of the grid cube -> a raw density
and appearance features, grown coarse-to-fine.

- ``vm``: TensoRF's vector-matrix factorisation, one for density (its components summed) and
  one for appearance (a linear basis to the features); growth resamples the lattice.
- ``planes``: K-Planes' multi-scale space planes (Hadamard product of the three planes per
  scale), one set for density (summed) and one for appearance (concatenated over scales, a
  linear basis); growth switches the finer scales on.
- ``hash``: Instant-NGP's multi-resolution hash grid and a one-hidden-layer MLP to the raw
  density and geometry features; growth switches the finer levels on.

Every encoding takes ``resolution`` (the cube root of the finest lattice, per axis in
proportion to ``aspect``) and exposes three parameter groups: density grids, appearance
grids, networks.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn

from rainyscape.fields.feature_grids import PlaneTables, VMTables, axis_sizes
from rainyscape.fields.hash_grid import HashGrid
from rainyscape.fields.optim_state import replace_adam_param


class Encoding(nn.Module):
    """Interface: ``density`` (P,) raw, ``appearance`` (P, feature_dim), ``set_resolution``."""

    feature_dim: int
    resolution: int

    def density(self, g: Tensor) -> Tensor:
        raise NotImplementedError  # abstract

    def appearance(self, g: Tensor) -> Tensor:
        raise NotImplementedError  # abstract

    def groups(self) -> tuple[list[nn.Parameter], list[nn.Parameter], list[nn.Parameter]]:
        """(density grids, appearance grids, networks)."""
        raise NotImplementedError  # abstract

    def set_resolution(self, resolution: int, optimizers: dict, names: tuple[str, str]) -> None:
        raise NotImplementedError  # abstract


class VMEncoding(Encoding):
    def __init__(self, resolution: int, aspect: Tensor, density_components: int,
                 color_components: int, feature_dim: int):
        super().__init__()
        self.aspect, self.resolution, self.feature_dim = aspect.clone(), resolution, feature_dim
        sizes = axis_sizes(resolution, aspect)
        self.density_grid = VMTables(density_components, sizes)
        self.color_grid = VMTables(color_components, sizes)
        self.basis = nn.Linear(self.color_grid.channels, feature_dim, bias=False)

    def density(self, g: Tensor) -> Tensor:
        return self.density_grid(g).sum((0, 2))

    def appearance(self, g: Tensor) -> Tensor:
        feats = self.color_grid(g)  # (3, P, C)
        return self.basis(feats.permute(1, 0, 2).reshape(g.shape[0], -1))

    def groups(self):
        return self.density_grid.factors(), self.color_grid.factors(), list(self.basis.parameters())

    @torch.no_grad()
    def set_resolution(self, resolution: int, optimizers: dict, names: tuple[str, str]) -> None:
        sizes = axis_sizes(resolution, self.aspect)
        for name, grid in zip(names, (self.density_grid, self.color_grid)):
            for old, new, fn in grid.resize(sizes):
                if name in optimizers:
                    replace_adam_param(optimizers[name], old, new, fn)
        self.resolution = resolution


class PlanesEncoding(Encoding):
    def __init__(self, resolution: int, final: int, aspect: Tensor, scales: int,
                 density_channels: int, color_channels: int, feature_dim: int):
        super().__init__()
        self.feature_dim, self.final = feature_dim, final
        sizes = axis_sizes(final, aspect)
        self.density_planes = PlaneTables(density_channels, scales, sizes)
        self.color_planes = PlaneTables(color_channels, scales, sizes)
        # a product of three planes near 0.3 each is ~0.03: scale density so it starts as a haze
        self.basis = nn.Linear(self.color_planes.channels, feature_dim, bias=False)
        self.scale_res = [final / 2 ** (scales - 1 - s) for s in range(scales)]
        self.set_resolution(resolution, {}, ("", ""))

    def _active(self) -> int:
        return max(1, sum(r <= self.resolution * 1.001 for r in self.scale_res))

    def density(self, g: Tensor) -> Tensor:
        feats = self.density_planes.scale_features(g, self._active())
        return torch.cat(feats, -1).sum(-1)

    def appearance(self, g: Tensor) -> Tensor:
        return self.basis(torch.cat(self.color_planes.scale_features(g, self._active()), -1))

    def groups(self):
        return self.density_planes.factors(), self.color_planes.factors(), list(self.basis.parameters())

    def set_resolution(self, resolution: int, optimizers: dict, names: tuple[str, str]) -> None:
        self.resolution = resolution


class HashEncoding(Encoding):
    def __init__(self, resolution: int, final: int, aspect: Tensor, levels: int, features: int,
                 log2_table: int, base: int, hidden: int, feature_dim: int):
        super().__init__()
        self.feature_dim = feature_dim
        ratio = aspect / aspect.prod() ** (1.0 / 3.0)
        self.grid = HashGrid(levels, features, log2_table, base, final, tuple(float(r) for r in ratio))
        self.mlp = nn.Sequential(nn.Linear(self.grid.channels, hidden), nn.ReLU(),
                                 nn.Linear(hidden, 1 + feature_dim))
        self.level_res = [base * math.exp((math.log(final) - math.log(base)) * lvl / max(1, levels - 1))
                          for lvl in range(levels)]
        self.set_resolution(resolution, {}, ("", ""))

    def _active(self) -> int:
        return max(1, sum(r <= self.resolution * 1.001 for r in self.level_res))

    def _out(self, g: Tensor) -> Tensor:
        return self.mlp(self.grid(g, self._active()))

    def density(self, g: Tensor) -> Tensor:
        return self._out(g)[:, 0]

    def appearance(self, g: Tensor) -> Tensor:
        return self._out(g)[:, 1:]

    def groups(self):
        return [self.grid.table], [], list(self.mlp.parameters())

    def set_resolution(self, resolution: int, optimizers: dict, names: tuple[str, str]) -> None:
        self.resolution = resolution
