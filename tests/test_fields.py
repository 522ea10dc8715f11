"""The NeRF fields: shapes, chunking, checkpoints, coarse-to-fine growth, occupancy, fits."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from rainyscape import config
from rainyscape.cameras import Window, pixel_rays
from rainyscape.components import TrainState
from rainyscape.errors import ConfigError
from rainyscape.fields.grid import GridField, check_growth, growth_resolution
from rainyscape.fields.ndc import ndc_near
from rainyscape.fields.nerf_mlp import NerfMLP, NerfMLPField
from rainyscape.fields.packed import distortion, packed_weights
from rainyscape.scene import faces_forward, points_box
from rainyscape.workflow import wants_sparse_points

from _scenes import forward_facing_scene

SMALL_MLP = dict(depth=4, width=64, skips=(2,), samples_coarse=16, samples_fine=16, train_chunk=0)
SMALL_GRID = dict(resolution_init=8, resolution_final=24, growth_at=(0.2, 0.5), occupancy_from=0.3,
                  occupancy_every=10, occupancy_resolution=32)


def _options(name: str, **extra):
    cls = NerfMLPField if name == "nerf-mlp" else GridField
    base = SMALL_MLP if name == "nerf-mlp" else SMALL_GRID
    return cls.Config(**{**base, **extra})


def _field(name: str, scene, **extra):
    torch.manual_seed(0)
    cls = NerfMLPField if name == "nerf-mlp" else GridField
    return cls(_options(name, **extra), scene)


def _full(scene, views):
    cams = scene.cameras[views]
    return cams, Window.full(cams)


def test_nerf_mlp_has_the_paper_architecture():
    net = NerfMLP(pos_freqs=10, dir_freqs=4, depth=8, width=256, skips=(4,))
    linears = [m for m in net.trunk]
    assert [l.in_features for l in linears] == [63, 256, 256, 256, 256, 256 + 63, 256, 256]
    assert net.view.in_features == 256 + 27 and net.view.out_features == 128
    assert sum(p.numel() for p in net.parameters()) == 595_844  # as nerf-pytorch
    sigma, rgb = net(torch.randn(5, 7, 3), torch.randn(5, 7, 3))
    assert sigma.shape == (5, 7) and rgb.shape == (5, 7, 3)


@pytest.mark.parametrize("name", ["nerf-mlp", "grid"])
def test_render_shapes_and_chunking(name, tiny_scene):
    field = _field(name, tiny_scene).eval()
    cams, window = _full(tiny_scene, [0, 3])
    with torch.no_grad():
        field.eval_chunk = 10**9
        whole = field.render(cams, window)
        field.eval_chunk = 333  # not a divisor of the ray count
        chunked = field.render(cams, window)
    h, w = tiny_scene.height, tiny_scene.width
    assert whole.rgb.shape == (2, 3, h, w)
    assert whole.depth.shape == (2, 1, h, w) and whole.acc.shape == (2, 1, h, w)
    assert torch.allclose(whole.rgb, chunked.rgb, atol=1e-6)
    assert torch.allclose(whole.depth, chunked.depth, atol=1e-4)
    assert torch.all((whole.rgb >= 0) & (whole.rgb <= 1 + 1e-5))
    assert torch.all((whole.acc >= 0) & (whole.acc <= 1 + 1e-5))


def test_gradient_checkpointed_chunks_match_one_pass(tiny_scene):
    field = _field("nerf-mlp", tiny_scene, perturb=False, density_noise=0.0).train()
    cams, window = _full(tiny_scene, [1])
    grads = []
    for chunk in (0, 500):
        field.zero_grad()
        field.train_chunk = chunk
        out = field.render(cams, window)
        (out.rgb.square().mean() + out.extras["rgb_coarse"].mean()).backward()
        grads.append(torch.cat([p.grad.flatten() for p in field.parameters()]))
    assert torch.allclose(grads[0], grads[1], atol=1e-6, rtol=1e-4)


def test_nerf_mlp_coarse_loss_and_lr_schedule(tiny_scene):
    field = _field("nerf-mlp", tiny_scene)
    cams, window = _full(tiny_scene, [0])
    out = field.train().render(cams, window)
    target = torch.rand_like(out.rgb)
    losses = field.extra_losses(out, target)
    assert set(losses) == {"coarse"}
    assert losses["coarse"].item() == pytest.approx(((out.extras["rgb_coarse"] - target) ** 2).mean().item())
    (group,) = field.param_groups()
    assert group.lr == 5e-4  # the paper's, and 1e-6 after the warm-up (a phase setting):
    assert config.method_config("rainyscape-vanilla-nerf").phases["joint"].field_lr == 1e-6
    assert group.lr_decay == 0.1 and group.lr_decay_steps == 250_000
    assert len(group.params) == len(list(field.parameters()))


def test_nerf_mlp_density_noise_only_while_training(tiny_scene):
    field = _field("nerf-mlp", tiny_scene, perturb=False)
    cams, window = _full(tiny_scene, [0])
    with torch.no_grad():
        field.eval()
        a, b = field.render(cams, window).rgb, field.render(cams, window).rgb
        assert torch.equal(a, b)
        field.train()
        c, d = field.render(cams, window).rgb, field.render(cams, window).rgb
        assert not torch.equal(c, d)


def test_growth_schedule_is_log_spaced_and_monotone():
    res = [growth_resolution(s, 100, 16, 128, (0.1, 0.2, 0.4)) for s in range(101)]
    assert res[0] == 16 and res[9] == 16 and res[10] == 32 and res[20] == 64 and res[40] == 128
    assert res == sorted(res) and res[-1] == 128
    assert growth_resolution(0, 100, 16, 128, ()) == 128


def test_a_schedule_the_lattice_cannot_follow_is_refused():
    plan = dataclasses.make_dataclass("Plan", ["resolution_init", "resolution_final", "growth_at"])
    check_growth(plan(16, 128, (0.1, 0.8)))
    with pytest.raises(ConfigError, match="resolution_init <= resolution_final"):
        check_growth(plan(256, 128, (0.1,)))  # a lattice that would shrink
    with pytest.raises(ConfigError, match="growth_at"):
        check_growth(plan(16, 128, (0.1, 1.5)))  # past the run's end


def _state(field, step, max_iters, optimizers):
    return TrainState(step, max_iters, "fit", optimizers, torch.device("cpu"))


def _adam(field):
    return {g.name: torch.optim.Adam(g.params, lr=g.lr, eps=g.eps) for g in field.param_groups()}


def _step(field, optimizers, scene, view=0):
    cams, window = _full(scene, [view])
    out = field.train().render(cams, window)
    loss = (out.rgb - 0.5).square().mean()
    for opt in optimizers.values():
        opt.zero_grad()
    loss.backward()
    for opt in optimizers.values():
        opt.step()


def test_grid_growth_carries_adam_state_over(tiny_scene):
    field = _field("grid", tiny_scene)
    opts = _adam(field)
    _step(field, opts, tiny_scene)
    old = [p for g in opts.values() for group in g.param_groups for p in group["params"]]
    old_shapes = {id(p): p.shape for p in old}
    (grow_cb, _) = field.callbacks()
    grow_cb.before_step(_state(field, 50, 100, opts))  # past growth_at 0.2 and 0.5
    assert field.resolution == 24
    current = {id(p) for p in field.parameters()}
    for opt in opts.values():
        for group in opt.param_groups:
            for p in group["params"]:
                assert id(p) in current  # the optimiser follows the new parameters
                state = opt.state.get(p)
                if state:
                    assert state["exp_avg"].shape == p.shape == state["exp_avg_sq"].shape
                    assert torch.all(state["exp_avg_sq"] >= 0)
    grown = [p for p in field.density_grid.factors()]
    assert all(p.shape != old_shapes.get(id(p)) for p in grown)
    _step(field, opts, tiny_scene)  # trains on at the new size


def test_every_grid_parameter_group_gets_gradients(tiny_scene):
    """Density tables, colour tables and the networks all learn from one photometric loss
    (the grids through the compiled lookup on a CPU where it was built)."""
    field = _field("grid", tiny_scene, resolution_init=24)
    cams, window = _full(tiny_scene, [0])
    loss = (field.train().render(cams, window).rgb - 0.3).square().mean()
    loss.backward()
    for group in field.param_groups():
        assert group.params and all(p.grad is not None for p in group.params), group.name
        assert sum(float(p.grad.abs().sum()) for p in group.params) > 0, group.name


def test_grid_distortion_is_the_double_sum_over_sample_ranks(tiny_scene):
    """The grid field's distortion is mip-NeRF 360's double sum with each of a ray's real
    samples one interval of width 1/N in rank order (N the ray's slots): its live samples'
    ranks skip the empty and the padded slots, which carry no weight and take no room."""
    field = _field("grid", tiny_scene, resolution_init=24, distortion=0.01)
    cams, window = _full(tiny_scene, [0])
    ys, xs = window.pixel_grid()
    world = pixel_rays(cams, xs, ys)
    rays = field.space.sample_rays(world.origins.reshape(-1, 3)[:64], world.directions.reshape(-1, 3)[:64])
    live = field.train()._march(rays)
    weights = packed_weights(field._sigma(live.g), live.delta, live.ray, 64)[0].detach()
    got = distortion(weights, live.rank / live.slots, (live.rank + 1) / live.slots, live.ray, 64)
    for r in range(0, 64, 9):
        ws, mid = weights[live.ray == r], (live.rank[live.ray == r] + 0.5) / live.slots
        want = (ws[:, None] * ws[None] * (mid[:, None] - mid[None]).abs()).sum() + (ws ** 2).sum() / (3 * live.slots)
        assert torch.isclose(got[r], want, atol=1e-6)
    # weight gathered at one sample costs less than the same weight spread over the ray
    ray, s0 = torch.zeros(8, dtype=torch.long), torch.arange(8) / 8
    spread, gathered = torch.full((8,), 0.1), torch.zeros(8)
    gathered[3] = 0.8
    assert distortion(gathered, s0, s0 + 1 / 8, ray, 1) < distortion(spread, s0, s0 + 1 / 8, ray, 1)


def test_grid_distortion_loss_in_training_only_and_it_reaches_the_density(tiny_scene):
    field = _field("grid", tiny_scene, resolution_init=24, distortion=0.01)
    cams, window = _full(tiny_scene, [0])
    out = field.train().render(cams, window)
    losses = field.extra_losses(out, out.rgb)
    assert set(losses) == {"distortion"} and losses["distortion"] > 0
    losses["distortion"].backward()
    assert sum(float(p.grad.abs().sum()) for p in field.density_grid.factors()) > 0
    with torch.no_grad():
        assert "distortion" not in field.eval().render(cams, window).extras
    off = _field("grid", tiny_scene, resolution_init=24)
    assert off.extra_losses(off.train().render(cams, window), out.rgb) == {}


def test_grid_stats_count_the_samples_of_the_last_training_render(tiny_scene):
    """``stats``: marched and shaded samples per ray come from training renders only, and an
    occupancy grid that empties space cuts the marched ones."""
    field = _field("grid", tiny_scene, resolution_init=24)
    cams, window = _full(tiny_scene, [0])
    assert "shaded_per_ray" not in field.stats()
    with torch.no_grad():
        field.eval().render(cams, window)
    assert "shaded_per_ray" not in field.stats()
    field.train().render(cams, window)
    full = field.stats()
    assert 0 < full["shaded_per_ray"] <= full["marched_per_ray"]
    occupied = torch.zeros_like(field.occupancy.occupied)
    occupied[:, :, : occupied.shape[2] // 2] = True  # half the cube empty
    field.occupancy.set(occupied)
    field.train().render(cams, window)
    assert field.stats()["marched_per_ray"] < full["marched_per_ray"]


def test_grid_near_gradient_scales_only_the_gradients_of_near_samples(tiny_scene):
    """``field.near_gradient``: the same render, smaller gradients; next to none reach the
    grids when every sample lies far inside the reference distance."""
    cams, window = _full(tiny_scene, [0])

    def grads(**extra):
        field = _field("grid", tiny_scene, resolution_init=24, **extra)
        out = field.train().render(cams, window)
        out.rgb.sum().backward()
        return out.rgb.detach(), [p.grad.clone() for p in field.density_grid.factors() + field.color_grid.factors()]

    rgb, plain = grads()
    rgb_near, near = grads(near_gradient=0.5)
    assert torch.equal(rgb, rgb_near)
    norms = [(float(a.norm()), float(b.norm())) for a, b in zip(plain, near)]
    assert all(b < a for a, b in norms)
    _, none = grads(near_gradient=1000.0)
    assert all(float(g.norm()) < 1e-3 * a for g, (a, _) in zip(none, norms))


def test_grid_gives_what_loss_terms_request_in_training_only(tiny_scene):
    """``Field.request``: the grid adds the requested per-ray measures to its training
    renders (with their gradient into the density), never to evaluation renders; the
    pipeline refuses a term whose measure the field cannot give, naming the term."""
    from rainyscape.engine.pipeline import build_pipeline

    field = _field("grid", tiny_scene, resolution_init=24)
    cams, window = _full(tiny_scene, [0])
    assert "front_weight" not in field.train().render(cams, window).extras
    field.request({"front_weight", "distortion"})
    out = field.train().render(cams, window)
    assert out.extras["front_weight"].shape == out.depth.shape and out.extras["distortion"].shape == out.depth.shape
    assert field.extra_losses(out, out.rgb) == {}  # the field's own distortion term stays off
    out.extras["front_weight"].sum().backward()
    assert sum(float(p.grad.abs().sum()) for p in field.density_grid.factors()) > 0
    with torch.no_grad():
        assert not field.eval().render(cams, window).extras
    nerf = config.method_config("rainyscape-nerf", ["losses.floater-rays.weight=1", "field.resolution_final=32"])
    assert build_pipeline(nerf, tiny_scene, torch.device("cpu")).field.requested == {"front_weight"}
    gs = config.method_config("rainyscape-plus", ["losses.floater-rays.weight=1"])
    with pytest.raises(ConfigError, match="losses.floater-rays reads the 'front_weight'"):
        build_pipeline(gs, tiny_scene, torch.device("cpu"))


def test_points_box_bounds_the_grids_by_the_sparse_points(tiny_scene):
    g = torch.Generator().manual_seed(0)
    points = torch.randn(500, 3, generator=g) * torch.tensor([0.2, 0.1, 0.3]) + torch.tensor([0.1, 0.0, -0.2])
    field = _field("grid", dataclasses.replace(tiny_scene, points=points), box="points")
    lo, hi = points_box(points)
    assert torch.allclose(field.space.box_center, (lo + hi) / 2) and torch.allclose(field.space.box_half, (hi - lo) / 2)
    assert (field.space.box_half < (tiny_scene.scene_box[1] - tiny_scene.scene_box[0]) / 2).all()
    with pytest.raises(ConfigError, match="field.box=points"):
        _field("grid", dataclasses.replace(tiny_scene, points=None), box="points")
    with pytest.raises(ConfigError, match="field.shell_reach"):  # inside the box's share: no shell
        _field("grid", tiny_scene, shell_reach=0.3)
    # auto (the default): the points' box when there are points, else the scene's
    auto = _field("grid", dataclasses.replace(tiny_scene, points=points))
    assert torch.allclose(auto.space.box_half, field.space.box_half)
    bare = _field("grid", dataclasses.replace(tiny_scene, points=None))
    assert torch.allclose(bare.space.box_half, (tiny_scene.scene_box[1] - tiny_scene.scene_box[0]) / 2)
    # rs-train, rs-eval, rs-render and rs-export triangulate points for it when a scene has none
    assert wants_sparse_points(config.method_config("nerf", ["field.box=points"]))
    assert wants_sparse_points(config.method_config("nerf"))
    assert not wants_sparse_points(config.method_config("nerf", ["field.box=scene"]))
    # ... and for the NDC layout (auto: on forward-facing captures), whose near plane they set
    assert wants_sparse_points(config.method_config("nerf", ["field.box=scene"]), forward_facing=True)
    assert not wants_sparse_points(config.method_config("nerf", ["field.layout=contract", "field.box=scene"]),
                                   forward_facing=True)


def test_points_box_keeps_the_bulk_of_the_points_not_the_far_ones():
    # a capture's SfM points: the object (the cube [-1, 1]^3) and 7 % of stray points far off, as
    # a handheld capture triangulates the room behind it from a few views
    g = torch.Generator().manual_seed(0)
    content = torch.rand(1000, 3, generator=g) * 2 - 1
    far = torch.randn(80, 3, generator=g) * 10.0
    lo, hi = points_box(torch.cat([content, far]))
    assert (lo > -1.3).all() and (hi < 1.3).all()  # the object, not the room
    assert (lo < -0.8).all() and (hi > 0.8).all()  # all of the object's bulk
    lo1, hi1 = points_box(torch.cat([content, far]), quantile=0.01)  # the old rule: the room
    assert ((hi1 - lo1) > 2 * (hi - lo)).any()


def test_faces_forward_tells_camera_arrays_from_orbits(tiny_scene):
    assert faces_forward(forward_facing_scene().cameras.c2w)
    ring = []
    for a in torch.linspace(0, 2 * torch.pi, 9)[:-1]:  # eight cameras around the origin, looking in
        eye = torch.stack([4 * torch.cos(a), torch.tensor(0.0), 4 * torch.sin(a)])
        fwd = -eye / eye.norm()
        right = torch.linalg.cross(fwd, torch.tensor([0.0, 1.0, 0.0]))
        c2w = torch.eye(4)
        c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, torch.linalg.cross(fwd, right), fwd, eye
        ring.append(c2w)
    assert not faces_forward(torch.stack(ring))
    assert not faces_forward(tiny_scene.cameras.c2w)  # the simulator's 3 x 4 street array spans more than 35 degrees


def test_grid_works_in_ndc_on_forward_facing_captures():
    """A wall 4 units ahead of a camera array: the grid field lays its cube out in NDC, with
    the near plane at 3/4 of the points' depth, and renders the wall at its depth."""
    g = torch.Generator().manual_seed(0)
    wall = torch.cat([torch.rand(400, 2, generator=g) * 4 - 2, torch.full((400, 1), 4.0)], 1)
    scene = forward_facing_scene(points=wall)
    field = GridField(GridField.Config(**{**SMALL_GRID, "resolution_init": 64, "resolution_final": 64},
                                       density_grid="dense"), scene)
    assert field.layout == "ndc" and field.space.near == pytest.approx(3.0, rel=1e-3)
    assert ndc_near(field.space.ndc_frame, None, 2.0) == pytest.approx(1.5)  # no points: 3/4 of the bound
    # NDC texels keep their pixel footprint: the lattice stops at about one texel per pixel
    assert GridField(GridField.Config(resolution_final=512), scene).final_resolution == pytest.approx(
        32 * float(field.space.extent().prod()) ** (1 / 3), abs=1)
    assert GridField(GridField.Config(**SMALL_GRID, layout="contract"), scene).layout == "contract"
    with torch.no_grad():  # opaque from the wall's NDC depth on, empty in front of it
        grid = field.density_grid.grid  # (1, 1, nz, ny, nx)
        z_ndc = 1.0 - 2.0 * field.space.near / 4.0
        g_wall = (z_ndc - float(field.space.box_center[2])) / float(field.space.box_half[2])
        gz = torch.linspace(-1, 1, grid.shape[2])
        grid.copy_(torch.where(gz >= g_wall, 10.0, -20.0).view(1, 1, -1, 1, 1).expand_as(grid))
    cams, window = _full(scene, [0, 4])
    with torch.no_grad():
        out = field.eval().render(cams, window)
    assert torch.all(out.acc > 0.99)
    assert (out.depth - 4.0).abs().max() < 0.3  # a sample step at that depth is about 0.2


def test_occupancy_skips_empty_space_without_changing_the_image(tiny_scene):
    field = _field("grid", tiny_scene, resolution_init=24, density_grid="dense")
    with torch.no_grad():  # a single opaque block in an otherwise empty box
        grid = field.density_grid.grid
        grid.fill_(-20.0)
        n = grid.shape[-3:]
        grid[..., n[0] // 3: n[0] // 2, n[1] // 3: n[1] // 2, n[2] // 3: n[2] // 2] = 10.0
    cams, window = _full(tiny_scene, [0, 5])
    field.eval()
    with torch.no_grad():
        before = field.render(cams, window)
        field.update_occupancy()
        after = field.render(cams, window)
    assert field.occupancy.fraction() < 0.2
    assert torch.allclose(before.rgb, after.rgb, atol=2e-3)
    assert torch.allclose(before.acc, after.acc, atol=2e-3)


@pytest.mark.parametrize("name", ["nerf-mlp", "grid"])
def test_checkpoint_round_trip(name, tiny_scene, tmp_path):
    field = _field(name, tiny_scene)
    opts = _adam(field)
    if name == "grid":
        field.grow(20, opts)
        field.update_occupancy()
    _step(field, opts, tiny_scene)
    path = tmp_path / "ckpt.pt"
    torch.save({"field": field.state_dict(), "opt": {k: o.state_dict() for k, o in opts.items()}}, path)
    fresh = _field(name, tiny_scene)
    state = torch.load(path, weights_only=False)
    fresh.load_state_dict(state["field"])
    fresh_opts = _adam(fresh)  # as the trainer does: optimisers rebuilt after loading
    for k, opt in fresh_opts.items():
        opt.load_state_dict(state["opt"][k])
    cams, window = _full(tiny_scene, [2])
    with torch.no_grad():
        a = field.eval().render(cams, window)
        b = fresh.eval().render(cams, window)
    assert torch.equal(a.rgb, b.rgb) and torch.equal(a.depth, b.depth)
    if name == "grid":
        assert fresh.resolution == 20
        assert torch.equal(fresh.occupancy.occupied, field.occupancy.occupied)
    # Both continue identically.
    torch.manual_seed(1)
    _step(field, opts, tiny_scene)
    torch.manual_seed(1)
    _step(fresh, fresh_opts, tiny_scene)
    for p, q in zip(field.parameters(), fresh.parameters()):
        assert torch.allclose(p, q, atol=1e-6)


@pytest.mark.parametrize("name", ["nerf-mlp", "grid"])
def test_density_for_export(name, tiny_scene):
    field = _field(name, tiny_scene)
    pts = torch.randn(100, 3)
    with torch.no_grad():
        sigma = field.density(pts)
    assert sigma.shape == (100,) and torch.all(sigma >= 0)


FIT = {  # short CPU fits on the 48 px tiny scene; floors measured (see docs/fields.md), minus margin
    "nerf": (["trainer.max_iters=150", "phases.fit.patches=512", "field.resolution_final=48",
              "field.lr_decay_steps=150"], 0.0),
    "vanilla-nerf": (["trainer.max_iters=150", "phases.fit.patches=512", "field.depth=4",
                      "field.width=64", "field.skips=2", "field.samples_coarse=24",
                      "field.samples_fine=24", "field.train_chunk=0", "field.lr=2e-3"], 0.0),
}


@pytest.mark.parametrize("method", sorted(FIT))
def test_short_fit_raises_heldout_psnr(method, tiny_scene_dir, tmp_path):
    from rainyscape.workflow import train_and_evaluate

    overrides, floor = FIT[method]
    cfg = config.method_config(method, [f"data={tiny_scene_dir}", f"trainer.output_dir={tmp_path}",
                                        "trainer.eval_every=0", "trainer.checkpoint_every=0",
                                        "trainer.progress=false", *overrides])
    result = train_and_evaluate(cfg)
    summary = result.metrics["summary"]
    print(method, {k: round(v, 2) for k, v in summary.items()})
    assert summary["heldout_psnr"] > floor
