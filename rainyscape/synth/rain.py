"""Rain as a 3D field of drops, rendered as depth-tested streaks integrated over each pixel.

Physics (per drop): radius from a Marshall-Palmer (exponential) size distribution truncated
to [radius_min, radius_max]; terminal velocity 200 * sqrt(radius / 1 m) m/s; a common wind
(one direction, or a mixture of two) with a small per-drop jitter. Over the exposure a drop
moves along a 3D segment; its projection is a streak: a rectangle along the projected
motion whose width is the projected diameter (times ``size_scale``, as Maya artists enlarge
drop models) and whose length is the projected motion plus that width.

Sizes are set in metres and in output pixels: a streak is never drawn thinner than
``min_width_px`` nor shorter than ``min_length_px``. A drop whose true streak is smaller is
drawn at that floor with a probability equal to the ratio of the true streak's area to the
drawn streak's energy (its summed squared coverage), with a per-drop random rank, so every
drawn streak is distinct and bright and the expected rain energy of a view is that of the
true-size drops at any resolution: sub-threshold drops are dropped, not smeared into a
faint veil. The rank is the drop's own, so a drop kept in a far view is kept in nearer ones.

Each streak's coverage of a pixel is the exact box-filtered coverage across the streak
times that along it (the pixel square projected on the streak's axes); the streak's depth
is tested against the depths of the pixel's base samples (the covered fraction of the
pixel). Streaks are composited over the clean image as I = B (1 - A) + A C with the
coverages of all drops combined as A = 1 - prod(1 - a_i); drops refract a wide, bright
field of view, so C is the sky's radiance times ``brightness``.

Static mode: one field at one instant, seen by every camera. Dynamic mode: frame k sees the
field at time k / fps (drops wrap around the field's box, so the density stays constant).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch
from torch import Tensor

from rainyscape.cameras import Cameras
from rainyscape.errors import ConfigError
from rainyscape.synth.params import RainConfig


def terminal_velocity(radius_m: np.ndarray) -> np.ndarray:
    """Fall speed in m/s of drops of radius ``radius_m`` (metres)."""
    return 200.0 * np.sqrt(radius_m)


def sample_radii(n: int, cfg: RainConfig, rng: np.random.Generator) -> np.ndarray:
    """Radii in metres: N(D) ~ exp(-L D), L = 4.1 R^-0.21 per mm of diameter (Marshall-Palmer),
    truncated to the configured radius range (inverse-CDF sampling)."""
    lam = 4.1 * max(cfg.rain_rate_mm_h, 1e-3) ** -0.21
    d0, d1 = 2 * cfg.radius_min_mm, 2 * cfg.radius_max_mm
    u = rng.random(n)
    e0, e1 = np.exp(-lam * d0), np.exp(-lam * d1)
    diameter_mm = -np.log(e0 - u * (e0 - e1)) / lam
    return diameter_mm / 2000.0


def _wind(deg: float, azimuth_deg: float, fall_speed: float) -> np.ndarray:
    az = np.radians(azimuth_deg)
    speed = fall_speed * np.tan(np.radians(np.clip(deg, -80, 80)))
    return speed * np.array([np.cos(az), 0.0, np.sin(az)])


@dataclass
class DropField:
    positions: np.ndarray  # (N, 3) at t = 0
    velocities: np.ndarray  # (N, 3) m/s
    radii: np.ndarray  # (N,) metres
    tint: np.ndarray  # (N,) per-drop brightness factor
    lo: np.ndarray  # (3,) box corner
    hi: np.ndarray
    rank: np.ndarray | None = None  # (N,) in [0, 1): which drops a view keeps below the size floor
    strength: np.ndarray | None = None  # (N,) streak alpha relative to ``opacity``
    wind: np.ndarray | None = None  # (N,) which wind drives the drop: 0 the first, 1 the second (mix)
    _last: tuple | None = field(default=None, repr=False)

    def __post_init__(self) -> None:
        if self.rank is None:
            self.rank = np.zeros(len(self.radii))
        if self.strength is None:
            self.strength = np.ones(len(self.radii))
        if self.wind is None:
            self.wind = np.zeros(len(self.radii), dtype=np.int64)

    def fall_directions(self) -> np.ndarray:
        """(K, 3) unit directions the drops fall along, the mean of their own per wind (K = 1, or
        2 with ``mix``). Not the wind preset's angle: small drops fall slower, so the wind slants
        the field more than it slants a drop of the mid radius. Evaluation's true streak angles
        come from them (scene.json's ``rain_falls``)."""
        unit = self.velocities / np.linalg.norm(self.velocities, axis=1, keepdims=True).clip(1e-12)
        means = [unit[self.wind == k].mean(0) for k in np.unique(self.wind)]
        return np.array([m / np.linalg.norm(m) for m in means])

    def __len__(self) -> int:
        return len(self.radii)

    def segments(self, time_s: float, exposure_s: float) -> tuple[np.ndarray, np.ndarray]:
        """Start and end (N, 3) float32 of each drop's motion during the exposure centred at
        ``time_s`` (the last answer is kept: static rain asks the same for every view)."""
        key = (float(time_s), float(exposure_s))
        if self._last is not None and self._last[0] == key:
            return self._last[1]
        size = self.hi - self.lo
        centre = self.lo + np.mod(self.positions + self.velocities * time_s - self.lo, size)
        half = 0.5 * exposure_s * self.velocities
        seg = ((centre - half).astype(np.float32), (centre + half).astype(np.float32))
        self._last = (key, seg)
        return seg


def make_drop_field(lo: np.ndarray, hi: np.ndarray, cfg: RainConfig, seed: int, max_drops: int = 5_000_000) -> DropField:
    """Drops uniformly in the box [lo, hi] at ``cfg.density`` per m^3.

    Each attribute comes from its own random stream, so drop i is the same drop at any
    density: a denser field adds drops to a sparser one (calibration is smooth)."""
    def stream(k: int) -> np.random.Generator:
        return np.random.default_rng([int(seed), k])

    volume = float(np.prod(hi - lo))
    n = int(stream(0).poisson(max(cfg.density, 0.0) * volume))
    if n > max_drops:
        raise ConfigError(f"density={cfg.density:g} puts {n} drops in the {volume:.0f} m^3 rain volume; "
                          f"at most {max_drops} are supported (lower density)")
    radii = sample_radii(n, cfg, stream(1))
    fall = terminal_velocity(radii)
    median_fall = float(terminal_velocity(np.array([0.5 * (cfg.radius_min_mm + cfg.radius_max_mm) / 1000]))[0])
    second = stream(2).random(n) < cfg.mix
    wind = np.where(second[:, None], _wind(cfg.wind2_deg, cfg.wind2_azimuth_deg, median_fall),
                    _wind(cfg.wind_deg, cfg.wind_azimuth_deg, median_fall))
    vel = wind.copy()
    vel[:, 1] = -fall
    jitter = stream(3).standard_normal((n, 4))
    vel *= 1.0 + cfg.jitter * jitter[:, :1]
    vel += cfg.jitter * median_fall * 0.3 * jitter[:, 1:]
    pos = lo + stream(4).random((n, 3)) * (hi - lo)
    tint = 1.0 + 0.1 * stream(5).standard_normal(n)
    rank = stream(6).random(n)
    strength = 0.5 + 0.5 * stream(7).random(n)  # half to full opacity
    return DropField(pos, vel, radii, tint, np.asarray(lo, float), np.asarray(hi, float), rank, strength,
                     second.astype(np.int64))


@dataclass
class RainLayer:
    alpha: np.ndarray  # (H, W) coverage of rain in [0, 1]
    color: np.ndarray  # (H, W, 3) colour of the rain where alpha > 0
    streaks: int = 0  # streaks drawn

    def composite(self, clean: np.ndarray) -> np.ndarray:
        a = self.alpha[..., None]
        return clean * (1 - a) + self.color * a


def _project_segments(start: np.ndarray, end: np.ndarray, c2w: np.ndarray, near: float,
                      half_tan: tuple[float, float], margin: float):
    """Camera-space segments of drops in (or within ``margin`` metres of) the view frustum,
    clipped to z >= near: (a, b) each (M, 3), and the indices of the kept drops."""
    rot, t = c2w[:3, :3].astype(np.float32), c2w[:3, 3].astype(np.float32)
    a = start @ rot - t @ rot
    # cheap cull on the start point; segments are shorter than ``margin``
    z = a[:, 2]
    inside = ((z > near - margin) & (np.abs(a[:, 0]) < z * half_tan[0] + margin)
              & (np.abs(a[:, 1]) < z * half_tan[1] + margin))
    idx = np.flatnonzero(inside)
    a = a[idx]
    b = end[idx] @ rot - t @ rot
    keep = (a[:, 2] > near) | (b[:, 2] > near)
    a, b, idx = a[keep], b[keep], idx[keep]
    # move an endpoint that is behind the near plane onto it
    for p, q in ((a, b), (b, a)):
        behind = p[:, 2] < near
        lam = (near - p[behind, 2]) / (q[behind, 2] - p[behind, 2])
        p[behind] = p[behind] + lam[:, None] * (q[behind] - p[behind])
    return a, b, idx


def streak_energy(width: np.ndarray, length: np.ndarray) -> np.ndarray:
    """Expected summed squared coverage (px^2) of a box-filtered ``width`` x ``length``
    rectangle at a random sub-pixel position: per axis W - 1/3 (W >= 1), W^2 - W^3 / 3 below."""
    def axis(x):
        return np.where(x >= 1.0, x - 1.0 / 3.0, x * x - x ** 3 / 3.0)

    return axis(width) * axis(length)


def render_rain(drops: DropField, cameras: Cameras, index: int, depth: np.ndarray, time_s: float,
                cfg: RainConfig, drop_rgb: np.ndarray, max_candidates: int = 3_000_000) -> RainLayer:
    """Rain layer of one view: the visible drops' streaks, depth-tested against ``depth``
    ((H, W) or (H, W, S): the z-depths of S samples per pixel)."""
    h, w = cameras.height, cameras.width
    c2w = cameras.c2w[index].double().numpy()
    fx, fy = float(cameras.fx[index]), float(cameras.fy[index])
    cx, cy = float(cameras.cx[index]), float(cameras.cy[index])
    start, end = drops.segments(time_s, cfg.exposure_s)
    margin = 1.0 + float(np.abs(drops.velocities).max(initial=0.0)) * cfg.exposure_s
    half_tan = (max(cx, w - cx) / fx, max(cy, h - cy) / fy)
    a, b, keep = _project_segments(start, end, c2w, cfg.near_clip, half_tan, margin)
    radii, tint, rank, strength = drops.radii[keep], drops.tint[keep], drops.rank[keep], drops.strength[keep]
    ua, va = fx * a[:, 0] / a[:, 2] + cx, fy * a[:, 1] / a[:, 2] + cy
    ub, vb = fx * b[:, 0] / b[:, 2] + cx, fy * b[:, 1] / b[:, 2] + cy
    z_mid = 0.5 * (a[:, 2] + b[:, 2])
    # true streak (the drawn drop model) and the drawn one, floored in output pixels
    width = 2 * radii * cfg.size_scale * fx / z_mid
    ex, ey = ub - ua, vb - va
    length = np.hypot(ex, ey)
    degenerate = length < 1e-6  # falling straight along the view ray: draw it upright
    ex, ey = np.where(degenerate, 0.0, ex), np.where(degenerate, 1.0, ey)
    norm = np.hypot(ex, ey)
    ex, ey = ex / norm, ey / norm
    w_draw = np.maximum(width, cfg.min_width_px)
    l_draw = np.maximum(length, cfg.min_length_px)
    ratio = width * (length + width) / np.maximum(streak_energy(w_draw, l_draw + w_draw), 1e-12)
    mx, my = 0.5 * (ua + ub), 0.5 * (va + vb)
    half_len = 0.5 * (l_draw + w_draw)
    half_w = 0.5 * w_draw
    # bounding boxes (the pixel's own half-diagonal of reach on each side)
    rx = np.abs(ex) * half_len + np.abs(ey) * half_w + 1.0
    ry = np.abs(ey) * half_len + np.abs(ex) * half_w + 1.0
    x0 = np.floor(mx - rx).clip(0, w)
    x1 = np.ceil(mx + rx).clip(0, w)
    y0 = np.floor(my - ry).clip(0, h)
    y1 = np.ceil(my + ry).clip(0, h)
    visible = np.flatnonzero((x1 > x0) & (y1 > y0) & (rank < ratio))

    def t(x: np.ndarray) -> Tensor:
        return torch.as_tensor(np.ascontiguousarray(x[visible]), dtype=torch.float32)

    # depth at the streak's centre line: perspective-correct between the endpoints
    streaks = Streaks(t(mx), t(my), t(ex), t(ey), t(half_len), t(half_w), t(ua), t(va), t(ub - ua), t(vb - va),
                      t(a[:, 2]), t(b[:, 2]), t(cfg.opacity * strength), t(tint),
                      t(x0).long(), t(y0).long(), t(x1 - x0).long(), t(y1 - y0).long())
    depth_t = torch.as_tensor(np.asarray(depth, np.float32)).reshape(h * w, -1)
    acc = torch.zeros(3, h * w, dtype=torch.float64)  # sum log(1 - a), sum a, sum a * tint
    cum = torch.cumsum(streaks.bw * streaks.bh, 0)
    first = 0
    while first < len(visible):  # chunks bound the memory of the per-pixel candidates
        base = int(cum[first - 1]) if first else 0
        last = int(torch.searchsorted(cum, torch.tensor(base + max_candidates), right=True))
        last = max(last, first + 1)
        streaks.splat(torch.arange(first, last), depth_t, w, acc)
        first = last
    alpha = (1.0 - torch.exp(acc[0])).reshape(h, w).numpy()
    mean_tint = (acc[2] / acc[1].clamp_min(1e-12)).reshape(h, w).numpy()
    color = np.clip(drop_rgb[None, None] * mean_tint[..., None], 0, 1)
    color[alpha <= 0] = 0
    return RainLayer(alpha, color, len(visible))


def _cdf(s: Tensor, big: Tensor, small: Tensor) -> Tensor:
    """CDF of U(-big/2, big/2) + U(-small/2, small/2) (big >= small) at ``s``."""
    h = 0.5 * (big + small)
    x = torch.minimum(s.abs(), h)
    flat = x <= h - small
    upper = torch.where(flat, 0.5 + x / big, 1.0 - (h - x) ** 2 / (2.0 * big * small).clamp_min(1e-30))
    return torch.where(s < 0, 1.0 - upper, upper)


def _box_interval(s: Tensor, half: Tensor, big: Tensor, small: Tensor) -> Tensor:
    """Mass of [-half, half] under the pixel's projected kernel centred at ``s``."""
    return (_cdf(half - s, big, small) - _cdf(-half - s, big, small)).clamp(0, 1)


@dataclass
class Streaks:
    """One view's drawn streaks: centre, unit direction, half length and half width (pixels),
    the segment (start, offset to end) and its endpoint depths, peak alpha, brightness, and
    the integer bounding box."""

    mx: Tensor
    my: Tensor
    ex: Tensor
    ey: Tensor
    half_len: Tensor
    half_w: Tensor
    ua: Tensor
    va: Tensor
    dx: Tensor
    dy: Tensor
    za: Tensor
    zb: Tensor
    peak: Tensor
    tint: Tensor
    x0: Tensor
    y0: Tensor
    bw: Tensor
    bh: Tensor

    def splat(self, idx: Tensor, depth: Tensor, width: int, acc: Tensor) -> None:
        """Add drops ``idx`` to ``acc`` over every pixel of their bounding boxes."""
        n = self.bw[idx] * self.bh[idx]
        drop = torch.repeat_interleave(idx, n)
        offsets = torch.cumsum(n, 0) - n
        local = torch.arange(int(n.sum())) - torch.repeat_interleave(offsets, n)
        bw = self.bw[drop]
        px = self.x0[drop] + local % bw
        py = self.y0[drop] + torch.div(local, bw, rounding_mode="floor")
        qx, qy = px.float() + 0.5 - self.mx[drop], py.float() + 0.5 - self.my[drop]
        ex, ey = self.ex[drop], self.ey[drop]
        along, across = qx * ex + qy * ey, qx * ey - qy * ex
        # the unit pixel projected on the streak's axes: two boxes |ex| and |ey| wide
        aex, aey = ex.abs(), ey.abs()
        big, small = torch.maximum(aex, aey), torch.minimum(aex, aey)
        cover = (_box_interval(along, self.half_len[drop], big, small)
                 * _box_interval(across, self.half_w[drop], big, small))
        a = self.peak[drop] * cover
        ok = a > 1e-4
        drop, px, py, a = drop[ok], px[ok], py[ok], a[ok]
        # depth where the pixel centre projects onto the segment (perspective-correct)
        dx, dy = self.dx[drop], self.dy[drop]
        tau = (((px.float() + 0.5 - self.ua[drop]) * dx + (py.float() + 0.5 - self.va[drop]) * dy)
               / (dx * dx + dy * dy).clamp_min(1e-9)).clamp(0, 1)
        z = 1.0 / ((1 - tau) / self.za[drop] + tau / self.zb[drop])
        pix = py * width + px
        seen = (z[:, None] < depth[pix]).float().mean(1)  # covered share of the pixel's samples
        a = (a * seen).double().clamp(max=0.995)
        ok = a > 0
        a, pix, drop = a[ok], pix[ok], drop[ok]
        acc[0].index_add_(0, pix, torch.log1p(-a))
        acc[1].index_add_(0, pix, a)
        acc[2].index_add_(0, pix, a * self.tint[drop].double())
