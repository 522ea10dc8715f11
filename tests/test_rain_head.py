"""The rain head: windowed output equals the full-view map, latents, parameter groups."""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F

from rainyscape.cameras import Cameras, Window
from rainyscape.errors import ConfigError
from rainyscape.rain import head as head_module
from rainyscape.rain.head import RainPredictor, camera_vectors
from rainyscape.scene import SceneData


def _scene(n=3, height=37, width=45) -> SceneData:
    g = torch.Generator().manual_seed(0)
    c2w = torch.eye(4).repeat(n, 1, 1)
    c2w[:, :3, 3] = torch.randn(n, 3, generator=g) * 4
    f = torch.full((n,), 40.0)
    cams = Cameras(c2w, f, f, torch.full((n,), width / 2), torch.full((n,), height / 2), width, height)
    return SceneData(name="toy", images=torch.zeros(n, height, width, 3, dtype=torch.uint8), cameras=cams,
                     image_names=[f"{i:03d}.png" for i in range(n)], train_indices=list(range(n)),
                     eval_indices=[], near=0.1, far=10.0, scene_box=torch.tensor([[-1.0] * 3, [1.0] * 3]))


def _head(scene, **options) -> RainPredictor:
    torch.manual_seed(0)
    opts = dict(lowres_channels=(6, 6, 6, 6), highres_channels=4, max_rain=0.5)
    opts.update(options)
    head = RainPredictor(RainPredictor.Config(**opts), scene)
    with torch.no_grad():  # positive biases so that most of the map is non-zero
        for conv in [*head.lowres, head.to_subpixels, head.to_rgb]:
            conv.bias.add_(0.1)
    return head


def _full_view_reference(head: RainPredictor, view: int) -> torch.Tensor:
    """The same network run the plain way: whole latent map, zero-padded convolutions."""
    c = head.config
    code = head.embedding(torch.tensor([view]))
    x = F.relu(head.to_map(code)).reshape(1, c.latent_channels, head.latent_h, head.latent_w)
    for conv in head.lowres:
        x = F.relu(F.conv2d(x, conv.weight, conv.bias, padding=1))
    x = F.relu(F.conv2d(x, head.to_subpixels.weight, head.to_subpixels.bias, padding=1))
    x = F.pixel_shuffle(x, c.upscale)[:, :, : head.height, : head.width]
    return head.bound(F.conv2d(x, head.to_rgb.weight, head.to_rgb.bias, padding=1))


@pytest.mark.parametrize("upscale,latent_channels", [(2, 1), (3, 2), (1, 1)])
def test_windows_equal_crops_of_the_full_view(upscale, latent_channels):
    scene = _scene()
    head = _head(scene, upscale=upscale, latent_channels=latent_channels)
    with torch.no_grad():
        reference = _full_view_reference(head, 1)[0]
        assert (reference > 0).float().mean() > 0.2  # the comparison is not all zeros
        full = head(torch.tensor([1]), Window.full(scene.cameras[[1]]))[0]
        assert torch.allclose(full, reference, atol=1e-6)
        # Windows of one size at corners, edges and inside, with both parities of offset.
        corners = [(0, 0), (45 - 13, 37 - 11), (5, 3), (0, 26), (32, 0), (17, 14)]
        x0 = torch.tensor([c[0] for c in corners])
        y0 = torch.tensor([c[1] for c in corners])
        windows = head(torch.ones(len(corners), dtype=torch.long), Window(x0, y0, 13, 11))
        for b, (x, y) in enumerate(corners):
            assert torch.allclose(windows[b], reference[:, y:y + 11, x:x + 13], atol=1e-6)


def test_masks_are_kept_for_the_same_window_only(monkeypatch):
    """A latent update predicts one crop several times, so the head keeps the last window's
    masks; another window, even with the same view ids object, gets its own."""
    scene = _scene()
    head, fresh = _head(scene), _head(scene)
    built = []
    region_masks = head_module.region_masks
    monkeypatch.setattr(head_module, "region_masks", lambda *a: built.append(1) or region_masks(*a))
    views = torch.tensor([1, 2])
    corner = Window(torch.tensor([0, 32]), torch.tensor([0, 26]), 13, 11)
    inside = Window(torch.tensor([17, 5]), torch.tensor([14, 3]), 13, 11)
    with torch.no_grad():
        first = head(views, corner)
        assert torch.equal(head(views, corner), first) and len(built) == 1  # kept
        for window in (inside, corner):
            assert torch.equal(head(views, window), fresh(views.clone(), window))
    assert len(built) == 5  # the head: corner, inside, corner; the fresh head: inside, corner


@pytest.mark.parametrize("share", [0, 10**9])
def test_gathered_and_dense_latent_regions_agree(monkeypatch, share):
    """Both ways of computing a latent region (rows of the last MLP layer gathered, or the
    whole map cut) give the windows of the full-view reference."""
    scene = _scene(height=70, width=90)
    head = _head(scene)
    monkeypatch.setattr(head_module, "DENSE_REGION_SHARE", share)
    with torch.no_grad():
        reference = _full_view_reference(head, 2)[0]
        corners = [(0, 0), (90 - 13, 70 - 11), (37, 22), (3, 50)]
        windows = head(torch.full((4,), 2), Window(torch.tensor([c[0] for c in corners]),
                                                   torch.tensor([c[1] for c in corners]), 13, 11))
    for b, (x, y) in enumerate(corners):
        assert torch.allclose(windows[b], reference[:, y:y + 11, x:x + 13], atol=1e-6)


def test_channels_last_and_autocast_off_cuda_change_nothing():
    scene = _scene()
    window = Window(torch.tensor([0, 7]), torch.tensor([3, 0]), 20, 16)
    ids = torch.tensor([0, 2])
    outs, grads = [], []
    for options in ({"channels_last": False}, {"channels_last": True}, {"autocast": True}):
        head = _head(scene, **options)
        rain = head(ids, window)
        rain.square().sum().backward()
        outs.append(rain.detach())
        grads.append(torch.cat([p.grad.flatten() for p in head.parameters() if p.grad is not None]))
    for out, grad in zip(outs[1:], grads[1:]):
        assert torch.allclose(out, outs[0], atol=1e-6)
        assert torch.allclose(grad, grads[0], rtol=1e-4, atol=1e-6)


def test_output_is_non_negative_and_bounded():
    scene = _scene()
    head = _head(scene, max_rain=0.05)
    with torch.no_grad():
        for conv in [*head.lowres, head.to_subpixels, head.to_rgb]:
            conv.bias.add_(5.0)
        rain = head(torch.tensor([0, 2]), Window(torch.tensor([0, 3]), torch.tensor([1, 4]), 20, 16))
    assert rain.shape == (2, 3, 16, 20)
    assert rain.min() >= 0 and rain.max() <= 0.05 and rain.max() > 0.04


def test_views_are_independent():
    # No recurrence between views: changing view 0's state leaves view 2's rain unchanged.
    scene = _scene()
    head = _head(scene)
    window = Window.full(scene.cameras[[2]])
    with torch.no_grad():
        before = head(torch.tensor([2]), window)
        head.view_states[0].add_(3.0)
        assert torch.equal(head(torch.tensor([2]), window), before)
        head.view_states[2].add_(3.0)
        assert not torch.equal(head(torch.tensor([2]), window), before)


def test_latents_are_checkpointed_and_not_optimised_by_the_network_groups():
    scene = _scene()
    head = _head(scene)
    latents = head.latents()
    assert [tuple(p.shape) for p in latents] == [(128,), (3, 64)]
    state = head.state_dict()
    assert "scene_state" in state and "view_states" in state
    assert "camera_vectors" not in state  # derived from the scene, not learned
    grouped = {id(p) for g in head.param_groups() for p in g.params}
    assert not grouped & {id(p) for p in latents}
    assert grouped | {id(p) for p in latents} == {id(p) for p in head.parameters()}
    other = _head(scene)
    other.load_state_dict(state)
    assert torch.equal(other.view_states, head.view_states)


def test_param_groups_follow_the_paper():
    groups = {g.name: g for g in _head(_scene()).param_groups()}
    assert set(groups) == {"rain_mlp", "rain_cnn"}
    assert groups["rain_mlp"].lr == 1e-3 and groups["rain_cnn"].lr == 1e-4
    assert all(g.betas == (0.5, 0.999) for g in groups.values())


def test_gradients_reach_latents_of_the_requested_view_only():
    scene = _scene()
    head = _head(scene)
    rain = head(torch.tensor([1]), Window(torch.tensor([4]), torch.tensor([6]), 16, 16))
    s_grad, v_grad = torch.autograd.grad(rain.sum(), head.latents())
    assert s_grad.abs().sum() > 0 and v_grad[1].abs().sum() > 0
    assert v_grad[0].abs().sum() == 0 and v_grad[2].abs().sum() == 0


def test_camera_vectors_are_normalised_poses():
    scene = _scene()
    p = camera_vectors(scene.cameras)
    assert p.shape == (3, 16)
    assert p.reshape(3, 4, 4)[:, :3, 3].norm(dim=-1).max() == pytest.approx(1.0)
    assert torch.equal(p.reshape(3, 4, 4)[:, :3, :3], scene.cameras.c2w[:, :3, :3])


def test_resolution_comes_from_the_scene():
    head = _head(_scene(height=21, width=30), upscale=2)
    assert (head.latent_h, head.latent_w) == (11, 15)
    assert head.to_map.out_features == 11 * 15


def test_bad_options_are_config_errors():
    with pytest.raises(ConfigError):
        _head(_scene(), upscale=0)
    with pytest.raises(ConfigError):
        _head(_scene(), lowres_channels=())


def test_the_field_fits_without_the_streak_shaped_part_of_r_only():
    """``field_streaks``: of a whole-view R holding rain streaks and a smear across them (detail
    the field missed, taken for rain), the field is fitted without the streaks; 0 keeps R."""
    import math

    scene = _scene(n=1, height=48, width=48)
    ys, xs = torch.meshgrid(torch.arange(48.0), torch.arange(48.0), indexing="ij")
    streaks = ((xs % 8 == 3) & (ys % 24 < 14)).float() * 0.3  # vertical, 14 px long
    smear = ((ys == 30) & (xs > 5) & (xs < 40)).float() * 0.4  # horizontal
    rain = (streaks + smear).expand(1, 3, 48, 48)
    residual = streaks.expand(1, 3, 48, 48) + 0.01 * torch.randn(1, 3, 48, 48)
    assert _head(scene).for_field(rain, residual, torch.tensor([0])) is rain
    kept = _head(scene, field_streaks=2).for_field(rain, residual, torch.tensor([0]))[0, 0]
    on_streaks, on_smear = streaks > 0, (smear > 0) & (streaks == 0)
    assert float(kept[on_streaks].mean()) > 0.25
    assert float(kept[on_smear].max()) < 0.02
    assert math.isclose(float(kept.clamp_min(0).min()), 0.0, abs_tol=1e-6)


def test_the_field_fits_without_r_minus_what_runs_across_the_streaks():
    """``field_across``: the smear across the streaks (detail taken for rain) is left to the
    field, and short drops stay subtracted with the streaks, where ``field_streaks`` of the
    same length gives them to the field."""
    scene = _scene(n=1, height=48, width=48)
    ys, xs = torch.meshgrid(torch.arange(48.0), torch.arange(48.0), indexing="ij")
    streaks = ((xs % 8 == 3) & (ys % 24 < 14)).float() * 0.3
    drops = ((xs % 8 == 7) & (ys % 12 == 5)).float() * 0.3  # 1 px drops
    smear = ((ys == 20) & (xs > 5) & (xs < 40)).float() * 0.4  # between the streaks
    rain = (streaks + drops + smear).expand(1, 3, 48, 48)
    residual = streaks.expand(1, 3, 48, 48) + 0.01 * torch.randn(1, 3, 48, 48)
    view = torch.tensor([0])
    across = _head(scene, field_across=2).for_field(rain, residual, view)[0, 0]
    along = _head(scene, field_streaks=2).for_field(rain, residual, view)[0, 0]
    assert float(across[streaks > 0].min()) > 0.29
    assert float(across[drops > 0].min()) > 0.29 and float(along[drops > 0].max()) < 0.01
    assert float(across[smear > 0].max()) < 0.05  # the estimated direction is a few degrees off


def test_the_field_takes_more_of_r_where_the_residual_stands_out_across_the_streaks():
    """``field_gain``: on a streak where R holds a third of what the residual shows, the field
    is fitted without up to ``field_gain`` times R; on an edge along the streaks (a step in
    the residual, the field's misfit) R stays as it was; 1 leaves R."""
    scene = _scene(n=1, height=48, width=48)
    ys, xs = torch.meshgrid(torch.arange(48.0), torch.arange(48.0), indexing="ij")
    streaks = ((xs % 8 == 3) & (ys % 24 < 14)).float() * 0.3
    step = (xs >= 40).float() * 0.3  # a vertical edge, along the streaks
    residual = (streaks + step).expand(1, 3, 48, 48)
    rain = (streaks / 3 + 0.1 * (xs == 40).float()).expand(1, 3, 48, 48)
    view = torch.tensor([0])
    assert _head(scene, field_across=2).for_field(rain, residual, view).equal(
        _head(scene, field_across=2, field_gain=1.0).for_field(rain, residual, view))
    raised = _head(scene, field_gain=2.0).for_field(rain, residual, view)[0, 0]
    assert torch.allclose(raised[streaks > 0], torch.full_like(raised[streaks > 0], 0.2), atol=1e-4)
    assert torch.allclose(raised[:, 40], torch.full((48,), 0.1), atol=1e-4)
    assert float(raised[(streaks == 0) & (xs != 40)].abs().max()) < 1e-6
    tripled = _head(scene, field_gain=5.0).for_field(rain, residual, view)[0, 0]
    assert float(tripled[streaks > 0].max()) < 0.3 + 1e-4  # never more than the residual shows


def test_the_field_keeps_the_bright_side_of_a_blurred_edge():
    """``field_edge``: R on a streak over a background the field has right stays subtracted; R
    on the bright side of an edge along the streaks, whose dark side the field renders too
    bright (the residual's negative partner 1 px across), is left to the field; 0 keeps R."""
    scene = _scene(n=1, height=48, width=48)
    ys, xs = torch.meshgrid(torch.arange(48.0), torch.arange(48.0), indexing="ij")
    streaks = ((xs % 8 == 3) & (ys % 24 < 14) & (xs < 30)).float() * 0.3
    bright, dark = (xs == 38).float(), (xs == 39).float()  # a blurred vertical edge
    residual = (streaks + 0.2 * bright - 0.2 * dark).expand(1, 3, 48, 48)
    rain = (streaks + 0.2 * bright).expand(1, 3, 48, 48)
    view = torch.tensor([0])
    kept = _head(scene, field_edge=0.5).for_field(rain, residual, view)[0, 0]
    assert torch.allclose(kept[streaks > 0], streaks[streaks > 0], atol=1e-4)
    assert float(kept[bright > 0].max()) < 0.01  # the estimated direction is a little off vertical
    assert _head(scene).for_field(rain, residual, view) is rain


def test_the_field_keeps_r_on_a_streak_it_holds_in_part_with_one_sided_edges():
    """``field_edge_sides=one``: where the field holds a fainter, wider copy of a streak (the
    residual too bright on both sides of it) R stays subtracted, where ``either`` hands part of
    it back; the bright side of a blurred edge is left to the field either way."""
    scene = _scene(n=1, height=48, width=48)
    ys, xs = torch.meshgrid(torch.arange(48.0), torch.arange(48.0), indexing="ij")
    streaks = ((xs % 8 == 3) & (ys % 24 < 14) & (xs < 30)).float() * 0.3
    held = ((xs % 8 >= 2) & (xs % 8 <= 4)).float() * ((ys % 24 < 14) & (xs < 30)).float() * 0.12
    bright, dark = (xs == 38).float(), (xs == 39).float()  # a blurred vertical edge
    residual = (streaks - held + 0.2 * bright - 0.2 * dark).expand(1, 3, 48, 48)
    rain = (streaks + 0.2 * bright).expand(1, 3, 48, 48)
    view = torch.tensor([0])
    on = streaks > 0
    one = _head(scene, field_edge=0.5, field_edge_sides="one").for_field(rain, residual, view)[0, 0]
    either = _head(scene, field_edge=0.5).for_field(rain, residual, view)[0, 0]
    assert float(one[on].mean()) > 0.95 * 0.3 and float(either[on].mean()) < 0.9 * 0.3
    assert float(one[bright > 0].max()) < 0.01 and float(either[bright > 0].max()) < 0.01


def test_the_fields_lines_run_near_the_views_down():
    """``max_tilt``: where horizontal scene edges outweigh the streaks in the residual, the lines
    still run along the streaks, or across them (the view is upright: the world's down runs
    down the image)."""
    scene = _scene(n=1, height=48, width=48)
    ys, xs = torch.meshgrid(torch.arange(48.0), torch.arange(48.0), indexing="ij")
    streaks = ((xs % 8 == 3) & (ys % 24 < 14)).float() * 0.3
    edges = (ys % 4 == 1).float() * 0.5  # the residual's dominant direction: horizontal
    rain = streaks.expand(1, 3, 48, 48)
    residual = (streaks + edges).expand(1, 3, 48, 48)
    view = torch.tensor([0])
    on_streaks = streaks > 0
    for shape in ("field_streaks", "field_across"):
        free = _head(scene, **{shape: 2}).for_field(rain, residual, view)[0, 0]
        prior = _head(scene, **{shape: 2}, max_tilt=45.0).for_field(rain, residual, view)[0, 0]
        # along a horizontal line, or across it, the field is fitted without none of the streaks
        assert float(free[on_streaks].mean()) < 0.05, shape
        assert float(prior[on_streaks].mean()) > 0.25, shape
