"""Simulator rain: preset strengths hold at a small size, rain is streaks, haze is separate."""

from __future__ import annotations

import json

import imageio.v3 as iio
import numpy as np
import pytest

from rainyscape.synth import generate
from rainyscape.synth.params import RainConfig
from rainyscape.synth.presets import PRESETS
from rainyscape.synth.rain import streak_energy


@pytest.mark.parametrize("preset", ["plaza", "street"])
def test_preset_strength_at_64_px_is_within_1_5_db_of_its_label(tmp_path, preset):
    # a 2 x 4 array spans the preset's sphere cap like its default 5 x 10 one
    out = generate(tmp_path / preset, preset, rows=2, cols=4, width=64, height=64)
    m = json.loads((out / "scene.json").read_text())["metrics"]
    label = PRESETS[preset].label_db
    assert abs(m["psnr_rainy_vs_clean"] - label) <= 1.5, (m["psnr_rainy_vs_clean"], label)
    # streaks, not a veil: a minority of the pixels, and little of the error is the image mean
    assert m["rain_coverage"] < 0.25
    assert m["rain_mean_share"] < 0.15


def test_every_rain_preset_has_a_label_in_the_papers_range():
    labels = {p.label_db for p in PRESETS.values() if not p.transients}
    assert min(labels) <= 21 and max(labels) >= 30
    assert all(p.rain.get("haze", 0.0) == 0.0 for p in PRESETS.values())
    assert any(p.rain.get("mix", 0.0) > 0 for p in PRESETS.values())  # two directions
    assert any(p.rain.get("wind_deg", 0.0) >= 30 for p in PRESETS.values())  # slanted by wind


def test_streak_energy_is_the_area_for_big_streaks_and_falls_for_thin_ones():
    assert streak_energy(np.array(10.0), np.array(40.0)) == pytest.approx((10 - 1 / 3) * (40 - 1 / 3))
    thin = streak_energy(np.array(0.1), np.array(5.0))
    assert thin < 0.1 * 5.0 * 0.2  # a sub-pixel line puts far less energy than its area


def test_haze_is_separate_from_the_rain_layer(tmp_path):
    args = dict(rows=1, cols=1, width=32, height=32, density=3.0)
    plain = generate(tmp_path / "plain", "crossroad", **args)
    hazy = generate(tmp_path / "hazy", "crossroad", haze=0.5, **args)
    for sub in ("rain", "images_wo_rain"):
        assert np.array_equal(iio.imread(plain / sub / "001.png"), iio.imread(hazy / sub / "001.png"))
    assert not (plain / "haze").exists()
    t = iio.imread(hazy / "haze" / "001.png")[..., 0] / 255.0
    assert 0.0 < t.min() and t.max() < 1.0  # the fog dims near and far scene parts
    rainy_plain = iio.imread(plain / "images_rain" / "001.png").astype(float)
    rainy_hazy = iio.imread(hazy / "images_rain" / "001.png").astype(float)
    assert np.abs(rainy_plain - rainy_hazy).mean() > 5
    info = json.loads((hazy / "scene.json").read_text())
    assert info["haze"]["haze"] == 0.5 and info["rain_layer"]["contents"] == "streaks only"
    assert RainConfig().haze == 0.0
