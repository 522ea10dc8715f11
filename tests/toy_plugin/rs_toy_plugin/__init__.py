"""A third-party plugin as users write one: a field, a rain head, a loss, a method.

It lives outside the rainyscape package and registers only through entry points
(tests build a real ``*.dist-info`` for it), so it proves a renderer drops in without
touching rainyscape/.
"""

from __future__ import annotations

import io
import os
import signal
import time
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from rainyscape.cameras import window_rays
from rainyscape.components import Field, Loss, LossContext, ParamGroup, RainHead, RenderOutput
from rainyscape.config import (ComponentConfig, LossConfig, MethodSpec, PhaseConfig, PipelineConfig,
                               TrainerConfig)


class DirectionField(Field):
    """Colour as a function of the viewing direction only (a learnable environment map)."""

    @dataclass
    class Config:
        hidden: int = 32
        lr: float = 1e-2
        delay: float = 0.0  # seconds each training render sleeps (fault tests kill a run mid-way)

    def __init__(self, config: "DirectionField.Config", scene):
        super().__init__()
        self.config = config
        self.mlp = nn.Sequential(nn.Linear(3, config.hidden), nn.ReLU(),
                                 nn.Linear(config.hidden, config.hidden), nn.ReLU(),
                                 nn.Linear(config.hidden, 3))

    def render(self, cameras, window) -> RenderOutput:
        if self.config.delay and torch.is_grad_enabled():
            time.sleep(self.config.delay)
        rays = window_rays(cameras, window)  # (B, h, w, 3)
        rgb = torch.sigmoid(self.mlp(rays.directions)).permute(0, 3, 1, 2)
        ones = torch.ones_like(rgb[:, :1])
        return RenderOutput(rgb=rgb, depth=ones, acc=ones)

    def param_groups(self) -> list[ParamGroup]:
        return [ParamGroup("direction_mlp", list(self.mlp.parameters()), lr=self.config.lr)]


class ToyRain(RainHead):
    """A rain layer per view: a learnable coarse map, upsampled to the image (no latents)."""

    @dataclass
    class Config:
        cells: int = 8
        lr: float = 1e-2

    def __init__(self, config: "ToyRain.Config", scene):
        super().__init__()
        self.config = config
        self.maps = nn.Parameter(torch.full((scene.num_images, 1, config.cells, config.cells), -4.0))
        self.size = (scene.height, scene.width)

    def forward(self, view_ids, window):
        full = F.interpolate(self.maps[view_ids], size=self.size, mode="bilinear", align_corners=False)
        return window.crop(torch.sigmoid(full).expand(-1, 3, -1, -1))

    def param_groups(self) -> list[ParamGroup]:
        return [ParamGroup("toy_rain", [self.maps], lr=self.config.lr)]


class MeanAbsolute(Loss):
    """Mean absolute error between the render (plus rain, if any) and the input."""

    phases = ("warmup", "joint")  # its default phases (those a method has)

    def __call__(self, ctx: LossContext) -> torch.Tensor:
        pred = ctx.rendered if ctx.rain is None else ctx.rendered + ctx.rain
        return (pred - ctx.target).abs().mean()


toy_method = MethodSpec(
    name="toy",
    description="Direction-only field fitted with an L1 loss (plugin test method).",
    config=PipelineConfig(
        method="toy",
        dataparser=ComponentConfig("auto"),
        field=ComponentConfig("direction", {"hidden": 16}),
        # A warm-up over the whole run; the empty joint phase lets loss terms name it.
        phases={"warmup": PhaseConfig(end=1.0, patches=16, patch_size=16),
                "joint": PhaseConfig(end=1.0)},
        losses={"mean-abs": LossConfig("mean-abs", weight=1.0, phases=("warmup",))},
        trainer=TrainerConfig(max_iters=20, eval_every=0, log_every=5,
                              checkpoint_every=10, progress=False),
    ),
    gpu=["trainer.max_iters=400", "field.hidden=64"],  # its "paper-scale" recipe
)


def _kill_during_checkpoint_write(nth: int) -> None:
    """Fault tests: the ``nth`` checkpoint write stops half-way with SIGKILL (a power cut)."""
    real_save = torch.save
    calls = {"n": 0}

    def save(obj, f, *args, **kwargs):
        if isinstance(f, (str, os.PathLike)) and str(f).endswith(".pt.tmp"):
            calls["n"] += 1
            if calls["n"] == nth:
                buffer = io.BytesIO()
                real_save(obj, buffer, *args, **kwargs)
                with open(f, "wb") as fh:
                    fh.write(buffer.getvalue()[: len(buffer.getvalue()) // 2])
                os.kill(os.getpid(), signal.SIGKILL)
        return real_save(obj, f, *args, **kwargs)

    torch.save = save


if os.environ.get("RS_TOY_KILL_IN_SAVE"):
    _kill_during_checkpoint_write(int(os.environ["RS_TOY_KILL_IN_SAVE"]))
