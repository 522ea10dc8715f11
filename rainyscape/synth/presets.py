"""Named simulator presets: a scene, a rain setting and a default camera array."""

from __future__ import annotations

from dataclasses import dataclass, field


@dataclass(frozen=True)
class Preset:
    name: str
    scene: str
    description: str
    rain: dict = field(default_factory=dict)  # RainConfig overrides
    rows: int = 5  # the paper's array is 5 x 10 (at 1024 px)
    cols: int = 10
    width: int = 256
    height: int = 256


PRESETS: dict[str, Preset] = {p.name: p for p in [
    Preset("demo", "street", "street corner, medium rain slanted by a light wind (the embedded demo)",
           {"density": 27.0, "wind_deg": 12.0, "wind_azimuth_deg": 20.0}, rows=3, cols=8, width=192, height=192),
    Preset("yard", "yard", "house, fence and garden, light vertical drizzle",
           {"density": 28.0, "rain_rate_mm_h": 3.0, "opacity": 0.6}),
    Preset("street", "street", "street with shops, cars and lamps, heavy wind-driven rain",
           {"density": 32.0, "rain_rate_mm_h": 40.0, "wind_deg": 30.0, "wind_azimuth_deg": 0.0}),
    Preset("bridge", "bridge", "river, footbridge and boat, medium rain from two directions (gusts)",
           {"density": 20.0, "wind_deg": 25.0, "wind_azimuth_deg": 0.0, "wind2_deg": 18.0,
            "wind2_azimuth_deg": 160.0, "mix": 0.45}),
    Preset("plaza", "plaza", "square with fountain, benches and signs, heavy near-vertical downpour",
           {"density": 30.0, "rain_rate_mm_h": 50.0, "wind_deg": 6.0, "wind_azimuth_deg": 200.0,
            "exposure_s": 1.0 / 20.0}),
]}
