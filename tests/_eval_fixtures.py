"""In-memory stand-ins for evaluation tests (no tests here): a rainy scene with known streaks,
a field that renders the clean images with a known error, and a rain head that predicts the
true rain layer. They make every metric of the protocol known in advance."""

from __future__ import annotations

import math
from dataclasses import dataclass

import pytest
import torch
from torch import nn

from rainyscape.cameras import Cameras, Window
from rainyscape.components import Field, ParamGroup, RainHead, RenderOutput
from rainyscape.config import ComponentConfig, PipelineConfig
from rainyscape.engine.pipeline import Pipeline
from rainyscape.scene import SceneData

STREAK_DEG = 70.0  # streaks run at 70 degrees from +x towards +y (down)
OFFSET = 0.05  # the oracle field renders clean + OFFSET: PSNR = -10 log10(OFFSET^2) = 26.02 dB


def streaks(h: int, w: int, angle_deg: float, period: float, seed: int) -> torch.Tensor:
    """Thin parallel bright lines (H, W) along ``angle_deg``, phase-shifted per seed."""
    a = math.radians(angle_deg)
    ys, xs = torch.meshgrid(torch.arange(h, dtype=torch.float32), torch.arange(w, dtype=torch.float32),
                            indexing="ij")
    # distance across the streaks: project on the normal (-sin a, cos a)
    across = -xs * math.sin(a) + ys * math.cos(a) + seed * 2.7
    return (torch.remainder(across, period) < 1.0).float()


def make_scene(n: int = 4, h: int = 32, w: int = 40) -> SceneData:
    g = torch.Generator().manual_seed(0)
    base = torch.rand(n, h // 8, w // 8, 3, generator=g)
    clean = torch.nn.functional.interpolate(base.permute(0, 3, 1, 2), size=(h, w), mode="bilinear",
                                            align_corners=False).permute(0, 2, 3, 1) * 0.6 + 0.1
    rain = torch.stack([streaks(h, w, STREAK_DEG, 6.0, i) for i in range(n)])[..., None].expand(-1, -1, -1, 3) * 0.3
    clean_u8 = (clean * 255).round().to(torch.uint8)
    rainy_u8 = ((clean_u8.float() / 255 + rain).clamp(0, 1) * 255).round().to(torch.uint8)
    c2w = torch.eye(4).repeat(n, 1, 1)
    c2w[:, 0, 3] = torch.arange(n, dtype=torch.float32) * 0.1
    cams = Cameras(c2w, torch.full((n,), 40.0), torch.full((n,), 40.0), torch.full((n,), w / 2),
                   torch.full((n,), h / 2), w, h)
    return SceneData(name="fake", images=rainy_u8, cameras=cams, image_names=[f"{i:03d}.png" for i in range(n)],
                     train_indices=list(range(n - 1)), eval_indices=[n - 1], near=0.1, far=5.0,
                     scene_box=torch.tensor([[-1.0, -1, -1], [1, 1, 1]]), clean_images=clean_u8,
                     rain_layers=(rainy_u8.float() - clean_u8.float()) / 255)


class OracleField(Field):
    """Renders each camera's clean image plus OFFSET (cameras matched by position)."""

    def __init__(self, scene: SceneData):
        super().__init__()
        self.scene = scene
        self.clean = scene.clean_images.clone()  # the scene may later lose its clean images
        self.dummy = nn.Parameter(torch.zeros(1))

    def render(self, cameras: Cameras, window: Window) -> RenderOutput:
        d = torch.cdist(cameras.centers.cpu(), self.scene.cameras.centers)
        idx = d.argmin(1)
        clean = self.clean[idx].permute(0, 3, 1, 2).float() / 255
        rgb = window.crop(clean).clamp(0, 1 - OFFSET) + OFFSET
        depth = torch.ones_like(rgb[:, :1]) * (1 + idx.float()[:, None, None, None])
        return RenderOutput(rgb=rgb + 0 * self.dummy, depth=depth, acc=torch.ones_like(depth))

    def param_groups(self) -> list[ParamGroup]:
        return [ParamGroup("dummy", [self.dummy], lr=0.0)]


class TrueRainHead(RainHead):
    """Predicts the scene's true rain layer for training views."""

    def __init__(self, scene: SceneData):
        super().__init__()
        self.scene = scene
        self.state = nn.Parameter(torch.zeros(4))

    def forward(self, view_ids, window):
        layers = self.scene.rain_layers[view_ids.cpu()].permute(0, 3, 1, 2)
        return window.crop(layers) + 0 * self.state.sum()

    def param_groups(self):
        return [ParamGroup("rain", [self.state], lr=0.0)]


@dataclass
class _Keep:
    """A post-process that returns the rainy input (so its metrics equal the floor)."""

    config: object = None

    def __call__(self, rendered, rain, rainy):
        return rainy


def make_pipeline(with_rain: bool = True, post: bool = True) -> Pipeline:
    scene = make_scene()
    cfg = PipelineConfig(method="fake", dataparser=ComponentConfig("auto"), field=ComponentConfig("fake"))
    heads = {"rain_head": TrueRainHead(scene)} if with_rain else {}
    return Pipeline(cfg, scene, OracleField(scene), heads, {}, {"keep": _Keep()} if post and with_rain else {},
                    torch.device("cpu"))


@pytest.fixture
def fake_pipeline() -> Pipeline:
    return make_pipeline()
