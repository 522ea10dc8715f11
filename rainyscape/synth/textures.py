"""Procedural textures: albedo as a pure function of surface position, box-filtered over
each sample's footprint (numpy, vectorised).

Every texture takes an :class:`~rainyscape.synth.filtering.Fp` (surface coordinates ``u``
horizontal and ``v`` vertical or the second ground axis, in metres, with the footprint
kernel of each sample) plus a per-part ``seed``, and returns (M, 3) albedo: the mean of the
pattern over the footprint. Patterns are built only from primitives that integrate over a
footprint in closed form (intervals, periodic lines, cells with per-cell random values and
grout, filtered value noise), so a texture seen from any distance gives the colour a pixel
integrates rather than an aliased point sample. With a zero footprint they are point
samples of the same pattern.

The patterns carry detail at the 2-10 cm scale (mortar lines, grout, glyph strokes, leaf
cells), so a de-rainer that blurs the image loses PSNR. Hashing is integer arithmetic, so
textures are identical on every run.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from rainyscape.synth.filtering import Cells, Fp, fbm, hash01, interval, noise, pulse

Array = np.ndarray

MORTAR = np.array([0.78, 0.76, 0.72])
WHITE_PAINT = np.array([0.92, 0.92, 0.88])


def _rgb(color) -> Array:
    return np.asarray(color, np.float64)


def grout_fraction(cw: float, ch: float, gu: float, gv: float) -> float:
    return gu / cw + gv / ch - gu * gv / (cw * ch)


def cell_mean(p: Fp, cw: float, ch: float, value: Callable[[Array, Array], Array], mean,
              row_shift: Callable[[Array], Array] | None = None, gu: float = 0.0, gv: float = 0.0,
              max_cells: int = 4) -> tuple[Array, Array]:
    """A grid of cells ``cw`` x ``ch`` (rows along v; row r shifted along u by
    ``row_shift(r)``), each with a grout strip ``gu`` wide at its start along u and ``gv``
    along v. Returns, per sample, the footprint integral of ``value(rows, cols)`` (an (m, C)
    array) over the cells' interiors, and the interior mass (1 minus the grout's share).
    Mass beyond the evaluated cells counts as interior with value ``mean`` in proportion
    to the pattern's interior fraction."""
    mean = np.atleast_1d(np.asarray(mean, np.float64))
    out = np.zeros((len(p), mean.shape[-1]))
    inner_mass = np.zeros(len(p))
    covered = np.zeros(len(p))
    rows = Cells(p.v, ch, p.kv, max_cells)
    for j in range(rows.count):
        live_r = np.flatnonzero(rows.weight(j) > 1e-12)
        if not len(live_r):
            continue
        q = p[live_r]
        r = rows.index(j)[live_r]
        w_r = rows.weight(j)[live_r]
        s_v = interval(rows.local(j)[live_r], 0.0, gv, q.kv) if gv > 0 else 0.0
        shift = row_shift(r) if row_shift is not None else 0.0
        cols = Cells(q.u, cw, q.ku, max_cells, offset=shift)
        for i in range(cols.count):
            w = w_r * cols.weight(i)
            live = np.flatnonzero(w > 1e-12)
            if not len(live):
                continue
            s_u = cols.part(i, 0.0, gu)[live] if gu > 0 else 0.0
            s_vl = s_v[live] if gv > 0 else 0.0
            inner = (w_r[live] - s_vl) * (cols.weight(i)[live] - s_u)
            idx = live_r[live]
            out[idx] += inner[:, None] * value(r[live], cols.index(i)[live])
            inner_mass[idx] += inner
            covered[idx] += w[live]
    rest = np.clip(1.0 - covered, 0.0, 1.0) * (1.0 - grout_fraction(cw, ch, gu, gv))
    return out + rest[:, None] * mean, np.clip(inner_mass + rest, 0.0, 1.0)


def _tone(seed: int, lo: float, span: float) -> Callable[[Array, Array], Array]:
    """Per-cell brightness factor ``lo + span * hash`` (a cell_mean value function)."""
    return lambda r, c: (lo + span * hash01(r, c, seed=seed))[:, None]


def _stagger(width: float) -> Callable[[Array], Array]:
    return lambda r: 0.5 * width * (r % 2)


def brick(p: Fp, seed: int, color=(0.55, 0.25, 0.18)) -> Array:
    """Running-bond bricks 40 x 16 cm with 3 cm light mortar, per-brick colour jitter and grain."""
    bw, bh, mortar = 0.40, 0.16, 0.03
    tone, inner = cell_mean(p, bw, bh, _tone(seed, 0.75, 0.5), 1.0, _stagger(bw), mortar, mortar)
    grain = 0.05 * (fbm(p, 0.05, 2, seed) - 0.5)
    out = _rgb(color) * tone + MORTAR * (1.0 - inner)[:, None] + (grain * inner)[:, None]
    return np.clip(out, 0, 1)


def plaster(p: Fp, seed: int, color=(0.80, 0.74, 0.62)) -> Array:
    """Painted render with stains and fine grain."""
    stain = fbm(p, 1.5, 3, seed)
    grain = noise(p.scaled(0.03, 0.03), seed + 7)
    shade = 0.8 + 0.25 * stain + 0.12 * (grain - 0.5)
    return np.clip(_rgb(color) * shade[:, None], 0, 1)


GLYPH_MEAN = 35 / 63 * 0.45 * 0.85  # inked fraction of a text block (bitmap, bits, spaces)


def glyphs(p: Fp, seed: int, cell_w: float = 0.14, cell_h: float = 0.22) -> Array:
    """Text-like marks: a 5 x 7 bitmap per character cell (with a 1-cell margin: 7 x 9 bits
    per cell); returns the inked fraction of each footprint."""
    bw, bh = cell_w / 7, cell_h / 9

    def bits(r: Array, c: Array) -> Array:
        cu, cv = np.floor_divide(c, 7), np.floor_divide(r, 9)
        bx, by = np.mod(c, 7) - 1, np.mod(r, 9) - 1
        inside = (bx >= 0) & (bx < 5) & (by >= 0) & (by < 7)
        char = (hash01(cu, cv, seed=seed) * 40).astype(np.int64)
        bit = hash01(char, np.clip(bx, 0, 4), np.clip(by, 0, 6), seed=seed + 3) < 0.45
        space = hash01(cu, cv, seed=seed + 11) < 0.15  # word gaps
        return (inside & bit & ~space).astype(np.float64)[:, None]

    ink, _ = cell_mean(p, bw, bh, bits, GLYPH_MEAN)
    return ink[:, 0]


def facade(p: Fp, seed: int, wall=(0.55, 0.25, 0.18), wall_kind: str = "brick", floor_h: float = 3.0,
           bay_w: float = 2.2, ground_shop: bool = True) -> Array:
    """Building wall: bricks or plaster with a grid of framed, mullioned windows with sills,
    and on the ground floor (``ground_shop``) a shop sign with lettering and doors.
    ``v`` is the height above the building's base; each (floor, bay) cell is integrated
    over the footprint region by region."""
    base = brick(p, seed, wall) if wall_kind == "brick" else plaster(p, seed, wall)
    frame_rgb, sill_rgb = np.array([0.88, 0.88, 0.84]), np.array([0.7, 0.7, 0.68])
    door_rgb, sign_rgb = np.array([0.3, 0.18, 0.1]), np.array([0.12, 0.22, 0.45])
    wx0, wx1, frame, mull = 0.45, bay_w - 0.45, 0.08, 0.03
    mid_u = 0.5 * (wx0 + wx1)
    out = np.zeros((len(p), 3))
    covered = np.zeros(len(p))
    rows = Cells(p.v, floor_h, p.kv, 3)
    cols = Cells(p.u, bay_w, p.ku, 3)
    marks = np.zeros(len(p))
    door_lines = np.zeros(len(p))
    if ground_shop:  # lettering and door planks only where a footprint reaches them
        on_sign = np.flatnonzero(interval(p.v, 2.25, 2.85, p.kv) > 0)
        marks[on_sign] = glyphs(p[on_sign].moved(v=p.v[on_sign] - 2.3), seed + 9, 0.12, 0.5)
        on_door = np.flatnonzero(interval(p.v, 0.0, 2.1, p.kv) > 0)
        door_lines[on_door] = pulse(p.v[on_door], 0.3, 0.0, 0.03, (p.av[on_door], p.bv[on_door]))
    for j in range(rows.count):
        w_r = rows.weight(j)
        for i in range(cols.count):
            w_all = w_r * cols.weight(i)
            live = np.flatnonzero(w_all > 1e-12)
            if not len(live):
                continue
            w = w_all[live]
            floor, bay = rows.index(j)[live], cols.index(i)[live]
            lv, lu = rows.local(j)[live], cols.local(i)[live]
            kv, ku = (p.av[live], p.bv[live]), (p.au[live], p.bu[live])

            def part_v(lo, hi):
                return interval(lv, lo, hi, kv)

            def part_u(lo, hi):
                return interval(lu, lo, hi, ku)

            shop = (floor == 0) & ground_shop
            wy0 = 0.9
            wy1 = np.where(shop, 2.15, floor_h - 0.5)
            mid_v = wy0 + 0.6 * (wy1 - wy0)
            is_door = shop & (np.mod(bay, 3) == 1)
            no_win = np.where(is_door, 0.0, 1.0)
            win = no_win * part_u(wx0, wx1) * part_v(wy0, wy1)
            m_glass = (no_win * (part_u(wx0 + frame, mid_u - mull) + part_u(mid_u + mull, wx1 - frame))
                       * (part_v(wy0 + frame, mid_v - mull) + part_v(mid_v + mull, wy1 - frame)))
            m_frame = win - m_glass
            m_sill = no_win * part_u(wx0 - 0.1, wx1 + 0.1) * part_v(wy0 - 0.12, wy0)
            w_c = cols.weight(i)[live]
            m_sign = np.where(shop, w_c * part_v(2.25, 2.85), 0.0)
            m_door = np.where(is_door, part_u(0.5 * bay_w - 0.5, 0.5 * bay_w + 0.5) * part_v(0.0, 2.1), 0.0)
            m_wall = w - m_glass - m_frame - m_sill - m_sign - m_door
            lit = hash01(floor, bay, seed=seed + 5)[:, None]
            glass = np.array([0.18, 0.22, 0.28]) + 0.35 * lit * np.array([0.9, 0.8, 0.5]) * (lit > 0.7)
            acc = (m_glass[:, None] * glass + m_frame[:, None] * frame_rgb + m_sill[:, None] * sill_rgb
                   + m_wall[:, None] * base[live])
            if ground_shop:
                acc += m_sign[:, None] * (sign_rgb + marks[live, None] * (np.array([0.95, 0.92, 0.85]) - sign_rgb))
                acc += m_door[:, None] * door_rgb * (0.8 + 0.4 * door_lines[live])[:, None]
            out[live] += acc
            covered[live] += w
    rest = np.clip(1.0 - covered, 0.0, 1.0)
    win_frac = (wx1 - wx0) * (floor_h - 1.4) / (bay_w * floor_h)
    mean = base * (1 - win_frac) + win_frac * np.array([0.45, 0.47, 0.5])
    return np.clip(out + rest[:, None] * mean, 0, 1)


def roof_tiles(p: Fp, seed: int, color=(0.55, 0.2, 0.14)) -> Array:
    """Overlapping clay tiles: 25 x 18 cm staggered rows, dark gaps between tiles and a
    shadow band under each row's overlap."""
    col = _rgb(color)
    tone, inner = cell_mean(p, 0.25, 0.18, _tone(seed, 0.8, 0.35), 0.975, _stagger(0.25), 0.02, 0.04)
    grain = 0.06 * (fbm(p, 0.08, 2, seed + 1) - 0.5)
    return np.clip(col * tone + 0.35 * col * (1.0 - inner)[:, None] + (grain * inner)[:, None], 0, 1)


def paving(p: Fp, seed: int, color=(0.62, 0.6, 0.56), tile: float = 0.5) -> Array:
    """Square paving slabs with dark grout, per-slab tone and grain."""
    tone, inner = cell_mean(p, tile, tile, _tone(seed, 0.8, 0.3), 0.95, None, 0.03, 0.03)
    grain = 0.2 * (fbm(p, 0.04, 2, seed + 1) - 0.5)
    out = _rgb(color) * (tone + (grain * inner)[:, None]) + np.array([0.25, 0.24, 0.22]) * (1.0 - inner)[:, None]
    return np.clip(out, 0, 1)


def asphalt(p: Fp, seed: int, half_width: float = 3.5, axis_u: bool = True, markings: bool = True,
            dash_phase: float = 0.0, no_dash: tuple[int, int] = (1, 1),
            zebras: tuple[tuple[float, float], ...] = ((2.5, 5.5),)) -> Array:
    """Road surface with fine aggregate noise, a dashed centre line (dash k covers
    [3k + ``dash_phase``, +1.6) m along the road; dashes ``no_dash[0]`` .. ``no_dash[1]`` are
    left out), solid edge lines and zebra crossings over the ``zebras`` ranges along the road.
    The road runs along ``u`` (``axis_u``) or ``v``; ``half_width`` in metres. Dashes left
    out must cover the zebras, so the markings never overlap."""
    q = p if axis_u else p.swapped()
    along, across, k_along, k_across = q.u, q.v, q.ku, q.kv
    agg = noise(p.scaled(0.025, 0.025), seed)
    patch = fbm(p, 2.0, 3, seed + 3)
    out = np.array([0.2, 0.2, 0.21]) * (0.75 + 0.35 * agg + 0.35 * (patch - 0.5))[:, None]
    if not markings:
        return np.clip(out, 0, 1)
    # centre dashes, edge lines and zebra stripes: disjoint regions
    dashes = pulse(along, 3.0, dash_phase, dash_phase + 1.6, k_along)
    for k in range(no_dash[0], no_dash[1] + 1):
        dashes = dashes - interval(along, 3.0 * k + dash_phase, 3.0 * k + dash_phase + 1.6, k_along)
    dash = interval(across, -0.08, 0.08, k_across) * np.clip(dashes, 0.0, 1.0)
    e = half_width - 0.3
    edge = interval(across, e - 0.08, e + 0.08, k_across) + interval(across, -e - 0.08, -e + 0.08, k_across)
    stripes = sum(interval(across, 0.8 * s, 0.8 * s + 0.4, k_across) for s in range(-3, 4))  # |across| < 2.8
    zebra = sum(interval(along, lo, hi, k_along) for lo, hi in zebras) * stripes
    marks = np.clip(dash + edge + zebra, 0.0, 1.0)
    paint = WHITE_PAINT * (0.85 + 0.15 * agg)[:, None]
    return np.clip(out * (1.0 - marks)[:, None] + paint * marks[:, None], 0, 1)


def grass(p: Fp, seed: int) -> Array:
    blades = noise(p.scaled(0.03, 0.09), seed)
    patch = fbm(p, 1.5, 3, seed + 1)
    col = np.array([0.22, 0.38, 0.14]) * (0.6 + 0.5 * patch[:, None] + 0.4 * (blades[:, None] - 0.5))
    return np.clip(col, 0, 1)


def foliage(p: Fp, seed: int) -> Array:
    """Leaf canopy: staggered 6 cm leaf cells, each a dark gap, a leaf or a bright leaf, over
    large-scale light and shade."""
    big = fbm(p, 0.6, 3, seed + 2)
    col = np.array([0.18, 0.36, 0.12]) * (0.5 + 0.9 * big)[:, None]

    def leaf(r: Array, c: Array) -> Array:
        h = hash01(r, c, seed=seed)
        factor = np.where(h < 0.3, 0.35, np.where(h > 0.75, 1.5, 1.0))
        return np.stack([factor, (h > 0.75).astype(np.float64)], 1)

    mean = [0.3 * 0.35 + 0.45 * 1.0 + 0.25 * 1.5, 0.25]
    cells, _ = cell_mean(p, 0.06, 0.06, leaf, mean, lambda r: 0.03 * np.mod(r * 7, 5) / 2.0)
    return np.clip(col * cells[:, :1] + np.array([0.05, 0.06, 0.0]) * cells[:, 1:], 0, 1)


def bark(p: Fp, seed: int) -> Array:
    ridges = noise(p.scaled(0.04, 0.4), seed)
    return np.clip(np.array([0.32, 0.22, 0.14]) * (0.6 + 0.7 * ridges)[:, None], 0, 1)


def planks(p: Fp, seed: int, color=(0.5, 0.36, 0.22), width: float = 0.2) -> Array:
    """Wooden boards along ``u`` with dark gaps, per-board tone and grain."""
    col = _rgb(color)
    boards = Cells(p.v, width, p.kv, 4)
    tone = np.zeros(len(p))
    inner = np.zeros(len(p))
    for j in range(boards.count):
        w = boards.weight(j)
        gap = boards.part(j, 0.0, 0.02)
        tone += (w - gap) * (0.75 + 0.3 * hash01(boards.index(j), seed=seed))
        inner += w - gap
    rest = boards.rest * (1 - 0.02 / width)
    tone += rest * 0.9
    inner += rest
    grain = noise(p.scaled(0.3, 0.015), seed + 1)
    out = col * (tone * (0.8 + 0.35 * grain))[:, None] + 0.25 * col * (1.0 - inner)[:, None]
    return np.clip(out, 0, 1)


def metal(p: Fp, seed: int, color=(0.45, 0.47, 0.5)) -> Array:
    brushed = noise(p.scaled(0.5, 0.01), seed)
    bands = pulse(p.v, 1.0, 0.0, 0.05, p.kv)
    return np.clip(_rgb(color) * (0.85 + 0.25 * brushed - 0.3 * bands)[:, None], 0, 1)


def concrete(p: Fp, seed: int, color=(0.6, 0.6, 0.58)) -> Array:
    pores = noise(p.scaled(0.02, 0.02), seed)
    stain = fbm(p, 1.0, 3, seed + 1)
    ju, jv = pulse(p.u, 2.0, 0.0, 0.025, p.ku), pulse(p.v, 1.0, 0.0, 0.025, p.kv)
    joints = ju + jv - ju * jv
    col = _rgb(color) * (0.75 + 0.3 * stain + 0.15 * (pores - 0.5))[:, None]
    return np.clip(col * (1.0 - 0.5 * joints)[:, None], 0, 1)


def paint(p: Fp, seed: int, color=(0.7, 0.1, 0.1)) -> Array:
    """Car paint: flat colour with a lighter stripe and panel seams."""
    base = _rgb(color)
    col = base * (0.9 + 0.1 * noise(p.scaled(0.05, 0.05), seed))[:, None]
    seam = pulse(p.u, 1.1, 0.535, 0.565, p.ku)
    stripe = interval(p.v, 0.71, 0.79, p.kv)
    col = col * (1.0 - 0.6 * seam)[:, None]
    light = np.minimum(base * 1.6 + 0.2, 1.0)
    return np.clip(col * (1.0 - stripe)[:, None] + light * stripe[:, None], 0, 1)


def glass(p: Fp, seed: int) -> Array:
    refl = fbm(p, 0.5, 2, seed)
    return np.clip(np.array([0.12, 0.15, 0.2]) + 0.25 * refl[:, None] * np.array([0.7, 0.8, 1.0]), 0, 1)


def rubber(p: Fp, seed: int) -> Array:
    tread = pulse(p.u, 0.06, 0.0, 0.02, p.ku)
    return np.clip(np.array([0.07, 0.07, 0.07]) + 0.06 * tread[:, None], 0, 1)


def sign(p: Fp, seed: int, color=(0.1, 0.35, 0.15)) -> Array:
    """A signboard: coloured panel, white border lines and text-like marks."""
    marks = glyphs(p, seed, 0.1, 0.16)
    bv, bu = pulse(p.v, 0.5, 0.0, 0.04, p.kv), pulse(p.u, 1.5, 0.0, 0.04, p.ku)
    border = bu + bv - bu * bv
    white = border + (1.0 - border) * marks
    return np.clip(_rgb(color) * (1.0 - white)[:, None] + np.array([0.95, 0.95, 0.92]) * white[:, None], 0, 1)


def water(p: Fp, seed: int) -> Array:
    """Water: large swell and bright ripple glints (8 x 30 cm cells, a quarter of them lit)."""
    swell = fbm(p, 3.0, 3, seed + 1)
    glint, _ = cell_mean(p, 0.08, 0.3, lambda r, c: (hash01(r, c, seed=seed) > 0.75).astype(np.float64)[:, None],
                         0.25, lambda r: 0.04 * np.mod(r, 2))
    col = np.array([0.16, 0.26, 0.3]) * (0.7 + 0.4 * swell)[:, None] + 0.12 * glint
    return np.clip(col, 0, 1)


def ground(p: Fp, seed: int, road_half_width: float = 0.0, road_along_x: bool = True, sidewalk: float = 3.0,
           outer: str = "grass", river_half_width: float = 0.0, cross: bool = False) -> Array:
    """Ground plane (u = x, v = z): optional road with kerbs and sidewalks (``cross``: a second
    road along z crossing it at the origin), optional river along z at |x| <
    ``river_half_width`` with concrete banks, grass or paving elsewhere. Each region's
    texture is evaluated only where the footprint overlaps the region, weighted by its share
    of the footprint (regions along x and z combine as products: exact for separable masks)."""
    n = len(p)
    masses: dict[str, Array] = {}
    rest = np.ones(n)
    if river_half_width > 0:
        r = river_half_width
        masses["water"] = interval(p.u, -(r - 0.4), r - 0.4, p.ku)
        masses["bank"] = interval(p.u, r - 0.4, r + 0.4, p.ku) + interval(p.u, -(r + 0.4), -(r - 0.4), p.ku)
        rest = rest - masses["water"] - masses["bank"]
    h = road_half_width
    if h > 0:
        def profile(x, k):  # cumulative masses along one axis: road, road+kerb, road+kerb+sidewalk
            def both(lo, hi):
                return interval(x, lo, hi, k) + interval(x, -hi, -lo, k)

            road = interval(x, -(h - 0.12), h - 0.12, k)
            kerb = road + both(h - 0.12, h + 0.12)
            return road, kerb, kerb + both(h + 0.12, h + sidewalk)

        if cross:
            rv, kv, sv = profile(p.v, p.kv)
            ru, ku, su = profile(p.u, p.ku)
            road = 1 - (1 - rv) * (1 - ru)
            kerb = 1 - (1 - kv) * (1 - ku)
            side = 1 - (1 - sv) * (1 - su)
            masses["road_x"] = rest * rv * (1 - ru)
            masses["road_z"] = rest * ru * (1 - rv)
            masses["crossing"] = rest * ru * rv
        else:
            road, kerb, side = profile(p.v, p.kv) if road_along_x else profile(p.u, p.ku)
            masses["road_x" if road_along_x else "road_z"] = rest * road
        masses["kerb"] = rest * (kerb - road)
        masses["sidewalk"] = rest * (side - kerb)
        rest = rest * (1 - side)
    masses["outer"] = np.clip(rest, 0.0, 1.0)
    if cross:  # no centre dashes across the junction, zebra crossings on every arm
        arms = {"dash_phase": 0.7, "no_dash": (-3, 2), "zebras": ((-(h + 3.8), -(h + 0.8)), (h + 0.8, h + 3.8))}
    else:
        arms = {}
    painters = {
        "outer": grass if outer == "grass" else (lambda q, s: paving(q, s, tile=0.6)),
        "sidewalk": lambda q, s: paving(q, s + 1, tile=0.4),
        "kerb": lambda q, s: np.broadcast_to(np.array([0.7, 0.7, 0.68]), (len(q), 3)),
        "road_x": lambda q, s: asphalt(q, s + 2, h, True, **arms),
        "road_z": lambda q, s: asphalt(q, s + 2, h, False, **arms),
        "crossing": lambda q, s: asphalt(q, s + 2, h, True, markings=False),
        "water": lambda q, s: water(q, s + 3),
        "bank": lambda q, s: concrete(q, s + 4),
    }
    out = np.zeros((n, 3))
    for name, m in masses.items():
        sel = np.flatnonzero(m > 1e-9)
        if len(sel):
            out[sel] += m[sel, None] * painters[name](p[sel], seed)
    return out


TEXTURES: dict[str, Callable[..., Array]] = {
    "brick": brick, "plaster": plaster, "facade": facade, "roof": roof_tiles, "paving": paving,
    "asphalt": asphalt, "grass": grass, "foliage": foliage, "bark": bark, "planks": planks,
    "metal": metal, "concrete": concrete, "paint": paint, "glass": glass, "rubber": rubber,
    "sign": sign, "water": water, "ground": ground,
}
