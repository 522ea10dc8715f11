"""The Gaussian field: initialisation, rendering, densification with optimiser state,
checkpoints with a changed number of Gaussians, .ply export, the 3DGS loss and methods,
and a short fit on the tiny scene."""

from __future__ import annotations

import copy
import json
import math
from dataclasses import replace
from types import SimpleNamespace

import pytest
import torch

from rainyscape.cameras import Window
from rainyscape.components import LossContext, RenderOutput, TrainState
from rainyscape.config import method_config
from rainyscape.engine.loss_sum import compute_losses
from rainyscape.engine.pipeline import build_pipeline
from rainyscape.errors import ConfigError
from rainyscape.fields.gaussians.densify import DensifySchedule, ramped_cap
from rainyscape.fields.gaussians.field import GaussianField, growth_cap
from rainyscape.fields.gaussians.ops import replace_params
from rainyscape.fields.gaussians.ply import read_ply
from rainyscape.fields.gaussians.sh import SH_C0, sh_basis, sh_to_rgb
from rainyscape.losses.l1_ssim import L1SSIM


def make_field(scene, **options) -> GaussianField:
    return GaussianField(GaussianField.Config(**{"init_points": 2000, **options}), scene)


def adam_for(field: GaussianField) -> dict[str, torch.optim.Adam]:
    return {g.name: torch.optim.Adam(g.params, lr=g.lr, eps=g.eps) for g in field.param_groups()}


def train_state(optimizers, step=0, max_iters=100) -> TrainState:
    return TrainState(step, max_iters, "fit", optimizers, torch.device("cpu"))


def test_initialises_from_scene_points(tiny_scene):
    field = make_field(tiny_scene)
    assert field.num_gaussians == 2000
    p = field.params
    assert {k: tuple(v.shape) for k, v in p.items()} == {
        "means": (2000, 3), "scales": (2000, 3), "quats": (2000, 4), "opacities": (2000,),
        "sh0": (2000, 1, 3), "shN": (2000, 15, 3)}
    # every mean is one of the scene's points, with that point's colour
    d = torch.cdist(p["means"].detach(), tiny_scene.points.float(),
                    compute_mode="donot_use_mm_for_euclid_dist")
    nearest = d.argmin(1)
    assert d.min(1).values.max() < 1e-6
    rgb = p["sh0"].detach()[:, 0] * SH_C0 + 0.5
    assert torch.allclose(rgb, tiny_scene.point_colors[nearest].float() / 255, atol=1e-5)
    assert torch.allclose(torch.sigmoid(p["opacities"]), torch.tensor(0.1))
    # isotropic, sized by the RMS distance to the 3 nearest other initial points
    means = p["means"].detach().double()
    for i in (0, 7, 1999):
        d = (means - means[i]).norm(dim=-1).sort().values[1:4]
        assert torch.allclose(p["scales"][i].exp().double(), d.pow(2).mean().sqrt(), rtol=1e-4)


def test_random_initialisation_in_scene_box_or_gsplat_cube(tiny_scene):
    scene = replace(tiny_scene, points=None, point_colors=None)
    field = make_field(scene, random_points=500, random_extent=0.0)
    m = field.params["means"].detach()
    assert len(m) == 500
    assert (m >= scene.scene_box[0]).all() and (m <= scene.scene_box[1]).all()
    # gsplat's: a cube of 3 x the scene extent about the training cameras' centroid
    field = make_field(scene, random_points=2000)
    m = field.params["means"].detach()
    centre = scene.cameras[scene.train_indices].centers.float().mean(0)
    offset = (m - centre).abs()
    assert offset.max() <= 3 * field.extent + 1e-4 and offset.max() > 2.8 * field.extent
    # init=random ignores the scene's points; init=points needs them
    assert make_field(tiny_scene, init="random", random_points=300).num_gaussians == 300
    with pytest.raises(ConfigError, match="no sparse points"):
        make_field(scene, init="points")


def test_forward_facing_captures_without_points_start_in_the_training_frustums(tiny_scene):
    """An LLFF capture without sparse points (the authors' Yard): a cube about the cameras
    would put every Gaussian in front of the lenses; the frustum init puts each on a training
    pixel's ray between the near and far bounds, in that pixel's colour."""
    from rainyscape.fields.gaussians.field import frustum_points, init_mode

    scene = replace(tiny_scene, points=None, point_colors=None, forward_facing=True)
    assert init_mode("auto", scene) == "frustum" and init_mode("auto", tiny_scene) == "points"
    assert init_mode("auto", replace(scene, forward_facing=False)) == "random"
    points, colors = frustum_points(scene, 400, torch.Generator().manual_seed(0))
    cams = scene.cameras[scene.train_indices]
    uv, z = cams.project(points)
    inside = ((uv[..., 0] >= 0) & (uv[..., 0] <= scene.width) & (uv[..., 1] >= 0) & (uv[..., 1] <= scene.height)
              & (z >= scene.near * 0.999) & (z <= scene.far * 1.001))
    # every point is on a pixel centre's ray of a training view, within its bounds ...
    source = inside & ((uv - uv.floor() - 0.5).abs() < 2e-3).all(-1)
    assert source.any(0).all()
    # ... and has that pixel's colour
    b = source.float().argmax(0)
    px = uv[b, torch.arange(len(points))].floor().long()
    train = torch.tensor(scene.train_indices)
    assert torch.allclose(scene.images[train[b], px[:, 1], px[:, 0]].float() / 255.0, colors)
    field = make_field(scene, random_points=300)
    assert field.num_gaussians == 300


def test_sh_degree_zero_is_view_independent_and_matches_basis():
    dirs = torch.nn.functional.normalize(torch.randn(2, 5, 3), dim=-1)
    coeffs = torch.randn(5, 16, 3)
    rgb0 = sh_to_rgb(coeffs, dirs, 0)
    assert torch.allclose(rgb0[0], rgb0[1])
    assert torch.allclose(rgb0[0], (coeffs[:, 0] * SH_C0 + 0.5).clamp_min(0))
    # the degree-3 basis is orthonormal on the sphere (Monte Carlo check)
    d = torch.nn.functional.normalize(torch.randn(200_000, 3, dtype=torch.float64), dim=-1)
    b = sh_basis(d, 3)
    gram = b.T @ b / len(d) * 4 * math.pi
    assert torch.allclose(gram, torch.eye(16, dtype=torch.float64), atol=0.03)


def test_render_window_and_training_extras(tiny_scene):
    field = make_field(tiny_scene).train()
    cams = tiny_scene.cameras[[0, 3]]
    window = Window(torch.tensor([8, 20]), torch.tensor([4, 16]), 24, 20)
    out = field.render(cams, window)
    assert out.rgb.shape == (2, 3, 20, 24) and out.depth.shape == (2, 1, 20, 24)
    assert out.acc.shape == (2, 1, 20, 24) and 0.3 < float(out.acc.detach().mean()) <= 1
    out.rgb.mean().backward()
    means2d = out.extras["means2d"]
    assert means2d.shape == (2, 2000, 2) and means2d.grad is not None
    assert out.extras["radii"].shape == (2, 2000, 2)
    assert all(p.grad is not None for p in field.params.values() if p.numel())
    field.eval()
    with torch.no_grad():
        full = field.render(cams, Window.full(cams))
    part = field.render(cams, window)
    assert torch.allclose(part.rgb[1], full.rgb[1, :, 16:36, 20:44], atol=1e-5)


def test_param_groups_have_3dgs_rates(tiny_scene):
    field = make_field(tiny_scene)
    groups = {g.name: g for g in field.param_groups()}
    assert list(groups) == ["means", "scales", "quats", "opacities", "sh0", "shN"]
    assert all(len(g.params) == 1 for g in groups.values())
    assert groups["means"].lr == pytest.approx(1.6e-4 * field.extent)
    assert groups["means"].lr_decay == pytest.approx(0.01)
    assert groups["opacities"].lr == 0.05 and groups["shN"].lr == pytest.approx(2.5e-3 / 20)


def test_schedule_scales_with_run_length():
    s = DensifySchedule.scaled(3000, 30_000, 500, 15_000, 100, 3000, 1000)
    assert (s.start, s.stop, s.every, s.reset_every, s.sh_every) == (50, 1500, 10, 300, 100)
    assert DensifySchedule.scaled(30_000, 30_000, 500, 15_000, 100, 3000, 1000).stop == 15_000
    # opacity resets keep a floor: recovering from one takes a fixed number of steps
    assert DensifySchedule.scaled(3000, 30_000, 500, 15_000, 100, 3000, 1000, 1000).reset_every == 1000
    # and so do refinements: new Gaussians settle before they are judged again
    assert DensifySchedule.scaled(3000, 30_000, 500, 15_000, 100, 3000, 1000, 1000, 100).every == 100
    # the first refinement and the SH degree steps have floors of their own
    s = DensifySchedule.scaled(1500, 30_000, 500, 15_000, 100, 3000, 1000, min_start=200, min_sh_every=250)
    assert (s.start, s.sh_every, s.stop) == (200, 250, 750)


def test_schedule_shape_long_run_is_the_papers():
    """At the paper's 30k steps: SH degree +1 every 1000, refinements every 100 after step 500
    and before 15k, opacity resets at 3k, 6k, 9k, 12k (each followed by 3k of densification)."""
    s = DensifySchedule.scaled(30_000, 30_000, 500, 15_000, 100, 3000, 1000, 1000, 0, 0, 0)
    assert s.resets() == [3000, 6000, 9000, 12_000]
    refines = [it for it in range(1, 30_001) if s.refines_at(it)]
    assert refines[0] == 600 and refines[-1] == 14_900 and len(refines) == 144
    assert [s.sh_degree_at(step, 3) for step in (0, 998, 999, 1999, 2999, 29_999)] == [0, 0, 1, 2, 3, 3]


@pytest.mark.parametrize("method", ["3dgs", "rainyscape-3dgs", "rainyscape-plus", "robust-3dgs", "desplat"])
def test_gpu_recipe_cut_short_keeps_the_papers_refinement_interval(method):
    """The GPU recipe at 30k steps is the paper's schedule; cut short, its window shrinks but
    refinements stay 100 steps apart (stretched to 17 at 5k steps, a run without a Gaussian
    cap grew fern's 569 points to 938k Gaussians: docs/profiles.md)."""
    opts = method_config(method, ["profile=gpu", "trainer.device=cpu"]).field.options
    def schedule(steps):
        return GaussianField.schedule(SimpleNamespace(config=opts), steps)
    full, short = schedule(30_000), schedule(5000)
    assert (full.stop, full.every) == (15_000, 100)
    assert (short.stop, short.every) == (2500, 100)


def test_schedule_shape_short_runs_leave_time_to_recover():
    """Short runs: resets only where a whole reset interval of densification follows."""
    four_k = DensifySchedule.scaled(4000, 30_000, 500, 15_000, 100, 3000, 1000, 1000)
    assert four_k.stop == 2000 and four_k.resets() == [1000]
    assert DensifySchedule.scaled(3000, 30_000, 500, 15_000, 100, 3000, 1000, 1000).resets() == []
    assert DensifySchedule.scaled(1500, 30_000, 500, 15_000, 100, 3000, 1000, 1000, 100).resets() == []
    short = DensifySchedule.scaled(1500, 30_000, 500, 15_000, 100, 3000, 1000, 250, 100)
    assert short.resets() == [250, 500]  # each followed by at least 250 steps of densification
    assert all(r + short.reset_every <= short.stop for r in short.resets())
    # no refinement, statistic or reset at or after the stop
    assert not any(short.refines_at(it) or short.resets_at(it) for it in range(short.stop, 1501))


def test_growth_cap_is_the_smaller_of_the_absolute_and_per_pixel_caps():
    assert growth_cap(0, 0, 10_000) == 0  # no limit
    assert growth_cap(40_000, 0, 10_000) == 40_000
    assert growth_cap(40_000, 20, 18 * 64 * 64) == 3686  # a 64 px scene: the per-pixel cap
    assert growth_cap(40_000, 20, 21 * 192 * 192) == 38_707
    assert growth_cap(30_000, 20, 21 * 192 * 192) == 30_000
    assert growth_cap(0, 20, 18 * 64 * 64) == 3686


def test_replace_params_keeps_adam_state_consistent():
    params = torch.nn.ParameterDict({"a": torch.nn.Parameter(torch.randn(5, 2)),
                                     "b": torch.nn.Parameter(torch.randn(5))})
    opts = {k: torch.optim.Adam([p], lr=0.1) for k, p in params.items()}
    (params["a"].sum() + params["b"].pow(2).sum()).backward()
    for o in opts.values():
        o.step()
    moments = opts["a"].state[params["a"]]["exp_avg"].clone()
    keep = torch.tensor([True, False, True, True, False])
    replace_params(params, opts, lambda name, p: torch.cat([p[keep], p[:1]]),
                   lambda v: torch.cat([v[keep], torch.zeros_like(v[:1])]))
    for name, p in params.items():
        assert opts[name].param_groups[0]["params"][0] is p and len(p) == 4
        state = opts[name].state[p]
        assert state["exp_avg"].shape == p.shape and state["exp_avg_sq"].shape == p.shape
    assert torch.equal(opts["a"].state[params["a"]]["exp_avg"][:3], moments[keep])
    assert opts["a"].state[params["a"]]["exp_avg"][3].abs().sum() == 0
    params["a"].sum().backward()
    opts["a"].step()  # the optimiser still works on the new tensor


def test_grow_clones_small_and_splits_large(tiny_scene):
    field = make_field(tiny_scene, init_points=200)
    opts = adam_for(field)
    cb = field.callbacks()[0]
    dens = cb.strategy
    n = field.num_gaussians
    with torch.no_grad():  # half of them below the clone / split size threshold
        field.params["scales"][::2] = math.log(0.5 * dens.grow_scale3d * dens.extent)
    small = field.params["scales"].exp().amax(-1) <= dens.grow_scale3d * dens.extent
    assert small.any() and (~small).any()
    dens.grad2d = torch.zeros(n)
    dens.count = torch.ones(n)
    chosen = torch.zeros(n, dtype=torch.bool)
    chosen[:20] = True
    dens.grad2d[chosen] = 1.0
    parents = {k: v.detach().clone() for k, v in field.params.items()}
    n_clone, n_split = dens.grow(field.params, opts)
    assert n_clone == int((chosen & small).sum()) and n_split == int((chosen & ~small).sum())
    assert field.num_gaussians == n + n_clone + n_split
    split_parents = chosen & ~small
    children_scales = field.params["scales"].detach()[-2 * n_split:]
    expected = (parents["scales"][split_parents] - math.log(1.6)).repeat_interleave(2, 0)
    assert torch.allclose(children_scales, expected)
    field.sync_param_groups()
    assert all(opts[g.name].param_groups[0]["params"][0] is g.params[0] for g in field._groups.values())


def test_ramped_cap():
    assert ramped_cap(50_000, 0.5, 1.0) == 25_000  # half the window: half the cap
    assert ramped_cap(50_000, 0.25, 0.5) == 25_000
    assert ramped_cap(50_000, 0.9, 0.5) == 50_000  # past the ramp: the whole cap
    assert ramped_cap(50_000, 0.1, 0.0) == 50_000  # no ramp
    assert ramped_cap(0, 0.5, 1.0) == 0  # no cap stays none


def test_ramped_cap_holds_growth_back_early(tiny_scene):
    """With cap_ramp, a refinement early in the window grows nothing past the ramp's share;
    later the same candidates grow up to the cap."""
    field = make_field(tiny_scene, init_points=200, max_gaussians=400, cap_ramp=1.0, grow_grad2d=0.0,
                       refine_start=1, refine_every=1, refine_stop=100, reference_iters=100)
    opts = adam_for(field)
    dens = field.callbacks()[0].strategy
    n = field.num_gaussians

    def refine_at(step: int) -> None:
        dens.grad2d = torch.ones(field.num_gaussians)
        dens.count = torch.ones(field.num_gaussians)
        dens.refine(train_state(opts, step=step, max_iters=100), field.params)

    refine_at(29)  # 30 % of the window: at most 120, fewer than the 200 there are
    assert field.num_gaussians == n
    refine_at(74)  # 75 %: up to 300
    assert field.num_gaussians == 300
    refine_at(98)  # 99 %: up to 396
    assert field.num_gaussians == 396


def test_prune_and_opacity_reset(tiny_scene):
    field = make_field(tiny_scene, init_points=300)
    opts = adam_for(field)
    field.params["opacities"].sum().backward()
    opts["opacities"].step()
    with torch.no_grad():
        field.params["opacities"][:50] = -10.0  # nearly transparent
    dens = field.callbacks()[0].strategy
    assert dens.prune(field.params, opts, prune_large=False) == 50
    assert field.num_gaussians == 250
    dens.reset_opacity(field.params, opts, 0.01)
    assert torch.sigmoid(field.params["opacities"]).max() <= 0.01 + 1e-6
    state = opts["opacities"].state[field.params["opacities"]]
    assert state["exp_avg"].abs().sum() == 0 and len(state["exp_avg"]) == 250


def test_callback_schedule_sh_degree_lr_and_densification(tiny_scene):
    field = make_field(tiny_scene, init_points=300, grow_grad2d=0.0, refine_start=1,
                       refine_every=2, sh_degree_every=10, reference_iters=100)
    opts = adam_for(field)
    cb = field.callbacks()[0]
    state = train_state(opts, step=49, max_iters=100)
    cb.before_step(state)
    assert int(field.active_sh_degree) == 3  # (49 + 1) // 1 step per degree at this scale
    means = next(g for g in field.param_groups() if g.name == "means")  # the schedule it states
    assert means.lr_at(state.step, state.max_iters) == pytest.approx(1.6e-4 * field.extent * 0.01 ** 0.49)
    cams = tiny_scene.cameras[[0]]
    out = field.train().render(cams, Window.full(cams))
    out.rgb.mean().backward()
    cb.after_backward(state, out)
    assert cb.strategy.count.sum() > 0
    before = field.num_gaussians
    cb.after_step(replace(state, step=9))  # 10th step: a refinement step
    assert field.num_gaussians > before and cb.last_stats["gaussians"] == field.num_gaussians


def test_state_dict_loads_other_gaussian_count(tiny_scene):
    a = make_field(tiny_scene, init_points=400)
    b = make_field(tiny_scene, init_points=100, seed=3)
    a.active_sh_degree.fill_(2)
    b.param_groups()
    b.load_state_dict(a.state_dict())
    assert b.num_gaussians == 400 and int(b.active_sh_degree) == 2
    assert all(torch.equal(a.params[k], b.params[k]) for k in a.params)
    assert all(g.params[0] is b.params[g.name] for g in b._groups.values())
    cams = tiny_scene.cameras[[1]]
    with torch.no_grad():
        assert torch.equal(a.eval().render(cams, Window.full(cams)).rgb,
                           b.eval().render(cams, Window.full(cams)).rgb)


def test_ply_export_round_trip(tiny_scene, tmp_path):
    field = make_field(tiny_scene, init_points=50)
    with torch.no_grad():
        field.params["shN"].normal_()
        field.params["quats"].normal_()
    path = tmp_path / "point_cloud.ply"
    field.export_ply(path)
    header = path.read_bytes().split(b"end_header")[0].decode()
    assert "element vertex 50" in header and "property float f_rest_44" in header
    back = read_ply(path)
    p = {k: v.detach() for k, v in field.params.items()}
    original = tiny_scene.to_original(p["means"])
    assert torch.allclose(back["means"], original, atol=1e-5)
    assert torch.allclose(back["scales"], p["scales"] - math.log(tiny_scene.scale), atol=1e-6)
    for key in ("quats", "opacities", "sh0", "shN"):
        assert torch.equal(back[key], p[key]), key


def test_l1_ssim_loss_and_authors_split():
    g = torch.Generator().manual_seed(0)
    rendered = torch.rand(1, 3, 16, 16, generator=g, requires_grad=True)
    rain = (0.1 * torch.rand(1, 3, 16, 16, generator=g)).requires_grad_(True)
    target = torch.rand(1, 3, 16, 16, generator=g)
    ctx = LossContext(rendered, target, {"rain": rain}, RenderOutput(rendered), torch.tensor([0]), 0, "joint")
    plain = L1SSIM()(replace(ctx, layers={}))
    assert plain.item() == pytest.approx(0.8 * (rendered - target).abs().mean().item()
                                         + 0.2 * (1 - _ssim(rendered, target)), rel=1e-6)
    both = L1SSIM(L1SSIM.Config(with_rain=True, render_l1=True))(ctx)
    expected = (0.8 * ((rendered + rain - target).abs().mean() + (rendered - target).abs().mean())
                + 0.2 * (1 - _ssim(rendered + rain, target)))
    assert both.item() == pytest.approx(expected.item(), rel=1e-6)
    # rainyscape-3dgs routes gradients as the authors: Gaussians never push R, rain terms never push B
    cfg = method_config("rainyscape-3dgs")
    pipe_terms = {k: (c, _loss(c)) for k, c in cfg.losses.items() if "joint" in c.phases}
    gaussian_terms = {k: v for k, v in pipe_terms.items() if k in ("gaussians", "tv")}
    total, _ = compute_losses(gaussian_terms, ctx)
    grads = torch.autograd.grad(total, [rendered, rain], allow_unused=True)
    assert grads[0].abs().sum() > 0 and (grads[1] is None or grads[1].abs().sum() == 0)
    rain_terms = {k: v for k, v in pipe_terms.items() if k not in ("gaussians", "tv")}
    total, _ = compute_losses(rain_terms, ctx)
    grads = torch.autograd.grad(total, [rendered, rain], allow_unused=True)
    assert (grads[0] is None or grads[0].abs().sum() == 0) and grads[1].abs().sum() > 0


def _ssim(a, b):
    from rainyscape.imaging.metrics import ssim

    return ssim(a, b, padding="same").item()


def _loss(cfg):
    from rainyscape import registry

    return registry.load("loss", cfg.name)(cfg.options)


def test_method_configs():
    plain = method_config("3dgs")
    assert plain.field.name == "gaussians" and plain.rain_head is None
    assert list(plain.phases) == ["fit"]
    assert [(l.name, l.options.ssim_weight) for l in plain.losses.values()] == [("l1-ssim", 0.2)]
    rs = method_config("rainyscape-3dgs")
    assert rs.phases["warmup"].end == pytest.approx(4000 / 30000)
    assert rs.trainer.max_iters == plain.trainer.max_iters and rs.field == plain.field
    assert rs.losses["gaussians"].detach == "rain" and rs.losses["gaussians"].options.render_l1
    assert {rs.losses[k].detach for k in ("likelihood", "reconstruction", "agr")} == {"rendered"}
    assert rs.losses["photometric"].phases == ("warmup",)
    assert "rain-mask-fusion" in rs.postprocess
    # whole views in both phases, as 3dgs; latent updates on a 64 x 64 crop
    assert (rs.phases["warmup"].patch_size, rs.phases["joint"].patch_size) == (0, 0)
    assert rs.phases["joint"].heads == ("rain_head",) and rs.rain_head.options.latent_patch_size == 64


def _quiet_pipeline(method: str, scene, overrides: list[str]):
    """``method`` on ``scene`` with no periodic evaluation, checkpoints or progress bar."""
    cfg = method_config(method, overrides + ["trainer.eval_every=0", "trainer.checkpoint_every=0",
                                             "trainer.progress=false"])
    torch.manual_seed(0)
    return cfg, build_pipeline(cfg, scene, torch.device("cpu"))


def test_short_fit_raises_heldout_psnr(tiny_scene, tmp_path):
    """A few hundred steps of 3dgs on the 48 px tiny scene beat the initial render on the
    held-out view (clean image) by a margin measured on this scene: 12.96 -> 20.23-20.36 dB
    over three seeds. Growth is capped at 5000 Gaussians (uncapped, 48 px views grow to 40000
    and the fit takes 5x longer); refinements every 10 steps up to step 100 (the CPU
    recipe's 100-step floor would leave none in a 200-step run)."""
    from rainyscape.engine.trainer import Trainer
    from rainyscape.eval.views import render_image
    from rainyscape.imaging.metrics import psnr

    cfg, pipe = _quiet_pipeline("3dgs", tiny_scene, ["trainer.max_iters=200", "phases.fit.patch_size=0",
                                                     "field.init_points=3000", "field.init_fill=0", "field.max_gaussians=5000",
                                                     "field.min_refine_every=10", "trainer.log_every=5"])
    view = tiny_scene.eval_indices[0]
    clean = tiny_scene.clean_images[view].permute(2, 0, 1).float() / 255

    def heldout() -> float:
        return float(psnr(render_image(pipe, view), clean))

    before = heldout()
    initial = pipe.field.num_gaussians
    trainer = Trainer(pipe, tmp_path)
    trainer.train()
    after = heldout()
    assert after > before + 5.0 and after > 19.0, (before, after)
    # the log carries the field's stats: the count and the densifier's cumulative changes
    records = [json.loads(line) for line in (tmp_path / "log.jsonl").read_text().splitlines()]
    last = records[-1]["stats"]
    e = pipe.field.events
    assert last["field.num_gaussians"] == pipe.field.num_gaussians == initial + e["cloned"] + e["split"] - e["pruned"]
    assert last["field.sh_degree"] == 3 and e["refinements"] > 0 and e["cloned"] + e["split"] > 0
    assert all(last[f"field.{k}"] == v for k, v in e.items())
    counts = [r["stats"]["field.num_gaussians"] for r in records]
    assert counts[0] == initial and counts[-1] > initial  # logged as it changes
    # resume from the checkpoint into a fresh pipeline: same number of Gaussians, same render
    fresh = build_pipeline(copy.deepcopy(cfg), tiny_scene, torch.device("cpu"))
    again = Trainer(fresh, tmp_path)
    again.load()
    assert fresh.field.num_gaussians == pipe.field.num_gaussians
    assert fresh.field.events == pipe.field.events
    assert torch.allclose(render_image(fresh, view), render_image(pipe, view))


def test_rainyscape_3dgs_trains_whole_views_and_updates_latents_on_a_crop(tiny_scene, tmp_path):
    """The joint phase renders whole views; the Langevin latent updates run on a crop and
    still move the latents (of every view: the prior pulls them all)."""
    from rainyscape.engine.trainer import Trainer

    _, pipe = _quiet_pipeline("rainyscape-3dgs", tiny_scene, ["trainer.max_iters=12", "phases.warmup.end=0.25",
                                                             "rain_head.latent_patch_size=16", "field.init_points=500"])
    trainer = Trainer(pipe, tmp_path)
    seen = []
    predict = pipe.rain_head.forward

    def recording_forward(view_ids, window):
        seen.append((window.width, window.height))
        return predict(view_ids, window)

    pipe.rain_head.forward = recording_forward
    agr = pipe.losses["agr"][1]
    recorded, estimate = [], agr.estimate

    def recording_estimate(ctx):
        theta, valid = estimate(ctx)
        recorded.append((ctx.record, ctx.rendered.shape[-1], torch.rad2deg(theta)))
        return theta, valid

    agr.estimate = recording_estimate
    views = pipe.rain_head.view_states.detach().clone()
    trainer.train()
    size = (tiny_scene.width, tiny_scene.height)
    # 9 joint steps: one whole-view prediction, then 5 latent steps on 16 x 16 crops each
    assert seen == [size, *[(16, 16)] * 5] * 9
    assert not torch.equal(pipe.rain_head.view_states.detach(), views)
    # the latent updates evaluate AGR on crops without recording: the logged angles are the
    # network update's, on the whole view (issue 28: they were the last crop's); the angles of
    # a crop are estimated once for its 5 latent steps (LossContext.memo)
    assert [(r, w) for r, w, _ in recorded] == [(True, tiny_scene.width), (False, 16)] * 9
    last_update = [deg for r, _, deg in recorded if r][-1]
    logged = [json.loads(line) for line in (tmp_path / "log.jsonl").read_text().splitlines()]
    streak = [v for k, v in logged[-1].get("metrics", {}).items() if k.startswith("agr.streak_deg")]
    assert streak and abs(streak[0] - float((last_update[0, 0] + 90) % 180)) < 1e-3


def test_rainyscape_plus_trains_with_its_floater_prior_acting(tiny_scene, tmp_path):
    """End to end on the tiny scene: in every joint step the free-space prior is a term of
    the loss, and it finds Gaussians in front of the surface where the head sees rain (what
    it does to their opacity: tests/test_losses_rain.py)."""
    from rainyscape.engine.trainer import Trainer

    _, pipe = _quiet_pipeline("rainyscape-plus", tiny_scene, ["trainer.max_iters=12", "phases.warmup.end=0.25",
                                                             "rain_head.latent_patch_size=16", "field.init_points=500",
                                                             "trainer.log_every=1"])
    Trainer(pipe, tmp_path).train()
    joint = [r for r in map(json.loads, (tmp_path / "log.jsonl").read_text().splitlines()) if r.get("phase") == "joint"]
    assert len(joint) == 9 and all("floater-opacity" in r["terms"] for r in joint)
    shares = [r["metrics"]["floater-opacity.gated_share"] for r in joint]
    assert max(shares) > 0 and all(0 <= s <= 1 for s in shares)


def test_depth_guided_fill_lands_on_the_surfaces_the_sparse_points_sample(tiny_scene):
    """field.init_fill: points on training pixels at the depth of their nearest sparse points
    in the image; with sparse points on the surfaces, the fill lands on them too."""
    from rainyscape.fields.gaussians.field import depth_guided_points

    sparse = tiny_scene.points[torch.randperm(len(tiny_scene.points), generator=torch.Generator().manual_seed(0))[:400]]
    points, colors = depth_guided_points(tiny_scene, sparse, 2000, torch.Generator().manual_seed(1))
    assert points.shape == (2000, 3) and colors.shape == (2000, 3) and 0 <= colors.min() <= colors.max() <= 1
    errors = []
    for v in tiny_scene.train_indices:
        uv, z = tiny_scene.cameras[[v]].project(points)
        x, y = uv[0, :, 0].long(), uv[0, :, 1].long()
        inside = (z[0] > 0) & (x >= 0) & (x < tiny_scene.width) & (y >= 0) & (y < tiny_scene.height)
        truth = tiny_scene.depths[v, y[inside], x[inside]]
        ok = torch.isfinite(truth)
        errors.append(((z[0][inside][ok] - truth[ok]).abs() / truth[ok]))
    assert torch.cat(errors).median() < 0.05  # median depth error under 5 % (true depth scores only)
    field = make_field(tiny_scene, init_points=300, init_fill=700)
    assert field.num_gaussians == 1000
