"""The rain losses on tiny tensors (hand computations) and the AGR's directional behaviour."""

from __future__ import annotations

import math

import pytest
import torch

from rainyscape.components import LossContext, RenderOutput
from rainyscape.errors import ConfigError
from rainyscape.losses.agr import AdaptiveGradientRotation, agr_loss, mean_abs_derivative
from rainyscape.imaging.gradients import directional_derivative, image_gradients
from rainyscape.losses.l1_ssim import L1SSIM
from rainyscape.losses.photometric import Photometric
from rainyscape.losses.rain_losses import (Likelihood, Reconstruction, TotalVariation, dry_weight,
                                          reconstruction_loss)
from rainyscape.testing.streaks import streak_layer, textured_background


def _ctx(rendered, target, rain, view_ids=(0,)):
    return LossContext(rendered, target, {} if rain is None else {"rain": rain}, RenderOutput(rgb=rendered),
                       torch.tensor(view_ids), step=0, phase="joint")


def _tiny():
    target = torch.tensor([[[[3.0, 1.0], [4.0, 2.0]]]])
    rendered = torch.tensor([[[[1.0, 1.0], [1.0, 1.0]]]])
    rain = torch.tensor([[[[1.0, 1.0], [1.0, 1.0]]]])
    return target, rendered, rain  # residual I - B - R = [[1, -1], [2, 0]]


def test_reconstruction_by_hand():
    target, rendered, rain = _tiny()
    assert float(Reconstruction()(_ctx(rendered, target, rain))) == pytest.approx((1 + 1 + 4 + 0) / 4)


def test_brighter_pixels_weigh_less_only_where_rain_is_a_constant():
    target, rendered, rain = _tiny()  # residual [[1, -1], [2, 0]]: two pixels brighter than B + R
    term = Reconstruction(Reconstruction.Config(brighter=0.25))
    # the field's rays: R read from the head's cache, a constant
    assert float(term(_ctx(rendered, target, rain))) == pytest.approx((0.25 * 1 + 1 + 0.25 * 4 + 0) / 4)
    # where the head learns from the term (R carries gradient), the paper's term unchanged
    learning = rain.clone().requires_grad_(True)
    assert float(term(_ctx(rendered, target, learning)).detach()) == pytest.approx((1 + 1 + 4 + 0) / 4)
    # the warm-up's photometric term on the input alone, residual [[2, 0], [3, 1]]
    plain = Photometric(Photometric.Config(brighter=0.25))
    assert float(plain(_ctx(rendered, target, None))) == pytest.approx(0.25 * (4 + 0 + 9 + 1) / 4)


def test_exclude_leaves_pixels_under_cached_rain_to_the_other_views():
    """``exclude``: where R is the cache's constant, a pixel weighs exp(-(R / s)^2): R = 0.1 at
    s = 0.05 weighs e^-4, a dry pixel 1; where the head learns from the term, every pixel counts."""
    target = torch.tensor([[[[1.0, 1.0]]]])
    rendered = torch.tensor([[[[0.5, 0.5]]]])
    rain = torch.tensor([[[[0.1, 0.0]]]])  # residual I - B - R = [0.4, 0.5]
    term = Reconstruction(Reconstruction.Config(exclude=0.05))
    assert float(term(_ctx(rendered, target, rain))) == pytest.approx((math.exp(-4) * 0.16 + 0.25) / 2)
    learning = rain.clone().requires_grad_(True)
    assert float(term(_ctx(rendered, target, learning)).detach()) == pytest.approx((0.16 + 0.25) / 2)


def test_streak_scale_keeps_the_brighter_weight_for_streaks_and_not_for_detail():
    """``streak_scale``: of two pixels equally brighter than the render, the one on a streak
    falling along the view's down weighs ``brighter``, the one on a blob (detail) weighs 1."""
    from rainyscape.cameras import Cameras, Window
    from rainyscape.scene import SceneData

    images = torch.full((1, 24, 32, 3), 50, dtype=torch.uint8)
    images[0, 4:19, 10] = 250  # a streak down the upright view
    images[0, 6:12, 18:24] = 250  # a blob wider than a streak
    f = torch.full((1,), 30.0)
    cams = Cameras(torch.eye(4)[None], f, f, torch.full((1,), 16.0), torch.full((1,), 12.0), 32, 24)
    scene = SceneData(name="toy", images=images, cameras=cams, image_names=["0.png"], train_indices=[0],
                      eval_indices=[], near=0.1, far=10.0, scene_box=torch.tensor([[-1.0] * 3, [1.0] * 3]))
    term = Photometric(Photometric.Config(brighter=0.5, streak_scale=0.02))
    term.setup(scene, torch.device("cpu"))
    rendered = torch.full((2, 3, 1, 1), 50 / 255)
    target = torch.full((2, 3, 1, 1), 250 / 255)
    rays = Window(torch.tensor([10, 21]), torch.tensor([12, 9]), 1, 1)  # (x, y): the streak, the blob
    ctx = LossContext(rendered, target, {}, RenderOutput(rgb=rendered), torch.tensor([0, 0]), 0, "warmup", rays)
    r2 = (200 / 255) ** 2
    assert float(term(ctx)) == pytest.approx((0.5 * r2 + 1.0 * r2) / 2, rel=1e-5)
    # without the option both weigh ``brighter``
    plain = Photometric(Photometric.Config(brighter=0.5))
    plain.setup(scene, torch.device("cpu"))
    assert float(plain(ctx)) == pytest.approx(0.5 * r2, rel=1e-5)


def test_colour_keeps_the_brighter_weight_for_a_residual_towards_white_and_not_for_coloured_detail():
    """``colour``: of two pixels brighter than the same green render, the one brightened
    towards white (rain: I = (1 - a) B + a) weighs ``brighter``, the one brighter in its own
    green (a leaf the field has not resolved) weighs 1; a darker pixel weighs 1 either way."""
    render = torch.tensor([0.2, 0.4, 0.2]).view(1, 3, 1, 1).expand(3, 3, 1, 1)
    target = torch.stack([0.6 * render[0] + 0.4, torch.tensor([0.25, 0.7, 0.2]).view(3, 1, 1),
                          render[0] - 0.1])
    ctx = LossContext(render, target, {}, RenderOutput(rgb=render), torch.tensor([0, 0, 0]), 0, "warmup")
    squares = (target - render).pow(2).mean((1, 2, 3))
    term = Photometric(Photometric.Config(brighter=0.5, colour=0.1))
    assert float(term(ctx)) == pytest.approx(float((0.5 * squares[0] + squares[1] + squares[2]) / 3), rel=1e-5)
    plain = Photometric(Photometric.Config(brighter=0.5))
    assert float(plain(ctx)) == pytest.approx(float((0.5 * squares[0] + 0.5 * squares[1] + squares[2]) / 3), rel=1e-5)


def test_a_fitted_rain_colour_keeps_the_brighter_weight_on_tinted_rain_where_white_does_not():
    """``rain_colour=fitted``: rain tinted blue over a grey render departs from the line towards
    white (full weight with ``white``); fitted from the brighter pixels over a few steps, the
    colour is the rain's and the rain weighs ``brighter``. The fit survives a checkpoint."""
    tint = torch.tensor([0.5, 0.7, 1.0]).view(1, 3, 1, 1)
    render = torch.full((8, 3, 1, 1), 0.2)
    target = 0.5 * render + 0.5 * tint
    ctx = LossContext(render, target, {}, RenderOutput(rgb=render), torch.zeros(8, dtype=torch.long), 0, "warmup")
    white = Photometric(Photometric.Config(brighter=0.5, colour=0.1))
    fitted = Photometric(Photometric.Config(brighter=0.5, colour=0.1, rain_colour="fitted"))
    for _ in range(20):
        fitted(ctx)
    assert torch.allclose(fitted.rain_colour, tint.flatten(), atol=0.02)
    assert torch.allclose(white._brighter(ctx), torch.ones(8, 1, 1, 1))
    assert torch.allclose(fitted._brighter(ctx), torch.full((8, 1, 1, 1), 0.5), atol=1e-3)
    restored = Photometric(Photometric.Config(brighter=0.5, colour=0.1, rain_colour="fitted"))
    restored.load_state_dict(fitted.state_dict())
    assert torch.allclose(restored.rain_colour, fitted.rain_colour)
    assert white.state_dict() == {}


def test_brighter_weight_fits_a_point_nearer_its_dry_views():
    # one 3D point seen dry in three views and brightened by rain in the fourth: the least-squares
    # fit is their mean, with the brighter views weighted less it stays nearer the dry value
    seen = torch.tensor([0.5, 0.5, 0.5, 0.9]).reshape(4, 1, 1, 1).expand(4, 3, 1, 1)
    fits = {}
    for brighter in (1.0, 0.5):
        b = torch.zeros(1, requires_grad=True)
        opt = torch.optim.SGD([b], lr=0.5)
        for _ in range(300):
            opt.zero_grad()
            loss = reconstruction_loss(seen - b.expand(4, 3, 1, 1), brighter)
            loss.backward()
            opt.step()
        fits[brighter] = float(b.detach())
    assert fits[1.0] == pytest.approx(0.6, abs=1e-4)
    assert fits[0.5] == pytest.approx((3 * 0.5 + 0.5 * 0.9) / 3.5, abs=1e-4)


def test_likelihood_by_hand_and_variance_detached():
    target, rendered, rain = _tiny()
    rendered.requires_grad_(True)
    loss = Likelihood()(_ctx(rendered, target, rain))
    # mean(r) = 0.5, mean(r^2) = 1.5, population variance 1.25
    assert float(loss.detach()) == pytest.approx(1.5 / (1.25 + 1e-6))
    loss.backward()
    # Only the numerator carries gradient: d/dB mean(r^2) / var = -2 r / (n var)
    expected = -2 * torch.tensor([[1.0, -1.0], [2.0, 0.0]]) / (4 * 1.25)
    assert torch.allclose(rendered.grad[0, 0], expected, atol=1e-5)


def test_rain_counts_as_zero_without_a_rain_head():
    target, rendered, _ = _tiny()
    # residual I - B = [[2, 0], [3, 1]]
    assert float(Reconstruction()(_ctx(rendered, target, None))) == pytest.approx((4 + 0 + 9 + 1) / 4)


def test_total_variation_by_hand():
    b = torch.tensor([[[[0.0, 1.0], [3.0, 3.0]]]])
    # |dx|: 1 + 0, |dy|: 3 + 2, over 4 elements
    assert float(TotalVariation()(_ctx(b, b, None))) == pytest.approx(6 / 4)
    # colour: over the element count (3 channels x 4 pixels), the scale the weights were
    # measured at (the authors' pixel count is 3 times stronger: docs/rain.md, defect 2)
    rgb = torch.cat([b, 2 * b, 0 * b], 1)
    assert float(TotalVariation()(_ctx(rgb, rgb, None))) == pytest.approx((6 + 12 + 0) / 12)


def test_capped_total_variation_leaves_strong_edges_alone():
    b = torch.tensor([[[[0.0, 1.0], [3.0, 3.0]]]], requires_grad=True)
    capped = TotalVariation(TotalVariation.Config(cap=1.5))
    loss = capped(_ctx(b, b, None))
    assert float(loss.detach()) == pytest.approx((1 + 0 + 1.5 + 1.5) / 4)  # |dy| 3 and 2 count 1.5
    loss.backward()
    # only the weak step (0 -> 1 along the top row) pulls; the strong vertical ones do not
    assert b.grad.flatten().tolist() == pytest.approx([-0.25, 0.25, 0.0, 0.0])


def test_directional_derivative_of_a_ramp():
    ramp = (torch.arange(5.0) * 0.1).expand(1, 1, 5, 5)  # +0.1 per column
    for kernel in ("scharr", "sobel"):
        gx, gy = image_gradients(ramp, kernel)
        assert torch.allclose(gx, torch.full_like(gx, 0.8)) and gy.abs().max() < 1e-6
        d = directional_derivative(ramp, torch.tensor([math.pi / 3]), kernel)
        assert torch.allclose(d, torch.full_like(d, 0.1 * math.cos(math.pi / 3)), atol=1e-6)
    with pytest.raises(ValueError):
        image_gradients(ramp, "prewitt")


def test_agr_value_by_hand():
    cols = torch.arange(3.0)
    rain = (0.1 * cols).expand(1, 3, 3, 3)  # derivative 0.1 along x, 0 along y
    rendered = (0.2 * cols).expand(1, 3, 3, 3)  # 0.2 along x
    target = rain + rendered + (0.3 * cols[:, None]).expand(1, 3, 3, 3)  # I - R: 0.2 along x, 0.3 along y
    valid = torch.tensor([[True]])
    per_pixel = 0.125  # a unit step gives 4 at the Sobel gain: 1/8 reads derivatives per pixel
    # theta = 0: along = |D_y R| = 0, across = |D_x R| = 0.1, scene = |D_x B| + |D_x (I - R)| = 0.4
    loss = agr_loss(rendered, target, rain, torch.tensor([[0.0]]), valid, background_weight=0.5, gain=per_pixel)
    assert float(loss) == pytest.approx(0.0 - 0.1 + 0.5 * 0.4, abs=1e-6)
    # theta = pi / 2: along = |D_-x R| = 0.1, across = 0, scene = 0 + 0.3
    loss = agr_loss(rendered, target, rain, torch.tensor([[math.pi / 2]]), valid, background_weight=1.0, gain=per_pixel)
    assert float(loss) == pytest.approx(0.1 - 0.0 + 1.0 * 0.3, abs=1e-6)
    # K = 2 averages the directions; invalid directions are left out.
    both = agr_loss(rendered, target, rain, torch.tensor([[0.0, math.pi / 2]]),
                    torch.tensor([[True, True]]), background_weight=0.5, gain=per_pixel)
    assert float(both) == pytest.approx(0.5 * ((-0.1 + 0.2) + (0.1 + 0.15)), abs=1e-6)
    # The paper's operator (gain 1) reads the same image 8 times larger.
    sobel = agr_loss(rendered, target, rain, torch.tensor([[0.0, math.pi / 2]]),
                     torch.tensor([[True, True]]), background_weight=0.5)
    assert float(sobel) == pytest.approx(8 * float(both), rel=1e-5)
    one = agr_loss(rendered, target, rain, torch.tensor([[0.0, math.pi / 2]]),
                   torch.tensor([[True, False]]), background_weight=0.5, gain=per_pixel)
    assert float(one) == pytest.approx(-0.1 + 0.2, abs=1e-6)


def test_mean_abs_derivative_shapes():
    images = torch.rand(2, 3, 8, 9)
    assert mean_abs_derivative(images, torch.rand(2, 4)).shape == (2, 4)


def _streak_scene(angle, seed=0):
    g = torch.Generator().manual_seed(seed)
    background = textured_background(64, g).expand(1, 3, 64, 64)
    rain = streak_layer(64, angle, 25, g).expand(1, 3, 64, 64)
    rotated = streak_layer(64, angle + 90, 25, torch.Generator().manual_seed(seed + 100)).expand(1, 3, 64, 64)
    return background, background + rain, rain, rotated


@pytest.mark.parametrize("angle", [20.0, 90.0, 135.0])
def test_agr_prefers_rain_aligned_with_the_streaks(angle):
    background, rainy, rain, rotated = _streak_scene(angle)
    agr = AdaptiveGradientRotation()
    aligned = agr(_ctx(background, rainy, rain))
    crossed = agr(_ctx(background, rainy, rotated))
    assert float(aligned) < float(crossed)
    assert float(aligned) < 0  # strong across-streak gradients of R dominate


def test_agr_logs_streak_angles_per_view():
    background, rainy, rain, _ = _streak_scene(75.0)
    agr = AdaptiveGradientRotation(AdaptiveGradientRotation.Config(top_k=1))
    agr(_ctx(background, rainy, rain, view_ids=(7,)))
    assert set(agr.metrics) == {"streak_deg/view7"}
    assert abs(agr.metrics["streak_deg/view7"] - 75.0) <= 3.0
    assert agr.view_angles[7] == [agr.metrics["streak_deg/view7"]]
    restored = AdaptiveGradientRotation()
    restored.load_state_dict(agr.state_dict())
    assert restored.view_angles == agr.view_angles


def test_agr_looks_for_rain_near_each_views_down():
    """``max_tilt``: of streaks at 80 degrees under stronger horizontal edges, an upright view's
    AGR finds the streaks and a view rolled by 90 degrees (the world's down along its x axis)
    the edges; without the prior both find the edges."""
    from rainyscape.cameras import Cameras
    from rainyscape.imaging.angles import angle_difference_deg as angle_difference
    from rainyscape.scene import SceneData
    from rainyscape.testing.streaks import streak_layer

    g = torch.Generator().manual_seed(0)
    rain = streak_layer(64, 80.0, 12, g)
    rain[..., 2::6, :] += 0.8
    rain = rain.expand(2, 3, 64, 64)
    c2w = torch.eye(4).repeat(3, 1, 1)  # views 0 and 2 upright, view 1 rolled: its x is the world's down
    c2w[1, :3, :3] = torch.tensor([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    f = torch.full((3,), 50.0)
    cams = Cameras(c2w, f, f, torch.full((3,), 32.0), torch.full((3,), 32.0), 64, 64)
    scene = SceneData(name="toy", images=torch.zeros(3, 64, 64, 3, dtype=torch.uint8), cameras=cams,
                      image_names=["0.png", "1.png", "2.png"], train_indices=[0, 1, 2], eval_indices=[],
                      near=0.1, far=10.0, scene_box=torch.tensor([[-1.0] * 3, [1.0] * 3]))
    found = {}
    for tilt in (45.0, 90.0):
        agr = AdaptiveGradientRotation(AdaptiveGradientRotation.Config(max_tilt=tilt))
        agr.setup(scene, torch.device("cpu"))
        agr(_ctx(torch.zeros_like(rain), rain, rain, view_ids=(0, 1)))
        found[tilt] = [agr.view_angles[v][0] for v in (0, 1)]
    assert abs(found[45.0][0] - 80.0) <= 3.0 and angle_difference(found[45.0][1], 0.0) <= 3.0
    assert all(angle_difference(a, 0.0) <= 3.0 for a in found[90.0])


def test_agr_gradients_reach_rain_and_render():
    background, rainy, rain, _ = _streak_scene(40.0)
    rendered = background.clone().requires_grad_(True)
    predicted = (0.5 * rain).requires_grad_(True)
    AdaptiveGradientRotation()(_ctx(rendered, rainy, predicted)).backward()
    assert rendered.grad.abs().sum() > 0 and predicted.grad.abs().sum() > 0


def test_agr_flat_patch_gives_zero_loss_and_no_angle():
    flat = torch.full((1, 3, 16, 16), 0.5)
    agr = AdaptiveGradientRotation()
    assert float(agr(_ctx(flat, flat, torch.zeros_like(flat)))) == 0.0
    assert agr.metrics == {}


def test_agr_rejects_bad_options():
    with pytest.raises(ConfigError):
        AdaptiveGradientRotation(AdaptiveGradientRotation.Config(bins=2))
    with pytest.raises(ConfigError):
        AdaptiveGradientRotation(AdaptiveGradientRotation.Config(kernel="prewitt"))


def test_dry_weight_by_hand():
    layer = torch.tensor([0.0, 0.1, 0.2]).view(1, 3, 1, 1).expand(1, 3, 2, 2).clone()  # channel mean 0.1
    assert torch.allclose(dry_weight(layer, 0.1), torch.full((1, 1, 2, 2), math.exp(-1.0)))
    assert torch.equal(dry_weight(torch.zeros(2, 3, 4, 4), 0.05), torch.ones(2, 1, 4, 4))


def _rain_split(brightness: float = 0.5, **options):
    """The Gaussians' l1-ssim (authors' split) on a 4 x 4 view of ``brightness`` whose left
    half has strong predicted rain (0.5, render 0.3); the loss's gradient on the render."""
    target = torch.full((1, 3, 4, 4), brightness)
    rain = torch.zeros(1, 3, 4, 4)
    rain[..., :2] = 0.5
    rendered = torch.full((1, 3, 4, 4), 0.3, requires_grad=True)
    loss = L1SSIM(L1SSIM.Config(ssim_weight=0.0, with_rain=True, render_l1=True, **options))(
        _ctx(rendered, target, rain))
    loss.backward()
    return rendered.grad


def test_rain_exclusion_leaves_rainy_pixels_to_the_other_views():
    # I = 1 > B + R: both L1 terms pull the render up, unless the rainy pixels are left out
    grad = _rain_split(1.0, rain_exclusion=0.05)
    assert grad[..., :2].abs().max() < 1e-12 and grad[..., 2:].abs().min() > 0
    assert _rain_split(1.0)[..., :2].abs().min() > 0


def test_anchor_scale_drops_the_anchor_where_rain_is_predicted():
    # left half: B + R = 0.8 > I pushes B down, and only the anchor |B - I| pulls it back up
    left = _rain_split(anchor_scale=0.05)[..., :2]
    assert (left > 0).all()  # a positive gradient: descent lowers B towards I - R
    assert _rain_split()[..., :2].abs().max() < 1e-6  # the dead band: the two L1 terms cancel


def test_floater_gate_takes_what_is_in_front_of_the_surface_under_rain():
    from rainyscape.losses.free_space import front_floater_gate, sample_at

    rain = torch.zeros(1, 3, 8, 8)
    rain[0, :, 5, 2] = 0.2  # a streak pixel at column 2, row 5
    depth = torch.full((1, 1, 8, 8), 10.0)
    # four Gaussians: in front of the surface under the rain; on the surface under the rain;
    # in front at a dry pixel; in front under the rain but not visible
    means2d = torch.tensor([[[2.5, 5.5], [2.4, 5.6], [6.5, 1.5], [2.5, 5.5]]])
    depths = torch.tensor([[3.0, 9.95, 3.0, 3.0]])
    visible = torch.tensor([[True, True, True, False]])
    assert sample_at(rain[:, :1], means2d)[0, :, 0].tolist() == pytest.approx([0.2, 0.2, 0.0, 0.2])
    gate = front_floater_gate(rain, depth, means2d, depths, visible, margin=0.1, rain_scale=0.05)
    assert gate.tolist() == [[1.0, 0.0, 0.0, 0.0]]
    faint = front_floater_gate(rain * 0.1, depth, means2d, depths, visible, margin=0.1, rain_scale=0.05)
    assert faint[0, 0].item() == pytest.approx(0.4)  # rain below the scale gates in proportion


def test_floater_opacity_lowers_only_the_gated_gaussians_opacity():
    from rainyscape.losses.free_space import FloaterOpacity

    opacities = torch.full((3,), 0.5, requires_grad=True)
    rain = torch.zeros(1, 3, 8, 8)
    rain[0, :, 5, 2] = 0.2
    output = RenderOutput(rgb=torch.zeros(1, 3, 8, 8), depth=torch.full((1, 1, 8, 8), 10.0),
                          acc=torch.ones(1, 1, 8, 8),
                          extras={"opacities": opacities, "means2d": torch.tensor([[[2.5, 5.5], [2.5, 5.5], [6.5, 1.5]]]),
                                  "centre_depths": torch.tensor([[3.0, 10.0, 3.0]]), "radii": torch.ones(1, 3, 2)})
    ctx = LossContext(output.rgb, output.rgb, {"rain": rain}, output, torch.tensor([0]), 0, "joint")
    loss = FloaterOpacity()(ctx)
    loss.backward()
    assert loss.item() == pytest.approx(0.5 / 64)
    assert opacities.grad.tolist() == pytest.approx([1 / 64, 0.0, 0.0])  # descent lowers the floater's alone
    # a render without Gaussians (a ray field, a crop of a render) gives nothing
    plain = LossContext(output.rgb, output.rgb, {"rain": rain}, RenderOutput(rgb=output.rgb), torch.tensor([0]), 0, "joint")
    assert FloaterOpacity()(plain).item() == 0.0


def test_front_weight_is_the_weight_in_front_of_the_median_depth():
    """A ray with a floater (0.2 at distance 1) before its surface (0.7 at 5, 0.1 at 6): the
    median depth is the surface's, the floater's weight alone is in front, and only it gets
    the gradient. Without a floater nothing is in front."""
    from rainyscape.fields.packed import front_weight

    # packed samples: rows of ray 0, then of ray 1; a third ray has none
    weights = torch.tensor([0.2, 0.0, 0.7, 0.1, 0.0, 0.0, 0.9, 0.1], requires_grad=True)
    distance = torch.tensor([1.0, 3.0, 5.0, 6.0] * 2)
    ray = torch.tensor([0, 0, 0, 0, 1, 1, 1, 1])
    front = front_weight(weights, distance, ray, 3)
    assert front.tolist() == pytest.approx([0.2, 0.0, 0.0])
    front.sum().backward()
    assert weights.grad.tolist() == [1.0, 1.0, 0.0, 0.0, 1.0, 1.0, 0.0, 0.0]
    # a floater holding most of the light is the surface as far as the median can tell
    assert front_weight(torch.tensor([0.6, 0.0, 0.3, 0.1]), distance[:4], ray[:4], 1).item() == 0.0


def test_floater_rays_weighs_each_ray_by_the_rain_at_its_pixel():
    from rainyscape.losses.free_space import FloaterRays

    rain = torch.zeros(1, 3, 2, 2)
    rain[0, :, 0, 0] = 0.2  # rain at one pixel (over the scale), a trace at another
    rain[0, :, 1, 1] = 0.01
    front = torch.full((1, 1, 2, 2), 0.5, requires_grad=True)
    output = RenderOutput(rgb=torch.zeros(1, 3, 2, 2), extras={"front_weight": front})
    ctx = LossContext(output.rgb, output.rgb, {"rain": rain}, output, torch.tensor([0]), 0, "joint")
    term = FloaterRays()
    assert term.render_extras == ("front_weight",)
    loss = term(ctx)
    loss.backward()
    assert loss.item() == pytest.approx(0.5 * (1.0 + 0.2) / 4)
    assert front.grad.flatten().tolist() == pytest.approx([0.25, 0.0, 0.0, 0.05])
    assert term.metrics["gate_mean"] == pytest.approx(1.2 / 4)
    # a render without the measure (the field's cached views, a crop) gives nothing
    plain = LossContext(output.rgb, output.rgb, {"rain": rain}, RenderOutput(rgb=output.rgb), torch.tensor([0]), 0, "joint")
    assert term(plain).item() == 0.0
    assert FloaterRays(FloaterRays.Config(measure="distortion")).render_extras == ("distortion",)


def test_agr_view_directions_carry_a_whole_views_direction_to_its_patches():
    """``directions=view``: a 4 x 4 patch whose residual is a scene edge (horizontal) takes the
    streak direction its view's last whole-view batch found; a view with none estimates its
    own; the kept directions survive a checkpoint. ``batch`` (the paper's) reads the edge."""
    from rainyscape.cameras import Cameras, Window
    from rainyscape.scene import SceneData

    background, rainy, rain, _ = _streak_scene(70.0)
    f = torch.full((2,), 50.0)
    cams = Cameras(torch.eye(4).repeat(2, 1, 1), f, f, torch.full((2,), 32.0), torch.full((2,), 32.0), 64, 64)
    scene = SceneData(name="toy", images=torch.zeros(2, 64, 64, 3, dtype=torch.uint8), cameras=cams,
                      image_names=["0.png", "1.png"], train_indices=[0, 1], eval_indices=[],
                      near=0.1, far=10.0, scene_box=torch.tensor([[-1.0] * 3, [1.0] * 3]))
    edge = torch.zeros(2, 3, 4, 4)
    edge[..., 2:, :] = 0.8
    patch = Window(torch.zeros(2, dtype=torch.long), torch.zeros(2, dtype=torch.long), 4, 4)

    def patch_angles(agr):
        ctx = LossContext(torch.zeros_like(edge), edge, {"rain": edge}, RenderOutput(rgb=edge), torch.tensor([0, 1]),
                          step=0, phase="joint", window=patch)
        agr(ctx)
        return [agr.view_angles[v][0] for v in (0, 1)]

    found = {}
    for directions in ("batch", "view"):
        agr = AdaptiveGradientRotation(AdaptiveGradientRotation.Config(directions=directions))
        agr.setup(scene, torch.device("cpu"))
        whole = LossContext(background, rainy, {"rain": rain}, RenderOutput(rgb=background), torch.tensor([0]),
                            step=0, phase="joint", window=Window.full(cams[torch.tensor([0])]), record=False)
        agr(whole)
        found[directions] = patch_angles(agr)
    assert abs(found["view"][0] - 70.0) <= 3.0  # view 0: its whole view's streaks
    assert abs(found["view"][1] - 0.0) <= 3.0  # view 1: no whole view yet, its own patch's edge
    assert all(abs(a - 0.0) <= 3.0 for a in found["batch"])
    restored = AdaptiveGradientRotation(AdaptiveGradientRotation.Config(directions="view"))
    restored.setup(scene, torch.device("cpu"))
    restored.load_state_dict(agr.state_dict())
    assert torch.equal(restored.kept[1], agr.kept[1]) and torch.allclose(restored.kept[0], agr.kept[0])
    assert abs(patch_angles(restored)[0] - 70.0) <= 3.0
    with pytest.raises(ConfigError):
        AdaptiveGradientRotation(AdaptiveGradientRotation.Config(directions="crop"))


def test_agr_reads_the_direction_where_the_head_sees_rain():
    """``where_rain``: a residual whose strongest structure is a scene edge (horizontal stripes
    in the top half) and whose rain (streaks at 70 degrees) is in the bottom half: with R over
    the streaks only, the direction is the rain's; without the gate, the edges'."""
    g = torch.Generator().manual_seed(3)
    rain = streak_layer(64, 70.0, 25, g).expand(1, 3, 64, 64).clone()
    rain[..., :32, :] = 0
    edges = torch.zeros(1, 3, 64, 64)
    edges[..., 2:32:4, :] = 1.0
    rendered = torch.zeros(1, 3, 64, 64)
    found = {}
    for where in (0.0, 0.02):
        agr = AdaptiveGradientRotation(AdaptiveGradientRotation.Config(where_rain=where))
        agr(_ctx(rendered, edges + rain, rain))
        found[where] = agr.view_angles[0][0]
    assert abs(found[0.02] - 70.0) <= 3.0
    assert abs(found[0.0] - 0.0) <= 3.0
    nothing = AdaptiveGradientRotation(AdaptiveGradientRotation.Config(where_rain=0.02))
    nothing(_ctx(rendered, edges + rain, torch.zeros_like(rain)))  # no rain seen: the whole residual
    assert abs(nothing.view_angles[0][0] - 0.0) <= 3.0
