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

from dataclasses import asdict, dataclass, field, fields

import numpy as np
import torch
from torch import Tensor

from rainyscape.cameras import Cameras
from rainyscape.errors import ConfigError


@dataclass
class RainConfig:
    density: float = 20.0  # drops per cubic metre (of radius_min .. radius_max)
    rain_rate_mm_h: float = 10.0  # sets the Marshall-Palmer slope: heavier rain, bigger drops
    radius_min_mm: float = 0.5
    radius_max_mm: float = 3.0
    wind_deg: float = 0.0  # fall direction's angle from vertical (for a median drop)
    wind_azimuth_deg: float = 0.0  # horizontal wind direction: 0 = +X, 90 = +Z
    wind2_deg: float = 0.0  # second rain direction (a mixture) ...
    wind2_azimuth_deg: float = 180.0
    mix: float = 0.0  # ... taken by this fraction of the drops (0: one direction)
    jitter: float = 0.08  # per-drop relative velocity noise
    exposure_s: float = 1.0 / 30.0
    brightness: float = 1.15  # drop radiance relative to the mean sky
    opacity: float = 0.8  # peak alpha of an in-focus streak at least one pixel wide
    size_scale: float = 3.0  # drawn radius / physical radius
    f_number: float = 2.8  # defocus of drops off the focus plane (the look-at point)
    near_clip: float = 0.3  # metres: drops closer to the lens are not drawn
    fps: float = 24.0  # dynamic mode: time between frames is 1 / fps

    @classmethod
    def keys(cls) -> list[str]:
        return [f.name for f in fields(cls)]

    def to_dict(self) -> dict:
        return asdict(self)


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
    # Defocus spreads a streak's light over w_draw (peak falls as width / w_draw). A streak
    # narrower than a pixel fades with its area, (width)^2: it covers that fraction of the
    # pixel's width for that fraction of the time the pixel sees it (time-integrated coverage).
    peak = cfg.opacity * np.minimum(width, 1.0) * width / w_draw
    soft = 0.5 + coc / 4
    reach = w_draw / 2 + soft
    x0 = np.floor(np.minimum(ua, ub) - reach).clip(0, w)
    x1 = np.ceil(np.maximum(ua, ub) + reach).clip(0, w)
    y0 = np.floor(np.minimum(va, vb) - reach).clip(0, h)
    y1 = np.ceil(np.maximum(va, vb) + reach).clip(0, h)
    visible = (x1 > x0) & (y1 > y0) & (peak > 3e-3)  # fainter: below one grey level
    sel = np.flatnonzero(visible)
    dev = torch.device("cpu")
    t = lambda x: torch.as_tensor(np.ascontiguousarray(x[sel]), dtype=torch.float32, device=dev)  # noqa: E731
    ua_t, va_t, ub_t, vb_t = t(ua), t(va), t(ub), t(vb)
    za_t, zb_t = t(a[:, 2]), t(b[:, 2])
    half_t, soft_t, peak_t = t(w_draw / 2), t(soft), t(peak)
    tint_t = t(tint)
    x0_t, y0_t = t(x0).long(), t(y0).long()
    bw_t, bh_t = (t(x1) - t(x0)).long(), (t(y1) - t(y0)).long()
    depth_t = torch.as_tensor(depth, dtype=torch.float32).reshape(-1)
    log_t = torch.zeros(h * w, dtype=torch.float64)
    wsum = torch.zeros(h * w, dtype=torch.float64)
    tsum = torch.zeros(h * w, dtype=torch.float64)
    counts = bw_t * bh_t
    cum = torch.cumsum(counts, 0)
    first = 0
    while first < len(sel):  # chunks bound the memory of the per-pixel candidates
        base = int(cum[first - 1]) if first else 0
        last = int(torch.searchsorted(cum, torch.tensor(base + max_candidates), right=True))
        last = max(last, first + 1)
        idx = torch.arange(first, last)
        _splat(idx, counts, ua_t, va_t, ub_t, vb_t, za_t, zb_t, half_t, soft_t, peak_t, tint_t,
               x0_t, y0_t, bw_t, w, depth_t, log_t, wsum, tsum)
        first = last
    alpha = (1.0 - torch.exp(log_t)).reshape(h, w).numpy()
    mean_tint = (tsum / wsum.clamp_min(1e-12)).reshape(h, w).numpy()
    color = np.clip(drop_rgb[None, None] * mean_tint[..., None], 0, 1)
    color[alpha <= 0] = 0
    return RainLayer(alpha.astype(np.float64), color)


def _splat(idx: Tensor, counts: Tensor, ua: Tensor, va: Tensor, ub: Tensor, vb: Tensor, za: Tensor,
           zb: Tensor, half: Tensor, soft: Tensor, peak: Tensor, tint: Tensor, x0: Tensor, y0: Tensor,
           bw: Tensor, width: int, depth: Tensor, log_t: Tensor, wsum: Tensor, tsum: Tensor) -> None:
    """Accumulate the streaks of drops ``idx``: every pixel of each drop's bounding box."""
    n = counts[idx]
    drop = torch.repeat_interleave(idx, n)
    offsets = torch.cumsum(n, 0) - n
    local = torch.arange(int(n.sum())) - torch.repeat_interleave(offsets, n)
    px = x0[drop] + local % bw[drop]
    py = y0[drop] + torch.div(local, bw[drop], rounding_mode="floor")
    # closest point of the segment to the pixel centre
    ex, ey = ub[drop] - ua[drop], vb[drop] - va[drop]
    qx, qy = px.float() + 0.5 - ua[drop], py.float() + 0.5 - va[drop]
    tau = ((qx * ex + qy * ey) / (ex * ex + ey * ey).clamp_min(1e-9)).clamp(0, 1)
    dist = torch.hypot(qx - tau * ex, qy - tau * ey)
    cover = ((half[drop] - dist) / (2 * soft[drop]) + 0.5).clamp(0, 1)
    a = peak[drop] * cover
    z = 1.0 / ((1 - tau) / za[drop] + tau / zb[drop])  # perspective-correct depth on the streak
    pix = py * width + px
    ok = (a > 1e-3) & (z < depth[pix])
    a, pix, t = a[ok].double().clamp(max=0.995), pix[ok], tint[drop][ok].double()
    log_t.index_add_(0, pix, torch.log1p(-a))
    wsum.index_add_(0, pix, a)
    tsum.index_add_(0, pix, a * t)
