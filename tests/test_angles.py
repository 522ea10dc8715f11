"""Rain-angle estimation: orientation histogram of a residual, top-K peaks, bin centres."""

from __future__ import annotations

import math

import pytest
import torch

from rainyscape.imaging.angles import (angle_difference_deg, bin_centers, estimate_rain_angles, fall_mask,
                                       histogram_peaks, matched_angle_error_deg, orientation_histogram,
                                       residual_streak_angle, streak_angle)
from rainyscape.testing.streaks import streak_layer, textured_background


def _rainy(angle_deg: float, seed: int, count: int = 25) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    image = textured_background(64, g) + streak_layer(64, angle_deg, count, g)
    return image.expand(1, 3, 64, 64)


@pytest.mark.parametrize("angle", [0.0, 20.0, 75.0, 135.0])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_recovers_streak_angle_on_textured_background(angle, seed):
    theta, valid = estimate_rain_angles(_rainy(angle, seed), bins=60, k=1)
    assert valid.all()
    estimate = math.degrees(float(streak_angle(theta)[0, 0]))
    assert angle_difference_deg(estimate, angle) <= 3.0


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_recovers_two_directions_with_k2(seed):
    g = torch.Generator().manual_seed(seed)
    image = textured_background(64, g) + streak_layer(64, 30, 20, g) + streak_layer(64, 110, 20, g)
    theta, valid = estimate_rain_angles(image, k=2)
    assert valid.all()
    found = sorted(torch.rad2deg(streak_angle(theta))[0].tolist())
    assert angle_difference_deg(found[0], 30) <= 3.0 and angle_difference_deg(found[1], 110) <= 3.0


def test_theta_is_across_the_streaks():
    # Vertical streaks (90 degrees): their gradients are horizontal, theta near 0 or 180.
    theta, _ = estimate_rain_angles(_rainy(90.0, 0), k=1)
    assert angle_difference_deg(math.degrees(float(theta[0, 0])), 0.0) <= 3.0


def test_angle_is_the_bin_centre_in_radians():
    # The authors' code used the bin index as radians; the angle is (k + 0.5) * pi / bins.
    assert torch.allclose(bin_centers(torch.tensor([0, 29, 59]), 60),
                          torch.tensor([0.5, 29.5, 59.5]) * math.pi / 60)


def test_histogram_ignores_small_gradients():
    g = torch.Generator().manual_seed(0)
    faint = textured_background(32, g, contrast=0.002).expand(1, 3, 32, 32)
    assert orientation_histogram(faint, threshold=0.1).sum() == 0
    theta, valid = estimate_rain_angles(faint)
    assert not valid.any()
    # A single horizontal step (gradient along +y: orientation 90 degrees) fills one bin.
    step = torch.zeros(1, 1, 8, 8)
    step[..., 4:, :] = 1.0
    hist = orientation_histogram(step, bins=60)
    assert hist[0, 30] == hist.sum() == 2 * 6  # two rows straddle the edge, 6 valid columns


def test_peaks_are_separated_and_wrap_around():
    hist = torch.zeros(1, 60)
    hist[0, [58, 59, 0]] = torch.tensor([5.0, 9.0, 8.0])  # one peak across the wrap, at 59
    hist[0, 20] = 4.0
    index, valid = histogram_peaks(hist, k=2, separation=2)
    assert index.tolist() == [[59, 20]] and valid.all()
    index, valid = histogram_peaks(hist, k=3)
    assert valid.tolist() == [[True, True, False]]


def test_batched_estimates_are_per_image():
    batch = torch.cat([_rainy(20.0, 0), _rainy(135.0, 1)])
    theta, _ = estimate_rain_angles(batch)
    est = torch.rad2deg(streak_angle(theta))[:, 0].tolist()
    assert angle_difference_deg(est[0], 20) <= 3 and angle_difference_deg(est[1], 135) <= 3


def test_matched_angle_error():
    # one true direction: the strongest prediction alone counts (a lucky second one does not)
    assert matched_angle_error_deg([100.0, 80.0], [80.0]) == 20.0
    # two: the pairing that fits, whichever of them was the stronger in either image
    assert matched_angle_error_deg([112.0, 70.0], [68.0, 110.0]) == 2.0
    assert matched_angle_error_deg([179.0, 60.0], [1.0, 64.0]) == 3.0  # period 180
    assert matched_angle_error_deg([90.0], [68.0, 110.0]) == 22.0  # one predicted: the strongest true
    assert matched_angle_error_deg([], [90.0]) is None and matched_angle_error_deg([90.0], []) is None


def test_residual_streak_angle_reads_the_brighter_part_of_a_residual():
    """Rain adds light: streaks at 75 degrees in the brighter part of a residual are found
    through dark detail at 20 degrees that the render overshot; an empty residual has none."""
    g = torch.Generator().manual_seed(4)
    bright = streak_layer(64, 75.0, 25, g)
    dark = streak_layer(64, 20.0, 40, g)
    residual = (bright - dark).expand(2, 3, 64, 64).clone()
    residual[1] = 0.0
    angle, valid = residual_streak_angle(residual)
    assert valid.tolist() == [True, False]
    assert angle_difference_deg(math.degrees(float(angle[0])), 75.0) <= 3.0


def _streaks_under_a_roofline(seed: int) -> torch.Tensor:
    """Rain at 80 degrees under stronger horizontal scene edges (a roof, steps): the edges
    own the histogram's highest peak."""
    g = torch.Generator().manual_seed(seed)
    image = streak_layer(64, 80.0, 12, g)
    image[..., 2::6, :] += 0.8
    return image.expand(1, 3, 64, 64)


@pytest.mark.parametrize("seed", [0, 1])
def test_the_fall_prior_keeps_scene_edges_across_the_fall_out(seed):
    image = _streaks_under_a_roofline(seed)
    free, _ = estimate_rain_angles(image)
    assert angle_difference_deg(math.degrees(float(streak_angle(free)[0, 0])), 0.0) <= 3.0  # the edges
    down = torch.tensor([math.pi / 2])  # an upright camera: the world's down runs down the image
    theta, valid = estimate_rain_angles(image, down=down, max_tilt=45.0)
    assert valid.all()
    assert angle_difference_deg(math.degrees(float(streak_angle(theta)[0, 0])), 80.0) <= 3.0
    # a camera rolled by 90 degrees sees the fall along the image's x axis: the edges are rain-like
    rolled, _ = estimate_rain_angles(image, down=torch.tensor([0.0]), max_tilt=45.0)
    assert angle_difference_deg(math.degrees(float(streak_angle(rolled)[0, 0])), 0.0) <= 3.0
    # 90 degrees: every direction, the paper's estimator
    assert torch.equal(estimate_rain_angles(image, down=down, max_tilt=90.0)[0], free)


def test_fall_mask_by_hand():
    # 6 bins of 30 degrees: gradient bins centred at 15, 45, ... 165 -> streaks at 105, 135, 165, 15, 45, 75
    mask = fall_mask(torch.tensor([math.pi / 2, math.radians(170.0)]), 6, 40.0)
    assert mask.tolist() == [[True, False, False, False, False, True],
                             [False, True, True, True, False, False]]
