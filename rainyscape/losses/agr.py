"""Adaptive gradient rotation (AGR) loss of the paper (III-D).

Per patch, the dominant gradient directions theta_k of the residual I - B (detached) are
estimated (:mod:`rainyscape.imaging.angles`); theta points ACROSS the rain streaks. Then

    L = 1/K sum_k  mean|D_{theta_k + pi/2} R| - mean|D_{theta_k} R|
                   + w (mean|D_{theta_k} B| + mean|D_{theta_k} (I - R)|)

with D_phi = cos(phi) d/dx + sin(phi) d/dy (steered derivatives, no image rotation), in
grey levels per pixel: rain should vary across its streaks and little along them, while
the background and the de-rained input should not vary across the streaks. The paper's
equation has w = 1; the authors' code used w = 0.5.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from rainyscape.cameras import down_directions
from rainyscape.components import Loss, LossContext
from rainyscape.config.schema import bounded, choice
from rainyscape.errors import ConfigError
from rainyscape.imaging.gradients import GRADIENT_KERNELS, image_gradients, steer
from rainyscape.imaging.angles import ORIENTATION_ESTIMATORS, estimate_rain_angles, streak_angle
from rainyscape.scene import SceneData

AGR_DIRECTIONS = ("batch", "view")


def mean_abs_derivative(images: Tensor, theta: Tensor, kernel: str = "scharr", gain: float = 1.0) -> Tensor:
    """mean |D_theta images| for every image and direction: (B, C, h, w), (B, K) -> (B, K).

    ``gain`` 1 keeps the 3x3 kernel's Sobel gain (a unit step gives 4), the units of the
    angle threshold; 1/8 gives grey levels per pixel."""
    gx, gy = image_gradients(images, kernel)
    d = steer(gx.unsqueeze(1), gy.unsqueeze(1), theta) * gain  # (B, K, C, h-2, w-2)
    return d.abs().mean(dim=(2, 3, 4))


def agr_loss(rendered: Tensor, target: Tensor, rain: Tensor, theta: Tensor, valid: Tensor,
             background_weight: float = 0.5, kernel: str = "scharr", gain: float = 1.0) -> Tensor:
    """The AGR loss for directions ``theta`` (B, K) (gradient directions, across streaks),
    averaged over the valid (image, direction) pairs; 0 when none is valid."""
    across = mean_abs_derivative(rain, theta, kernel, gain)
    along = mean_abs_derivative(rain, theta + math.pi / 2, kernel, gain)
    scene = (mean_abs_derivative(rendered, theta, kernel, gain)
             + mean_abs_derivative(target - rain, theta, kernel, gain))
    per_direction = along - across + background_weight * scene  # (B, K)
    weights = valid.to(per_direction.dtype)
    return (per_direction * weights).sum() / weights.sum().clamp_min(1.0)


class AdaptiveGradientRotation(Loss):
    """Adaptive gradient rotation: rain varies across its estimated direction, the scene does not."""

    description = "agr: adaptive gradient rotation loss along the estimated rain direction(s)"
    phases = ("joint",)
    spatial = True
    needs = ("rain",)

    @dataclass
    class Config:
        bins: int = 60  # orientation histogram bins over [0, 180) degrees (3 degrees each)
        top_k: int = 1  # rain directions per patch (2 or more for multi-direction rain)
        threshold: float = 0.1  # gradients at most this (Sobel gain, grey levels) are ignored
        smoothing: int = 2  # [1, 2, 1] passes over the histogram before peak picking (0: raw)
        background_weight: float = 0.5  # w above: 0.5 as the authors' code, 1 as the paper's equation
        kernel: str = "scharr"  # derivative kernel: scharr | sobel
        # derivative scale: 1 the kernel's Sobel gain (the paper's operator; measured: rain angle
        # error 6.0 vs 8.5 degrees at 1/8, docs/rain.md), 1/8 per pixel (the earlier default)
        gain: float = 1.0
        # directions whose streaks lean more than this (degrees) from the world's down in the
        # view are no candidates (rain falls; the world's down as the level cameras see it,
        # rainyscape.cameras.down_directions); 90: any direction, as the paper
        max_tilt: float = bounded(90.0, above=0.0, hi=90.0)
        # how the orientation histogram counts: gradient (each pixel's 3x3 gradient, the paper's)
        # | structure (the structure tensor's direction pooled over 2 px, weighted by its coherence)
        estimator: str = choice("gradient", ORIENTATION_ESTIMATORS)
        # where the direction comes from: batch (each batch's own residual, as the paper) | view
        # (a batch of whole views keeps each view's; a batch of patches or crops takes its views'
        # kept directions, estimating only for a view that has none yet: a 4 x 4 patch's few
        # gradients are mostly the scene's edges)
        directions: str = choice("batch", AGR_DIRECTIONS)
        # the direction is read off the residual only where the head's R (channel mean) exceeds
        # this, so that scene edges the field has not fitted are no rain; an image where R
        # exceeds it nowhere is read whole (0: everywhere, as the paper)
        where_rain: float = bounded(0.0, lo=0.0, hi=1.0)

    def __init__(self, config: "AdaptiveGradientRotation.Config | None" = None):
        super().__init__(config or self.Config())
        c = self.config
        if c.bins < 3:
            raise ConfigError(f"agr.bins must be at least 3, got {c.bins}")
        if c.top_k < 1:
            raise ConfigError(f"agr.top_k must be at least 1, got {c.top_k}")
        if c.estimator not in ORIENTATION_ESTIMATORS:
            raise ConfigError(f"agr.estimator '{c.estimator}' is not one of {', '.join(ORIENTATION_ESTIMATORS)}")
        if c.directions not in AGR_DIRECTIONS:
            raise ConfigError(f"agr.directions '{c.directions}' is not one of {', '.join(AGR_DIRECTIONS)}")
        if c.kernel not in GRADIENT_KERNELS:
            raise ConfigError(f"agr.kernel '{c.kernel}' is not one of {', '.join(GRADIENT_KERNELS)}")
        # Last estimated streak direction(s) in degrees, per view id (for reports).
        self.view_angles: dict[int, list[float]] = {}
        self.down: Tensor | None = None  # per view: where the world's down runs in it (radians)
        # directions="view": each view's directions (N, K) from its last whole-view batch, and
        # whether each was found; ``found`` (N,), on the CPU, whether any was, so that a patch
        # batch reads it without waiting for the device; the image size tells a whole view
        self.kept: tuple[Tensor, Tensor] | None = None
        self.found = torch.zeros(0, dtype=torch.bool)
        self.image_size = (0, 0)

    def setup(self, scene: SceneData, device: torch.device) -> None:
        if self.config.max_tilt < 90.0:
            self.down = down_directions(scene.cameras).to(device)
        if self.config.directions == "view":
            n, k = len(scene.cameras), int(self.config.top_k)
            self.kept = (torch.zeros(n, k, device=device), torch.zeros(n, k, dtype=torch.bool, device=device))
            self.found = torch.zeros(n, dtype=torch.bool)
            self.image_size = (scene.cameras.width, scene.cameras.height)

    def angle_settings(self) -> dict:
        """:class:`rainyscape.components.MeasuresRainAngles`: how this term measures angles."""
        c = self.config
        return {"bins": c.bins, "threshold": c.threshold, "smoothing": c.smoothing, "kernel": c.kernel,
                "k": int(c.top_k), "max_tilt": c.max_tilt, "estimator": c.estimator}

    def estimate(self, ctx: LossContext) -> tuple[Tensor, Tensor]:
        """Gradient directions theta (B, K) of the detached residual I - B, and validity."""
        residual = (ctx.target - ctx.rendered).detach()
        down = None if self.down is None else self.down[ctx.view_ids.to(self.down.device)]
        if self.config.where_rain > 0 and ctx.rain is not None:
            seen = ctx.rain.detach().mean(dim=1, keepdim=True) > self.config.where_rain
            seen = seen | ~seen.flatten(1).any(dim=1)[:, None, None, None]  # no rain seen: everywhere
            residual = residual * seen
        return estimate_rain_angles(residual, down=down, **self.angle_settings())

    def directions_for(self, ctx: LossContext) -> tuple[Tensor, Tensor]:
        """theta (B, K) and validity for the batch (see ``Config.directions``)."""
        if self.kept is None:
            return self.estimate(ctx)
        theta_kept, valid_kept = self.kept
        views = ctx.view_ids.cpu()
        if ctx.window is None or (ctx.window.width, ctx.window.height) == self.image_size:  # whole views
            theta, valid = self.estimate(ctx)
            rows = views.to(theta_kept.device)
            theta_kept[rows], valid_kept[rows] = theta.to(theta_kept.device), valid.to(valid_kept.device)
            self.found[views] = valid.any(dim=1).cpu()
            return theta, valid
        device = ctx.rendered.device
        rows = views.to(theta_kept.device)
        view_theta, view_valid = theta_kept[rows].to(device), valid_kept[rows].to(device)
        found = self.found[views]
        if bool(found.all()):
            return view_theta, view_valid
        theta, valid = self.estimate(ctx)
        found = found.to(device)[:, None]
        return torch.where(found, view_theta, theta), torch.where(found, view_valid, valid)

    def __call__(self, ctx: LossContext) -> Tensor:
        rain = ctx.rain if ctx.rain is not None else torch.zeros_like(ctx.rendered)
        theta, valid = ctx.memoized((id(self), "angles"), lambda: self.directions_for(ctx))
        if ctx.record:  # the network update's angles, not a latent update's crop
            self._record(ctx.view_ids, theta, valid)
        return agr_loss(ctx.rendered, ctx.target, rain, theta, valid,
                        self.config.background_weight, self.config.kernel, self.config.gain)

    def _record(self, view_ids: Tensor, theta: Tensor, valid: Tensor) -> None:
        streaks = torch.rad2deg(streak_angle(theta)).tolist()
        self.metrics = {}
        for vid, angles, ok in zip(view_ids.tolist(), streaks, valid.tolist()):
            kept = [round(a, 2) for a, v in zip(angles, ok) if v]
            if not kept:
                continue
            self.view_angles[int(vid)] = kept
            for j, angle in enumerate(kept):
                suffix = "" if j == 0 else str(j + 1)
                self.metrics[f"streak{suffix}_deg/view{int(vid)}"] = angle

    def state_dict(self) -> dict:
        state = {"view_angles": {str(k): v for k, v in self.view_angles.items()}}
        if self.kept is not None:
            state["kept"] = [t.tolist() for t in self.kept]
        return state

    def load_state_dict(self, state: dict) -> None:
        self.view_angles = {int(k): list(v) for k, v in state.get("view_angles", {}).items()}
        if self.kept is not None and "kept" in state:
            theta, valid = self.kept
            self.kept = (torch.tensor(state["kept"][0], dtype=theta.dtype, device=theta.device),
                         torch.tensor(state["kept"][1], dtype=torch.bool, device=valid.device))
            self.found = self.kept[1].any(dim=1).cpu()
