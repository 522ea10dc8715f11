"""The true rain's streak angles from the directions the simulator let the drops fall in, and the
structure-tensor orientation estimator that reads thin, short streaks without the pixel grid's
pull."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from rainyscape.cameras import Cameras, line_directions
from rainyscape.eval.rain_stats import fall_angles_deg, true_rain_falls
from rainyscape.imaging.angles import (angle_difference_deg, estimate_rain_angles, streak_angle,
                                       weighted_mean_angle_deg)
from rainyscape.synth.rain import DropField
from rainyscape.testing.streaks import streak_layer


def _median_disagreement(scene, estimator: str) -> float:
    """Median over views of the angle between the geometric truth and the orientation
    histogram of the scene's own true rain layer."""
    layers = scene.rain_layers.permute(0, 3, 1, 2).float()
    theta, valid = estimate_rain_angles(layers.abs(), estimator=estimator)
    found = torch.rad2deg(streak_angle(theta[:, 0]))
    falls = true_rain_falls(scene)
    out = [angle_difference_deg(fall_angles_deg(scene.cameras[i], falls, layers[i])[0], float(found[i]))
           for i in range(scene.num_images) if bool(valid[i, 0])]
    assert len(out) >= scene.num_images // 2
    return float(np.median(out))


def test_a_lines_image_runs_where_its_projection_moves():
    """At a pixel, the line direction is where the projection of a point on that pixel's ray
    moves when the point steps along the 3D direction, for any rotation and depth."""
    gen = torch.Generator().manual_seed(1)
    q, _ = torch.linalg.qr(torch.randn(3, 3, generator=gen, dtype=torch.float64))
    c2w = torch.eye(4, dtype=torch.float64)
    c2w[:3, :3] = q * torch.sign(torch.det(q))
    c2w[:3, 3] = torch.tensor([0.3, -0.2, 0.5])
    cams = Cameras(c2w[None].float(), torch.tensor([40.0]), torch.tensor([44.0]), torch.tensor([17.0]),
                   torch.tensor([13.0]), 36, 28)
    direction = torch.tensor([0.3, -0.9, 0.2], dtype=torch.float64)
    angles = line_directions(cams, direction / direction.norm())[0]
    for u, v, depth in ((3, 4, 2.0), (30, 20, 0.7), (17, 13, 5.0)):
        ray = torch.tensor([(u + 0.5 - 17.0) / 40.0, (v + 0.5 - 13.0) / 44.0, 1.0], dtype=torch.float64)
        point = c2w[:3, :3] @ (depth * ray) + c2w[:3, 3]
        uv, _ = cams.project(torch.stack([point, point + 1e-3 * direction]).float())
        step = (uv[0, 1] - uv[0, 0]).double()
        moved = math.degrees(math.atan2(step[1], step[0])) % 180.0
        assert angle_difference_deg(moved, math.degrees(float(angles[v, u]))) < 0.5


def test_a_weighted_mean_of_angles_wraps_and_follows_its_weights():
    theta = torch.deg2rad(torch.tensor([178.0, 4.0]))
    assert angle_difference_deg(weighted_mean_angle_deg(theta, torch.ones(2)), 1.0) < 1e-4
    assert angle_difference_deg(weighted_mean_angle_deg(theta, torch.tensor([1.0, 0.0])), 178.0) < 1e-4
    assert weighted_mean_angle_deg(theta, torch.zeros(2)) is None


def test_the_drops_fall_along_the_mean_of_their_own_directions_per_wind():
    """Two winds, each direction the normalised mean of its drops' unit velocities: a slow drop
    leans further than the wind's angle of a fast one, and counts as much."""
    vel = np.array([[1.0, -1.0, 0.0], [0.0, -2.0, 0.0], [0.0, -1.0, 1.0]])
    field = DropField(np.zeros((3, 3)), vel, np.full(3, 1e-3), np.ones(3), np.zeros(3), np.ones(3),
                      wind=np.array([0, 0, 1]))
    falls = field.fall_directions()
    first = np.array([math.sqrt(0.5), -math.sqrt(0.5) - 1.0, 0.0])
    assert np.allclose(falls[0], first / np.linalg.norm(first))
    assert np.allclose(falls[1], [0.0, -math.sqrt(0.5), math.sqrt(0.5)])


def test_the_true_angles_come_from_the_simulators_fall(tiny_scene):
    """rs-synth records where its drops fall; the per-view angle from it agrees with the true rain
    layer's own streaks, read either way (the tiny scene's streaks are long)."""
    falls = true_rain_falls(tiny_scene)
    assert falls is not None and falls.shape == (1, 3) and float(falls[0, 1]) < -0.8
    assert _median_disagreement(tiny_scene, "structure") < 6.0
    assert _median_disagreement(tiny_scene, "gradient") < 6.0


def test_a_rainy_captures_fall_is_recorded_in_its_own_world(tiny_scene, tmp_path):
    """capture-rain records the drops' fall in the capture's frame (out of its rain frame), so
    a parsed rainy capture's true angles agree with its rain layer's streaks."""
    from dataclasses import replace

    from rainyscape.dataparsers.transforms_json import TransformsJsonConfig, TransformsJsonParser
    from rainyscape.synth.capture_rain import CaptureRain, add_rain

    capture = replace(tiny_scene, images=tiny_scene.clean_images, clean_images=None, rain_layers=None,
                      depths=None, points=None, point_colors=None)
    out = add_rain(capture, tmp_path / "r", CaptureRain(level="heavy", mode="static"))
    scene = TransformsJsonParser(TransformsJsonConfig()).parse(out)
    assert true_rain_falls(scene) is not None
    assert _median_disagreement(scene, "structure") < 6.0


@pytest.mark.parametrize("angle", [35.0, 70.0, 100.0, 120.0])
def test_the_structure_tensor_reads_short_streaks_among_speckles(angle):
    """Streaks 4 px long, under a pixel wide, among isolated bright pixels: each pixel's own
    gradient leans to the grid's axes and diagonals; the pooled structure tensor does not."""
    gen = torch.Generator().manual_seed(int(angle))
    rain = streak_layer(96, angle, 40, gen, length=4.0, width=0.6)
    rain = rain + 0.15 * (torch.rand(1, 1, 96, 96, generator=gen) > 0.97).float()
    theta, valid = estimate_rain_angles(rain, estimator="structure")
    assert bool(valid[0, 0])
    assert angle_difference_deg(math.degrees(float(streak_angle(theta[0, 0]))), angle) <= 3.0



def test_an_unknown_estimator_is_refused_by_name():
    from rainyscape.errors import ConfigError
    from rainyscape.losses.agr import AdaptiveGradientRotation

    with pytest.raises(ConfigError, match="agr.estimator 'hough'"):
        AdaptiveGradientRotation(AdaptiveGradientRotation.Config(estimator="hough"))
    with pytest.raises(ValueError, match="hough"):
        estimate_rain_angles(torch.zeros(1, 1, 8, 8), estimator="hough")
