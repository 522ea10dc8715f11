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

import dataclasses
import math
from dataclasses import dataclass

import torch
from torch import Tensor

from rainyscape.cameras import down_directions, level_up, line_directions
from rainyscape.components import Loss, LossContext
from rainyscape.config.schema import bounded, choice
from rainyscape.errors import ConfigError
from rainyscape.imaging.gradients import GRADIENT_KERNELS, image_gradients, steer
from rainyscape.imaging.angles import ORIENTATION_ESTIMATORS, estimate_rain_angles, streak_angle, weighted_mean_angle_deg
from rainyscape.losses.fall import GradientSamples, fit_fall_direction, gradient_samples, tilt_deg
from rainyscape.scene import SceneData

AGR_DIRECTIONS = ("batch", "view", "world")


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
        # gradients are mostly the scene's edges) | world (one 3D fall direction, losses/fall.py,
        # steering every pixel by its own streak direction: the world's down until two fits in
        # a row to the whole views' residual gradients agree)
        directions: str = choice("batch", AGR_DIRECTIONS)
        # directions=world: the fall leans less than this from the world's down (degrees: a fit
        # at the bound is no fit), is refitted after every fall_refit whole views from
        # fall_samples gradients a view, and taken when within fall_agree of the fit before
        fall_max_tilt: float = bounded(60.0, 0.0, 89.0)
        fall_refit: int = bounded(25, 1)
        fall_samples: int = bounded(512, 1)
        fall_agree: float = bounded(2.0, 0.0)
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
        # directions="world": the cameras, each view's latest gradient samples and rain mask, the
        # fall (3,) steered by and its streak direction at every pixel of every view (N, H, W),
        # the last fit (not yet agreed with) and whole views since it
        self.cameras = None
        self.fit_cameras = None
        self.world_down: Tensor | None = None
        self.samples: dict[int, GradientSamples] = {}
        self.masks: dict[int, Tensor] = {}
        self.fall: Tensor | None = None
        self.streaks: Tensor | None = None
        self.last_fit: Tensor | None = None
        self.unfitted_views = 0
        self.generator = torch.Generator().manual_seed(0)

    def setup(self, scene: SceneData, device: torch.device) -> None:
        if self.config.max_tilt < 90.0:
            self.down = down_directions(scene.cameras).to(device)
        if self.config.directions == "world":
            if self.config.top_k != 1:
                raise ConfigError(f"agr.directions=world fits one fall direction; agr.top_k must be 1, got {self.config.top_k}")
            self.cameras = scene.cameras.to(device)
            self.fit_cameras = scene.cameras.to("cpu")  # the fit runs on the CPU
            self.world_down = -level_up(self.fit_cameras.c2w)
            self.image_size = (scene.cameras.width, scene.cameras.height)
            self.set_fall(self.world_down)
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

    def rain_residual(self, ctx: LossContext) -> tuple[Tensor, Tensor]:
        """The detached residual I - B where the head sees rain (``where_rain``), and that mask
        (B, 1, h, w); everywhere when the gate is off or the head sees no rain in an image."""
        residual = (ctx.target - ctx.rendered).detach()
        seen = torch.ones_like(residual[:, :1], dtype=torch.bool)
        if self.config.where_rain > 0 and ctx.rain is not None:
            seen = ctx.rain.detach().mean(dim=1, keepdim=True) > self.config.where_rain
            seen = seen | ~seen.flatten(1).any(dim=1)[:, None, None, None]  # no rain seen: everywhere
            residual = residual * seen
        return residual, seen

    def estimate(self, ctx: LossContext) -> tuple[Tensor, Tensor]:
        """Gradient directions theta (B, K) of the detached residual I - B, and validity."""
        down = None if self.down is None else self.down[ctx.view_ids.to(self.down.device)]
        return estimate_rain_angles(self.rain_residual(ctx)[0], down=down, **self.angle_settings())

    def observe_fall(self, ctx: LossContext) -> None:
        """directions=world, a batch of whole views: keep each view's gradient samples and rain
        mask, and refit the fall after every ``fall_refit`` whole views."""
        c = self.config
        residual, seen = self.rain_residual(ctx)
        for b, view in enumerate(ctx.view_ids.tolist()):
            self.samples[view] = gradient_samples(residual[b].cpu(), view, c.threshold, c.fall_samples,
                                                  self.generator, c.estimator, c.kernel)
            self.masks[view] = seen[b, 0].cpu()
            self.unfitted_views += 1
        if self.unfitted_views >= c.fall_refit:
            samples = GradientSamples.cat(list(self.samples.values()))
            down = self.world_down
            fit = fit_fall_direction(self.fit_cameras, samples, down, c.fall_max_tilt) if len(samples.u) else None
            if fit is not None and tilt_deg(fit, down) >= c.fall_max_tilt - 1.0:
                fit = None  # a best at the bound: the residual is ruled by the scene, no fall in it
            # a young head calls the field's unfitted edges rain, and a fit to them moves from one
            # refit to the next; the rain's fall stays
            if fit is not None and self.last_fit is not None and tilt_deg(fit, self.last_fit) <= c.fall_agree:
                self.set_fall(fit)
            self.last_fit = fit
            self.unfitted_views = 0

    def set_fall(self, fall: Tensor) -> None:
        """Steer by ``fall`` (3,), world frame: its streak direction at every pixel of every view."""
        self.fall = fall.cpu()
        self.streaks = line_directions(self.cameras, self.fall.to(self.cameras.c2w))

    def pixel_directions(self, ctx: LossContext) -> tuple[Tensor, Tensor]:
        """directions=world: theta (B, 1, 1, h-2, w-2), the gradient direction
        across the fall's streak at each pixel of the batch's valid 3x3 region, all valid."""
        b, _, h, w = ctx.rendered.shape
        views = ctx.view_ids.to(self.streaks.device)
        if ctx.window is None:
            x0 = y0 = torch.zeros(b, dtype=torch.long)
        else:
            x0, y0 = ctx.window.x0, ctx.window.y0
        rows = y0.to(views.device)[:, None] + torch.arange(1, h - 1, device=views.device)
        cols = x0.to(views.device)[:, None] + torch.arange(1, w - 1, device=views.device)
        streak = self.streaks[views[:, None, None], rows[:, :, None], cols[:, None, :]]
        theta = (streak + math.pi / 2).to(ctx.rendered.device)[:, None, None]
        return theta, torch.ones(b, 1, dtype=torch.bool, device=ctx.rendered.device)

    def view_fall_angle(self, view: int) -> float | None:
        """The fall's streak direction in a view (degrees), averaged over where its last whole
        view saw rain, as the true angle is over the true rain (eval.rain_stats)."""
        streaks = self.streaks[view].cpu()
        mask = self.masks.get(view)
        weights = torch.ones_like(streaks) if mask is None else mask.to(streaks.dtype)
        return weighted_mean_angle_deg(streaks, weights)

    def directions_for(self, ctx: LossContext) -> tuple[Tensor, Tensor]:
        """theta (B, K), or per pixel (B, 1, 1, h-2, w-2) for directions=world, and validity
        for the batch (see ``Config.directions``)."""
        whole = ctx.window is None or (ctx.window.width, ctx.window.height) == self.image_size
        if self.cameras is not None:  # directions=world
            if whole:
                self.observe_fall(ctx)
            return self.pixel_directions(ctx)
        if self.kept is None:
            return self.estimate(ctx)
        theta_kept, valid_kept = self.kept
        views = ctx.view_ids.cpu()
        if whole:
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
        if ctx.record and self.cameras is not None:
            self._record_fall(ctx.view_ids)
        elif ctx.record:  # the network update's angles, not a latent update's crop
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

    def _record_fall(self, view_ids: Tensor) -> None:
        self.metrics = {}
        for vid in view_ids.tolist():
            angle = self.view_fall_angle(int(vid))
            if angle is not None:
                self.view_angles[int(vid)] = [round(angle, 2)]
                self.metrics[f"streak_deg/view{int(vid)}"] = round(angle, 2)
        self.metrics["fall_tilt_deg"] = round(tilt_deg(self.fall, self.world_down), 2)

    def state_dict(self) -> dict:
        state = {"view_angles": {str(k): v for k, v in self.view_angles.items()}}
        if self.kept is not None:
            state["kept"] = [t.tolist() for t in self.kept]
        if self.cameras is not None:
            state["fall"] = {"fall": self.fall, "last_fit": self.last_fit, "masks": self.masks,
                             "unfitted": self.unfitted_views,
                             "samples": {k: dataclasses.asdict(v) for k, v in self.samples.items()},
                             "generator": self.generator.get_state()}
        return state

    def load_state_dict(self, state: dict) -> None:
        self.view_angles = {int(k): list(v) for k, v in state.get("view_angles", {}).items()}
        if self.kept is not None and "kept" in state:
            theta, valid = self.kept
            self.kept = (torch.tensor(state["kept"][0], dtype=theta.dtype, device=theta.device),
                         torch.tensor(state["kept"][1], dtype=torch.bool, device=valid.device))
            self.found = self.kept[1].any(dim=1).cpu()
        if self.cameras is not None and "fall" in state:
            fall = state["fall"]
            self.set_fall(fall["fall"])
            self.last_fit = fall["last_fit"]
            self.masks = dict(fall["masks"])
            self.samples = {k: GradientSamples(**v) for k, v in fall["samples"].items()}
            self.unfitted_views = int(fall["unfitted"])
            self.generator.set_state(fall["generator"])
