"""Loss terms that let other views vote on what is rain (beyond the paper).

- ``mv-photometric`` (the field's): the photometric loss with each pixel weighted by how
  little rain it shows, judged by the other views (and optionally by the predicted rain):
  a rain pixel stops pulling the scene, and the scene there is filled in by the views that
  see it dry.
- ``mv-rain`` (the rain head's): the predicted rain R should match the multi-view evidence
  (how much brighter a pixel is than its neighbours' views of the same point).

Both use the field's rendered depth of the batch (detached) and the scene's training views
(:mod:`rainyscape.losses.multiview_evidence`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import torch
from torch import Tensor

from rainyscape.components import Loss, LossContext
from rainyscape.config.schema import bounded
from rainyscape.errors import ConfigError
from rainyscape.imaging.metrics import ssim_map
from rainyscape.losses.multiview_evidence import (backproject, evidence_over, evidence_with_reach,
                                                  neighbour_colours, neighbour_median, neighbour_table,
                                                  with_brightest)
from rainyscape.losses.rain_losses import dry_weight
from rainyscape.scene import SceneData


class _Evidence:
    """The scene's cameras, training images, neighbour table and every view's last rendered
    depth (for the occlusion test: filled as batches render them); the evidence of a batch.

    With a ``reach`` the evidence is also taken against each neighbour's brightest within that
    many pixels: that evidence alone, or with ``reach_gain`` the evidence at the projection
    capped by it (multiview_evidence.py's ``evidence_with_reach``)."""

    def __init__(self, scene: SceneData, device: torch.device, views: int, min_views: int,
                 occlusion_tolerance: float, reach: int = 0, reach_gain: float = 0.0):
        self.cameras = scene.cameras.to(device)
        images = scene.images.to(device).permute(0, 3, 1, 2).float() / 255.0
        self.images = with_brightest(images, reach)  # channels 3: (if any): the brightest
        self.reach_gain = reach_gain
        self.neighbours = neighbour_table(self.cameras.centers, list(scene.train_indices), views)
        self.min_views = min_views
        self.tolerance = occlusion_tolerance
        self.depths = torch.full((scene.num_images, 1, scene.height, scene.width), float("nan"), device=device)

    def __call__(self, ctx: LossContext) -> tuple[Tensor, Tensor]:
        """The rain evidence of the batch (B, 3, h, w) and where it is defined (B, 1, h, w)."""
        ref, defined = self._medians(ctx)
        evidence = evidence_over(ctx.target, ref[:, :3], defined)
        if ref.shape[1] == 3:
            return evidence, defined
        within = evidence_over(ctx.target, ref[:, 3:], defined)
        return evidence_with_reach(evidence, within, self.reach_gain), defined

    def reference(self, ctx: LossContext) -> tuple[Tensor, Tensor]:
        """The median of what the neighbour views see at the batch's pixels (B, 3, h, w; NaN
        where undefined) and where it is defined (B, 1, h, w)."""
        ref, defined = self._medians(ctx)
        return ref[:, :3], defined

    def _medians(self, ctx: LossContext) -> tuple[Tensor, Tensor]:
        """The neighbours' medians of every channel of the stack; once per batch (``ctx.memo``)."""
        return ctx.memoized((id(self), "reference"), lambda: self._reference(ctx))

    def _reference(self, ctx: LossContext) -> tuple[Tensor, Tensor]:
        if ctx.output is None or ctx.output.depth is None or ctx.window is None:
            raise ConfigError("multi-view rain evidence needs the field's depth and the batch window")
        depth = ctx.output.depth.detach()
        views = ctx.view_ids.to(depth.device)
        if ctx.record:  # the network update's render (a latent update's crop says nothing new)
            w = ctx.window
            for i, v in enumerate(views.tolist()):
                x0, y0 = int(w.x0[i]), int(w.y0[i])
                self.depths[v, :, y0:y0 + w.height, x0:x0 + w.width] = depth[i]
        points = backproject(self.cameras[views], ctx.window, depth)
        colours, valid = neighbour_colours(points, self.neighbours[views], self.cameras, self.images,
                                           self.depths if self.tolerance > 0 else None, self.tolerance)
        return neighbour_median(colours, valid, self.min_views)


class _WithEvidence(Loss):
    """A term built on :class:`_Evidence`; checkpoints keep its depth cache, so a resumed run
    votes as the uninterrupted one would."""

    def __init__(self, config=None):
        super().__init__(config or self.Config())
        self.evidence: _Evidence | None = None

    def setup(self, scene: SceneData, device: torch.device) -> None:
        c = self.config  # every such term's Config has views, min_views, occlusion
        self.evidence = _Evidence(scene, device, c.views, c.min_views, c.occlusion)

    def state_dict(self) -> dict:
        return {"depths": self.evidence.depths.cpu()} if self.evidence is not None else {}

    def load_state_dict(self, state: dict) -> None:
        if self.evidence is not None and "depths" in state:
            self.evidence.depths.copy_(state["depths"])


class MultiviewPhotometric(_WithEvidence):
    """Photometric loss weighted by how dry each pixel is, as the other views see it."""

    description = "mv-photometric: render vs input, rain pixels (other views' vote) weighted down"
    phases = ("joint",)

    @dataclass
    class Config:
        views: int = bounded(6, 2)  # neighbouring training views that vote
        min_views: int = bounded(2, 1)  # a pixel with fewer valid votes keeps full weight
        scale: float = bounded(0.05, 1e-4)  # evidence (grey levels) at which the weight is 1/e
        use_rain: bool = False  # the predicted rain (detached) lowers the weight too
        occlusion: float = bounded(0.05, 0.0, 1.0)  # a neighbour nearer by this share does not vote (0: no test)
        residual: Literal["l2", "l1"] = "l2"
        ssim_weight: float = bounded(0.0, 0.0, 1.0)  # w: (1 - w) weighted residual + w weighted D-SSIM (3DGS: 0.2)

    def weights(self, ctx: LossContext) -> Tensor:
        evidence, _ = self.evidence(ctx)
        grey = evidence.mean(1, keepdim=True)
        if self.config.use_rain and ctx.rain is not None:
            grey = torch.maximum(grey, ctx.rain.detach().mean(1, keepdim=True))
        return dry_weight(grey, self.config.scale)

    def __call__(self, ctx: LossContext) -> Tensor:
        c = self.config
        w = self.weights(ctx)
        diff = ctx.rendered - ctx.target
        per_pixel = (diff ** 2 if c.residual == "l2" else diff.abs()).mean(1, keepdim=True)
        if c.ssim_weight > 0:
            dssim = 1.0 - ssim_map(ctx.rendered, ctx.target, padding="same").mean(1, keepdim=True)
            per_pixel = (1.0 - c.ssim_weight) * per_pixel + c.ssim_weight * dssim
        self.metrics = {"kept": float(w.mean())}
        return (w * per_pixel).sum() / w.sum().clamp_min(1e-6)


def evidence_error(rain: Tensor, evidence: Tensor, defined: Tensor, where_rain: float = 0.0) -> Tensor:
    """Mean squared difference of the predicted rain (B, 3, h, w) and the evidence over the
    pixels where the evidence is ``defined`` (B, 1, h, w); with ``where_rain`` > 0 a pixel
    counts as much as the head itself sees rain there (1 - dry_weight of R, detached), and
    still weighs as it would ungated (the mean stays over every defined pixel)."""
    mask = defined.to(evidence.dtype)
    count = (3 * mask.sum()).clamp_min(1.0)
    if where_rain > 0:
        mask = mask * (1.0 - dry_weight(rain, where_rain))
    return ((rain - evidence) ** 2 * mask).sum() / count


class MultiviewRain(_WithEvidence):
    """The predicted rain should be what a pixel shows beyond its neighbours' views."""

    description = "mv-rain: predicted rain vs the multi-view rain evidence"
    phases = ("joint",)
    needs = ("rain",)

    @dataclass
    class Config:
        views: int = bounded(6, 2)
        min_views: int = bounded(2, 1)
        occlusion: float = bounded(0.05, 0.0, 1.0)  # a neighbour nearer by this share does not vote (0: no test)
        # Only where the head itself sees rain (R, detached, at this scale counts 1 - 1/e): the
        # neighbours then say how much, never where (an edge the reprojection misses is not
        # made rain). 0: every pixel votes.
        where_rain: float = bounded(0.0, 0.0, 1.0)
        # A neighbour offers the brightest it sees within this many pixels of the projection:
        # an edge the rendered depth reprojects a pixel or two off is then no rain. 0: the
        # pixel it projects to.
        reach: int = bounded(0, 0, 8)
        reach_gain: float = bounded(0.0, 0.0, 100.0)  # above 0: the evidence at the pixel, capped at this many times the reach's

    def setup(self, scene: SceneData, device: torch.device) -> None:
        # the reach is this term's only (measured here); the anchor compares colours, which a
        # window's brightest would bias
        c = self.config
        self.evidence = _Evidence(scene, device, c.views, c.min_views, c.occlusion, c.reach, c.reach_gain)

    def __call__(self, ctx: LossContext) -> Tensor:
        evidence, defined = self.evidence(ctx)
        return evidence_error(ctx.rain, evidence, defined, self.config.where_rain)


class MultiviewAnchor(_WithEvidence):
    """Where the rain head sees rain, the render B should be what the neighbour views see
    there: R decides where, the neighbours decide how much (beyond the paper). The anchor is
    the median of the occlusion-checked neighbours' colours at the pixel's point (the
    rendered depth, detached); a pixel the head calls dry is left to the photometric loss."""

    description = "mv-anchor: on the predicted rain, B vs the median of the neighbour views"
    phases = ("joint",)
    needs = ("rain",)

    @dataclass
    class Config:
        views: int = bounded(6, 2)
        min_views: int = bounded(2, 1)
        occlusion: float = bounded(0.05, 0.0, 1.0)  # a neighbour nearer by this share does not vote (0: no test)
        scale: float = bounded(0.02, 1e-4, 1.0)  # predicted rain (grey levels) at which a pixel counts 1 - 1/e

    def __call__(self, ctx: LossContext) -> Tensor:
        ref, defined = self.evidence.reference(ctx)
        rainy = (1.0 - dry_weight(ctx.rain, self.config.scale)) * defined  # (B, 1, h, w), detached
        diff = torch.where(defined, ctx.rendered - ref, torch.zeros_like(ctx.rendered)).abs()
        self.metrics = {"anchored": float(rainy.mean())}
        return (rainy * diff).sum() / (3 * rainy.numel())
