"""Simulator parameters that are cheap to import (no torch): the rain options and the version."""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, fields

# Bump when the simulator's output changes: cached demo and benchmark scenes are keyed by it.
SIM_VERSION = "4"


def _opt(default: float, help: str, lo: float | None = None, hi: float | None = None,
         above: float | None = None):
    """A rain option with the line ``rs-synth --help`` shows for it and its range (the
    metadata keys of ``cli.args.opt`` and ``config.schema.bounded``: checked as the command
    line is read, and again by :func:`rainyscape.synth.simulate.rain_config`)."""
    return field(default=default, metadata={"help": help, "min": lo, "max": hi, "above": above})


@dataclass
class RainConfig:
    """Rain options (docs/simulator.md); presets and `key=value` arguments override them."""

    density: float = _opt(2.0, "drops per cubic metre (of radius_min .. radius_max); 0: a dry scene", 0.0, 1000.0)
    rain_rate_mm_h: float = _opt(10.0, "sets the Marshall-Palmer slope: heavier rain, bigger drops",
                                 hi=500.0, above=0.0)
    radius_min_mm: float = _opt(0.5, "smallest drop radius", hi=10.0, above=0.0)
    radius_max_mm: float = _opt(3.0, "largest drop radius (at least radius_min_mm)", hi=10.0, above=0.0)
    wind_deg: float = _opt(0.0, "fall direction's angle from vertical (for a median drop)", -80.0, 80.0)
    wind_azimuth_deg: float = _opt(0.0, "horizontal wind direction: 0 = +X, 90 = +Z", -360.0, 360.0)
    wind2_deg: float = _opt(0.0, "second rain direction's angle from vertical (a mixture) ...", -80.0, 80.0)
    wind2_azimuth_deg: float = _opt(180.0, "second direction's horizontal azimuth", -360.0, 360.0)
    mix: float = _opt(0.0, "... taken by this fraction of the drops (0: one direction)", 0.0, 1.0)
    jitter: float = _opt(0.08, "per-drop relative velocity noise", 0.0, 1.0)
    exposure_s: float = _opt(1.0 / 30.0, "shutter time: longer streaks", hi=1.0, above=0.0)
    brightness: float = _opt(1.3, "drop radiance relative to the mean sky", 0.0, 10.0)
    opacity: float = _opt(0.9, "alpha of the most opaque streaks (each drop: half to full)", hi=1.0, above=0.0)
    size_scale: float = _opt(3.0, "drawn radius / physical radius", hi=100.0, above=0.0)
    min_width_px: float = _opt(1.0, "streaks are never drawn thinner (smaller drops: fewer, see docs)", 0.0, 100.0)
    min_length_px: float = _opt(2.0, "... nor shorter than this along their motion", 0.0, 1000.0)
    near_clip: float = _opt(1.0, "metres: drops closer to the lens are not drawn", 0.0, 1000.0)
    haze: float = _opt(0.0, "fog veil (light lost over 100 m); separate from the rain layer", 0.0, 1.0)
    fps: float = _opt(24.0, "dynamic mode: time between frames is 1 / fps", hi=1000.0, above=0.0)

    @classmethod
    def keys(cls) -> list[str]:
        return [f.name for f in fields(cls)]

    def to_dict(self) -> dict:
        return asdict(self)
