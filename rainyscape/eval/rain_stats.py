"""Rain statistics of a view: the streak directions of predicted rain and of the residual I - B
(measured as the run's AGR loss measures them), the true rain's (from the directions the
simulator let it fall in, where the scene records them), and how well the predicted rain layer
correlates with the true one."""

from __future__ import annotations

import math

import torch
from torch import Tensor

from rainyscape.cameras import Cameras, down_directions, line_directions
from rainyscape.components import MeasuresRainAngles
from rainyscape.engine.pipeline import Pipeline
from rainyscape.eval.metric_keys import (ANGLE_ERROR, CORRELATION, RAIN_ANGLE, RAIN_ANGLES, RESIDUAL_ANGLE,
                                         TRUE_ANGLE, TRUE_ANGLES, rain_stat)
from rainyscape.eval.views import ViewImages
from rainyscape.imaging.angles import (estimate_rain_angles, matched_angle_error_deg, streak_angle,
                                       weighted_mean_angle_deg)
from rainyscape.scene import SceneData


def angle_options(pipeline: Pipeline) -> dict:
    """The angle settings of the run's term that measures rain angles (the AGR loss: its
    histogram and ``k``, its rain directions per image, with ``down``: where the world's down
    runs in each view), so evaluation measures angles as training did; {} (the estimator's
    defaults) when no term measures them. :func:`view_options` picks a view's."""
    for _, term in pipeline.losses.values():
        if isinstance(term, MeasuresRainAngles):
            settings = term.angle_settings()
            if settings.get("max_tilt", 90.0) < 90.0:
                settings["down"] = down_directions(pipeline.scene.cameras)
            return settings
    return {}


def view_options(options: dict, index: int) -> dict:
    """``options`` (:func:`angle_options`) for view ``index``'s images: its own down direction."""
    if "down" not in options:
        return options
    return {**options, "down": options["down"][index:index + 1]}


def true_rain_directions(pipeline: Pipeline) -> int:
    """How many directions the scene's true rain falls in (the simulator records it; 1 when
    unknown)."""
    return int(pipeline.scene.metadata.get("rain_directions", 1))


def true_rain_falls(scene: SceneData) -> Tensor | None:
    """(K, 3) directions the true rain falls along in the scene's normalised world (the
    simulator's ``rain_falls``), or None when the scene does not record them."""
    falls = scene.metadata.get("rain_falls")
    if not falls:
        return None
    return torch.tensor(falls, dtype=torch.float64) @ scene.transform[:3, :3].double().T


def fall_angles_deg(cameras: Cameras, falls: Tensor, true_rain: Tensor) -> list[float]:
    """The true streak direction of each fall direction in ``falls`` (K, 3) in the one view of
    ``cameras``: the direction a drop falling that way runs through each pixel, averaged over
    the pixels weighted by the true rain there ``true_rain`` (3, H, W). Exact where the
    estimator on the true rain layer is not: on the cpu set's short, sparse streaks the
    layer's orientation histogram is 4 to 7 degrees off on average, 30 to 45 in some views
    (docs/rain.md, "The true rain's angle from the simulator's geometry, ...")."""
    weights = true_rain.abs().sum(0).cpu()
    out = []
    for fall in falls:
        mean = weighted_mean_angle_deg(line_directions(cameras, fall)[0].cpu(), weights)
        if mean is not None:
            out.append(mean)
    return out


def streak_angles_deg(image: Tensor, options: dict) -> list[float]:
    """Directions the dominant streaks run along (``options["k"]`` of them, strongest first),
    degrees in [0, 180) from the image +x axis towards +y (down), estimated as the AGR loss
    does; empty if the image has no edges."""
    theta, valid = estimate_rain_angles(image[None], **{"k": 1, **options})
    return [math.degrees(float(streak_angle(t))) for t, ok in zip(theta[0], valid[0]) if bool(ok)]


def streak_angle_deg(image: Tensor, options: dict) -> float | None:
    """The dominant streak direction (see :func:`streak_angles_deg`), or None."""
    angles = streak_angles_deg(image, {**options, "k": 1})
    return angles[0] if angles else None


def correlation(a: Tensor, b: Tensor) -> float | None:
    """Pearson correlation of two images' grey levels (None when either is constant)."""
    x, y = a.double().mean(0).flatten(), b.double().mean(0).flatten()
    x, y = x - x.mean(), y - y.mean()
    den = float(x.norm() * y.norm())
    return float((x * y).sum()) / den if den > 0 else None


def view_rain_stats(v: ViewImages, options: dict, true_directions: int = 1,
                    falls: tuple[Cameras, Tensor] | None = None) -> dict:
    """The rain keys of a view's metrics row (empty for views without predicted or true rain).
    ``true_directions``: how many directions the true rain falls in (the simulator records it);
    with two, the predicted rain's two strongest are matched to the true rain's two. ``falls``:
    the view's camera and the directions the rain falls along (:func:`true_rain_falls`), for
    the true angles; without them the true rain layer's own histogram estimates them."""
    row: dict = {}
    truth = None
    options = view_options(options, v.index)
    if v.true_rain is not None and v.split == "train":
        if falls is not None:
            truth = fall_angles_deg(falls[0], falls[1], v.true_rain)
        else:
            truth = streak_angles_deg(v.true_rain, {**options, "k": max(1, true_directions)})
        row[rain_stat(TRUE_ANGLE).key] = truth[0] if truth else None
        if len(truth) > 1:
            row[rain_stat(TRUE_ANGLES).key] = truth
    if v.rain is not None:
        k = options.get("k", 1)
        # strongest first; as many as the AGR term uses or the true rain has (the first k of
        # them are the k strongest: the histogram's peaks are ranked)
        predicted = streak_angles_deg(v.rain, {**options, "k": max(len(truth or ()), k)})
        angles = predicted[:k]
        row[rain_stat(RAIN_ANGLE).key] = angles[0] if angles else None
        if k > 1:  # multi-direction rain: every direction the AGR term uses
            row[rain_stat(RAIN_ANGLES).key] = angles
        row[rain_stat(RESIDUAL_ANGLE).key] = streak_angle_deg(v.rainy - v.rendered, options)
        if v.true_rain is not None:
            row[rain_stat(CORRELATION).key] = correlation(v.rain, v.true_rain)
        if truth:
            row[rain_stat(ANGLE_ERROR).key] = matched_angle_error_deg(predicted, truth)
    return row
