"""Simulator parameters that are cheap to import (no torch): the rain options and the version."""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, fields

# Bump when the simulator's output changes: cached demo and benchmark scenes are keyed by it.
SIM_VERSION = "4"


def _opt(default: float, help: str):
    """A rain option with the line ``rs-synth --help`` shows for it."""
    return field(default=default, metadata={"help": help})


@dataclass
class RainConfig:
    """Rain options (docs/simulator.md); presets and `key=value` arguments override them."""

    density: float = _opt(2.0, "drops per cubic metre (of radius_min .. radius_max)")
    rain_rate_mm_h: float = _opt(10.0, "sets the Marshall-Palmer slope: heavier rain, bigger drops")
    radius_min_mm: float = _opt(0.5, "smallest drop radius")
    radius_max_mm: float = _opt(3.0, "largest drop radius")
    wind_deg: float = _opt(0.0, "fall direction's angle from vertical (for a median drop)")
    wind_azimuth_deg: float = _opt(0.0, "horizontal wind direction: 0 = +X, 90 = +Z")
    wind2_deg: float = _opt(0.0, "second rain direction's angle from vertical (a mixture) ...")
    wind2_azimuth_deg: float = _opt(180.0, "second direction's horizontal azimuth")
    mix: float = _opt(0.0, "... taken by this fraction of the drops (0: one direction)")
    jitter: float = _opt(0.08, "per-drop relative velocity noise")
    exposure_s: float = _opt(1.0 / 30.0, "shutter time: longer streaks")
    brightness: float = _opt(1.3, "drop radiance relative to the mean sky")
    opacity: float = _opt(0.9, "alpha of the most opaque streaks (each drop: half to full)")
    size_scale: float = _opt(3.0, "drawn radius / physical radius")
    min_width_px: float = _opt(1.0, "streaks are never drawn thinner (smaller drops: fewer, see docs)")
    min_length_px: float = _opt(2.0, "... nor shorter than this along their motion")
    near_clip: float = _opt(1.0, "metres: drops closer to the lens are not drawn")
    haze: float = _opt(0.0, "0..1: fog veil (light lost over 100 m); separate from the rain layer")
    fps: float = _opt(24.0, "dynamic mode: time between frames is 1 / fps")

    @classmethod
    def keys(cls) -> list[str]:
        return [f.name for f in fields(cls)]

    def to_dict(self) -> dict:
        return asdict(self)
