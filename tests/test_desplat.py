"""DeSplat's pieces: the over-compositing of the distractor layer, the per-view distractor
Gaussians (each view renders its own only), DeSplat's loss and the per-view densification."""

from __future__ import annotations

import pytest
import torch

from rainyscape.cameras import Window
from rainyscape.components import LossContext, RenderOutput, TrainState
from rainyscape.distractors.head import DistractorGaussians
from rainyscape.imaging.compositing import over
from rainyscape.losses.desplat import DistractorComposite


def test_over_composites_by_hand():
    layer = torch.tensor([0.2, 0.2, 0.2, 0.5]).reshape(1, 4, 1, 1)  # premultiplied colour, alpha
    below = torch.tensor([1.0, 0.0, 0.4]).reshape(1, 3, 1, 1)
    assert torch.allclose(over(layer, below).flatten(), torch.tensor([0.7, 0.2, 0.4]))
    with pytest.raises(ValueError, match="4 channels"):
        over(below, below)


@pytest.fixture(scope="module")
def head(tiny_scene):
    return DistractorGaussians(DistractorGaussians.Config(gaussians_per_view=200, reference_pixels=0, backend="torch"), tiny_scene)


def _full(scene, view: int) -> tuple[torch.Tensor, Window]:
    zeros = torch.zeros(1, dtype=torch.long)
    return torch.tensor([view]), Window(zeros, zeros.clone(), scene.width, scene.height)


def test_a_view_starts_with_desplats_density_of_distractors(tiny_scene):
    # 1000 per 504 x 378 px view (DeSplat's images): 1000 x 48 x 48 / 190512 = 12 here
    head = DistractorGaussians(DistractorGaussians.Config(backend="torch"), tiny_scene)
    assert head.initial_count() == round(1000 * 48 * 48 / (504 * 378)) == 12
    assert set(head.counts().values()) == {12}


def test_each_view_renders_only_its_own_distractors(head, tiny_scene):
    a, b = head.views[0], head.views[1]
    layer_a = head(*_full(tiny_scene, a))
    assert layer_a.shape == (1, 4, tiny_scene.height, tiny_scene.width)
    alpha = layer_a[:, 3]
    assert 0.05 < float(alpha.detach().mean()) < 0.95  # the initial Gaussians cover the view, partly
    assert float((layer_a[:, :3] - alpha[:, None]).detach().max()) <= 1e-5  # premultiplied: colour <= alpha
    with torch.no_grad():
        head.params_of(b)["colors"].add_(0.3)
        head.params_of(b)["opacities"].add_(2.0)
    assert torch.equal(head(*_full(tiny_scene, a)), layer_a)  # b's Gaussians do not show in a
    held_out = [i for i in range(tiny_scene.num_images) if i not in head.views]
    if held_out:  # a view without distractors gets an empty layer
        assert float(head(*_full(tiny_scene, held_out[0])).abs().max()) == 0.0


def test_the_loss_composites_the_layer_over_the_render_and_trains_only_that_views_set(head, tiny_scene):
    view = head.views[2]
    ids, window = _full(tiny_scene, view)
    head.train()
    layer = head(ids, window)
    rendered = torch.full((1, 3, tiny_scene.height, tiny_scene.width), 0.3, requires_grad=True)
    acc = torch.ones(1, 1, tiny_scene.height, tiny_scene.width)
    target = torch.rand(1, 3, tiny_scene.height, tiny_scene.width, generator=torch.Generator().manual_seed(0))
    term = DistractorComposite(DistractorComposite.Config(ssim_weight=0.0, distractor_alpha_weight=0.0))
    ctx = LossContext(rendered, target, {"distractor": layer}, RenderOutput(rendered, acc=acc), ids, 0, "fit")
    value = term(ctx)
    assert float(value.detach()) == pytest.approx(float((over(layer, rendered) - target).abs().mean().detach()), rel=1e-6)
    assert torch.allclose(head.composite(rendered, layer), over(layer, rendered))
    for p in head.parameters():
        p.grad = None
    value.backward()
    # the render's gradient is scaled by what the layer leaves visible: (1 - alpha_D)
    sign = torch.sign(over(layer, rendered) - target).detach()
    expected = sign * (1 - layer[:, 3:].detach()) / target.numel()
    assert torch.allclose(rendered.grad, expected, atol=1e-7)
    assert head.params_of(view)["colors"].grad is not None
    assert head.params_of(head.views[0])["colors"].grad is None


def test_an_opaque_layer_that_explains_the_view_leaves_the_render_untrained():
    target = torch.rand(1, 3, 8, 8, generator=torch.Generator().manual_seed(1))
    layer = torch.cat([target, torch.ones(1, 1, 8, 8)], 1)
    rendered = torch.zeros(1, 3, 8, 8, requires_grad=True)
    term = DistractorComposite(DistractorComposite.Config(ssim_weight=0.2, static_alpha_weight=0.0))
    value = term(LossContext(rendered, target, {"distractor": layer}, None, torch.zeros(1, dtype=torch.long), 0, "fit"))
    value.backward()
    assert float(value.detach()) == pytest.approx(0.01, abs=1e-5)  # only the alpha regulariser: 0.01 x mean(1)
    assert float(rendered.grad.abs().max()) == 0.0


def test_densification_culls_transparent_and_clones_high_gradient_distractors(tiny_scene):
    cfg = DistractorGaussians.Config(gaussians_per_view=50, reference_pixels=0, backend="torch", refine_every_views=1,
                                      refine_stop=1.0)
    head = DistractorGaussians(cfg, tiny_scene)
    optimizers = {g.name: torch.optim.Adam(g.params, lr=g.lr) for g in head.param_groups()}
    view = head.views[0]
    n = head.counts()[view]
    with torch.no_grad():
        head.params_of(view)["opacities"][:10] = -6.0  # ten nearly transparent ones
    head.train()
    layer = head(*_full(tiny_scene, view))
    (layer[:, :3].sum() * 100).backward()  # a strong gradient on the visible ones
    cb = head.callbacks()[0]
    state = TrainState(len(head.views) - 1, 1000, "fit", optimizers, torch.device("cpu"))
    cb.after_backward(state, RenderOutput(layer))
    cb.after_step(state)  # refines after a pass over the views
    assert cb.events["culled"] >= 10 and cb.events["cloned"] + cb.events["split"] > 0
    new = head.counts()[view]
    assert new == n + cb.events["cloned"] + cb.events["split"] - cb.events["culled"]
    assert head.counts()[head.views[1]] == 50  # a view not rendered since is left alone
    # the optimisers hold the new tensors, and a step after the surgery runs
    params = head.params_of(view)
    assert any(p is params["means"] for p in optimizers["distractor_means"].param_groups[0]["params"])
    head(*_full(tiny_scene, view))[:, :3].sum().backward()
    for opt in optimizers.values():
        opt.step()
    # a checkpoint of the resized head loads into a fresh one
    fresh = DistractorGaussians(cfg, tiny_scene)
    fresh.load_state_dict(head.state_dict())
    assert fresh.counts() == head.counts()


@pytest.mark.parametrize("backend", ["torch", "cpp"])
def test_absgrad_grows_a_distractor_whose_pixels_pull_it_opposite_ways(tiny_scene, backend):
    """DeSplat densifies with splatfacto's absolute 2D gradient (``absgrad``): a Gaussian
    inside the image under a loss on its total colour gets pulled equally both ways, so its
    net gradient (3DGS's statistic) is about zero while its absolute gradient is not."""
    from rainyscape.cameras import pixel_rays
    from rainyscape.fields.gaussians.rasterize_cpp import cpp_available

    if backend == "cpp" and not cpp_available():
        pytest.skip("the compiled rasteriser is not built")
    stats = {}
    for absgrad in (False, True):
        cfg = DistractorGaussians.Config(gaussians_per_view=1, reference_pixels=0, backend=backend,
                                          absgrad=absgrad, refine_every_views=1, refine_stop=1.0,
                                          grow_grad2d=1e-4, cull_opacity=0.0, split_screen=1.0)
        head = DistractorGaussians(cfg, tiny_scene)
        view = head.views[0]
        params = head.params_of(view)
        rays = pixel_rays(tiny_scene.cameras[[view]], torch.tensor([[23.5]]), torch.tensor([[23.5]]))
        with torch.no_grad():  # on the central ray, 3 px wide, half opaque
            params["means"][:] = (rays.origins + rays.directions * 0.5)[0].float()
            params["scales"][:] = torch.log(0.5 * 3 / tiny_scene.cameras.K()[view, 0, 0]).item()
            params["opacities"][:] = 0.0
        optimizers = {g.name: torch.optim.Adam(g.params, lr=g.lr) for g in head.param_groups()}
        head.train()
        layer = head(*_full(tiny_scene, view))
        layer[:, :3].sum().backward()  # the total colour: the same wherever it is inside the image
        cb = head.callbacks()[0]
        state = TrainState(len(head.views) - 1, 1000, "fit", optimizers, torch.device("cpu"))
        cb.after_backward(state, RenderOutput(layer))
        stats[absgrad] = float(cb.grad2d[view][0])
        cb.after_step(state)
        assert cb.events["cloned"] == (1 if absgrad else 0)
    assert stats[True] > 20 * stats[False]
