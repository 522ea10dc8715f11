"""Simulator parameters that are cheap to import (no torch): the rain options and the version."""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields

# Bump when the simulator's output changes: cached demo and benchmark scenes are keyed by it.
SIM_VERSION = "4"


@dataclass
class RainConfig:
    """Rain options (docs/simulator.md); presets and `key=value` arguments override them."""

    density: float = 2.0  # drops per cubic metre (of radius_min .. radius_max)
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
    brightness: float = 1.3  # drop radiance relative to the mean sky
    opacity: float = 0.9  # alpha of the most opaque streaks (each drop: half to full)
    size_scale: float = 3.0  # drawn radius / physical radius
    min_width_px: float = 1.0  # streaks are never drawn thinner (smaller drops: fewer, see docs)
    min_length_px: float = 2.0  # ... nor shorter than this along their motion
    near_clip: float = 1.0  # metres: drops closer to the lens are not drawn
    haze: float = 0.0  # 0..1: fog veil (light lost over 100 m); separate from the rain layer
    fps: float = 24.0  # dynamic mode: time between frames is 1 / fps

    @classmethod
    def keys(cls) -> list[str]:
        return [f.name for f in fields(cls)]

    def to_dict(self) -> dict:
        return asdict(self)
