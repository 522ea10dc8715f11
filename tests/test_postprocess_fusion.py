"""Rain-mask fusion: rendered pixels where rain is predicted, input pixels elsewhere."""

from __future__ import annotations

import re

import pytest
import torch

from rainyscape.errors import ConfigError
from rainyscape.postprocess.fusion import otsu_threshold, rain_mask, robust_threshold, view_threshold
from rainyscape.postprocess.rain_mask_fusion import RainMaskFusion


def test_mask_thresholds_any_channel_and_dilates():
    rain = torch.zeros(3, 7, 7)
    rain[1, 3, 3] = 0.2  # above the threshold in one channel
    rain[0, 0, 6] = 0.05  # below
    mask = rain_mask(rain, threshold=0.1, dilation=0)
    assert mask.shape == (1, 7, 7) and mask.sum() == 1 and mask[0, 3, 3]
    grown = rain_mask(rain, threshold=0.1, dilation=1)
    assert grown.sum() == 9 and grown[0, 2:5, 2:5].all()
    assert rain_mask(rain, threshold=0.01, dilation=0).sum() == 2


def test_fusion_keeps_render_under_rain_and_input_elsewhere():
    rendered = torch.full((3, 6, 6), 0.3)
    rainy = torch.full((3, 6, 6), 0.7)
    rain = torch.zeros(3, 6, 6)
    rain[:, 0, 0] = 0.5
    fused = RainMaskFusion(RainMaskFusion.Config(threshold=0.1, dilation=1))(rendered, rain, rainy)
    expected = rainy.clone()
    expected[:, :2, :2] = 0.3
    assert torch.equal(fused, expected)


def test_perfect_rain_prediction_recovers_the_clean_image():
    g = torch.Generator().manual_seed(0)
    clean = torch.rand(3, 16, 16, generator=g) * 0.5
    rain = torch.zeros(3, 16, 16)
    rain[:, 4:12, 7] = 0.4  # one streak
    rendered = clean + 0.05 * torch.randn(3, 16, 16, generator=g)  # a slightly blurry render
    fused = RainMaskFusion(RainMaskFusion.Config(below_input=False))(rendered, rain, clean + rain)
    outside = rain_mask(rain, 0.02, 1).expand(3, -1, -1)
    assert torch.equal(fused[~outside], clean[~outside])
    assert torch.equal(fused[outside], rendered[outside])


def test_below_input_takes_the_render_only_where_it_is_darker_than_the_input():
    """Rain only adds light (I = B + R, R >= 0): inside the mask, a render brighter than the
    input is wrong there and the input is kept; the result is closer to the clean scene than
    the paper's fusion whenever the render errs both ways."""
    g = torch.Generator().manual_seed(1)
    clean = 0.2 + 0.5 * torch.rand(3, 16, 16, generator=g)
    rain = torch.zeros(3, 16, 16)
    rain[:, 2:14, 5] = 0.3
    rain[:, 3:15, 11] = 0.25
    rainy = clean + rain
    rendered = clean + 0.08 * torch.randn(3, 16, 16, generator=g)  # under-fitted: errs both ways
    fusion = RainMaskFusion(RainMaskFusion.Config(threshold=0.02, dilation=1))
    fused = fusion(rendered, rain, rainy)
    inside = rain_mask(rain, 0.02, 1).expand(3, -1, -1)
    assert torch.equal(fused[inside], torch.minimum(rendered, rainy)[inside])
    assert torch.equal(fused[~inside], rainy[~inside])
    paper = RainMaskFusion(RainMaskFusion.Config(threshold=0.02, dilation=1, below_input=False))(rendered, rain, rainy)
    error = lambda x: float((x - clean).square().mean())  # noqa: E731
    assert error(fused) < error(paper) < error(rainy)


def test_bad_options():
    with pytest.raises(ConfigError):
        RainMaskFusion(RainMaskFusion.Config(threshold=-1))
    with pytest.raises(ConfigError):
        RainMaskFusion(RainMaskFusion.Config(dilation=-1))


def test_default_threshold_follows_each_views_own_rain_and_is_never_empty():
    """The fixed 0.02 left the mask empty on real photos (the head's rain stayed below it);
    the default finds the streaks that stand out of the view's own predicted rain."""
    gen = torch.Generator().manual_seed(0)
    for base, streak in ((0.002, 0.012), (0.05, 0.2)):  # a faint head and a strong one
        rain = base + 0.001 * torch.rand(3, 32, 32, generator=gen)
        rain[:, 4:28, 10] += streak  # one vertical streak, 24 of 1024 pixels
        fusion = RainMaskFusion(RainMaskFusion.Config(dilation=0))
        mask = fusion.mask(rain, rain, rain)[0]  # only the predicted rain counts
        assert mask[4:28, 10].all()  # the streak
        assert mask.sum() <= 24 + 10  # and hardly anything else
        fixed = RainMaskFusion(RainMaskFusion.Config(threshold=0.02, dilation=0)).mask(rain, rain, rain)
        assert fixed.any() == (base > 0.02)  # the old constant: empty under a faint head


def test_otsu_threshold_splits_two_levels_and_scales_with_the_map():
    gen = torch.Generator().manual_seed(2)
    level = torch.where(torch.rand(1, 40, 40, generator=gen) < 0.1, 0.3, 0.05)
    level = level + 0.01 * torch.rand(1, 40, 40, generator=gen)
    t = otsu_threshold(level.expand(3, -1, -1))
    assert 0.06 < t < 0.3  # between the two classes
    assert otsu_threshold(10 * level) == pytest.approx(10 * t, rel=1e-4)  # no constant in it
    assert otsu_threshold(torch.zeros(3, 8, 8)) == 0.0  # no rain: nothing is above 0


def test_otsu_leaves_the_faint_rain_a_head_spreads_over_the_view_out_of_the_mask():
    """A head with no rain on half the pixels puts the median and its deviation at 0, so
    median + deviations took every pixel with any rain at all (half the view and more on the
    real set); Otsu's level keeps the streaks and leaves the faint rest to the input."""
    gen = torch.Generator().manual_seed(3)
    u = torch.rand(1, 64, 64, generator=gen)
    rain = torch.where(u < 0.55, 0.0, 0.01 * torch.rand(1, 64, 64, generator=gen))  # faint, 40 %
    streaks = u > 0.95
    rain = torch.where(streaks, 0.1 + 0.2 * torch.rand(1, 64, 64, generator=gen), rain).expand(3, -1, -1)
    otsu = RainMaskFusion(RainMaskFusion.Config(dilation=0, rule="otsu")).mask(rain, rain, rain)
    deviations = RainMaskFusion(RainMaskFusion.Config(dilation=0, rule="deviations")).mask(rain, rain, rain)
    both = RainMaskFusion(RainMaskFusion.Config(dilation=0)).mask(rain, rain, rain)  # the default
    assert torch.equal(otsu, streaks) and torch.equal(both, streaks)
    assert deviations.float().mean() > 0.4


def test_both_keeps_the_faint_rain_out_when_it_is_most_of_the_view():
    """The other way round (the real Yard's head): faint rain on most of the view is a class
    of its own, and Otsu splits it from the zeros; the deviations above its median do not,
    and ``both`` takes the higher of the two levels."""
    gen = torch.Generator().manual_seed(4)
    u = torch.rand(1, 64, 64, generator=gen)
    faint = 0.04 + 0.06 * torch.rand(1, 64, 64, generator=gen)
    rain = torch.where(u < 0.3, 0.0, faint)  # zeros on 30 %, faint everywhere else
    streaks = u > 0.98
    rain = torch.where(streaks, 0.2 + 0.01 * torch.rand(1, 64, 64, generator=gen), rain).expand(3, -1, -1)
    otsu, deviations = otsu_threshold(rain), robust_threshold(rain, 3.0)
    assert (rain.amax(0) > otsu).float().mean() > 0.5  # Otsu: the faint rain is rain
    assert view_threshold(rain, "both", 3.0) == max(otsu, deviations) == deviations
    both = RainMaskFusion(RainMaskFusion.Config(dilation=0)).mask(rain, rain, rain)
    assert both.float().mean() < 0.1 and both[streaks].float().mean() > 0.9


def test_an_unknown_threshold_rule_is_refused():
    with pytest.raises(ConfigError, match=re.escape("rule=median: not one of both | otsu | deviations")):
        RainMaskFusion(RainMaskFusion.Config(rule="median"))
