"""Plain photometric loss: the render against the (rainy) input, no rain model."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

from rainyscape.cameras import down_directions
from rainyscape.components import Loss, LossContext
from rainyscape.config.schema import bounded, choice
from rainyscape.imaging.colour import colour_weights, departure, refit_colour
from rainyscape.imaging.streaks import streak_strength
from rainyscape.losses.rain_losses import reconstruction_loss

# A streak in the input for ``streak_scale``: at least 5 px long along a direction within 30
# degrees of the view's down (the wind's slant; perspective leans it more at the image's
# sides) and up to 2 px wide, as rain is at 128 to 240 px.
STREAK_TILTS_DEG = (-30.0, -15.0, 0.0, 15.0, 30.0)
STREAK_HALF_LENGTH = 2
STREAK_HALF_WIDTH = 2
STREAK_VIEWS_AT_ONCE = 8  # views whose streak maps are computed together (memory)
# ``rain_colour=fitted``: the colour is fitted on the pixels the input shows brighter than the
# render by this much (channel mean), as the head fits it where its R reaches 0.1
COLOUR_BRIGHTER = 0.1


def streak_maps(images: Tensor, down: Tensor) -> Tensor:
    """Per view, how far each pixel of the uint8 ``images`` (N, H, W, 3) stands out as a
    streak falling near the view's ``down`` (N,) radians: (N, H, W, 1) float."""
    tilts = torch.tensor([math.radians(t) for t in STREAK_TILTS_DEG])
    maps = []
    for start in range(0, images.shape[0], STREAK_VIEWS_AT_ONCE):
        chunk = images[start:start + STREAK_VIEWS_AT_ONCE].permute(0, 3, 1, 2).float() / 255.0
        angle = down[start:start + STREAK_VIEWS_AT_ONCE].to(chunk)
        maps.append(streak_strength(chunk, angle, tilts.to(chunk), STREAK_HALF_LENGTH, STREAK_HALF_WIDTH))
    return torch.cat(maps).permute(0, 2, 3, 1)


class Photometric(Loss):
    """Mean squared error of the render against the input image (NeRF's loss)."""

    description = "mean squared error of the render vs the rainy input (NeRF's loss)"
    phases = ()  # every phase of the method

    @dataclass
    class Config:
        brighter: float = bounded(1.0, 0.0, 1.0)  # the weight of pixels brighter than the render
        # > 0: ``brighter`` in full only where the input shows a streak standing out by this
        # much (linearly less below it), weight 1 elsewhere: rain falls in streaks, the
        # detail a field has not resolved yet does not
        streak_scale: float = bounded(0.0, 0.0)
        # > 0: ``brighter`` in full only where the residual runs from the render towards the
        # rain's colour (imaging/colour.py's departure under this, weight 1 at twice it): rain
        # takes the light around it, where detail the field has not resolved yet is brighter in
        # its own colour
        colour: float = bounded(0.0, 0.0, 1.0)
        # ... that colour: white, or fitted as the run goes on the pixels brighter than the
        # render by COLOUR_BRIGHTER (a running fit from white, as the head's; the warm-up has
        # no head yet to fit it)
        rain_colour: str = choice("white", ("white", "fitted"))

    def __init__(self, config: "Photometric.Config | None" = None):
        super().__init__(config or self.Config())
        self.streaks: Tensor | None = None  # (N, H, W, 1), with streak_scale
        self.rain_colour: Tensor | None = None  # (3,) and its fit's sums (4,), with rain_colour=fitted
        self.colour_sums: Tensor | None = None

    def setup(self, scene, device: torch.device) -> None:
        if self.config.brighter < 1.0 and self.config.streak_scale > 0:
            self.streaks = streak_maps(scene.images, down_directions(scene.cameras)).to(device)

    def _brighter(self, ctx: LossContext) -> float | Tensor:
        gate = None
        if self.streaks is not None and ctx.window is not None:
            gate = (ctx.window.table_values(self.streaks, ctx.view_ids) / self.config.streak_scale).clamp(max=1.0)
        if self.config.colour > 0:
            residual, background = (ctx.target - ctx.rendered).detach(), ctx.rendered.detach()
            colour = self._rain_colour(residual, background)
            rain_coloured = colour_weights(departure(residual, background, colour), self.config.colour)[:, None]
            gate = rain_coloured if gate is None else gate * rain_coloured
        return self.config.brighter if gate is None else 1.0 - (1.0 - self.config.brighter) * gate

    def _rain_colour(self, residual: Tensor, background: Tensor) -> Tensor:
        if self.config.rain_colour == "white":
            return torch.ones(3, device=residual.device, dtype=residual.dtype)
        if self.rain_colour is None:  # the running fit starts from white
            self.rain_colour, self.colour_sums = torch.ones(3), torch.zeros(4)
        self.colour_sums, self.rain_colour = refit_colour(self.colour_sums.to(residual), residual, background,
                                                          self.rain_colour.to(residual), residual.mean(1) >= COLOUR_BRIGHTER)
        return self.rain_colour

    def state_dict(self) -> dict:
        if self.rain_colour is None:
            return {}
        return {"rain_colour": self.rain_colour.tolist(), "colour_sums": self.colour_sums.tolist()}

    def load_state_dict(self, state: dict) -> None:
        if "rain_colour" in state:
            self.rain_colour = torch.tensor(state["rain_colour"])
            self.colour_sums = torch.tensor(state["colour_sums"])

    def __call__(self, ctx: LossContext) -> Tensor:
        if self.config.brighter == 1.0:
            return F.mse_loss(ctx.rendered, ctx.target)  # nerf's loss, as it always was
        return reconstruction_loss(ctx.target - ctx.rendered, self._brighter(ctx))
