"""Streak fusion: the render where the input stands above it in streaks of one direction. It
needs no rain head, finds streaks rather than the detail a render missed, and beats its
random-mask control; rain-mask fusion without a rain head is refused."""

from __future__ import annotations

import math

import pytest
import torch

from rainyscape.config import ComponentConfig, PipelineConfig, method_config
from rainyscape.engine.pipeline import Pipeline, build_pipeline
from rainyscape.errors import ConfigError
from rainyscape.eval.protocol import evaluate_pipeline
from rainyscape.imaging.metrics import psnr
from rainyscape.imaging.streaks import (across_opening, across_ridge, darker_partner, edge_weights, line_mean,
                                        line_opening, streak_strength)
from rainyscape.postprocess.fusion import THRESHOLD_RULES, rain_mask, view_threshold
from rainyscape.postprocess.streak_fusion import StreakFusion, streak_mask
from _eval_fixtures import OracleField, make_scene

KEY = "streak-fusion"


def test_line_mean_keeps_a_line_along_its_direction_and_spreads_it_across():
    image = torch.zeros(1, 1, 15, 15)
    image[0, 0, :, 7] = 1.0  # a vertical line
    along = line_mean(image, torch.tensor([math.pi / 2]), 3)[0, 0]
    across = line_mean(image, torch.tensor([0.0]), 3)[0, 0]
    assert torch.allclose(along[:, 7], torch.ones(15), atol=1e-5)
    assert torch.allclose(across[5, 4:11], torch.full((7,), 1 / 7), atol=1e-5)
    assert float(across[5, 2]) == pytest.approx(0.0, abs=1e-6)
    flat = torch.full((2, 3, 9, 11), 0.4)
    assert torch.allclose(line_mean(flat, torch.tensor([0.3, 2.0]), 4), flat, atol=1e-6)


def test_line_opening_keeps_what_runs_along_the_line_and_removes_the_rest():
    image = torch.zeros(1, 1, 24, 24)
    image[0, 0, 2:20, 6] = 1.0  # a vertical line, 18 px
    image[0, 0, 12, 10:22] = 0.6  # a horizontal one
    image[0, 0, 4, 16] = 0.8  # a dot
    image[0, 0, 20:23, 12] = 0.7  # a vertical line shorter than the opening's 5 px
    opened = line_opening(image, torch.tensor([math.pi / 2]), 2)[0, 0]
    assert torch.allclose(opened[2:20, 6], torch.ones(18), atol=1e-5)
    assert float(opened[12, 10:22].abs().max()) < 1e-6
    assert float(opened[4, 16]) < 1e-6 and float(opened[20:23, 12].max()) < 1e-6
    # a line 10 degrees off the direction keeps most of its level and nothing leaks beside it
    tilted = _streaks(40, 40, 100.0, 13.0, 0)[None, None]
    opened = line_opening(tilted, torch.tensor([math.pi / 2]), 2)
    assert bool((opened <= tilted + 1e-6).all())
    assert float(opened.sum() / tilted.sum()) > 0.5


def test_streak_strength_scores_streaks_near_the_fall_and_not_detail():
    image = torch.full((1, 3, 40, 40), 0.2)
    image[0, :, 4:16, 6] += 0.5  # a vertical streak
    image[0, :, 30, 4:20] += 0.5  # a horizontal line
    image[0, :, 8:11, 24:27] += 0.5  # a blob shorter than the line
    image[0, :, 20, 30] += 0.5  # a dot
    down = torch.tensor([math.pi / 2])
    tilts = torch.tensor([math.radians(t) for t in (-30.0, 0.0, 30.0)])
    strength = streak_strength(image, down, tilts, 2, 2)
    assert strength.shape == (1, 1, 40, 40)
    assert torch.allclose(strength[0, 0, 4:16, 6], torch.full((12,), 0.5), atol=1e-5)
    assert float(strength[0, 0, 28:33].max()) < 1e-6  # the line across the fall
    assert float(strength[0, 0, 20, 30]) < 1e-6
    # the blob: nothing along the fall; a tilted line's bilinear samples keep a little of it
    assert float(strength[0, 0, 6:14, 22:30].max()) < 0.3 * 0.5
    # a streak 30 degrees off the down is found with the tilts, not without them
    slanted = _streaks(40, 40, 120.0, 13.0, 0)[None, None].expand(1, 3, 40, 40)
    assert float(streak_strength(slanted, down, tilts, 2, 2).sum() / slanted[:, :1].sum()) > 0.5
    assert float(streak_strength(slanted, down, torch.zeros(1), 2, 2).sum() / slanted[:, :1].sum()) < 0.2


def test_across_opening_keeps_edges_across_the_direction_and_removes_streaks_and_dots():
    image = torch.zeros(1, 1, 24, 24)
    image[0, 0, 2:20, 6] = 1.0  # a vertical streak, along the direction
    image[0, 0, 12, 10:22] = 0.6  # a horizontal edge, across it
    for i in range(8):  # a diagonal edge, 45 degrees off it
        image[0, 0, 14 + i, 10 + i] = 0.5
    image[0, 0, 4, 16] = 0.8  # a dot
    across = across_opening(image, torch.tensor([math.pi / 2]), 2)[0, 0]
    assert float(across[2:20, 6].max()) < 1e-6 and float(across[4, 16]) < 1e-6
    assert torch.allclose(across[12, 11:21], torch.full((10,), 0.6), atol=1e-5)
    # a 1 px diagonal falls between the bilinear samples of its own line: half its level
    assert float(across[16:20, 12:16].diagonal().min()) > 0.25
    assert bool((across <= image + 1e-6).all())


def test_across_ridge_measures_streaks_over_their_background_and_not_edges_along_them():
    image = torch.full((1, 1, 24, 24), 0.2)
    image[0, 0, :, 14:] = 0.7  # a vertical step edge, along the direction
    image[0, 0, 2:20, 5] += 0.3  # a 1 px streak on the dark side
    image[0, 0, 2:20, 9:11] += 0.4  # a 2 px streak
    ridge = across_ridge(image, torch.tensor([math.pi / 2]), 2)[0, 0]
    assert torch.allclose(ridge[3:19, 5], torch.full((16,), 0.3), atol=1e-5)
    assert torch.allclose(ridge[3:19, 9:11], torch.full((16, 2), 0.4), atol=1e-5)
    assert float(ridge[:, 12:16].max()) < 1e-6  # neither side of the step stands out
    # a 2 px streak seen only one pixel across (half_width 1) has itself for a neighbour
    assert float(across_ridge(image, torch.tensor([math.pi / 2]), 1)[0, 0, 3:19, 9:11].max()) < 1e-6


def test_darker_partner_finds_a_blurred_edges_dark_side_and_not_a_streaks_background():
    residual = torch.zeros(1, 1, 16, 24)
    residual[0, 0, :, 4] = 0.3  # a streak over a background fitted right
    residual[0, 0, :, 14] = 0.2  # an edge's bright side, fitted too dark ...
    residual[0, 0, :, 16] = -0.1  # ... its dark side, 2 px across, fitted too bright
    partner = darker_partner(residual, torch.tensor([math.pi / 2]), 2)[0, 0]
    assert float(partner[:, 4].max()) < 1e-6
    assert torch.allclose(partner[:, 14], torch.full((16,), 0.1), atol=1e-6)
    assert float(darker_partner(residual, torch.tensor([math.pi / 2]), 1)[0, 0, :, 14].max()) < 1e-6  # out of reach
    # along the edge (a horizontal line) no pixel has the dark side for a neighbour
    assert float(darker_partner(residual, torch.tensor([0.0]), 2)[0, 0, :, 14].max()) < 1e-6
    # the weights: the partner is half the bright side's residual, so 1 at share 0.5, 0 at 0.25
    for share, edge in ((0.5, 1.0), (0.25, 0.0), (1 / 3, 0.5)):
        w = edge_weights(residual.expand(1, 3, 16, 24), torch.tensor([math.pi / 2]), 2, share)[0, 0]
        assert torch.allclose(w[:, 4], torch.ones(16)) and torch.allclose(w[:, 14], torch.full((16,), edge), atol=1e-5)


def test_a_one_sided_partner_tells_a_blurred_edge_from_a_streak_the_fit_holds_in_part():
    residual = torch.zeros(1, 1, 16, 24)
    residual[0, 0, :, 4] = 0.3  # a streak whose fit holds a wider, fainter copy ...
    residual[0, 0, :, 3] = residual[0, 0, :, 5] = -0.05  # ... too bright on both sides
    residual[0, 0, :, 14] = 0.2  # an edge's bright side, fitted too dark ...
    residual[0, 0, :, 16] = -0.1  # ... its dark side, on one side only
    across = torch.tensor([math.pi / 2])
    either, one = (darker_partner(residual, across, 2, sides)[0, 0] for sides in ("either", "one"))
    assert torch.allclose(either[:, 4], torch.full((16,), 0.05), atol=1e-6)  # either side: the streak has partners
    assert float(one[:, 4].max()) < 1e-6  # one side: they cancel
    assert torch.allclose(one[:, 14], torch.full((16,), 0.1), atol=1e-6)  # the edge keeps its partner
    w = edge_weights(residual.expand(1, 3, 16, 24), across, 2, 0.1, "one")[0, 0]
    assert torch.allclose(w[:, 4], torch.ones(16)) and float(w[:, 14].max()) < 1e-6
    assert float(edge_weights(residual.expand(1, 3, 16, 24), across, 2, 0.1)[0, 0, :, 4].max()) < 1.0


def _streaks(h: int, w: int, angle_deg: float, period: float, seed: int) -> torch.Tensor:
    """Parallel anti-aliased lines (H, W) about a pixel wide along ``angle_deg`` (from +x
    towards +y): jagged ones would bend the estimated direction by a few degrees."""
    a = math.radians(angle_deg)
    ys, xs = torch.meshgrid(torch.arange(h, dtype=torch.float32), torch.arange(w, dtype=torch.float32),
                            indexing="ij")
    across = torch.remainder(-xs * math.sin(a) + ys * math.cos(a) + seed * 2.7, period)
    return (1 - torch.minimum(across, period - across)).clamp_min(0)


def _view(seed: int = 0, h: int = 64, w: int = 80):
    """A clean view with bright grain (single pixels) that the render missed, and
    rain streaks at 70 degrees on the input; the streaks' pixels, the details'."""
    g = torch.Generator().manual_seed(seed)
    smooth = torch.nn.functional.interpolate(torch.rand(1, 3, h // 16, w // 16, generator=g), size=(h, w),
                                             mode="bilinear", align_corners=False)[0] * 0.5 + 0.1
    detail = (torch.rand(1, h, w, generator=g) < 0.05).float() * 0.3  # bright grain, no direction
    clean = smooth + detail
    rendered = smooth + 0.01 * torch.randn(3, h, w, generator=g)  # no render is exact
    rain = _streaks(h, w, 70.0, 9.0, seed)[None] * 0.3
    return clean, rendered, clean + rain, rain[0] > 0.1, detail[0] > 0


@pytest.mark.parametrize("rule", THRESHOLD_RULES)
def test_streak_mask_finds_the_streaks_not_the_missed_detail(rule):
    clean, rendered, rainy, wet, speck = _view()
    mask = streak_mask(rendered, rainy, sigmas=3.0, half_length=3, dilation=0, rule=rule)[0]
    residual = rainy - rendered
    residual_only = rain_mask(residual, view_threshold(residual, rule, 3.0), 0)[0]
    dry_speck = speck & ~wet
    assert mask[wet].float().mean() > 0.8  # the streaks
    assert residual_only[dry_speck].float().mean() > 0.9  # the residual alone takes the grain too ...
    assert mask[dry_speck].float().mean() < 0.5 * residual_only[dry_speck].float().mean()  # ... the line mean not


def test_streak_fusion_beats_its_random_mask_control_and_keeps_a_dry_view():
    clean, rendered, rainy, _, _ = _view(seed=3)
    fusion = StreakFusion()
    fused = fusion(rendered, None, rainy)
    control = fusion.control(rendered, None, rainy, seed=1)
    assert 0.05 < control.coverage < 0.5
    assert float(psnr(fused, clean)) > float(psnr(control.control, clean)) + 3
    assert float(psnr(fused, clean)) > float(psnr(rainy, clean)) + 3
    dry = fusion.control(rendered, None, rendered, seed=1)  # nothing above the render: no mask
    assert dry.coverage == 0.0 and torch.equal(fusion(rendered, None, rendered), rendered)


def test_a_field_without_a_rain_head_is_fused_and_controlled():
    scene = make_scene(n=5, h=48, w=64)
    cfg = PipelineConfig(method="fake", dataparser=ComponentConfig("auto"), field=ComponentConfig("fake"))
    pipeline = Pipeline(cfg, scene, OracleField(scene), {}, {}, {KEY: StreakFusion()}, torch.device("cpu"))
    s = evaluate_pipeline(pipeline)["summary"]
    assert s[f"train_{KEY}_coverage"] > 0.05
    assert s[f"train_{KEY}_psnr"] > s["rainy_input_psnr"] + 3
    assert s[f"train_{KEY}_psnr"] > s[f"train_{KEY}_random_psnr"] + 1


def test_rain_mask_fusion_without_a_rain_head_is_refused():
    cfg = method_config("nerf", ["postprocess.rain-mask-fusion=on", "trainer.device=cpu"])
    with pytest.raises(ConfigError, match="postprocess.rain-mask-fusion .*no rain head.*streak-fusion"):
        build_pipeline(cfg, make_scene(), torch.device("cpu"))
