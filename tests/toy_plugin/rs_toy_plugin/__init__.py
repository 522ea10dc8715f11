"""A third-party plugin as users write one: a field, a loss, a dataparser-free method.

It lives outside the rainyscape package and registers only through entry points
(tests build a real ``*.dist-info`` for it), so it proves a renderer drops in without
touching rainyscape/.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from rainyscape.cameras import window_rays
from rainyscape.components import Field, Loss, LossContext, ParamGroup, RenderOutput
from rainyscape.config import ComponentConfig, LossConfig, MethodSpec, PipelineConfig, TrainerConfig


class DirectionField(Field):
    """Colour as a function of the viewing direction only (a learnable environment map)."""

    @dataclass
    class Config:
        hidden: int = 32
        lr: float = 1e-2

    def __init__(self, config: "DirectionField.Config", scene):
        super().__init__()
        self.config = config
        self.mlp = nn.Sequential(nn.Linear(3, config.hidden), nn.ReLU(),
                                 nn.Linear(config.hidden, config.hidden), nn.ReLU(),
                                 nn.Linear(config.hidden, 3))

    def render(self, cameras, window) -> RenderOutput:
        rays = window_rays(cameras, window)  # (B, h, w, 3)
        rgb = torch.sigmoid(self.mlp(rays.directions)).permute(0, 3, 1, 2)
        ones = torch.ones_like(rgb[:, :1])
        return RenderOutput(rgb=rgb, depth=ones, acc=ones)

    def param_groups(self) -> list[ParamGroup]:
        return [ParamGroup("direction_mlp", list(self.mlp.parameters()), lr=self.config.lr)]


class MeanAbsolute(Loss):
    """Mean absolute error between the render (plus rain, if any) and the input."""

    phases = ("warmup", "joint")

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
        losses={"mean-abs": LossConfig("mean-abs", weight=1.0, phases=("warmup",))},
        trainer=TrainerConfig(max_iters=20, warmup_fraction=1.0, eval_every=0, log_every=5,
                              checkpoint_every=10, progress=False),
    ),
)
