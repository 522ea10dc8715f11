"""Explicit feature grids over [-1, 1]^3, interpolated at points and resampled to grow.

- :class:`DenseGrid`: C channels at nx * ny * nz lattice points, trilinear interpolation.
- :class:`VMTables`: TensoRF's vector-matrix factorisation. Feature r of mode m at (x, y, z)
  is plane_m[r](a, b) * line_m[r](c) for the axis pairs (x, y | z), (x, z | y), (y, z | x):
  R (na nb + nc) numbers per mode stand for R features on the whole lattice. Row-major
  tables, looked up by the compiled kernel on a CPU (vm_cpp.py) and by ``embedding_bag``
  elsewhere.
- :class:`PlaneTables`: K-Planes' multi-scale planes, row-major.

Lattices are corner-aligned (``align_corners=True``): n points span [-1, 1] on an axis.
``sizes`` are lattice points per axis in (x, y, z) order.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from rainyscape.fields import vm_cpp

# (plane axis a, plane axis b, line axis c) per mode
MODES = ((0, 1, 2), (0, 2, 1), (1, 2, 0))


def axis_sizes(resolution: int, aspect: Tensor) -> tuple[int, int, int]:
    """Lattice points per axis: about ``resolution``^3 in all, shared in proportion to ``aspect``
    (a box's half sizes: its texels are cubes)."""
    ratio = aspect / aspect.prod() ** (1.0 / 3.0)
    return tuple(max(2, int(round(resolution * float(r)))) for r in ratio)


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

    def features(self, x: Tensor) -> Tensor:
        """Features (P, C) at points (P, 3) in [-1, 1]."""
        out = F.grid_sample(self.grid, x.view(1, -1, 1, 1, 3), align_corners=True)
        return out.view(self.channels, -1).T

    def factors(self) -> list[nn.Parameter]:
        return [self.grid]

    @torch.no_grad()
    def resize(self, sizes: tuple[int, int, int]) -> list[tuple[nn.Parameter, nn.Parameter, object]]:
        """Resample to ``sizes`` with new Parameters (autograd fixes a leaf's shape); returns
        (old, new, how to resample a tensor like old) triples so optimisers can follow."""
        old = self.grid

        def remap(t: Tensor) -> Tensor:
            return resample(t, tuple(sizes[::-1]))

        self.grid = nn.Parameter(remap(old.detach()))
        return [(old, self.grid, remap)]


# ----------------------------------------------------------------------------------------
# Row-major feature tables: each lattice point's C features are one contiguous row, and an
# interpolated lookup is one ``embedding_bag`` (a weighted sum of rows). grid_sample reads
# (C, H, W) planes one channel at a time: on a CPU, with planes of a few hundred thousand
# points, it spends its time on cache misses (measured 5-15x slower forward, docs/fields.md).


def bilinear_taps(u: Tensor, v: Tensor, width: int, height: int) -> tuple[Tensor, Tensor]:
    """Row indices (P, 4) and weights (P, 4) of the bilinear blend at (u, v) in [-1, 1]^2 of a
    width x height lattice stored row-major (row = y * width + x), corners aligned."""
    px = ((u.clamp(-1, 1) + 1.0) * 0.5 * (width - 1))
    py = ((v.clamp(-1, 1) + 1.0) * 0.5 * (height - 1))
    x0 = px.floor().clamp(0, max(0, width - 2))
    y0 = py.floor().clamp(0, max(0, height - 2))
    fx, fy = px - x0, py - y0
    i00 = y0.long() * width + x0.long()
    dx, dy = int(width > 1), width * int(height > 1)
    idx = torch.stack([i00, i00 + dx, i00 + dy, i00 + dy + dx], -1)
    w = torch.stack([(1 - fx) * (1 - fy), fx * (1 - fy), (1 - fx) * fy, fx * fy], -1)
    return idx, w


def linear_taps(u: Tensor, length: int) -> tuple[Tensor, Tensor]:
    """Row indices (P, 2) and weights (P, 2) of the linear blend at u in [-1, 1] of ``length`` points."""
    p = (u.clamp(-1, 1) + 1.0) * 0.5 * (length - 1)
    i0 = p.floor().clamp(0, max(0, length - 2))
    f = p - i0
    i0 = i0.long()
    return torch.stack([i0, i0 + int(length > 1)], -1), torch.stack([1 - f, f], -1)


class _Lookup(torch.autograd.Function):
    """Weighted row sums; the backward is one ``index_add`` (embedding_bag's own sorts the
    indices first: measured 1.2-1.7x slower here)."""

    @staticmethod
    def forward(ctx, table: Tensor, idx: Tensor, weights: Tensor) -> Tensor:
        ctx.save_for_backward(idx, weights)
        ctx.rows = table.shape[0]
        return F.embedding_bag(idx, table, per_sample_weights=weights, mode="sum")

    @staticmethod
    def backward(ctx, grad: Tensor):
        idx, weights = ctx.saved_tensors
        contrib = (grad[:, None, :] * weights[..., None]).reshape(-1, grad.shape[1])
        table_grad = grad.new_zeros(ctx.rows, grad.shape[1]).index_add_(0, idx.reshape(-1), contrib)
        return table_grad, None, None


def lookup(table: Tensor, idx: Tensor, weights: Tensor) -> Tensor:
    """sum_k weights[:, k] * table[idx[:, k]]: (P, C)."""
    weights = weights.to(table.dtype)
    if torch.is_grad_enabled() and table.requires_grad:
        return _Lookup.apply(table, idx, weights)
    return F.embedding_bag(idx, table, per_sample_weights=weights, mode="sum")


def rows_to_lattice(rows: Tensor, shape: tuple[int, ...]) -> Tensor:
    """(prod(shape), C) rows -> (1, C, *shape) for resampling."""
    return rows.T.reshape(1, rows.shape[1], *shape)


def lattice_to_rows(lattice: Tensor) -> Tensor:
    return lattice.reshape(lattice.shape[1], -1).T.contiguous()


class VMTables(nn.Module):
    """TensoRF's vector-matrix factorisation in row-major tables: the three planes in one
    (sum H W, C) table and the three lines in one (sum N, C) table, so a lookup is one pass of
    the compiled kernel on a CPU (vm_cpp.py) or two ``embedding_bag`` calls for all modes.
    ``forward`` gives (3, P, C): mode m's plane times line features; ``features`` (P, 3 C)."""

    def __init__(self, components: int, sizes: tuple[int, int, int], init_scale: float = 0.1):
        super().__init__()
        self.components = components
        self._layout(sizes)
        # Drawn per mode as (C, H, W) lattices, planes then lines: the same numbers as a
        # channel-major (grid_sample) layout of the same seed.
        planes = [init_scale * torch.randn(components, h, w) for h, w in self.plane_shapes]
        lines = [init_scale * torch.randn(components, n) for n in self.line_lengths]
        self.plane = nn.Parameter(torch.cat([p.reshape(components, -1).T for p in planes]))
        self.line = nn.Parameter(torch.cat([l_.T for l_ in lines]))

    def _layout(self, sizes: tuple[int, int, int]) -> None:
        self.sizes = tuple(int(s) for s in sizes)
        self.plane_shapes = [(self.sizes[b], self.sizes[a]) for a, b, _ in MODES]  # (height, width)
        self.line_lengths = [self.sizes[c] for _, _, c in MODES]
        self.plane_offsets = [0]
        for h, w in self.plane_shapes[:-1]:
            self.plane_offsets.append(self.plane_offsets[-1] + h * w)
        self.line_offsets = [0]
        for n in self.line_lengths[:-1]:
            self.line_offsets.append(self.line_offsets[-1] + n)
        self.plane_rows = self.plane_offsets[-1] + self.plane_shapes[-1][0] * self.plane_shapes[-1][1]
        self.line_rows = self.line_offsets[-1] + self.line_lengths[-1]

    @property
    def channels(self) -> int:
        return 3 * self.components

    def layout(self) -> tuple[int, ...]:
        """(C, h0, w0, h1, w1, h2, w2, n0, n1, n2): the compiled lookup's description of the tables."""
        return (self.components, *(n for shape in self.plane_shapes for n in shape), *self.line_lengths)

    def features(self, x: Tensor) -> Tensor:
        """All features (P, 3 C), mode-major, at points (P, 3) in [-1, 1]."""
        if vm_cpp.usable(self.plane, x):
            return vm_cpp.vm_lookup(self.plane, self.line, x, self.layout())
        return self._lookup_modes(x).transpose(0, 1).reshape(x.shape[0], -1)

    def forward(self, x: Tensor) -> Tensor:
        if vm_cpp.usable(self.plane, x):  # (P, 3 C) viewed as (3, P, C): no copy
            return self.features(x).view(x.shape[0], 3, self.components).transpose(0, 1)
        return self._lookup_modes(x)

    def _lookup_modes(self, x: Tensor) -> Tensor:
        """The ``embedding_bag`` lookup: (3, P, C)."""
        pi, pw, li, lw = [], [], [], []
        for m, (a, b, c) in enumerate(MODES):
            h, w = self.plane_shapes[m]
            idx, wt = bilinear_taps(x[:, a], x[:, b], w, h)
            pi.append(idx + self.plane_offsets[m])
            pw.append(wt)
            idx, wt = linear_taps(x[:, c], self.line_lengths[m])
            li.append(idx + self.line_offsets[m])
            lw.append(wt)
        planes = lookup(self.plane, torch.cat(pi), torch.cat(pw))
        lines = lookup(self.line, torch.cat(li), torch.cat(lw))
        return (planes * lines).view(3, x.shape[0], self.components)

    def factors(self) -> list[nn.Parameter]:
        return [self.plane, self.line]

    def _resample_rows(self, rows: Tensor, shapes_old, shapes_new, offsets) -> Tensor:
        parts, start = [], 0
        for shape_old, shape_new in zip(shapes_old, shapes_new):
            n = math.prod(shape_old)
            lat = rows_to_lattice(rows[start:start + n], shape_old)
            parts.append(lattice_to_rows(resample(lat, shape_new)))
            start += n
        return torch.cat(parts)

    @torch.no_grad()
    def resize(self, sizes: tuple[int, int, int]) -> list[tuple[nn.Parameter, nn.Parameter, object]]:
        """Resample to ``sizes``; returns (old, new, how to resample a tensor like old) triples."""
        old_planes = list(self.plane_shapes)
        old_lines = [(n, 1) for n in self.line_lengths]
        self._layout(sizes)
        new_planes = list(self.plane_shapes)
        new_lines = [(n, 1) for n in self.line_lengths]

        def plane_map(t: Tensor) -> Tensor:
            return self._resample_rows(t, old_planes, new_planes, None)

        def line_map(t: Tensor) -> Tensor:
            return self._resample_rows(t, old_lines, new_lines, None)

        pairs = []
        for name, fn in (("plane", plane_map), ("line", line_map)):
            old = getattr(self, name)
            setattr(self, name, nn.Parameter(fn(old.detach())))
            pairs.append((old, getattr(self, name), fn))
        return pairs


class PlaneTables(nn.Module):
    """K-Planes' space planes at several scales, row-major (one table per scale holding its
    three planes): feature c of scale s at (x, y, z) is the product
    plane_xy[c](x, y) * plane_xz[c](x, z) * plane_yz[c](y, z). ``sizes`` are the finest
    scale's lattice points per axis; scale s is 2^(scales - 1 - s) times coarser. Planes start
    in [0.1, 0.5] (K-Planes' start): products of three stay away from 0, so every plane gets
    gradients."""

    def __init__(self, channels: int, scales: int, sizes: tuple[int, int, int],
                 init_range: tuple[float, float] = (0.1, 0.5)):
        super().__init__()
        self.channels_per_scale, self.scales = channels, scales
        self.shapes, self.offsets = [], []
        tables = []
        for s in range(scales):
            div = 2 ** (scales - 1 - s)
            sz = tuple(max(2, round((n - 1) / div) + 1) for n in sizes)
            shapes = [(sz[b], sz[a]) for a, b, _ in MODES]
            offsets = [0, shapes[0][0] * shapes[0][1], shapes[0][0] * shapes[0][1] + shapes[1][0] * shapes[1][1]]
            rows = offsets[2] + shapes[2][0] * shapes[2][1]
            self.shapes.append(shapes)
            self.offsets.append(offsets)
            tables.append(nn.Parameter(torch.empty(rows, channels).uniform_(*init_range)))
        self.tables = nn.ParameterList(tables)

    @property
    def channels(self) -> int:
        return self.scales * self.channels_per_scale

    def scale_features(self, x: Tensor, active: int | None = None) -> list[Tensor]:
        """Per scale (P, C) products at points (P, 3); scales from ``active`` on are zeros."""
        out = []
        for s in range(self.scales):
            if active is not None and s >= active:
                out.append(x.new_zeros(x.shape[0], self.channels_per_scale))
                continue
            idx, wts = [], []
            for m, (a, b, _) in enumerate(MODES):
                h, w = self.shapes[s][m]
                i, wt = bilinear_taps(x[:, a], x[:, b], w, h)
                idx.append(i + self.offsets[s][m])
                wts.append(wt)
            f = lookup(self.tables[s], torch.cat(idx), torch.cat(wts)).view(3, x.shape[0], -1)
            out.append(f[0] * f[1] * f[2])
        return out

    def factors(self) -> list[nn.Parameter]:
        return list(self.tables)
