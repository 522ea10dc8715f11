"""Procedural textures: albedo as a pure function of surface position (numpy, vectorised).

Every texture takes surface coordinates ``u`` (horizontal) and ``v`` (vertical or second
ground axis) in metres plus a per-part ``seed`` and returns (M, 3) albedo in [0, 1]. The
patterns carry detail at the 2-10 cm scale (mortar lines, grout, glyph strokes, leaf
speckle), i.e. a few pixels at the simulator's resolutions, so a de-rainer that blurs the
image loses PSNR. Hashing is integer arithmetic so textures are identical on every run.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

Array = np.ndarray


_PRIMES = (73856093, 19349663, 83492791, 2654435761)


def hash01(*ints: Array, seed: int = 0) -> Array:
    """Deterministic pseudo-random numbers in [0, 1) from integer lattice coordinates.

    Integer multiply-xor mixing in int64 (wrap-around is intended).
    """
    h = np.int64(seed * 2246822519 + 374761393)
    for k, x in enumerate(ints):
        h = h ^ (np.asarray(x, np.int64) * np.int64(_PRIMES[k % 4] + 2 * k))
        h = (h ^ (h >> 13)) * np.int64(1274126177)
    h = h ^ (h >> 16)
    return (h & 0xFFFFFF).astype(np.float64) * (1.0 / 0x1000000)


def value_noise(u: Array, v: Array, seed: int = 0) -> Array:
    """Smooth 2D value noise in [0, 1) with unit lattice spacing."""
    iu, iv = np.floor(u), np.floor(v)
    fu, fv = u - iu, v - iv
    su, sv = fu * fu * (3 - 2 * fu), fv * fv * (3 - 2 * fv)
    iu, iv = iu.astype(np.int64), iv.astype(np.int64)
    a = hash01(iu, iv, seed=seed)
    b = hash01(iu + 1, iv, seed=seed)
    c = hash01(iu, iv + 1, seed=seed)
    d = hash01(iu + 1, iv + 1, seed=seed)
    return (a * (1 - su) + b * su) * (1 - sv) + (c * (1 - su) + d * su) * sv


def fbm(u: Array, v: Array, scale: float, octaves: int = 4, seed: int = 0) -> Array:
    """Fractal noise in about [0, 1): ``octaves`` of value noise from ``scale`` metres down."""
    total, amp, norm = np.zeros_like(u), 1.0, 0.0
    freq = 1.0 / scale
    for k in range(octaves):
        total += amp * value_noise(u * freq, v * freq, seed + 101 * k)
        norm += amp
        amp *= 0.55
        freq *= 2.1
    return total / norm


def _mix(a: Array, b: Array, t: Array) -> Array:
    return a * (1 - t[:, None]) + b * t[:, None]


def _rgb(color, n: int) -> Array:
    return np.broadcast_to(np.asarray(color, np.float64), (n, 3)).copy()


def _lines(x: Array, period: float, width: float) -> Array:
    """1 on thin lines of ``width`` every ``period`` (box-filtered edges are left to the sampler)."""
    return (np.mod(x, period) < width).astype(np.float64)


def brick(u: Array, v: Array, seed: int, color=(0.55, 0.25, 0.18)) -> Array:
    """Running-bond bricks 40 x 16 cm with 3 cm light mortar and per-brick colour jitter."""
    bw, bh, mortar = 0.40, 0.16, 0.03
    row = np.floor(v / bh).astype(np.int64)
    uu = u + 0.5 * bw * (row % 2)
    col = np.floor(uu / bw).astype(np.int64)
    jitter = hash01(row, col, seed=seed)[:, None]
    base = np.asarray(color) * (0.75 + 0.5 * jitter) + 0.05 * (fbm(u, v, 0.05, 2, seed)[:, None] - 0.5)
    in_mortar = (np.mod(v, bh) < mortar) | (np.mod(uu, bw) < mortar)
    out = np.where(in_mortar[:, None], np.array([0.78, 0.76, 0.72]), base)
    return np.clip(out, 0, 1)


def plaster(u: Array, v: Array, seed: int, color=(0.80, 0.74, 0.62)) -> Array:
    """Painted render with stains and fine grain."""
    stain = fbm(u, v, 1.5, 3, seed)
    grain = value_noise(u / 0.03, v / 0.03, seed + 7)
    shade = 0.8 + 0.25 * stain + 0.12 * (grain - 0.5)
    return np.clip(np.asarray(color) * shade[:, None], 0, 1)


def glyphs(u: Array, v: Array, seed: int, cell_w: float = 0.14, cell_h: float = 0.22) -> Array:
    """Text-like marks: a 5 x 7 bitmap per character cell, 1 on strokes, 0 elsewhere."""
    cu, cv = np.floor(u / cell_w).astype(np.int64), np.floor(v / cell_h).astype(np.int64)
    fu, fv = np.mod(u, cell_w) / cell_w, np.mod(v, cell_h) / cell_h
    # 1-cell margins leave gaps between characters and lines: bitmap spans 7 x 9 of the cell.
    bx = np.floor(fu * 7).astype(np.int64) - 1
    by = np.floor(fv * 9).astype(np.int64) - 1
    inside = (bx >= 0) & (bx < 5) & (by >= 0) & (by < 7)
    char = (hash01(cu, cv, seed=seed) * 40).astype(np.int64)
    bit = hash01(char, np.clip(bx, 0, 4), np.clip(by, 0, 6), seed=seed + 3) < 0.45
    space = hash01(cu, cv, seed=seed + 11) < 0.15  # word gaps
    return (inside & bit & ~space).astype(np.float64)


def facade(u: Array, v: Array, seed: int, wall=(0.55, 0.25, 0.18), wall_kind: str = "brick",
           floor_h: float = 3.0, bay_w: float = 2.2, ground_shop: bool = True) -> Array:
    """Building wall: bricks or plaster with a grid of framed, mullioned windows and a shop sign.

    ``v`` is the height above the building's base.
    """
    n = u.shape[0]
    base = brick(u, v, seed, wall) if wall_kind == "brick" else plaster(u, v, seed, wall)
    fu, fv = np.mod(u, bay_w), np.mod(v, floor_h)
    floor = np.floor(v / floor_h).astype(np.int64)
    bay = np.floor(u / bay_w).astype(np.int64)
    wx0, wx1, wy0, wy1 = 0.45, bay_w - 0.45, 0.9, floor_h - 0.5
    frame = 0.08
    in_win = (fu > wx0) & (fu < wx1) & (fv > wy0) & (fv < wy1)
    in_glass = (fu > wx0 + frame) & (fu < wx1 - frame) & (fv > wy0 + frame) & (fv < wy1 - frame)
    mid_u, mid_v = 0.5 * (wx0 + wx1), wy0 + 0.6 * (wy1 - wy0)
    mullion = (np.abs(fu - mid_u) < 0.03) | (np.abs(fv - mid_v) < 0.03)
    lit = hash01(floor, bay, seed=seed + 5)[:, None]
    glass = np.array([0.16, 0.2, 0.26]) + 0.35 * lit * np.array([0.9, 0.8, 0.5]) * (lit > 0.7)
    glass = glass + 0.12 * (fv[:, None] / floor_h)  # sky reflection gradient
    out = np.where(in_win[:, None], np.array([0.88, 0.88, 0.84]), base)
    out = np.where((in_glass & ~mullion)[:, None], glass, out)
    sill = (fv > wy0 - 0.12) & (fv < wy0) & (fu > wx0 - 0.1) & (fu < wx1 + 0.1)
    out = np.where(sill[:, None], np.array([0.7, 0.7, 0.68]), out)
    if ground_shop:
        shop = floor == 0
        sign = np.flatnonzero(shop & (fv > 2.25) & (fv < 2.85))
        marks = glyphs(u[sign], v[sign] - 2.3, seed + 9, 0.12, 0.5) > 0
        out[sign] = np.where(marks[:, None], np.array([0.95, 0.92, 0.85]), np.array([0.12, 0.22, 0.45]))
        door = shop & (np.abs(fu - 0.5 * bay_w) < 0.5) & (fv < 2.1) & (np.mod(bay, 3) == 1)
        out = np.where(door[:, None], np.array([0.3, 0.18, 0.1]) * (0.8 + 0.4 * _lines(v, 0.3, 0.03))[:, None], out)
    return np.clip(out, 0, 1)[:n]


def roof_tiles(u: Array, v: Array, seed: int, color=(0.55, 0.2, 0.14)) -> Array:
    """Overlapping clay tiles: 25 x 18 cm rows with dark shadow lines."""
    row = np.floor(v / 0.18).astype(np.int64)
    uu = u + 0.125 * (row % 2)
    col = np.floor(uu / 0.25).astype(np.int64)
    j = hash01(row, col, seed=seed)[:, None]
    fv = np.mod(v, 0.18) / 0.18
    shade = (0.65 + 0.35 * fv)[:, None] * (0.8 + 0.35 * j)
    edge = (np.mod(uu, 0.25) < 0.02)[:, None]
    return np.clip(np.where(edge, 0.3 * np.asarray(color), np.asarray(color) * shade), 0, 1)


def paving(u: Array, v: Array, seed: int, color=(0.62, 0.6, 0.56), tile: float = 0.5) -> Array:
    """Square paving slabs with dark grout and per-slab tone."""
    iu, iv = np.floor(u / tile).astype(np.int64), np.floor(v / tile).astype(np.int64)
    j = hash01(iu, iv, seed=seed)[:, None]
    grain = fbm(u, v, 0.04, 2, seed + 1)[:, None]
    base = np.asarray(color) * (0.8 + 0.3 * j + 0.2 * (grain - 0.5))
    grout = (np.mod(u, tile) < 0.03) | (np.mod(v, tile) < 0.03)
    return np.clip(np.where(grout[:, None], np.array([0.25, 0.24, 0.22]), base), 0, 1)


def asphalt(u: Array, v: Array, seed: int, half_width: float = 3.5, axis_u: bool = True) -> Array:
    """Road surface with fine aggregate noise, a dashed centre line and solid edge lines.

    The road runs along ``u`` (``axis_u``) or ``v``; ``half_width`` in metres.
    """
    along, across = (u, v) if axis_u else (v, u)
    n = u.shape[0]
    agg = value_noise(u / 0.025, v / 0.025, seed)
    patch = fbm(u, v, 2.0, 3, seed + 3)
    out = _rgb((0.2, 0.2, 0.21), n) * (0.75 + 0.35 * agg + 0.35 * (patch - 0.5))[:, None]
    dash = (np.abs(across) < 0.08) & (np.mod(along, 3.0) < 1.6)
    edge = np.abs(np.abs(across) - (half_width - 0.3)) < 0.08
    zebra = (np.abs(along - 4.0) < 1.5) & (np.mod(across, 0.8) < 0.4)
    out = np.where((dash | edge | zebra)[:, None], np.array([0.92, 0.92, 0.88]) * (0.85 + 0.15 * agg[:, None]), out)
    return np.clip(out, 0, 1)


def grass(u: Array, v: Array, seed: int) -> Array:
    blades = value_noise(u / 0.03, v / 0.09, seed)
    patch = fbm(u, v, 1.5, 3, seed + 1)
    col = np.array([0.22, 0.38, 0.14]) * (0.6 + 0.5 * patch[:, None] + 0.4 * (blades[:, None] - 0.5))
    return np.clip(col, 0, 1)


def foliage(u: Array, v: Array, seed: int) -> Array:
    """Leaf canopy: dark gaps and bright leaves from thresholded high-frequency noise."""
    leaves = value_noise(u / 0.06, v / 0.06, seed)
    big = fbm(u, v, 0.6, 3, seed + 2)
    col = np.array([0.18, 0.36, 0.12]) * (0.5 + 0.9 * big)[:, None]
    gaps = leaves < 0.3
    bright = leaves > 0.75
    col = np.where(gaps[:, None], col * 0.35, col)
    col = np.where(bright[:, None], col * 1.5 + np.array([0.05, 0.06, 0.0]), col)
    return np.clip(col, 0, 1)


def bark(u: Array, v: Array, seed: int) -> Array:
    ridges = value_noise(u / 0.04, v / 0.4, seed)
    return np.clip(np.array([0.32, 0.22, 0.14]) * (0.6 + 0.7 * ridges)[:, None], 0, 1)


def planks(u: Array, v: Array, seed: int, color=(0.5, 0.36, 0.22), width: float = 0.2) -> Array:
    """Wooden boards along ``u`` with dark gaps and grain."""
    board = np.floor(v / width).astype(np.int64)
    j = hash01(board, seed=seed)[:, None]
    grain = value_noise(u / 0.3, v / 0.01 + board * 13.0, seed + 1)[:, None]
    col = np.asarray(color) * (0.75 + 0.3 * j) * (0.8 + 0.35 * grain)
    gap = (np.mod(v, width) < 0.02)[:, None]
    return np.clip(np.where(gap, 0.25 * np.asarray(color), col), 0, 1)


def metal(u: Array, v: Array, seed: int, color=(0.45, 0.47, 0.5)) -> Array:
    brushed = value_noise(u / 0.5, v / 0.01, seed)
    bands = _lines(v, 1.0, 0.05)
    return np.clip(np.asarray(color) * (0.85 + 0.25 * brushed - 0.3 * bands)[:, None], 0, 1)


def concrete(u: Array, v: Array, seed: int, color=(0.6, 0.6, 0.58)) -> Array:
    pores = value_noise(u / 0.02, v / 0.02, seed)
    stain = fbm(u, v, 1.0, 3, seed + 1)
    joints = (np.mod(u, 2.0) < 0.025) | (np.mod(v, 1.0) < 0.025)
    col = np.asarray(color) * (0.75 + 0.3 * stain + 0.15 * (pores - 0.5))[:, None]
    return np.clip(np.where(joints[:, None], col * 0.5, col), 0, 1)


def paint(u: Array, v: Array, seed: int, color=(0.7, 0.1, 0.1)) -> Array:
    """Car paint: flat colour with a lighter stripe, panel seams and a number plate."""
    col = _rgb(color, u.shape[0]) * (0.9 + 0.1 * value_noise(u / 0.05, v / 0.05, seed))[:, None]
    seam = (np.abs(np.mod(u, 1.1) - 0.55) < 0.015)
    stripe = np.abs(v - 0.75) < 0.04
    col = np.where(seam[:, None], col * 0.4, col)
    return np.clip(np.where(stripe[:, None], np.minimum(col * 1.6 + 0.2, 1.0), col), 0, 1)


def glass(u: Array, v: Array, seed: int) -> Array:
    refl = fbm(u, v, 0.5, 2, seed)
    return np.clip(np.array([0.12, 0.15, 0.2]) + 0.25 * refl[:, None] * np.array([0.7, 0.8, 1.0]), 0, 1)


def rubber(u: Array, v: Array, seed: int) -> Array:
    tread = _lines(u, 0.06, 0.02)
    return np.clip(_rgb((0.07, 0.07, 0.07), u.shape[0]) + 0.06 * tread[:, None], 0, 1)


def sign(u: Array, v: Array, seed: int, color=(0.1, 0.35, 0.15)) -> Array:
    """A signboard: coloured panel, white border and two lines of text-like marks."""
    marks = glyphs(u, v, seed, 0.1, 0.16) > 0
    border = _lines(v, 0.5, 0.04) + _lines(u, 1.5, 0.04) > 0
    col = np.where((marks | border)[:, None], np.array([0.95, 0.95, 0.92]), np.asarray(color))
    return np.clip(col, 0, 1)


def water(u: Array, v: Array, seed: int) -> Array:
    ripples = value_noise(u / 0.08, v / 0.3, seed)
    swell = fbm(u, v, 3.0, 3, seed + 1)
    col = np.array([0.16, 0.26, 0.3]) * (0.7 + 0.4 * swell)[:, None] + 0.12 * (ripples > 0.7)[:, None]
    return np.clip(col, 0, 1)


def ground(u: Array, v: Array, seed: int, road_half_width: float = 0.0, road_along_x: bool = True,
           sidewalk: float = 3.0, outer: str = "grass", river_half_width: float = 0.0) -> Array:
    """Ground plane (u = x, v = z): optional road with sidewalks, optional river along z at |x| <
    ``river_half_width``, and grass or paving elsewhere. Each region's texture is evaluated on
    that region's points only."""
    across = np.abs(v if road_along_x else u)
    region = np.zeros(u.shape[0], np.int8)  # 0 outer, 1 sidewalk, 2 kerb, 3 road, 4 water, 5 bank
    if road_half_width > 0:
        region[across < road_half_width + sidewalk] = 1
        region[np.abs(across - road_half_width) < 0.12] = 2
        region[across < road_half_width - 0.12] = 3
    if river_half_width > 0:
        region[np.abs(u) < river_half_width] = 4
        region[np.abs(np.abs(u) - river_half_width) < 0.4] = 5
    outer_fn = grass if outer == "grass" else (lambda a, b, s: paving(a, b, s, tile=0.6))
    painters = {
        0: outer_fn,
        1: lambda a, b, s: paving(a, b, s + 1, tile=0.4),
        2: lambda a, b, s: _rgb((0.7, 0.7, 0.68), a.shape[0]),
        3: lambda a, b, s: asphalt(a, b, s + 2, road_half_width, road_along_x),
        4: lambda a, b, s: water(a, b, s + 3),
        5: lambda a, b, s: concrete(a, b, s + 4),
    }
    out = np.empty((u.shape[0], 3))
    for code, paint_fn in painters.items():
        sel = np.flatnonzero(region == code)
        if len(sel):
            out[sel] = paint_fn(u[sel], v[sel], seed)
    return out


TEXTURES: dict[str, Callable[..., Array]] = {
    "brick": brick, "plaster": plaster, "facade": facade, "roof": roof_tiles, "paving": paving,
    "asphalt": asphalt, "grass": grass, "foliage": foliage, "bark": bark, "planks": planks,
    "metal": metal, "concrete": concrete, "paint": paint, "glass": glass, "rubber": rubber,
    "sign": sign, "water": water, "ground": ground,
}
