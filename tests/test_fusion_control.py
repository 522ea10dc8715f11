"""The fusion control: rain-mask fusion against the same fusion with a random mask of the same
coverage. A rain head that finds the rain beats its control clearly; one that predicts random
rain does not."""

from __future__ import annotations

import pytest
import torch
from torch import nn

from rainyscape.components import MaskFusion, ParamGroup, RainHead
from rainyscape.config import ComponentConfig, PipelineConfig
from rainyscape.engine.pipeline import Pipeline
from rainyscape.eval.protocol import evaluate_pipeline
from rainyscape.postprocess.fusion import fuse, rain_mask, random_mask_like
from rainyscape.postprocess.rain_mask_fusion import RainMaskFusion
from _eval_fixtures import OracleField, TrueRainHead, make_scene

KEY = "rain-mask-fusion"


class RandomRainHead(RainHead):
    """Predicts rain at random pixels (nothing to do with the scene's rain), 1 view in 8 seeds."""

    def __init__(self, h: int, w: int, n: int, coverage: float = 0.15):
        super().__init__()
        g = torch.Generator().manual_seed(123)
        self.layers = (torch.rand(n, 1, h, w, generator=g) < coverage).float().expand(-1, 3, -1, -1) * 0.4
        self.state = nn.Parameter(torch.zeros(1))

    def forward(self, view_ids, window):
        return window.crop(self.layers[view_ids.cpu()]) + 0 * self.state

    def param_groups(self):
        return [ParamGroup("rain", [self.state], lr=0.0)]


def _pipeline(head: str, n: int = 6, h: int = 48, w: int = 64) -> Pipeline:
    scene = make_scene(n=n, h=h, w=w)
    cfg = PipelineConfig(method="fake", dataparser=ComponentConfig("auto"), field=ComponentConfig("fake"))
    rain = TrueRainHead(scene) if head == "true" else RandomRainHead(h, w, n)
    fusion = RainMaskFusion(RainMaskFusion.Config(threshold=0.02, dilation=0))
    return Pipeline(cfg, scene, OracleField(scene), {"rain_head": rain}, {}, {KEY: fusion}, torch.device("cpu"))


def test_random_mask_has_the_same_coverage_and_is_seeded():
    mask = torch.zeros(1, 20, 30, dtype=torch.bool)
    mask[0, 5:9, 3:20] = True
    a, b, c = random_mask_like(mask, 1), random_mask_like(mask, 1), random_mask_like(mask, 2)
    assert a.shape == mask.shape and a.dtype == torch.bool
    assert int(a.sum()) == int(mask.sum()) == 68
    assert torch.equal(a, b) and not torch.equal(a, c)
    assert not torch.equal(a, mask)  # scattered, not the streak
    assert int(random_mask_like(torch.zeros(1, 4, 4, dtype=torch.bool), 0).sum()) == 0


def test_the_fusion_reports_its_mask_coverage_and_control():
    g = torch.Generator().manual_seed(0)
    rain = (torch.rand(3, 16, 16, generator=g) > 0.9).float() * 0.3
    rendered, rainy = torch.rand(3, 16, 16, generator=g), torch.rand(3, 16, 16, generator=g)
    post = RainMaskFusion(RainMaskFusion.Config(threshold=0.1, dilation=1))
    assert isinstance(post, MaskFusion)
    mask = rain_mask(rain, 0.1, 1)
    assert torch.equal(post(rendered, rain, rainy), fuse(rendered, rainy, mask))
    reported = post.control(rendered, rain, rainy, seed=5)
    assert reported.coverage == pytest.approx(float(mask.float().mean()))
    assert torch.equal(reported.control, fuse(rendered, rainy, random_mask_like(mask, 5)))
    assert not isinstance(lambda r, x, y: r, MaskFusion)  # not a mask fusion: no control


def test_true_rain_beats_its_random_control_clearly():
    s = evaluate_pipeline(_pipeline("true"))["summary"]
    fused, control = s[f"train_{KEY}_psnr"], s[f"train_{KEY}_random_psnr"]
    assert 0.1 < s[f"train_{KEY}_coverage"] < 0.3  # the streaks: one pixel row in six
    assert fused > s["rainy_input_psnr"] + 3  # the fused gain over the input ...
    assert fused > control + 3  # ... comes from finding the rain: a random mask gets far less
    assert s[f"train_{KEY}_ssim"] > s[f"train_{KEY}_random_ssim"]
    per_view = [r for r in evaluate_pipeline(_pipeline("true"))["per_view"] if r["split"] == "train"]
    assert all(f"train_{KEY}_random_psnr" in r for r in per_view)


def test_random_rain_scores_like_its_control():
    s = evaluate_pipeline(_pipeline("random"))["summary"]
    fused, control = s[f"train_{KEY}_psnr"], s[f"train_{KEY}_random_psnr"]
    assert s[f"train_{KEY}_coverage"] == pytest.approx(0.15, abs=0.03)
    assert abs(fused - control) < 0.5
    assert abs(s[f"train_{KEY}_ssim"] - s[f"train_{KEY}_random_ssim"]) < 0.02


def test_controls_are_deterministic_and_absent_without_a_fusion():
    a = evaluate_pipeline(_pipeline("random"))["summary"]
    b = evaluate_pipeline(_pipeline("random"))["summary"]
    assert a[f"train_{KEY}_random_psnr"] == b[f"train_{KEY}_random_psnr"]
    pipe = _pipeline("true")
    pipe.postprocess = {"keep": lambda rendered, rain, rainy: rainy}
    s = evaluate_pipeline(pipe)["summary"]
    assert "train_keep_psnr" in s and not any("random" in k or "coverage" in k for k in s)
