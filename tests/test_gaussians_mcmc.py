"""The MCMC densification strategy (fields/gaussians/mcmc.py): relocation keeps what a
Gaussian renders, dead Gaussians move onto live ones, growth stops at the cap, and the field
trains with it end to end."""

from __future__ import annotations

import torch

from rainyscape.cameras import Window
from rainyscape.fields.gaussians.field import GaussianField
from rainyscape.fields.gaussians.mcmc import MCMCStrategy, relocated_opacity_scale
from rainyscape.fields.gaussians.rasterize import rasterize
from test_gaussians import adam_for, make_field, train_state


def _alpha(opacity: float, scale: float, copies: int) -> torch.Tensor:
    """Alpha of ``copies`` identical round Gaussians 2 units in front of a 64 px camera."""
    means = torch.tensor([[0.0, 0.0, 2.0]]).repeat(copies, 1)
    quats = torch.tensor([[1.0, 0, 0, 0]]).repeat(copies, 1)
    k = torch.tensor([[[100.0, 0, 32], [0, 100, 32], [0, 0, 1]]])
    out = rasterize(means, quats, torch.full((copies, 3), scale), torch.full((copies,), opacity),
                    torch.ones(copies, 3), torch.eye(4)[None], k, 64, 64, backend="torch")
    return out.alpha[0, ..., 0]


def test_copies_of_a_relocated_gaussian_render_like_it():
    o, s = torch.tensor([0.3, 0.6, 0.9]), torch.full((3, 3), 0.1)
    same_o, same_s = relocated_opacity_scale(o, s, torch.ones(3))
    assert torch.allclose(same_o, o) and torch.allclose(same_s, s)  # one copy: itself
    for opacity in (0.3, 0.6, 0.9):
        one = _alpha(opacity, 0.1, 1)
        for n in (2, 4):
            new_o, new_s = relocated_opacity_scale(torch.tensor([opacity]), torch.full((1, 3), 0.1),
                                                   torch.tensor([n]))
            assert torch.allclose(1 - (1 - new_o) ** n, torch.tensor([opacity]))  # as opaque together
            many = _alpha(float(new_o), float(new_s[0, 0]), n)
            assert abs(float(many.max() - one.max())) < 5e-3  # the centre is as opaque
            assert abs(float(many.sum() / one.sum()) - 1) < 0.1  # and the footprint about as large
            assert new_s[0, 0] < 0.1  # each copy smaller than the original


def test_dead_gaussians_move_onto_live_ones_and_growth_stops_at_the_cap(tiny_scene):
    field = make_field(tiny_scene, init_points=300, strategy="mcmc", max_gaussians=320)
    opts = adam_for(field)
    strategy = field.strategy
    assert isinstance(strategy, MCMCStrategy) and strategy.cap == 320
    sum(p.sum() for p in field.params.values()).backward()
    for o in opts.values():
        o.step()
    with torch.no_grad():
        field.params["opacities"][:40] = -10.0  # dead
    live_means = field.params["means"].detach()[40:].clone()
    assert strategy.relocate(field.params, opts) == 40
    moved = field.params["means"].detach()[:40]
    assert (moved[:, None] - live_means[None]).norm(dim=-1).min(1).values.max() == 0  # each onto a live one
    assert torch.sigmoid(field.params["opacities"]).min() > strategy.min_opacity
    assert strategy.add(field.params, opts) == 15  # 5 % more
    assert strategy.add(field.params, opts) == 5 and strategy.add(field.params, opts) == 0  # the cap
    assert field.num_gaussians == 320
    for name, p in field.params.items():  # optimisers follow every change
        assert opts[name].state[p]["exp_avg"].shape == p.shape


def test_noise_moves_transparent_gaussians_and_leaves_opaque_ones(tiny_scene):
    field = make_field(tiny_scene, init_points=200, strategy="mcmc")
    with torch.no_grad():
        field.params["opacities"][:100] = -8.0  # nearly transparent
        field.params["opacities"][100:] = 4.0  # opaque
    before = field.params["means"].detach().clone()
    field.strategy.inject_noise(field.params, lr_means=1e-4)
    step = (field.params["means"].detach() - before).norm(dim=-1)
    assert step[:100].mean() > 100 * step[100:].mean() and step[:100].mean() > 0


def test_mcmc_trains_with_its_regularisers_within_the_cap(tiny_scene):
    field = make_field(tiny_scene, init_points=200, strategy="mcmc", max_gaussians=260,
                       refine_start=1, refine_every=2, reference_iters=20)
    opts = adam_for(field)
    cb = field.callbacks()[0]
    cams = tiny_scene.cameras[[0]]
    target = tiny_scene.images[0].permute(2, 0, 1)[None].float() / 255
    first = None
    for step in range(20):
        state = train_state(opts, step=step, max_iters=20)
        cb.before_step(state)
        out = field.train().render(cams, Window.full(cams))
        extra = field.extra_losses(out, target)
        assert set(extra) == {"opacity_reg", "scale_reg"}
        loss = (out.rgb - target).abs().mean() + sum(extra.values())
        first = float(loss.detach()) if first is None else first
        for o in opts.values():
            o.zero_grad()
        loss.backward()
        cb.after_backward(state, out)
        for o in opts.values():
            o.step()
        cb.after_step(state)
        for group in field.param_groups():
            opts[group.name].param_groups[0]["params"] = group.params
        assert field.num_gaussians <= 260
    assert field.num_gaussians == 260 and field.events["added"] == 60
    assert float(loss.detach()) < first
