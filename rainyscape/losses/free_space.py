"""A free-space prior against rain held as scene (beyond the paper; issue 28).

Rain fixed in 3D (a camera array's) is seen consistently by neighbouring views, so a field
fits it as geometry: small, semi-transparent floaters in front of the surface. The rain
head's prediction decides *where* the prior acts; a depth test spares the surface behind
the rain, which projects to the same pixels.

- ``floater-opacity`` (Gaussians): lowers the opacity of the Gaussians whose centre projects
  to rain and lies clearly in front of the rendered surface.
- ``floater-rays`` (ray fields): on rays through rain, the weight the ray puts in front of its
  median depth (``front``), or mip-NeRF 360's distortion of its weights (``distortion``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import torch
import torch.nn.functional as F
from torch import Tensor

from rainyscape.components import Loss, LossContext
from rainyscape.config.schema import bounded


def sample_at(image: Tensor, points: Tensor) -> Tensor:
    """``image`` (C, K, h, w) at window pixel positions ``points`` (C, N, 2), nearest pixel:
    (C, N, K); outside the window 0."""
    h, w = image.shape[-2:]
    grid = torch.stack([points[..., 0] / w * 2 - 1, points[..., 1] / h * 2 - 1], -1)
    out = F.grid_sample(image, grid[:, :, None], mode="nearest", padding_mode="zeros", align_corners=False)
    return out[..., 0].transpose(1, 2)


def rain_gate(rain: Tensor, rain_scale: float) -> Tensor:
    """Per pixel (B, 1, h, w), in [0, 1]: the rain's channel mean over ``rain_scale``, clipped."""
    return (rain.mean(1, keepdim=True) / rain_scale).clamp(0.0, 1.0)


def front_floater_gate(rain: Tensor, depth: Tensor, means2d: Tensor, centre_depths: Tensor, visible: Tensor,
                       margin: float, rain_scale: float) -> Tensor:
    """Per camera and Gaussian (C, N), in [0, 1]: how much rain its centre's pixel shows
    (the rain's channel mean over ``rain_scale``, clipped), where the Gaussian is visible and
    nearer than ``1 - margin`` times the rendered depth there; 0 elsewhere.

    rain (C, 3, h, w), depth (C, 1, h, w) rendered (0: nothing hit), means2d (C, N, 2) window
    pixels, centre_depths (C, N) the Gaussians' centres' z in each camera (the model's, not
    the scene's depth), visible (C, N) bool. Nothing here is ground truth: the rain is the
    head's prediction and the depth the field's render."""
    rain_at = sample_at(rain_gate(rain, rain_scale), means2d)[..., 0]
    surface = sample_at(depth, means2d)[..., 0]
    front = visible & (surface > 0) & (centre_depths > 0) & (centre_depths < (1.0 - margin) * surface)
    return rain_at * front


class FloaterOpacity(Loss):
    """Opacity of the Gaussians in front of the surface where the rain head sees rain, summed
    and divided by the batch's pixel count (a pixel's photometric gradient has that scale)."""

    description = "free-space prior: opacity of Gaussians in front of the rendered surface where the rain head sees rain"
    phases = ("joint",)
    needs = ("rain",)
    spatial = True

    @dataclass
    class Config:
        margin: float = bounded(0.1, 0.0, 1.0)  # in front: nearer than (1 - margin) x the rendered depth
        rain_scale: float = bounded(0.05, 1e-6)  # rain of this brightness (channel mean) or more gates fully

    def __init__(self, config: "FloaterOpacity.Config | None" = None):
        super().__init__(config or self.Config())

    def __call__(self, ctx: LossContext) -> Tensor:
        out = ctx.output
        extras = {} if out is None else out.extras
        if "opacities" not in extras or out.depth is None:  # not a Gaussian render (or a crop of one)
            return ctx.rendered.new_zeros(())
        c = self.config
        gate = front_floater_gate(ctx.layers["rain"].detach(), out.depth.detach(), extras["means2d"].detach(),
                                  extras["centre_depths"], (extras["radii"] > 0).all(-1), c.margin, c.rain_scale)
        if ctx.record:
            self.metrics = {"gated_share": float((gate > 0).float().mean())}
        pixels = ctx.rendered.shape[0] * ctx.rendered.shape[-2] * ctx.rendered.shape[-1]
        return (gate * extras["opacities"][None]).sum() / pixels


class FloaterRays(Loss):
    """The ray field's free-space prior: a per-ray measure of weight spread in front of the
    surface, weighted by the rain the head sees at the ray's pixel, averaged over the batch's
    pixels (a photometric term's scale). Renders without the measure (the field's cached
    whole views, crops) contribute nothing: there is no field gradient to give."""

    description = "free-space prior: weight in front of the ray's median depth (or its distortion) where the rain head sees rain"
    phases = ("joint",)
    needs = ("rain",)

    EXTRAS = {"front": "front_weight", "distortion": "distortion"}

    @dataclass
    class Config:
        measure: Literal["front", "distortion"] = "front"
        rain_scale: float = bounded(0.05, 1e-6)  # rain of this brightness (channel mean) or more gates fully

    def __init__(self, config: "FloaterRays.Config | None" = None):
        super().__init__(config or self.Config())
        self.render_extras = (self.EXTRAS[self.config.measure],)

    def __call__(self, ctx: LossContext) -> Tensor:
        value = None if ctx.output is None else ctx.output.extras.get(self.render_extras[0])
        if value is None:
            return ctx.rendered.new_zeros(())
        gate = rain_gate(ctx.layers["rain"].detach(), self.config.rain_scale)
        if ctx.record:
            self.metrics = {"gate_mean": float(gate.mean())}
        return (gate * value).mean()
