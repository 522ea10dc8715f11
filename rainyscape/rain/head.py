"""The rain prediction module E_phi of the paper (III-B): R_i = E(s, v_i, p_i) >= 0.

Rain embedding of view i: a learnable scene state ``s`` shared by all views, a learnable
view state ``v_i`` and the fixed camera vector ``p_i`` (the normalised camera-to-world
4x4, flattened). A 3-layer MLP maps them to a coarse latent rain map of the whole view
(image size / ``upscale``); a 6-layer CNN with sub-pixel (PixelShuffle) super-resolution
turns it into the rain layer at image resolution, so predicted rain is tied to pixels.

Windowed evaluation: only the rows and columns of the latent map that the requested
window needs (its receptive field) are produced, by gathering those rows of the MLP's
last layer, and the convolutions run "valid" on that region with everything outside the
image zeroed after each layer. That reproduces the zero padding of the full-view network
exactly, so a window equals the same window cut from the full-view map, and a 64 x 64
patch costs about a 64 x 64 forward whatever the image size.

Speed (benchmarks/joint_cost.py; docs/benchmarks.md, "Fields and profiles"): the
convolutions run channels-last (on a CPU the backward pass of the 3-channel output layer is
about 15x faster than with the default layout; results agree to float rounding); a region
that is a large part of the latent map is computed as the plain last MLP layer and cut out
rather than gathered row by row; ``autocast`` runs the CNN in bfloat16 on CUDA (opt-in:
it changes results by bfloat16's rounding, about 1e-2 relative).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from rainyscape.cameras import Cameras, Window, down_directions
from rainyscape.components import Energy, ParamGroup, RainHead
from rainyscape.config.schema import bounded, choice
from rainyscape.errors import ConfigError
from rainyscape.imaging.angles import residual_streak_angle
from rainyscape.imaging.colour import colour_weights, departure, refit_colour
from rainyscape.imaging.streaks import EDGE_SIDES, across_opening, across_ridge, edge_weights, line_opening
from rainyscape.rain.langevin import langevin_update
from rainyscape.scene import SceneData

CAMERA_DIM = 16
# latent_region computes the whole map with the plain layer when the region is at least
# 1 / DENSE_REGION_SHARE of it, and gathers the region's rows of the layer otherwise.
DENSE_REGION_SHARE = 8
# field_gain's test of a streak: how far the residual stands above both of its neighbours up to
# this many pixels across the streaks (all of a streak up to 2 px wide, the middle of a 3 px one:
# the cpu recipe's streaks at 128 to 240 px)
RIDGE_HALF_WIDTH = 2
# field_colour: the rain's colour is fitted on the pixels where R reaches this
COLOUR_RAIN = 0.1
# field_edge's reach across the streaks: a blurred edge's dark side lies within a few pixels of
# its bright side at 128 to 240 px
EDGE_HALF_WIDTH = 3


def camera_vectors(cameras: Cameras) -> Tensor:
    """p_i: camera-to-world 4x4 with translations divided by the largest camera distance from
    the origin (so every entry is O(1) whatever the scene scale), flattened to (N, 16)."""
    c2w = cameras.c2w.detach().clone().float()
    radius = c2w[:, :3, 3].norm(dim=-1).max().clamp_min(1e-8)
    c2w[:, :3, 3] /= radius
    return c2w.reshape(len(cameras), CAMERA_DIM)


def _inside(start_y: Tensor, start_x: Tensor, ly: int, lx: int, height: int, width: int) -> Tensor:
    """(B, 1, ly, lx) mask of region positions that lie inside a height x width grid."""
    ys = start_y[:, None] + torch.arange(ly, device=start_y.device)
    xs = start_x[:, None] + torch.arange(lx, device=start_x.device)
    in_y = (ys >= 0) & (ys < height)
    in_x = (xs >= 0) & (xs < width)
    return (in_y[:, :, None] & in_x[:, None, :])[:, None]


def region_masks(ay: Tensor, ax: Tensor, ly: int, lx: int, layers: int, upscale: int,
                 latent_hw: tuple[int, int], image_hw: tuple[int, int]) -> list[Tensor]:
    """The float masks of a window's regions (see :meth:`RainPredictor.forward`): the latent
    region and each low-res layer's output (``layers`` valid 3x3 convolutions from the latent
    region, each one pixel smaller a side), then the full-resolution region."""
    m, f = layers, upscale
    masks = [_inside(ay - m + k, ax - m + k, ly + 2 * (m - k), lx + 2 * (m - k), *latent_hw).float()
             for k in range(m)]
    return masks + [_inside(f * ay, f * ax, f * ly, f * lx, *image_hw).float()]


class RainPredictor(RainHead):
    """Rain head: scene / view / camera embeddings -> MLP latent map -> CNN + PixelShuffle."""

    description = "rain prediction module: latents + MLP + sub-pixel CNN (RainyScape)"

    @dataclass
    class Config:
        scene_dim: int = 128  # s
        view_dim: int = 64  # v_i
        mlp_width: int = 128
        latent_channels: int = 1  # channels of the coarse latent rain map
        upscale: int = 2  # latent map at image size / upscale; PixelShuffle restores it
        lowres_channels: tuple[int, ...] = (512, 256, 128, 128)  # 3x3 convs at latent resolution
        highres_channels: int = 64  # channels after PixelShuffle
        activation: Literal["softplus", "relu"] = "softplus"  # output non-linearity (authors: relu)
        initial_rain: float = 0.01  # softplus: R starts near this level everywhere
        max_rain: float = 1.0  # R = m tanh(act(x) / m) keeps R in [0, m]; 0: unbounded
        mlp_lr: float = 1e-3
        cnn_lr: float = 1e-4
        betas: tuple[float, float] = (0.5, 0.999)
        latent_std: float = 1.0  # s and v_i start as N(0, latent_std^2)
        # Latent updates after each network update (Algorithm 1): x <- x - d^2/2 (grad E +
        # x / prior_var) (+ d N(0, 1) on the first noise steps), networks frozen.
        latent_steps: int = 5
        latent_noise_steps: int = 2
        langevin_step: float = 0.03  # d
        langevin_noise: float = 1.0  # the noise's scale (1: d N(0, 1), the paper's)
        langevin_prior_var: float = 50.0
        latent_patch_size: int = 0  # latent steps on a random crop of the step's window (0: all of it)
        # The field is fitted to the input less R opened by a line of 2 n + 1 pixels along
        # the streaks (imaging/streaks.py; the direction from the window's residual, as
        # streak fusion's): what R holds that is not streak-shaped stays the field's to fit.
        # The line must be shorter than the rain's streaks (docs/rain.md). 0: less R, the paper's
        field_streaks: int = bounded(0, 0, 32)
        # ... or to the input less what is left of R once what it holds along lines of 2 n + 1
        # pixels across the streaks is taken out (imaging/streaks.py's across_opening): an edge
        # the head took for rain stays the field's, a drop shorter than the line is still
        # subtracted. 0: off. With field_streaks too, the rest is then opened along the streaks.
        field_across: int = bounded(0, 0, 32)
        # ... and, above 1, that R raised up to this many times itself where the residual
        # stands out across the streaks by more (imaging/streaks.py's across_ridge, up to
        # RIDGE_HALF_WIDTH pixels to each side): the head's R is a third to a half of the rain
        # at its streaks, and the rest stayed in the field (docs/rain.md). An edge along the
        # streaks does not stand out, so it does not raise R. 1: off.
        field_gain: float = bounded(1.0, 1.0, 10.0)
        # ... and, above 0, less where the residual has a darker partner across the streaks
        # (imaging/streaks.py's darker_partner, up to EDGE_HALF_WIDTH pixels to each side): all
        # of R where the partner lies less than this share of the pixel's own residual below
        # 0, none at twice it. The bright side of an edge the field blurs looks like a streak
        # when the edge runs along the fall, but the fit is too bright on its dark side; rain
        # over a background the field has right has no such partner. 0: off.
        field_edge: float = bounded(0.0, 0.0, 10.0)
        # ... the partner on either side, or (one) only as far as it is darker than the one on
        # the other side: a streak the field holds in part leaves a partner on both sides
        field_edge_sides: str = choice("either", EDGE_SIDES)
        # ... in a direction whose streaks lean at most this (degrees) from the world's down in
        # the view (as the AGR loss's max_tilt; 90: any direction)
        max_tilt: float = bounded(90.0, above=0.0, hi=90.0)
        # ... and, above 0, only where the residual has the rain's colour (imaging/colour.py: rain
        # pulls a pixel towards one colour, fitted on the head's strong R): all of R where
        # less than this share of the residual runs off that line, none at twice it. Detail
        # the field has not fitted, in its own colour, stays the field's. 0: off.
        field_colour: float = bounded(0.0, 0.0, 1.0)
        # Speed only (outputs agree to float rounding): channels-last convolutions ...
        channels_last: bool = True
        # ... and, opt-in, the CNN in bfloat16 under CUDA autocast (rounding ~1e-2 relative)
        autocast: bool = False

    def __init__(self, config: "RainPredictor.Config | None", scene: SceneData):
        super().__init__()
        self.config = c = config or self.Config()
        if c.upscale < 1:
            raise ConfigError(f"rain_head.upscale must be at least 1, got {c.upscale}")
        if not c.lowres_channels or min(c.lowres_channels) < 1:
            raise ConfigError("rain_head.lowres_channels must list at least one positive width")
        if c.max_rain < 0:
            raise ConfigError(f"rain_head.max_rain must be >= 0, got {c.max_rain}")
        self.height, self.width = scene.height, scene.width
        self.latent_h = -(-self.height // c.upscale)
        self.latent_w = -(-self.width // c.upscale)

        n = scene.num_images
        self.scene_state = nn.Parameter(torch.randn(c.scene_dim) * c.latent_std)
        self.view_states = nn.Parameter(torch.randn(n, c.view_dim) * c.latent_std)
        self.register_buffer("camera_vectors", camera_vectors(scene.cameras), persistent=False)
        # where the world's down runs in each view, for the field's lines (only with the prior)
        prior = c.max_tilt < 90.0 and self._reshapes_for_field()
        down = down_directions(scene.cameras) if prior else torch.zeros(n)
        self.register_buffer("down", down, persistent=False)
        if c.field_colour > 0:  # the rain's colour and its running least-squares sums
            self.register_buffer("rain_colour", torch.ones(3))
            self.register_buffer("colour_sums", torch.zeros(4))

        # MLP: (s, v_i) and p_i branches summed, a hidden layer, then the latent map.
        self.embed_state = nn.Linear(c.scene_dim + c.view_dim, c.mlp_width)
        self.embed_camera = nn.Linear(CAMERA_DIM, c.mlp_width)
        self.hidden = nn.Linear(c.mlp_width, c.mlp_width)
        self.to_map = nn.Linear(c.mlp_width, c.latent_channels * self.latent_h * self.latent_w)

        widths = [c.latent_channels, *c.lowres_channels]
        self.lowres = nn.ModuleList(nn.Conv2d(a, b, 3) for a, b in zip(widths[:-1], widths[1:]))
        self.to_subpixels = nn.Conv2d(widths[-1], c.highres_channels * c.upscale ** 2, 3)
        self.to_rgb = nn.Conv2d(c.highres_channels, 3, 3)
        if c.activation == "softplus" and not 0 < c.initial_rain < 0.5:
            raise ConfigError(f"rain_head.initial_rain must be in (0, 0.5), got {c.initial_rain}")
        self._init_cnn()
        self.lowres_layers = len(self.lowres) + 1  # valid 3x3 convs at latent resolution
        self._last_masks: tuple | None = None  # (view_ids, window, masks): see _masks

    @torch.no_grad()
    def _init_cnn(self) -> None:
        """He initialisation for the ReLU layers: PyTorch's default shrinks the signal about
        3x per layer, so six layers leave an output that ignores the latent map and learns
        very slowly. The output layer starts small, at a faint uniform rain level."""
        for conv in [*self.lowres, self.to_subpixels]:
            nn.init.kaiming_normal_(conv.weight, nonlinearity="relu")
            nn.init.zeros_(conv.bias)
        nn.init.normal_(self.to_rgb.weight, std=0.01)
        bias = math.log(math.expm1(self.config.initial_rain)) if self.config.activation == "softplus" else 0.0
        self.to_rgb.bias.fill_(bias)

    # ------------------------------------------------------------------ interface

    def latents(self) -> list[nn.Parameter]:
        return [self.scene_state, self.view_states]

    def update_latents(self, view_ids: Tensor, window: Window, energy: Energy,
                       generator: torch.Generator) -> None:
        c = self.config
        langevin_update(self.latents(), self, view_ids, window, energy, generator, c.latent_steps,
                        c.latent_noise_steps, c.langevin_step, c.langevin_prior_var, c.latent_patch_size,
                        c.langevin_noise)

    def _reshapes_for_field(self) -> bool:
        """Whether :meth:`for_field` changes R along the streaks (field_across, field_streaks,
        field_gain, field_edge)."""
        c = self.config
        return c.field_streaks > 0 or c.field_across > 0 or c.field_gain > 1.0 or c.field_edge > 0

    def for_field(self, layer: Tensor, residual: Tensor, view_ids: Tensor,
                  background: Tensor | None = None) -> Tensor:
        shaped = self._along_streaks(layer, residual, view_ids)
        if self.config.field_colour > 0:
            if background is None:
                raise ValueError("rain_head.field_colour needs the field's render")
            shaped = shaped * self._colour_weights(layer, residual, background)
        return shaped

    @torch.no_grad()
    def _colour_weights(self, layer: Tensor, residual: Tensor, background: Tensor) -> Tensor:
        """(B, 1, H, W) field_colour's weights; in training, the rain's colour refitted first."""
        if self.training:
            strong = layer.amax(1) >= COLOUR_RAIN
            if bool(strong.any()):
                sums, colour = refit_colour(self.colour_sums, residual, background, self.rain_colour, strong)
                self.colour_sums.copy_(sums)
                self.rain_colour.copy_(colour)
        departed = departure(residual, background, self.rain_colour)
        return colour_weights(departed, self.config.field_colour)[:, None]

    def _along_streaks(self, layer: Tensor, residual: Tensor, view_ids: Tensor) -> Tensor:
        c = self.config
        if not self._reshapes_for_field():
            return layer
        # as streak fusion finds it
        angle, valid = residual_streak_angle(residual, self.down[view_ids.to(self.down.device)],
                                             c.max_tilt)
        shaped = layer
        if c.field_across > 0:
            shaped = shaped - across_opening(shaped, angle, c.field_across)
        if c.field_streaks > 0:
            shaped = line_opening(shaped, angle, c.field_streaks)
        if c.field_gain > 1.0:
            ridge = across_ridge(residual, angle, RIDGE_HALF_WIDTH)
            shaped = torch.maximum(shaped, torch.minimum(c.field_gain * shaped, ridge))
        if c.field_edge > 0:
            shaped = shaped * edge_weights(residual, angle, EDGE_HALF_WIDTH, c.field_edge, c.field_edge_sides)
        # a window whose residual shows no direction keeps its whole R
        return torch.where(valid[:, None, None, None], shaped, layer)

    def param_groups(self) -> list[ParamGroup]:
        c = self.config
        mlp = [*self.embed_state.parameters(), *self.embed_camera.parameters(),
               *self.hidden.parameters(), *self.to_map.parameters()]
        cnn = [*self.lowres.parameters(), *self.to_subpixels.parameters(), *self.to_rgb.parameters()]
        return [ParamGroup("rain_mlp", mlp, lr=c.mlp_lr, betas=tuple(c.betas)),
                ParamGroup("rain_cnn", cnn, lr=c.cnn_lr, betas=tuple(c.betas))]

    def forward(self, view_ids: Tensor, window: Window) -> Tensor:
        """Rain (B, 3, window.height, window.width) >= 0 of ``window`` in each view."""
        dev = self.view_states.device
        view_ids = view_ids.to(dev)
        y0, x0 = window.y0.to(dev), window.x0.to(dev)
        f = self.config.upscale
        # Low-res rows feeding full-res rows [y0 - 1, y0 + h] (the last conv's 3x3 support).
        ay, ax = torch.div(y0 - 1, f, rounding_mode="floor"), torch.div(x0 - 1, f, rounding_mode="floor")
        ly, lx = (window.height + f) // f + 1, (window.width + f) // f + 1
        m = self.lowres_layers
        masks = self._masks(view_ids, window, ay, ax, ly, lx)
        x = self.latent_region(view_ids, ay - m, ax - m, ly + 2 * m, lx + 2 * m, masks[0])
        if self.config.channels_last:
            x = x.contiguous(memory_format=torch.channels_last)
        with self._autocast(x.device):
            for i, conv in enumerate(self.lowres):
                x = F.relu(conv(x)) * masks[i + 1].to(x.dtype)
            x = F.pixel_shuffle(F.relu(self.to_subpixels(x)), f)  # region starts at (f ay, f ax)
            x = x * masks[-1].to(x.dtype)
            x = self.to_rgb(x)  # region starts at (f ay + 1, f ax + 1)
        x = _crop(x.float(), y0 - f * ay - 1, x0 - f * ax - 1, window.height, window.width)
        return self.bound(x)

    def _masks(self, view_ids: Tensor, window: Window, ay: Tensor, ax: Tensor, ly: int, lx: int) -> list[Tensor]:
        """:func:`region_masks` of the window, kept for the last (view_ids, window) asked: a
        latent update predicts the same crop at each of its steps, and on a GPU the masks'
        small operators cost more launches than the convolutions."""
        last = self._last_masks
        if last is None or last[0] is not view_ids or last[1] is not window:
            masks = region_masks(ay, ax, ly, lx, self.lowres_layers, self.config.upscale,
                                 (self.latent_h, self.latent_w), (self.height, self.width))
            self._last_masks = last = (view_ids, window, masks)
        return last[2]

    def _autocast(self, device: torch.device):
        enabled = self.config.autocast and device.type == "cuda"
        return torch.autocast(device.type, dtype=torch.bfloat16, enabled=enabled)

    def bound(self, x: Tensor) -> Tensor:
        """Non-negative rain, softly bounded by ``max_rain`` (the AGR term rewards strong rain
        gradients without limit, so an unbounded head can grow without end).

        Softplus keeps a gradient at every pixel; with the authors' ReLU a pixel (or, at
        initialisation, a whole map) whose pre-activation goes negative never comes back."""
        x = F.softplus(x) if self.config.activation == "softplus" else F.relu(x)
        m = self.config.max_rain
        return m * torch.tanh(x / m) if m > 0 else x

    # ------------------------------------------------------------------ internals

    def embedding(self, view_ids: Tensor) -> Tensor:
        """The MLP's hidden code (B, mlp_width) of each view."""
        s = self.scene_state.expand(len(view_ids), -1)
        state = torch.cat([s, self.view_states[view_ids]], -1)
        h = F.relu(self.embed_state(state) + self.embed_camera(self.camera_vectors[view_ids]))
        return torch.tanh(self.hidden(h))

    def latent_region(self, view_ids: Tensor, start_y: Tensor, start_x: Tensor, ly: int, lx: int,
                      inside: Tensor) -> Tensor:
        """Rows [start_y, start_y + ly) x cols [start_x, start_x + lx) of each view's latent map
        (B, C, ly, lx), zero outside the map (``inside``, its float mask), computing only those
        outputs of the last layer."""
        code = self.embedding(view_ids)
        ys = start_y[:, None] + torch.arange(ly, device=code.device)
        xs = start_x[:, None] + torch.arange(lx, device=code.device)
        rows, cols = ys.clamp(0, self.latent_h - 1), xs.clamp(0, self.latent_w - 1)
        c = self.config.latent_channels
        if ly * lx * DENSE_REGION_SHARE >= self.latent_h * self.latent_w:
            # A large part of the map: the plain layer, then the region cut out (one matrix
            # product forward and backward instead of a gather and a scatter of its rows).
            full = F.relu(self.to_map(code)).view(-1, c, self.latent_h, self.latent_w)
            batch = torch.arange(len(code), device=code.device)[:, None, None]
            latent = full.permute(0, 2, 3, 1)[batch, rows[:, :, None], cols[:, None, :]].permute(0, 3, 1, 2)
        else:
            pos = rows[:, :, None] * self.latent_w + cols[:, None, :]
            chan = torch.arange(c, device=code.device) * (self.latent_h * self.latent_w)
            index = chan[None, :, None, None] + pos[:, None]  # (B, C, ly, lx)
            weight = F.embedding(index, self.to_map.weight)  # (B, C, ly, lx, width)
            bias = self.to_map.bias[index]
            latent = F.relu(torch.einsum("bcyxk,bk->bcyx", weight, code) + bias)
        return latent * inside


def _crop(x: Tensor, off_y: Tensor, off_x: Tensor, h: int, w: int) -> Tensor:
    """Per-image crop of (B, C, H', W') at offsets (B,) to (B, C, h, w)."""
    rows = off_y[:, None] + torch.arange(h, device=x.device)
    cols = off_x[:, None] + torch.arange(w, device=x.device)
    batch = torch.arange(x.shape[0], device=x.device)[:, None, None]
    return x.permute(0, 2, 3, 1)[batch, rows[:, :, None], cols[:, None, :]].permute(0, 3, 1, 2)
