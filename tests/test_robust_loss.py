"""The RobustNeRF-style trimmed loss: which pixels it keeps, its running threshold, its state."""

from __future__ import annotations

import pytest
import torch

from rainyscape.components import LossContext, RenderOutput
from rainyscape.losses.robust import (RobustPhotometric, block_inliers, pixel_residuals, robust_mask,
                                      smoothed_inliers)


def _outlier_image(seed: int = 0):
    """A render, and a target = render + faint noise + a 14 x 14 blob of clutter + three
    isolated bright pixels (fine texture the field has not learnt yet)."""
    g = torch.Generator().manual_seed(seed)
    rendered = torch.rand(1, 3, 48, 48, generator=g) * 0.5 + 0.25
    target = rendered + 0.01 * torch.randn(rendered.shape, generator=g)
    blob = torch.zeros(1, 1, 48, 48, dtype=torch.bool)
    blob[..., 18:32, 6:20] = True
    target = torch.where(blob, torch.ones_like(target), target)
    spikes = [(5, 40), (40, 5), (40, 40)]
    for y, x in spikes:
        target[..., y, x] += 0.3
    return rendered, target.clamp(0, 1), blob[0, 0], spikes


def _ctx(rendered, target, step=0):
    return LossContext(rendered, target, {}, RenderOutput(rendered), torch.zeros(1, dtype=torch.long),
                       step, "warmup")


def test_mask_trims_the_clutter_and_keeps_the_rest():
    rendered, target, blob, spikes = _outlier_image()
    residual = pixel_residuals(rendered, target, "l2")
    thr = torch.quantile(residual.flatten(), 0.8)
    mask = robust_mask(residual, thr, smooth_size=3, smooth_threshold=0.5, block_size=16, block_threshold=0.9)[0, 0]
    assert float(mask[blob].mean()) < 0.03  # the clutter is trimmed (smoothing rounds its 4 corners)
    assert float(mask[19:31, 7:19].max()) == 0.0
    assert float(mask[~blob].mean()) > 0.99
    for y, x in spikes:  # isolated outliers among inliers are kept by the smoothing
        assert mask[y, x] == 1
        assert (residual[0, 0, y, x] > thr)


def test_smoothing_and_block_decisions():
    inlier = torch.ones(1, 1, 16, 16)
    inlier[..., 3, 3] = 0  # a lone outlier: neighbours outvote it
    inlier[..., 8:12, 8:12] = 0  # a 4x4 cluster: its core stays out
    smooth = smoothed_inliers(inlier, 3, 0.5)
    assert smooth[0, 0, 3, 3] == 1 and smooth[0, 0, 10, 10] == 0
    scattered = (torch.arange(256).reshape(1, 1, 16, 16) % 3 != 0).float()  # 2/3 inliers, spread out
    assert bool((block_inliers(scattered, 8, 0.5) == 1).all())
    assert bool((block_inliers(scattered, 8, 0.7) == 0).all())
    assert bool((block_inliers(scattered, 0, 0.5) == 0).all())  # block decisions off


def test_threshold_comes_from_recent_batches_and_is_checkpointed():
    loss = RobustPhotometric(RobustPhotometric.Config(history=2))
    rendered, target, blob, _ = _outlier_image()
    assert loss.threshold() is None
    loss(_ctx(rendered, target))
    first = loss.threshold()
    assert first == pytest.approx(float(torch.quantile(pixel_residuals(rendered, target, "l2").flatten(), 0.8)),
                                  rel=1e-5)
    # A batch that is pure clutter cannot lower its own bar: it is judged by the learnt threshold.
    loss(_ctx(rendered, torch.ones_like(target)))
    assert loss.metrics["threshold"] == pytest.approx(first, rel=1e-6)
    assert loss.metrics["inlier_fraction"] < 0.2
    saved = loss.state_dict()
    restored = RobustPhotometric(RobustPhotometric.Config(history=2))
    restored.load_state_dict(saved)
    a, b = loss(_ctx(rendered, target)), restored(_ctx(rendered, target))
    assert float(a) == float(b) and loss.metrics == restored.metrics
    assert len(loss.recent) == 2  # history bounds the memory


@pytest.mark.parametrize("config", [RobustPhotometric.Config(),
                                    RobustPhotometric.Config(residual="l1", ssim_weight=0.2)])
def test_no_gradient_flows_from_trimmed_pixels(config):
    rendered, target, blob, _ = _outlier_image()
    loss = RobustPhotometric(config)
    loss(_ctx(rendered, target))  # learn the threshold
    x = rendered.clone().requires_grad_(True)
    value = loss(_ctx(x, target))
    value.backward()
    grad = x.grad.abs().sum(1)[0]
    core = torch.zeros_like(blob)
    core[24:26, 12:14] = True  # 6 px inside the blob: beyond the reach of D-SSIM's 11 x 11 window
    assert torch.isfinite(value) and float(grad[core].max()) == 0.0
    assert float(grad[~blob].mean()) > 0


def test_bad_options_are_config_errors():
    from rainyscape.errors import ConfigError

    with pytest.raises(ConfigError, match="inlier_quantile"):
        RobustPhotometric(RobustPhotometric.Config(inlier_quantile=0.0))
    with pytest.raises(ConfigError, match="ssim_weight"):
        RobustPhotometric(RobustPhotometric.Config(ssim_weight=1.5))
