"""Named simulator presets: a scene, a rain setting and a default camera array.

Each preset has a rain-strength label (``label_db``, the rainy-vs-clean PSNR it is set up
for); the rain's density was calibrated so that the measured strength is within 1.5 dB of
the label at 64, 128, 256 and 512 px (docs/benchmarks.md, Simulator; ``strength.py`` keeps
the measured values). No preset uses haze.
"""

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
    label_db: float = 26.0  # the rain strength it is made for: rainy-vs-clean PSNR
    level: str = "medium"
    # per-view transient objects instead of rain (synth/transients.py: people, cars, leaves);
    # a preset with transients has no rain (density 0)
    transients: dict = field(default_factory=dict)


PRESETS: dict[str, Preset] = {p.name: p for p in [
    Preset("demo", "street", "street corner, medium rain slanted by a light wind",
           {"density": 1.16, "wind_deg": 12.0, "wind_azimuth_deg": 20.0}, rows=3, cols=8, width=192, height=192,
           label_db=26.0, level="medium"),
    Preset("yard", "yard", "house, fence and garden, light near-vertical drizzle",
           {"density": 0.66, "rain_rate_mm_h": 3.0, "wind_deg": 5.0, "wind_azimuth_deg": 30.0},
           label_db=30.0, level="light"),
    Preset("crossroad", "crossroad", "road junction with zebra crossings, shops and cars, medium rain",
           {"density": 0.94, "rain_rate_mm_h": 10.0, "wind_deg": 8.0, "wind_azimuth_deg": 200.0},
           label_db=26.0, level="medium"),
    Preset("street", "street", "street with shops, cars and lamps, wind-driven rain at 30 degrees",
           {"density": 1.47, "rain_rate_mm_h": 20.0, "wind_deg": 30.0, "wind_azimuth_deg": 0.0},
           label_db=24.0, level="medium-heavy, wind 30 deg"),
    Preset("bridge", "bridge", "river, footbridge and boat, gusty rain from two directions",
           {"density": 0.97, "rain_rate_mm_h": 15.0, "wind_deg": 25.0, "wind_azimuth_deg": 0.0, "wind2_deg": 20.0,
            "wind2_azimuth_deg": 160.0, "mix": 0.45},
           label_db=25.0, level="medium-heavy, two directions"),
    Preset("plaza", "plaza", "square with fountain, benches and signs, heavy near-vertical downpour",
           {"density": 2.5, "rain_rate_mm_h": 50.0, "wind_deg": 6.0, "wind_azimuth_deg": 200.0,
            "exposure_s": 1.0 / 20.0},
           label_db=21.0, level="heavy"),
    # Distractors, not rain: a static scene with objects in one view only (bench scenes=distractors).
    Preset("plaza-crowd", "plaza", "the plaza on a dry day with people walking through every view",
           {"density": 0.0}, transients={"people": 16, "far_m": 20.0}, label_db=0.0, level="distractors: people"),
    Preset("crossroad-traffic", "crossroad", "the crossroad on a dry day with cars and pedestrians passing",
           {"density": 0.0}, transients={"cars": 3, "people": 6}, label_db=0.0, level="distractors: cars, people"),
    Preset("yard-leaves", "yard", "the yard on a dry, windy day: leaves blowing past the lens, a passer-by",
           {"density": 0.0}, transients={"leaves": 40, "people": 2}, label_db=0.0, level="distractors: leaves"),
]}

DISTRACTOR_PRESETS = tuple(name for name, p in PRESETS.items() if p.transients)
