"""Rain as a 3D field of drops, rendered as depth-tested, anti-aliased streaks.

Physics (per drop): radius from a Marshall-Palmer (exponential) size distribution truncated
to [radius_min, radius_max]; terminal velocity 200 * sqrt(radius / 1 m) m/s; a common wind
(one direction, or a mixture of two) with a small per-drop jitter. Over the exposure a drop
moves along a 3D segment; its projection is a streak whose width is the projected diameter
(scaled by ``size_scale``, as Maya artists enlarge drop models) widened by defocus. The
streak is composited over the clean image as I = B (1 - A) + A C: drops refract a wide,
bright field of view, so C is the sky's radiance times ``brightness``.

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
    _last: tuple | None = field(default=None, repr=False)

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
    """Drops uniformly in the box [lo, hi] at ``cfg.density`` per m^3."""
    rng = np.random.default_rng(seed)
    volume = float(np.prod(hi - lo))
    n = int(rng.poisson(max(cfg.density, 0.0) * volume))
    if n > max_drops:
        raise ConfigError(f"density={cfg.density:g} puts {n} drops in the {volume:.0f} m^3 rain volume; "
                          f"at most {max_drops} are supported (lower density)")
    radii = sample_radii(n, cfg, rng)
    fall = terminal_velocity(radii)
    median_fall = float(terminal_velocity(np.array([0.5 * (cfg.radius_min_mm + cfg.radius_max_mm) / 1000]))[0])
    second = rng.random(n) < cfg.mix
    wind = np.where(second[:, None], _wind(cfg.wind2_deg, cfg.wind2_azimuth_deg, median_fall),
                    _wind(cfg.wind_deg, cfg.wind_azimuth_deg, median_fall))
    vel = wind.copy()
    vel[:, 1] = -fall
    vel *= 1.0 + cfg.jitter * rng.standard_normal((n, 1))
    vel += cfg.jitter * median_fall * 0.3 * rng.standard_normal((n, 3))
    pos = lo + rng.random((n, 3)) * (hi - lo)
    tint = 1.0 + 0.1 * rng.standard_normal(n)
    return DropField(pos, vel, radii, tint, np.asarray(lo, float), np.asarray(hi, float))


@dataclass
class RainLayer:
    alpha: np.ndarray  # (H, W) coverage of rain in [0, 1]
    color: np.ndarray  # (H, W, 3) colour of the rain where alpha > 0

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


def render_rain(drops: DropField, cameras: Cameras, index: int, depth: np.ndarray, time_s: float,
                cfg: RainConfig, drop_rgb: np.ndarray, focus_distance: float, focal_m: float,
                max_candidates: int = 3_000_000) -> RainLayer:
    """Rain layer of one view: every visible drop's streak, depth-tested against ``depth``."""
    h, w = cameras.height, cameras.width
    c2w = cameras.c2w[index].double().numpy()
    fx, fy = float(cameras.fx[index]), float(cameras.fy[index])
    cx, cy = float(cameras.cx[index]), float(cameras.cy[index])
    start, end = drops.segments(time_s, cfg.exposure_s)
    margin = 1.0 + float(np.abs(drops.velocities).max(initial=0.0)) * cfg.exposure_s
    half_tan = (max(cx, w - cx) / fx, max(cy, h - cy) / fy)
    a, b, keep = _project_segments(start, end, c2w, cfg.near_clip, half_tan, margin)
    radii, tint = drops.radii[keep], drops.tint[keep]
    ua, va = fx * a[:, 0] / a[:, 2] + cx, fy * a[:, 1] / a[:, 2] + cy
    ub, vb = fx * b[:, 0] / b[:, 2] + cx, fy * b[:, 1] / b[:, 2] + cy
    z_mid = 0.5 * (a[:, 2] + b[:, 2])
    width = 2 * radii * cfg.size_scale * fx / z_mid
    aperture = focal_m / max(cfg.f_number, 0.1)  # lens opening diameter, metres
    coc = fx * aperture * np.abs(1.0 / z_mid - 1.0 / focus_distance)  # blur circle, pixels
    w_eff = np.sqrt(width ** 2 + coc ** 2)
    w_draw = np.maximum(w_eff, 1.0)
    # Defocus spreads a streak's light over w_draw (peak falls as width / w_draw; a streak
    # under a pixel wide covers that fraction of it). Streaks narrower than ``faint_width``
    # of the image also fade in proportion (time-integrated coverage of a tiny drop), so far
    # drops make a faint haze and near ones clear streaks. Measuring that threshold as a
    # fraction of the view, not in pixels, keeps the rain's strength independent of the
    # image resolution.
    faint = np.minimum(1.0, width / (cfg.faint_width * w))
    peak = cfg.opacity * faint * width / w_draw
    soft = 0.5 + coc / 4
    reach = w_draw / 2 + soft
    x0 = np.floor(np.minimum(ua, ub) - reach).clip(0, w)
    x1 = np.ceil(np.maximum(ua, ub) + reach).clip(0, w)
    y0 = np.floor(np.minimum(va, vb) - reach).clip(0, h)
    y1 = np.ceil(np.maximum(va, vb) + reach).clip(0, h)
    visible = np.flatnonzero((x1 > x0) & (y1 > y0) & (peak > 3e-3))  # fainter: below a grey level

    def t(x: np.ndarray) -> Tensor:
        return torch.as_tensor(np.ascontiguousarray(x[visible]), dtype=torch.float32)

    streaks = Streaks(t(ua), t(va), t(ub), t(vb), t(a[:, 2]), t(b[:, 2]), t(w_draw / 2), t(soft),
                      t(peak), t(tint), t(x0).long(), t(y0).long(), t(x1 - x0).long(), t(y1 - y0).long())
    depth_t = torch.as_tensor(depth, dtype=torch.float32).reshape(-1)
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
    return RainLayer(alpha, color)


@dataclass
class Streaks:
    """One view's projected streaks, one entry per drop: endpoints (pixels), endpoint depths,
    half width, edge softness, peak alpha, brightness and the integer bounding box."""

    ua: Tensor
    va: Tensor
    ub: Tensor
    vb: Tensor
    za: Tensor
    zb: Tensor
    half: Tensor
    soft: Tensor
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
        # closest point of the segment to the pixel centre
        ua, va = self.ua[drop], self.va[drop]
        ex, ey = self.ub[drop] - ua, self.vb[drop] - va
        qx, qy = px.float() + 0.5 - ua, py.float() + 0.5 - va
        tau = ((qx * ex + qy * ey) / (ex * ex + ey * ey).clamp_min(1e-9)).clamp(0, 1)
        dist = torch.hypot(qx - tau * ex, qy - tau * ey)
        cover = ((self.half[drop] - dist) / (2 * self.soft[drop]) + 0.5).clamp(0, 1)
        a = self.peak[drop] * cover
        z = 1.0 / ((1 - tau) / self.za[drop] + tau / self.zb[drop])  # perspective-correct depth
        pix = py * width + px
        ok = (a > 1e-3) & (z < depth[pix])
        a, pix = a[ok].double().clamp(max=0.995), pix[ok]
        acc[0].index_add_(0, pix, torch.log1p(-a))
        acc[1].index_add_(0, pix, a)
        acc[2].index_add_(0, pix, a * self.tint[drop][ok].double())
