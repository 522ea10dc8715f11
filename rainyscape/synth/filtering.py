"""Box-filtered (prefiltered) pattern primitives for the procedural textures.

A pixel's colour is the integral of the scene's radiance over the pixel's footprint. On a
planar surface, a sub-pixel cell of the image maps to a small parallelogram in texture
space (u, v); its projections on the u and v axes are trapezoids: the sum of two uniform
(box) distributions whose widths are the parallelogram's edge lengths along that axis
(|du/dx|, |du/dy| times the cell size). Every primitive here returns the exact mean of its
pattern under that kernel along one axis, and the product of the two axes' means in 2D
(exact for an axis-aligned footprint, a close approximation for a rotated one):

- :func:`interval`: indicator of ``lo <= x < hi``;
- :func:`pulse`: periodic indicator of ``lo <= mod(x, period) < hi`` (any number of
  periods under the kernel, closed form);
- :class:`Cells`: cells of a 1D lattice under the kernel and each cell's weight (per-cell
  random values, bricks, tiles, bitmaps); mass that falls outside the evaluated cells is
  returned separately so callers give it the pattern's mean;
- :func:`noise`, :func:`fbm`: value noise (smoothstep-interpolated lattice values) filtered
  in closed form by convolving the interpolation kernel with a box of the footprint
  kernel's variance (the noise is smooth, so only the kernel's width matters); lattice
  points beyond a small window take the noise's mean.

Footprint kernels are carried by :class:`Fp` (per-sample coordinates and kernel widths).
With zero widths every primitive is a point sample of the same pattern.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

Array = np.ndarray
_TINY = 1e-12


@dataclass
class Fp:
    """Texture coordinates (metres) of M samples and their footprint kernels along u and v:
    each is the sum of two boxes of widths (au, bu) and (av, bv)."""

    u: Array
    v: Array
    au: Array
    bu: Array
    av: Array
    bv: Array

    def __len__(self) -> int:
        return len(self.u)

    def __getitem__(self, idx) -> "Fp":
        return Fp(self.u[idx], self.v[idx], self.au[idx], self.bu[idx], self.av[idx], self.bv[idx])

    def moved(self, u: Array | None = None, v: Array | None = None) -> "Fp":
        """Same kernels at other coordinates (offsets keep the footprint's size)."""
        return Fp(self.u if u is None else u, self.v if v is None else v, self.au, self.bu, self.av, self.bv)

    def swapped(self) -> "Fp":
        return Fp(self.v, self.u, self.av, self.bv, self.au, self.bu)

    def scaled(self, su: float, sv: float) -> "Fp":
        """Coordinates divided by (su, sv): lattice units of a pattern of that period."""
        return Fp(self.u / su, self.v / sv, self.au / su, self.bu / su, self.av / sv, self.bv / sv)

    @staticmethod
    def point(u: Array, v: Array) -> "Fp":
        z = np.zeros_like(u)
        return Fp(u, v, z, z, z, z)

    @property
    def ku(self) -> tuple[Array, Array]:
        return self.au, self.bu

    @property
    def kv(self) -> tuple[Array, Array]:
        return self.av, self.bv


def cdf(s: Array, a: Array, b: Array) -> Array:
    """CDF at ``s`` of U(-a/2, a/2) + U(-b/2, b/2): the kernel mass at positions below ``s``."""
    big = np.maximum(np.maximum(a, b), _TINY)
    small = np.minimum(a, b)
    h = 0.5 * (big + small)
    x = np.minimum(np.abs(s), h)  # symmetric: F(-s) = 1 - F(s)
    flat = x <= h - small  # on the flat top of the trapezoid
    upper = np.where(flat, 0.5 + x / big, 1.0 - (h - x) ** 2 / np.maximum(2.0 * big * small, 1e-300))
    return np.where(s < 0, 1.0 - upper, upper)


def interval(x: Array, lo, hi, k: tuple[Array, Array]) -> Array:
    """Kernel mass of ``lo <= x' < hi`` around ``x``."""
    return np.clip(cdf(hi - x, *k) - cdf(lo - x, *k), 0.0, 1.0)


def _support(k: tuple[Array, Array]) -> Array:
    return 0.5 * (k[0] + k[1])


def _periodic_filter(x: Array, period: float, k: tuple[Array, Array], f0, f1, f2) -> Array:
    """Mean under the kernel of a periodic function given its value ``f0`` and first and
    second antiderivatives ``f1``, ``f2`` (functions of x >= 0 on the unrolled axis)."""
    a, b = np.maximum(k[0], k[1]), np.minimum(k[0], k[1])
    support = 0.5 * (a + b)
    # shift into a positive range (the pattern is periodic): keeps the antiderivatives small
    x = np.mod(x, period) + period * (np.floor(support / period) + 1.0)
    out = f0(x)
    box = a > 1e-7 * period
    if box.any():
        xa, aa = x[box], a[box]
        out[box] = (f1(xa + aa / 2) - f1(xa - aa / 2)) / aa
        # two boxes: only where the second is not negligible (the closed form cancels badly)
        trap = box & (b > 1e-4 * a) & (a * b > 1e-8 * period * period)
        if trap.any():
            xt, at, bt = x[trap], a[trap], b[trap]
            h1, h2 = 0.5 * (at + bt), 0.5 * (at - bt)
            out[trap] = (f2(xt + h1) - f2(xt + h2) - f2(xt - h2) + f2(xt - h1)) / (at * bt)
    return out


def pulse(x: Array, period: float, lo: float, hi: float, k: tuple[Array, Array]) -> Array:
    """Kernel mass of ``lo <= mod(x, period) < hi`` (0 <= lo < hi <= period)."""
    width = hi - lo
    p = float(period)

    def f0(y):
        return (np.mod(y, p) < width).astype(np.float64)

    def f1(y):
        n = np.floor(y / p)
        return n * width + np.minimum(y - n * p, width)

    def f2(y):
        n = np.floor(y / p)
        r = y - n * p
        g = np.where(r < width, 0.5 * r * r, 0.5 * width * width + width * (r - width))
        return width * p * n * (n - 1) / 2 + n * (width * p - 0.5 * width * width) + n * width * r + g

    return np.clip(_periodic_filter(np.asarray(x, np.float64) - lo, p, k, f0, f1, f2), 0.0, 1.0)


class Cells:
    """The cells ``[i c, (i+1) c)`` of a 1D lattice under each sample's kernel.

    ``index(j)`` and ``weight(j)`` for j < ``count``: the j-th evaluated cell and its kernel
    mass; ``rest``: the mass outside the evaluated cells (give it the pattern's mean). At
    most ``max_cells`` cells are evaluated, centred on the sample when the kernel is wider.
    """

    def __init__(self, x: Array, cell: float, k: tuple[Array, Array], max_cells: int = 4, offset: Array | float = 0.0):
        self.x = np.asarray(x, np.float64) - offset
        self.cell = float(cell)
        self.k = k
        support = _support(k)
        need = np.floor((self.x + support) / cell) - np.floor((self.x - support) / cell) + 1
        self.count = int(min(max_cells, need.max(initial=1)))
        first = np.floor((self.x - support) / cell)
        centred = np.floor(self.x / cell) - (self.count - 1) // 2
        self.first = np.where(need > self.count, centred, first).astype(np.int64)
        edges = [cdf((self.first + j) * cell - self.x, *k) for j in range(self.count + 1)]
        self._w = [np.clip(edges[j + 1] - edges[j], 0.0, 1.0) for j in range(self.count)]
        self.rest = np.clip(1.0 - sum(self._w), 0.0, 1.0)

    def index(self, j: int) -> Array:
        return self.first + j

    def weight(self, j: int) -> Array:
        return self._w[j]

    def local(self, j: int) -> Array:
        """Sample position relative to the start of cell j (metres)."""
        return self.x - (self.first + j) * self.cell

    def part(self, j: int, lo: float | Array, hi: float | Array) -> Array:
        """Kernel mass of ``[lo, hi)`` measured from the start of cell j."""
        return interval(self.local(j), lo, hi, self.k)


# ---------------------------------------------------------------------------- value noise

_PRIMES = (73856093, 19349663, 83492791, 2654435761)


def hash01(*ints: Array, seed: int = 0) -> Array:
    """Deterministic pseudo-random numbers in [0, 1) from integer lattice coordinates
    (integer multiply-xor mixing in int64; wrap-around is intended)."""
    h = np.int64(seed * 2246822519 + 374761393)
    for k, x in enumerate(ints):
        h = h ^ (np.asarray(x, np.int64) * np.int64(_PRIMES[k % 4] + 2 * k))
        h = (h ^ (h >> 13)) * np.int64(1274126177)
    h = h ^ (h >> 16)
    return (h & 0xFFFFFF).astype(np.float64) * (1.0 / 0x1000000)


def _phi(t: Array) -> Array:
    """Smoothstep interpolation kernel: 1 - 3 t^2 + 2 |t|^3 on |t| < 1."""
    a = np.minimum(np.abs(t), 1.0)
    return 1.0 - a * a * (3.0 - 2.0 * a)


def _phi1(t: Array) -> Array:
    """Antiderivative of :func:`_phi` (0 below -1, 1 above 1)."""
    a = np.minimum(np.abs(t), 1.0)
    g = a * (1.0 + a * a * (0.5 * a - 1.0))  # a - a^3 + a^4 / 2
    return 0.5 + np.copysign(g, t)


def kernel_weight(t: Array, k: tuple[Array, Array]) -> Array:
    """The interpolation kernel convolved with the footprint kernel, at offset ``t``.

    The footprint kernel (two boxes) is replaced by one box of the same variance: the
    interpolation kernel is smooth, so only the kernel's width matters to within a small
    fraction of the noise's amplitude."""
    w = np.sqrt(k[0] * k[0] + k[1] * k[1])
    out = _phi(t)
    box = w > 1e-6
    if box.any():
        tb, wb = t[box], w[box]
        out[box] = (_phi1(tb + wb / 2) - _phi1(tb - wb / 2)) / wb
    return out


def _axis_weights(x: Array, k: tuple[Array, Array], count: int) -> tuple[Array, list[Array]]:
    support = _support(k)
    need_first = np.floor(x - support - 1.0) + 1
    need = np.floor(x + support + 1.0) - need_first + 1
    centred = np.floor(x) - (count - 2) // 2
    first = np.where(need > count, centred, need_first).astype(np.int64)
    return first, [kernel_weight(x - (first + j), k) for j in range(count)]


def noise(p: Fp, seed: int = 0, max_points: int = 4) -> Array:
    """Value noise with unit lattice spacing in ``p``'s coordinates, filtered by its
    footprint; in [0, 1), mean 0.5."""
    out = np.full(len(p), 0.5)
    if not len(p):
        return out
    support = np.maximum(_support(p.ku), _support(p.kv))
    # samples grouped by how many lattice points per axis their kernel reaches
    need = np.minimum(np.ceil(2 * support + 2.0 + 1e-9), max_points).astype(np.int64)
    need[support > 0.5 * max_points + 1.0] = 0  # the noise averages out: its mean
    for count in np.unique(need):
        if count == 0:
            continue
        sel = np.flatnonzero(need == count)
        q = p[sel]
        fu, wu = _axis_weights(q.u, q.ku, int(count))
        fv, wv = _axis_weights(q.v, q.kv, int(count))
        total = np.zeros(len(sel))
        mass = np.zeros(len(sel))
        for j in range(count):
            for i in range(count):
                w = wu[i] * wv[j]
                total += w * hash01(fu + i, fv + j, seed=seed)
                mass += w
        out[sel] = total + (1.0 - mass) * 0.5
    return out


def fbm(p: Fp, scale: float, octaves: int = 4, seed: int = 0, ratio: float = 2.1, gain: float = 0.55) -> Array:
    """Fractal noise in about [0, 1): ``octaves`` of filtered value noise from ``scale`` metres
    down (each octave ``ratio`` times finer and ``gain`` times weaker)."""
    total, amp, norm = np.zeros(len(p)), 1.0, 0.0
    size = float(scale)
    for k in range(octaves):
        total += amp * noise(p.scaled(size, size), seed + 101 * k)
        norm += amp
        amp *= gain
        size /= ratio
    return total / norm
