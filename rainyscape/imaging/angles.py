"""Rain-angle estimation from the orientation histogram of a residual image (paper III-C).

The residual I - B of a rainy image minus a smooth render holds rain streaks and scene
detail. Scene detail has edges in all orientations; rain streaks share one (or a few)
orientations, so after dropping weak gradients the histogram of gradient orientations
peaks ACROSS the streaks. The returned angle theta is that gradient direction (radians
in [0, pi), from the image +x axis towards +y, i.e. downwards); the streaks themselves run
along theta + pi / 2 (see :func:`streak_angle`).
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor

from rainyscape.imaging.gradients import gradient_orientation, structure_orientation


# How a histogram counts orientations: "gradient" one vote per pixel of its own 3x3 gradient
# (the paper's); "structure" the structure tensor's direction weighted by its coherent strength
# (imaging/gradients.py: structure_orientation)
ORIENTATION_ESTIMATORS = ("gradient", "structure")


def orientation_histogram(residual: Tensor, bins: int = 60, threshold: float = 0.1,
                          kernel: str = "scharr", estimator: str = "gradient",
                          sigma: float = 2.0) -> Tensor:
    """Per-image histograms (B, bins) of gradient orientations over [0, pi).

    ``residual``: (B, C, h, w). Pixels whose raw gradient magnitude (Sobel gain, grey levels
    in [0, 1]) is at most ``threshold`` are ignored (0.1 is about a 0.025 grey-level step).
    ``estimator`` "gradient" counts each pixel's own gradient direction; "structure" adds each
    pixel's structure-tensor direction (pooled over ``sigma`` px) with its coherent strength,
    which a thin streak's pixels share and isolated pixels and tips do not.
    """
    orientation, weight, magnitude = pixel_orientations(residual, kernel, estimator, sigma)
    b = orientation.shape[0]
    index = (orientation / math.pi * bins).long().clamp_(0, bins - 1)
    keep = weight * (magnitude > threshold).to(orientation.dtype)
    hist = torch.zeros(b, bins, dtype=orientation.dtype, device=orientation.device)
    return hist.scatter_add_(1, index.reshape(b, -1), keep.reshape(b, -1))


def pixel_orientations(images: Tensor, kernel: str = "scharr", estimator: str = "gradient",
                       sigma: float = 2.0) -> tuple[Tensor, Tensor, Tensor]:
    """Each pixel's orientation in [0, pi), the weight its vote carries and its gradient
    magnitude, each (B, h-2, w-2), as ``estimator`` reads them (see :func:`orientation_histogram`)."""
    if estimator == "gradient":
        orientation, magnitude = gradient_orientation(images, kernel)
        return orientation, torch.ones_like(magnitude), magnitude
    if estimator == "structure":
        return structure_orientation(images, kernel, sigma)
    raise ValueError(f"unknown orientation estimator '{estimator}'; choose one of {ORIENTATION_ESTIMATORS}")


def smooth_histogram(hist: Tensor, passes: int) -> Tensor:
    """``passes`` circular [1, 2, 1] / 4 smoothings: steadier peaks, same bin width."""
    for _ in range(passes):
        hist = 0.25 * hist.roll(1, 1) + 0.5 * hist + 0.25 * hist.roll(-1, 1)
    return hist


def histogram_peaks(hist: Tensor, k: int = 1, separation: int = 2) -> tuple[Tensor, Tensor]:
    """The ``k`` largest local maxima of circular histograms (B, bins).

    A bin is a peak when it is the largest within ``separation`` bins on either side
    (orientations wrap around at pi), so K = 2 finds a second rain direction rather than
    the shoulder of the first. Returns (bin indices (B, k), valid (B, k)); a slot is invalid
    when the histogram has fewer than k non-empty peaks.
    """
    b, n = hist.shape
    # Tiny decreasing offsets break ties (the lower bin wins, so a plateau has one peak).
    scale = hist.amax(1, keepdim=True).clamp_min(1e-12)
    ranked = hist - torch.arange(n, device=hist.device, dtype=hist.dtype) * (1e-6 * scale / n)
    width = min(separation, (n - 1) // 2)
    padded = torch.cat([ranked[:, n - width:], ranked, ranked[:, :width]], 1) if width else ranked
    local_max = F.max_pool1d(padded[:, None], 2 * width + 1, stride=1)[:, 0]
    is_peak = (ranked >= local_max) & (hist > 0)
    score = torch.where(is_peak, ranked, torch.full_like(ranked, -1.0))
    top, index = score.topk(min(k, n), dim=1)
    return index, top >= 0


def bin_centers(index: Tensor, bins: int) -> Tensor:
    """Bin index -> the angle (radians) at the centre of the bin.

    (The authors' code fed the bin index itself to cos / sin as radians; this is the fix.)
    """
    return (index.to(torch.float32) + 0.5) * (math.pi / bins)


def fall_mask(down: Tensor, bins: int, max_tilt: float) -> Tensor:
    """Which histogram bins (B, bins) hold streaks that run within ``max_tilt`` degrees of each
    image's ``down`` (B,) (radians, the direction the world's down runs in the image): rain
    falls, so its streaks lean from the vertical only by the wind (and perspective)."""
    streaks = streak_angle(bin_centers(torch.arange(bins, device=down.device), bins))
    tilt = torch.remainder(streaks[None] - down[:, None] + math.pi / 2, math.pi) - math.pi / 2
    return tilt.abs() <= math.radians(max_tilt)


def estimate_rain_angles(residual: Tensor, bins: int = 60, k: int = 1, threshold: float = 0.1,
                         smoothing: int = 2, separation: int = 2, kernel: str = "scharr",
                         down: Tensor | None = None, max_tilt: float = 90.0,
                         estimator: str = "gradient") -> tuple[Tensor, Tensor]:
    """Dominant gradient directions theta (B, k) in radians of residual images (B, C, h, w).

    ``smoothing`` [1, 2, 1] passes over the histogram before picking peaks (0: raw counts as
    in the paper). With ``down`` (B,) (radians: where the world's down runs in each image,
    :func:`rainyscape.cameras.down_directions`) and ``max_tilt`` under 90 degrees, only
    directions whose streaks lean at most ``max_tilt`` from it are candidates (scene edges
    across the fall, a horizon or a roof, cannot win). ``estimator``: how the histogram counts
    (:func:`orientation_histogram`). Returns (theta, valid); ``valid`` is False where an image
    had no gradient above ``threshold`` (or fewer than k distinct peaks).
    """
    hist = smooth_histogram(orientation_histogram(residual, bins, threshold, kernel, estimator), smoothing)
    if down is not None and max_tilt < 90.0:
        hist = hist * fall_mask(down.to(hist.device), bins, max_tilt)
    index, valid = histogram_peaks(hist, k, separation)
    return bin_centers(index, bins).to(residual.device), valid


def streak_angle(theta: Tensor) -> Tensor:
    """Direction the streaks run along (radians in [0, pi)) for gradient direction theta."""
    return torch.remainder(theta + math.pi / 2, math.pi)


def residual_streak_angle(residual: Tensor, down: Tensor | None = None,
                          max_tilt: float = 90.0) -> tuple[Tensor, Tensor]:
    """The streak direction (B,) of residual images I - B (B, C, h, w), from their brighter
    part (rain adds light), and whether one was found (B,); ``down``, ``max_tilt``: as
    :func:`estimate_rain_angles`."""
    theta, valid = estimate_rain_angles(residual.clamp_min(0), down=down, max_tilt=max_tilt)
    return streak_angle(theta[:, 0]), valid[:, 0]


def angle_difference_deg(a: float, b: float) -> float:
    """Smallest difference of two undirected angles in degrees (period 180)."""
    d = abs(a - b) % 180.0
    return min(d, 180.0 - d)


def matched_angle_error_deg(predicted: list[float], true: list[float]) -> float | None:
    """Mean error of each true streak direction against the predicted one paired with it
    (degrees, period 180), over the pairing that fits best; None when either list is empty.

    With one true direction only the strongest predicted one counts; with two (rain in two
    directions of about equal strength), which of them is the dominant one is a coin flip
    per view, so both are matched."""
    if not predicted or not true:
        return None
    if len(true) == 1 or len(predicted) == 1:
        return angle_difference_deg(predicted[0], true[0])
    a, b = true[:2]
    p, q = predicted[:2]
    return min(angle_difference_deg(a, p) + angle_difference_deg(b, q),
               angle_difference_deg(a, q) + angle_difference_deg(b, p)) / 2


def mean_angle_deg(angles: list[float]) -> float | None:
    """Circular mean of undirected angles in degrees (period 180): average the doubled angles."""
    if not angles:
        return None
    theta = torch.deg2rad(torch.tensor(angles, dtype=torch.float64))
    return weighted_mean_angle_deg(theta, torch.ones_like(theta))


def weighted_mean_angle_deg(theta: Tensor, weights: Tensor) -> float | None:
    """Circular mean in degrees [0, 180) of undirected angles ``theta`` (radians) weighted by
    ``weights`` (same shape, >= 0); None when the weights sum to zero."""
    w = weights.double()
    if float(w.sum()) <= 0:
        return None
    s = float((w * torch.sin(2 * theta.double())).sum())
    c = float((w * torch.cos(2 * theta.double())).sum())
    return math.degrees(math.atan2(s, c)) / 2 % 180.0
