"""The weight-free robust losses on residuals worked out by hand: RobustNeRF's trimmed L2
(pixel test, 3 x 3 and 16 x 16 patch decisions, the previous batch's quantile) and
SpotLessSplats' RobustFilter (running-histogram percentile, 3 x 3 rule, blend-in, the SH
reset that goes with it)."""

from __future__ import annotations

import math

import pytest
import torch

from rainyscape.cameras import Window
from rainyscape.components import LossContext, RenderOutput, TrainState
from rainyscape.errors import ConfigError
from rainyscape.losses.robust import ResidualMap, RobustNeRFLoss, robustnerf_mask, virtual_patches
from rainyscape.losses.robust_filter import (ParamReset, RobustFilter, blend_weight, histogram_percentile,
                                             robust_filter_mask)


def _ctx(rendered, target, step=0):
    return LossContext(rendered, target, {}, RenderOutput(rendered), torch.zeros(len(rendered), dtype=torch.long),
                       step, "fit")


def _residual(inlier_rows: list[str]) -> torch.Tensor:
    """(1, 1, h, w) residuals: 0.1 where the row string has '1' (inlier), 0.9 where '0'."""
    grid = [[0.1 if ch == "1" else 0.9 for ch in row] for row in inlier_rows]
    return torch.tensor(grid)[None, None]


def _mask_rows(mask: torch.Tensor) -> list[str]:
    return ["".join(str(int(v)) for v in row) for row in mask[0, 0].tolist()]


# ---------------------------------------------------------------------------- RobustNeRF

def test_robustnerf_pixel_test_and_3x3_smoothing_by_hand():
    residual = _residual(["11111",
                          "10111",
                          "11100",
                          "11000",
                          "11000"])
    mask = robustnerf_mask(residual, 0.5, smooth_size=3, smooth_threshold=0.5, inner_patch=0)
    # (1, 1) has 8 of 9 inlier neighbours: inlier. (2, 3) has 4 of 9 (not more than half) and
    # (3, 2) 4 of 9: they stay out; the corner (4, 4) sees 0 of 9 (zero padding counts as out).
    assert _mask_rows(mask) == ["11111",
                                "11111",
                                "11100",
                                "11000",
                                "11000"]


def test_robustnerf_patch_decision_marks_the_inner_8x8_of_a_mostly_clean_16x16_patch():
    cols = 7  # 7 outlier columns: 144 / 256 = 56 % of the patch is inlier after smoothing
    rows = ["0" * cols + "1" * (16 - cols)] * 16
    mask = robustnerf_mask(_residual(rows), 0.5)[0, 0]
    assert bool((mask[4:12, 4:7] == 1).all())  # the inner 8 x 8 (rows / columns 4..11) is taken whole
    assert bool((mask[:4, :7] == 0).all()) and bool((mask[12:, :7] == 0).all())
    assert bool((mask[:, 7:] == 1).all())
    rows = ["0" * 9 + "1" * 7] * 16  # 44 % inlier: no patch decision
    mask = robustnerf_mask(_residual(rows), 0.5)[0, 0]
    assert bool((mask[:, :8] == 0).all())


def test_robustnerf_threshold_is_the_previous_batchs_quantile_and_is_checkpointed():
    g = torch.Generator().manual_seed(0)
    rendered = torch.rand(2, 3, 16, 16, generator=g)
    target = torch.rand(2, 3, 16, 16, generator=g)
    loss = RobustNeRFLoss()
    first = loss(_ctx(rendered, target))
    # before any batch the threshold is 1.0: every residual (< 1) is inlier, the plain MSE
    assert loss.metrics["threshold"] == 1.0 and loss.metrics["inlier_fraction"] == 1.0
    assert float(first) == pytest.approx(float(((rendered - target) ** 2).mean()), rel=1e-6)
    residual = ((rendered - target) ** 2).mean(1)
    assert loss.threshold == pytest.approx(float(torch.quantile(residual.flatten(), 0.8)), rel=1e-6)
    restored = RobustNeRFLoss()
    restored.load_state_dict(loss.state_dict())
    a, b = loss(_ctx(rendered, target)), restored(_ctx(rendered, target))
    assert float(a) == float(b) and loss.metrics == restored.metrics
    assert loss.metrics["inlier_fraction"] < 1.0


def test_robustnerf_threshold_pools_small_batches_up_to_the_papers_64_patches():
    g = torch.Generator().manual_seed(3)
    loss = RobustNeRFLoss()
    residuals = []
    for k in range(40):  # batches of 2 patches, each with its own error level
        rendered = torch.rand(2, 3, 16, 16, generator=g) * (k + 1) / 40
        target = torch.zeros(2, 3, 16, 16)
        loss(_ctx(rendered, target))
        residuals.append((rendered ** 2).mean(1).flatten(1))
    pooled = torch.cat(residuals[-32:])  # the last 32 batches: 64 patches
    assert loss.threshold == pytest.approx(float(torch.quantile(pooled.flatten(), 0.8)), rel=1e-5)
    assert sum(len(r) for r in loss.pool) == 64 * 16 * 16
    restored = RobustNeRFLoss()
    restored.load_state_dict(loss.state_dict())
    assert all(torch.equal(a, b) for a, b in zip(restored.pool, loss.pool))


def test_robustnerf_no_gradient_from_trimmed_pixels_and_mean_over_every_pixel():
    rendered = torch.full((1, 3, 16, 16), 0.5)
    target = rendered.clone()
    target[..., :4, :4] = 1.0  # a corner blob of clutter (outside the inner 8 x 8)
    loss = RobustNeRFLoss()
    loss.threshold = 0.01
    x = rendered.clone().requires_grad_(True)
    value = loss(_ctx(x, target))
    value.backward()
    # the blob is trimmed but for its inner corner (3, 3), whose 3 x 3 neighbourhood is 5 / 9
    # clean: one pixel of error 0.5 in each channel, over all 16 x 16 x 3 values
    assert float(value.detach()) == pytest.approx(0.25 / 256)
    assert float(x.grad[..., :3, :3].abs().max()) == 0.0 and float(x.grad[..., 3, 3].abs().min()) > 0
    with pytest.raises(ConfigError, match="inlier_quantile"):
        RobustNeRFLoss(RobustNeRFLoss.Config(inlier_quantile=0.0))


def _rays(xs: list[int], ys: list[int]) -> Window:
    """Single-ray windows at the pixels (xs[i], ys[i])."""
    return Window(torch.tensor(xs), torch.tensor(ys), 1, 1)


def test_residual_map_reads_what_was_written_and_forgets_old_pixels():
    grid = ResidualMap(views=2, height=4, width=5)
    grid.write(torch.tensor([1, 1]), _rays([0, 1], [0, 0]), torch.tensor([0.3, 0.7])[:, None, None, None], step=2)
    grid.write(torch.tensor([1]), _rays([2], [0]), torch.tensor([0.9])[:, None, None, None], step=9)
    residuals, known = grid.read(torch.tensor([1]), Window(torch.tensor([0]), torch.tensor([0]), 3, 2), since=5)
    # (0, 0) and (1, 0) were seen at step 2, before ``since``; (2, 0) at step 9; row 1 never
    assert known[0, 0].tolist() == [[0, 0, 1], [0, 0, 0]]
    assert residuals[0, 0, 0].tolist() == pytest.approx([0.3, 0.7, 0.9])
    _, known = grid.read(torch.tensor([0]), _rays([1], [0]), since=0)
    assert float(known.sum()) == 0  # view 0 was never seen


def test_virtual_patches_hold_their_ray_inside_the_view_at_every_place():
    g = torch.Generator().manual_seed(0)
    xs = torch.tensor([0, 3, 20, 47] * 500)
    patches, dy, dx = virtual_patches(_rays(xs.tolist(), (47 - xs).tolist()), 16, 48, 48, g)
    assert bool((patches.x0 + dx == xs).all()) and bool((patches.y0 + dy == 47 - xs).all())
    assert bool((patches.x0 >= 0).all()) and bool((patches.x0 + 16 <= 48).all())
    assert bool((patches.y0 >= 0).all()) and bool((patches.y0 + 16 <= 48).all())
    assert set(dx[xs == 20].tolist()) == set(range(16))  # inside: every place, as a random patch
    # at the edges only the places that keep the patch inside the view
    assert set(dx[xs == 3].tolist()) == {0, 1, 2, 3} and set(dx[xs == 0].tolist()) == {0}
    assert set(dx[xs == 47].tolist()) == {15}


def test_robustnerf_mask_leaves_unknown_pixels_out_of_the_shares():
    residual = _residual(["110",
                          "101",
                          "000"])
    known = torch.tensor([[1.0, 1, 1], [1, 1, 1], [0, 0, 0]])[None, None]  # the bottom row unseen
    # the centre's 3 x 3 holds 4 inliers: 4 of 9 without ``known`` (not more than half), 4 of
    # the 6 seen with it; the zero padding still counts as seen outliers ((0, 2): 2 of 9)
    with_known = robustnerf_mask(residual, 0.5, inner_patch=0, known=known)
    assert _mask_rows(with_known) == ["110", "111", "000"]
    assert _mask_rows(robustnerf_mask(residual, 0.5, inner_patch=0)) == ["110", "101", "000"]
    # the patch decision on the whole 3 x 3 window: 4 inliers of 6 seen, 4 of 9 without
    assert int(robustnerf_mask(residual, 0.5, smooth_size=1, inner_patch=1, known=known)[0, 0, 1, 1]) == 1
    assert int(robustnerf_mask(residual, 0.5, smooth_size=1, inner_patch=1)[0, 0, 1, 1]) == 0


def test_robustnerf_on_single_rays_trims_a_blob_the_map_has_seen():
    from types import SimpleNamespace
    loss = RobustNeRFLoss(RobustNeRFLoss.Config(residual_map=True))
    loss.setup(SimpleNamespace(images=torch.zeros(1, 32, 32, 3), height=32, width=32, train_pixels=32 * 32),
               torch.device("cpu"))
    loss.threshold = 0.01
    ys, xs = torch.meshgrid(torch.arange(32), torch.arange(32), indexing="ij")
    clean = torch.full((32 * 32, 3, 1, 1), 0.5)
    target = clean.clone()
    blob = ((xs - 16).abs() < 8) & ((ys - 16).abs() < 8)  # a 15 x 15 blob: over half of any patch holding its centre
    target[blob.flatten()] = 1.0
    window = Window(xs.flatten(), ys.flatten(), 1, 1)
    views = torch.zeros(32 * 32, dtype=torch.long)
    first = LossContext(clean, target, {}, RenderOutput(clean), views, 0, "fit", window)
    loss(first)  # every pixel seen once: the map now holds the blob
    ray = Window(torch.tensor([16, 2]), torch.tensor([16, 2]), 1, 1)  # the blob's centre, a clean pixel
    x = torch.full((2, 3, 1, 1), 0.5, requires_grad=True)
    target = torch.tensor([1.0, 0.6])[:, None, None, None].expand(2, 3, 1, 1)
    loss.threshold = 0.05  # the clean pixel's residual 0.01 is inlier
    loss(LossContext(x, target, {}, RenderOutput(x), views[:2], 1, "fit", ray)).backward()
    assert float(x.grad[0].abs().max()) == 0.0 and float(x.grad[1].abs().min()) > 0
    restored = RobustNeRFLoss(RobustNeRFLoss.Config(residual_map=True))
    restored.setup(SimpleNamespace(images=torch.zeros(1, 32, 32, 3), height=32, width=32, train_pixels=32 * 32),
                   torch.device("cpu"))
    restored.load_state_dict(loss.state_dict())
    assert torch.equal(restored.map.residuals, loss.map.residuals)


# ---------------------------------------------------------------------- RobustFilter

def test_histogram_percentile_by_hand():
    hist = torch.tensor([0.0, 3.0, 1.0, 0.0, 6.0])  # 5 bins over [0, 1]
    assert histogram_percentile(hist, 0.5) == pytest.approx(0.8)  # cumulative 0, 3, 4, 4, 10 >= 5
    assert histogram_percentile(hist, 0.3) == pytest.approx(0.2)  # >= 3 at the second bin
    assert histogram_percentile(torch.zeros(5), 0.7) == 1.0


def test_running_histogram_decays_and_gives_the_threshold():
    loss = RobustFilter(RobustFilter.Config(bins=10, blend_in=False, reset_group=""))
    assert loss.threshold == 1.0
    a = torch.full((1, 1, 2, 5), 0.05)  # ten residuals in the first bin
    b = torch.full((1, 1, 2, 5), 0.55)  # ten in the sixth
    loss.update(a)
    loss.update(b)
    expected = torch.zeros(10)
    expected[0], expected[5] = 0.95 * 10, 10
    assert torch.allclose(loss.hist, expected)
    # 70 % of 19.5 is 13.65: reached at the sixth bin, whose left edge is 0.5
    assert loss.threshold == pytest.approx(0.5)


def test_the_3x3_rule_relabels_a_1px_streak_as_clean_but_not_a_3px_band():
    thin = ["1111111"] * 7
    thin = [row[:3] + "0" + row[4:] for row in thin]  # a vertical 1 px streak in column 3
    mask = robust_filter_mask(_residual(thin), 0.5)
    # each streak pixel has 6 of 9 clean neighbours (the top and bottom ones 4 of 9, zero padding)
    assert bool((mask[0, 0, 1:6, 3] == 1).all()) and mask[0, 0, 0, 3] == 0 and mask[0, 0, 6, 3] == 0
    band = ["11" + "000" + "11"] * 7
    mask = robust_filter_mask(_residual(band), 0.5)
    assert bool((mask[0, 0, :, 2:5] == 0).all())  # 3 of 9 at its edges, 0 of 9 inside


def test_blend_in_schedule_by_hand():
    assert blend_weight(0, -3e-3) == 1.0  # every pixel trains at the start
    assert blend_weight(1, -3e-3) == pytest.approx(math.exp(-3e-3))  # floor(2 / 1.5) = 1
    assert blend_weight(2999, -3e-3) == pytest.approx(math.exp(-6.0))  # floor(3000 / 1.5) = 2000


def test_the_threshold_statistic_is_the_codes_column_means_or_the_pixels():
    rendered = torch.zeros(1, 3, 4, 2)
    target = torch.zeros(1, 3, 4, 2)
    target[:, :, 0, 0] = 0.8  # one bright pixel in the first column
    for statistic, expected in (("column", 0.2), ("pixel", 0.8)):
        loss = RobustFilter(RobustFilter.Config(bins=10, blend_in=False, reset_group="", percentile=1.0,
                                                statistic=statistic))
        loss(_ctx(rendered, target))
        # the largest value: a column mean of 0.8 / 4 rows, or the pixel itself
        assert loss.threshold == pytest.approx(expected)


def test_robust_filter_trains_only_inliers_once_blended_in():
    rendered = torch.full((1, 3, 12, 12), 0.5)
    target = rendered.clone()
    target[..., 3:8, 3:8] = 1.0  # a 5 x 5 distractor
    loss = RobustFilter(RobustFilter.Config(blend_in=False, reset_group=""))
    loss.threshold = 0.1
    x = rendered.clone().requires_grad_(True)
    value = loss(_ctx(x, target))
    value.backward()
    # trimmed but for the blob's four corners (5 of 9 neighbours clean): L1 of 0.5 there
    assert float(value.detach()) == pytest.approx(4 * 0.5 / 144)
    assert float(x.grad[..., 4:7, 4:7].abs().max()) == 0.0
    # blended in at the first step (a = 1): every pixel trains, the plain L1
    loss = RobustFilter(RobustFilter.Config(reset_group=""))
    loss.threshold = 0.1
    assert float(loss(_ctx(rendered, target, step=0))) == pytest.approx(
        float((rendered - target).abs().mean()))
    state = loss.state_dict()
    other = RobustFilter(RobustFilter.Config(reset_group=""))
    other.load_state_dict(state)
    assert torch.equal(other.hist, loss.hist) and other.threshold == loss.threshold


def test_sh_reset_clamps_the_group_once_at_its_step_and_restarts_its_moments():
    shN = torch.nn.Parameter(torch.tensor([[-0.5, 0.2, 0.0005]]))
    opt = torch.optim.Adam([shN], lr=0.1)
    shN.grad = torch.ones_like(shN)
    opt.step()
    reset = RobustFilter(RobustFilter.Config()).callbacks()[0]
    assert isinstance(reset, ParamReset)
    before = shN.detach().clone()
    state = lambda step: TrainState(step, 1500, "fit", {"shN": opt}, torch.device("cpu"))  # noqa: E731
    reset.after_step(state(398))  # step 8002 of 30k is step 400 of 1500
    assert torch.equal(shN.detach(), before)
    reset.after_step(state(399))
    assert torch.allclose(shN.detach(), before.clamp(max=0.001))
    assert float(opt.state[shN]["exp_avg"].abs().max()) == 0.0
    assert reset.state_dict() == {"done": True}
