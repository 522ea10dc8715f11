"""A latent update's energy: what it leaves out and what it computes once (engine/loss_sum.py,
LossContext.memo). Each Langevin step evaluates the energy again on the same crop; on a GPU
every operator is a launch and every value read back a wait, so what does not depend on the
predicted layer is computed once per crop, and terms constant in the layer are left out."""

from __future__ import annotations

from dataclasses import replace

import torch

from rainyscape.components import LossContext, RenderOutput
from rainyscape.config import LossConfig
from rainyscape.engine.loss_sum import compute_losses, energy_terms
from rainyscape.losses.agr import AdaptiveGradientRotation
from rainyscape.losses.l1_ssim import L1SSIM
from rainyscape.losses.rain_losses import Reconstruction
from rainyscape.testing.streaks import streak_layer, textured_background


def _ctx(rain: torch.Tensor, size: int = 32) -> LossContext:
    g = torch.Generator().manual_seed(0)
    background = textured_background(size, g).expand(1, 3, size, size)
    target = (background + streak_layer(size, 20.0, 12, g)).clamp(0, 1)
    return LossContext(background, target, {"rain": rain}, RenderOutput(rgb=background),
                       torch.tensor([0]), step=0, phase="joint", record=False)


def test_energy_leaves_out_the_terms_that_see_the_layer_detached():
    terms = {"fit": (LossConfig("l1-ssim", detach="rain"), L1SSIM()),
             "reconstruction": (LossConfig("reconstruction"), Reconstruction()),
             "agr": (LossConfig("agr", detach="rendered"), AdaptiveGradientRotation())}
    assert list(energy_terms(terms, "rain")) == ["reconstruction", "agr"]
    # and what is left has the same gradient in the layer as all of them
    rain = torch.rand(1, 3, 32, 32, generator=torch.Generator().manual_seed(2)).mul(0.1).requires_grad_(True)
    ctx = _ctx(rain)
    g_all, = torch.autograd.grad(compute_losses(terms, ctx)[0], rain)
    g_kept, = torch.autograd.grad(compute_losses(energy_terms(terms, "rain"), replace(ctx, memo={}))[0], rain)
    assert torch.allclose(g_all, g_kept, atol=1e-7)


def test_memo_computes_once_per_context_and_its_copies():
    ctx = _ctx(torch.zeros(1, 3, 32, 32))
    calls = []
    compute = lambda: calls.append(1) or len(calls)  # noqa: E731
    assert ctx.memoized("k", compute) == 1
    assert replace(ctx, layers={}).memoized("k", compute) == 1  # a copy with another layer: shared
    assert replace(ctx, memo={}).memoized("k", compute) == 2  # a new batch: its own
    assert len(calls) == 2


def test_agr_reuses_its_angles_and_still_follows_the_prediction(monkeypatch):
    """Two Langevin steps on one crop: the streak angles (from the detached residual) are
    estimated once, and each step's value is the one a fresh context gives."""
    agr = AdaptiveGradientRotation()
    estimates = []
    original = agr.estimate
    monkeypatch.setattr(agr, "estimate", lambda ctx: estimates.append(1) or original(ctx))
    g = torch.Generator().manual_seed(3)
    ctx = _ctx(torch.zeros(1, 3, 32, 32))
    for _ in range(2):
        rain = torch.rand(1, 3, 32, 32, generator=g) * 0.2
        step = agr(replace(ctx, layers={"rain": rain}))
        fresh = agr(replace(ctx, layers={"rain": rain}, memo={}))
        assert torch.equal(step, fresh)
    assert len(estimates) == 3  # once for the shared crop, once for each fresh context
