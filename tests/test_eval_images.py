"""The report's comparison strips: every panel named with its PSNR, rain shown bright enough."""

from __future__ import annotations

import torch

from rainyscape.eval.images import RAIN_DISPLAY_MAX_GAIN, rain_display_gain, side_by_side, strip_panels
from rainyscape.eval.views import ViewImages


def _view(with_truth: bool = True) -> ViewImages:
    g = torch.Generator().manual_seed(0)
    clean = torch.rand(3, 40, 48, generator=g) * 0.8
    true_rain = torch.zeros(3, 40, 48)
    true_rain[:, :, 10:12] = 0.2  # one faint streak
    rain = true_rain * 0.9
    return ViewImages(0, "000.png", "train", clean + true_rain, clean + 0.01, None,
                      clean=clean if with_truth else None, rain=rain,
                      true_rain=true_rain if with_truth else None, post={"fusion": clean})


def test_panels_carry_their_psnr_and_one_rain_gain():
    labels = [label for label, _ in strip_panels(_view())]
    assert labels[0].startswith("rainy input ") and labels[0].endswith(" dB")
    assert labels[1] == "render 40.0 dB"  # 0.01 off everywhere
    assert labels[2].startswith("+ fusion ") and labels[3] == "clean"
    # the faint streak (0.2) is shown at the capped gain on both rain panels
    assert labels[4].startswith("predicted rain ") and labels[4].endswith(f"dB x{RAIN_DISPLAY_MAX_GAIN:.1f}")
    assert labels[5] == f"true rain x{RAIN_DISPLAY_MAX_GAIN:.1f}"
    panels = dict(strip_panels(_view()))
    assert panels[labels[5]].max() == round(0.2 * RAIN_DISPLAY_MAX_GAIN * 255)
    strip = side_by_side(strip_panels(_view()))
    assert strip.shape[1] >= 6 * 128  # six panels, each at least the minimum width


def test_without_ground_truth_panels_are_named_only():
    labels = [label for label, _ in strip_panels(_view(with_truth=False))]
    assert labels[:3] == ["rainy input", "render", "+ fusion"] and "clean" not in labels
    assert labels[-1].startswith("predicted rain")


def test_rain_gain_brightens_faint_rain_only():
    assert rain_display_gain(torch.full((3, 8, 8), 1.0)) == 1.0
    assert rain_display_gain(torch.full((3, 8, 8), 0.5)) == 2.0
    assert rain_display_gain(torch.zeros(3, 8, 8)) == RAIN_DISPLAY_MAX_GAIN
