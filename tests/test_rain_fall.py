"""One world fall direction for the rain (rain/fall.py) and the AGR term steered by it per pixel
(``losses.agr.directions=world``)."""

from __future__ import annotations

import json
import math

import torch
from torch import Tensor

from rainyscape.cameras import Cameras, Window, level_up
from rainyscape.components import LossContext, RenderOutput
from rainyscape.eval.rain_stats import fall_angles_deg, true_rain_falls
from rainyscape.imaging.angles import angle_difference_deg
from rainyscape.losses.agr import AdaptiveGradientRotation
from rainyscape.cameras import projected_line_angles
from rainyscape.losses.fall import GradientSamples, fit_fall_direction, tilted_directions


def _ring_cameras(n: int = 8, pitch_deg: float = 30.0, size: int = 64) -> Cameras:
    """Cameras on a ring around the origin, looking at it from above (world up +y)."""
    c2w = torch.zeros(n, 4, 4)
    for i in range(n):
        a = 2 * math.pi * i / n
        p = math.radians(pitch_deg)
        eye = torch.tensor([4 * math.cos(a) * math.cos(p), 4 * math.sin(p), 4 * math.sin(a) * math.cos(p)])
        forward = -eye / eye.norm()
        right = torch.linalg.cross(forward, torch.tensor([0.0, 1.0, 0.0]))
        right = right / right.norm()
        down = torch.linalg.cross(forward, right)
        c2w[i, :3, :3] = torch.stack([right, down, forward], 1)  # OpenCV: x right, y down, z forward
        c2w[i, :3, 3] = eye
        c2w[i, 3, 3] = 1.0
    f = torch.full((n,), 50.0)
    c = torch.full((n,), size / 2)
    return Cameras(c2w, f, f, c, c, size, size)


def _samples(cams: Cameras, direction: Tensor, count: int, gen: torch.Generator, noise_deg: float = 2.0):
    """Gradients across ``direction``'s streaks at random pixels of every view."""
    n = len(cams)
    view = torch.randint(0, n, (count,), generator=gen)
    u = torch.rand(count, generator=gen) * cams.width
    v = torch.rand(count, generator=gen) * cams.height
    d_cam = (cams.c2w[:, :3, :3].transpose(1, 2) @ direction)[view]
    streak = projected_line_angles(d_cam, cams.fx[view], cams.fy[view], cams.cx[view], cams.cy[view], u, v)
    phi = streak + math.pi / 2 + torch.deg2rad(noise_deg * torch.randn(count, generator=gen))
    return GradientSamples(view, u, v, phi, torch.ones(count))



def test_the_fall_is_found_among_the_scenes_plumb_edges():
    """Rain falling 12 degrees off the vertical, with half as many gradients from vertical scene
    edges (a plumb line, sharper than the rain's) and as many from random edges: the fit finds
    the rain's direction, not the plumb."""
    cams = _ring_cameras()
    gen = torch.Generator().manual_seed(0)
    down = -level_up(cams.c2w)
    fall = tilted_directions(down, torch.tensor([12.0]), torch.tensor([70.0]))[0].float()
    rain = _samples(cams, fall, 3000, gen)
    plumb = _samples(cams, down, 1500, gen, noise_deg=0.5)
    clutter = GradientSamples(torch.randint(0, 8, (3000,), generator=gen), torch.rand(3000, generator=gen) * 64,
                              torch.rand(3000, generator=gen) * 64, torch.rand(3000, generator=gen) * math.pi,
                              torch.ones(3000))
    found = fit_fall_direction(cams, GradientSamples.cat([rain, plumb, clutter]), down)
    assert math.degrees(math.acos(float(found @ fall))) < 1.0
    tilt = math.degrees(math.acos(float(found @ down)))
    assert abs(tilt - 12.0) < 1.0


def test_world_directions_steer_every_pixel_by_the_simulators_fall(tiny_scene):
    """On a simulated scene, with its true rain as the residual: the fall is the world's down
    until a second pass over the whole views confirms the first's fit, the simulator's fall;
    the logged per-view angles are nearer the true angles than each view's own estimate;
    patches are steered per pixel; the fall and its masks survive a checkpoint."""
    scene = tiny_scene
    views = list(scene.train_indices)
    config = AdaptiveGradientRotation.Config(directions="world", fall_refit=len(views), where_rain=0.02,
                                             estimator="structure")
    agr = AdaptiveGradientRotation(config)
    agr.setup(scene, torch.device("cpu"))
    clean = scene.clean_images.permute(0, 3, 1, 2).float() / 255.0
    rainy = scene.images.permute(0, 3, 1, 2).float() / 255.0
    rain = (rainy - clean).clamp_min(0.0)

    def whole(v: int, record: bool = True) -> LossContext:
        return LossContext(clean[[v]], rainy[[v]], {"rain": rain[[v]]}, RenderOutput(rgb=clean[[v]]),
                           torch.tensor([v]), step=0, phase="joint", record=record)

    down = -level_up(scene.cameras.c2w)
    for _ in range(2):  # steered by the world's down until two fits in a row agree
        assert torch.allclose(agr.fall, down)
        for v in views:
            agr(whole(v))
    truth = true_rain_falls(scene)[0].float()
    assert agr.fall is not None and math.degrees(math.acos(float(agr.fall @ truth))) < 4.0
    per_view = AdaptiveGradientRotation(AdaptiveGradientRotation.Config(directions="view", where_rain=0.02,
                                                                          estimator="structure"))
    per_view.setup(scene, torch.device("cpu"))
    errors = {"world": [], "view": []}
    for v in views:
        true_angle = fall_angles_deg(scene.cameras[v], true_rain_falls(scene), rain[v])[0]
        for name, term in (("world", agr), ("view", per_view)):
            term(whole(v))
            errors[name].append(angle_difference_deg(term.view_angles[v][0], true_angle))
    world, view = (sum(e) / len(e) for e in (errors["world"], errors["view"]))
    assert world < 3.0 and world < view  # the 48 px scene's short streaks: each view alone errs more

    patch = Window(torch.tensor([3, 20]), torch.tensor([5, 11]), 6, 6)
    ctx = LossContext(clean[views[:2], :, :6, :6] * 0, rainy[views[:2], :, :6, :6], {"rain": rain[views[:2], :, :6, :6]},
                      None, torch.tensor(views[:2]), step=0, phase="joint", window=patch)
    theta, valid = agr.directions_for(ctx)
    assert theta.shape == (2, 1, 1, 4, 4) and bool(valid.all())
    expected = agr.streaks[views[1], 12, 21] + math.pi / 2  # the patch's valid pixel (0, 0)
    assert abs(float(theta[1, 0, 0, 0, 0]) - float(expected)) < 1e-6
    assert torch.isfinite(agr(ctx))

    restored = AdaptiveGradientRotation(config)
    restored.setup(scene, torch.device("cpu"))
    restored.load_state_dict(agr.state_dict())
    assert torch.equal(restored.fall, agr.fall) and torch.equal(restored.streaks, agr.streaks)
    assert torch.equal(restored.last_fit, agr.last_fit)
    assert restored.view_fall_angle(views[0]) == agr.view_fall_angle(views[0])


def test_rainyscape_plus_nerf_trains_end_to_end_steered_by_the_world_fall(tiny_scene_dir, tmp_path):
    """``losses.agr.directions=world`` through training (patches, single rays, a cached whole
    view each joint step): every joint log records the fall's tilt and per-view angles, and
    the run finishes and evaluates."""
    from test_render_cache import MIXED_JOINT, SMALL

    from rainyscape.config import method_config
    from rainyscape.workflow import train_and_evaluate

    run = train_and_evaluate(method_config("rainyscape-plus-nerf", [
        f"data={tiny_scene_dir}", *SMALL, *MIXED_JOINT, "losses.agr.directions=world",
        "losses.agr.fall_refit=2", f"trainer.output_dir={tmp_path}"]))
    assert "train_psnr" in json.loads((run.run_dir / "metrics.json").read_text())["summary"]
    records = [json.loads(line) for line in (run.run_dir / "log.jsonl").read_text().splitlines()]
    joint = [r.get("metrics", {}) for r in records if r.get("phase") == "joint" and "terms" in r]
    assert joint and all(0.0 <= m["agr.fall_tilt_deg"] < 60.0 for m in joint)
    assert all(any(k.startswith("agr.streak_deg/view") for k in m) for m in joint)
