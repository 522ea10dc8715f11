"""Simulator: geometry that reprojects, Maya conventions, rain physics and view consistency."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from rainyscape.cameras import pixel_rays
from rainyscape.dataparsers.maya_csv import MayaCsvConfig, MayaCsvParser
from rainyscape.dataparsers.maya_math import euler_xyz_to_matrix, look_at_angles, maya_c2w_opencv
from rainyscape.errors import ConfigError, DataError
from rainyscape.synth import generate
from rainyscape.synth.rain import DropField, RainConfig, make_drop_field, render_rain, sample_radii, terminal_velocity


def _bilinear(depth: torch.Tensor, u: torch.Tensor, v: torch.Tensor):
    """Depth at continuous pixel positions (inverse depth is linear across a plane) and whether
    the 4 neighbouring pixel centres lie on one smooth surface."""
    h, w = depth.shape
    x, y = u - 0.5, v - 0.5
    x0, y0 = x.floor().long(), y.floor().long()
    ok = (x0 >= 0) & (y0 >= 0) & (x0 + 1 < w) & (y0 + 1 < h)
    x0, y0 = x0.clamp(0, w - 2), y0.clamp(0, h - 2)
    d = torch.stack([depth[y0, x0], depth[y0, x0 + 1], depth[y0 + 1, x0], depth[y0 + 1, x0 + 1]])
    smooth = ok & torch.isfinite(d).all(0) & ((d.max(0).values - d.min(0).values) < 0.1 * d.min(0).values)
    fx, fy = (x - x0).clamp(0, 1), (y - y0).clamp(0, 1)
    inv = 1.0 / d
    val = (inv[0] * (1 - fx) + inv[1] * fx) * (1 - fy) + (inv[2] * (1 - fx) + inv[3] * fx) * fy
    return 1.0 / val, smooth


@pytest.mark.parametrize("view_a,view_b", [(0, 1), (5, 6), (2, 9)])
def test_depth_reprojects_between_views_within_half_a_pixel(tiny_scene, view_a, view_b):
    s = tiny_scene
    cams, depth = s.cameras, s.depths
    h, w = s.height, s.width
    ys, xs = torch.meshgrid(torch.arange(h), torch.arange(w), indexing="ij")
    rays = pixel_rays(cams[view_a], xs[None], ys[None])
    da = depth[view_a]
    finite = torch.isfinite(da)
    pts = (rays.origins[0] + rays.directions[0] * (da / rays.z_scale[0])[..., None])[finite]
    uv_b, z_b = cams[view_b].project(pts)
    uv_b, z_b = uv_b[0], z_b[0]
    depth_b, smooth = _bilinear(depth[view_b], uv_b[:, 0], uv_b[:, 1])
    visible = smooth & (z_b > 0) & ((z_b - depth_b).abs() < 0.01 * z_b)
    # most of A's surface that lands inside B is found there at the right depth
    inside = (uv_b[:, 0] > 0.5) & (uv_b[:, 0] < w - 0.5) & (uv_b[:, 1] > 0.5) & (uv_b[:, 1] < h - 0.5)
    assert visible.sum() > 0.5 * inside.sum()
    # round trip: B's surface point under that pixel projects back onto A's pixel centre
    k_inv = torch.linalg.inv(cams[view_b].K()[0])
    uv1 = torch.cat([uv_b[visible], torch.ones(int(visible.sum()), 1)], 1)
    cam_pts = (uv1 @ k_inv.T) * depth_b[visible, None]
    c2w = cams[view_b].c2w[0]
    world = cam_pts @ c2w[:3, :3].T + c2w[:3, 3]
    uv_a, _ = cams[view_a].project(world)
    pix_a = torch.stack([xs[finite], ys[finite]], -1)[visible].float() + 0.5
    err = (uv_a[0] - pix_a).norm(dim=-1)
    assert err.max() < 0.5, f"max reprojection error {err.max():.3f} px"


def test_cameras_look_at_the_scene_centre_upright(tiny_scene_dir):
    scene = MayaCsvParser(MayaCsvConfig(normalize=False)).parse(tiny_scene_dir)
    info = json.loads((tiny_scene_dir / "scene.json").read_text())
    look_at = torch.tensor(info["look_at"], dtype=torch.float32)
    c2w = scene.cameras.c2w
    to_target = look_at - c2w[:, :3, 3]
    cos = torch.nn.functional.cosine_similarity(to_target, c2w[:, :3, 2], dim=-1)
    assert torch.all(cos > 1 - 1e-6)
    assert torch.all(-c2w[:, 1, 1] > 0.5)  # image "up" (-y) points up the world's Y
    assert abs(float(c2w[:, 1, 0].abs().max())) < 1e-5  # rz = 0: image rows stay horizontal


def test_euler_xyz_matches_hand_computed_matrices():
    rx90 = np.array([[1, 0, 0], [0, 0, -1], [0, 1, 0]])
    ry90 = np.array([[0, 0, 1], [0, 1, 0], [-1, 0, 0]])
    rz90 = np.array([[0, -1, 0], [1, 0, 0], [0, 0, 1]])
    got = euler_xyz_to_matrix(np.array([[90, 0, 0], [0, 90, 0], [0, 0, 90], [90, 90, 0], [90, 0, 90]]))
    np.testing.assert_allclose(got[0], rx90, atol=1e-12)
    np.testing.assert_allclose(got[1], ry90, atol=1e-12)
    np.testing.assert_allclose(got[2], rz90, atol=1e-12)
    # XYZ order: X applied first, so R = Ry Rx (hand-multiplied)
    np.testing.assert_allclose(got[3], [[0, 1, 0], [0, 0, -1], [-1, 0, 0]], atol=1e-12)
    np.testing.assert_allclose(got[4], [[0, 0, 1], [1, 0, 0], [0, 1, 0]], atol=1e-12)


def test_maya_camera_axes_to_opencv():
    # rx = -90: looking straight down; Maya's camera up (+Y) becomes world -Z
    c2w = maya_c2w_opencv(np.array([[0.0, 10.0, 0.0]]), np.array([[-90.0, 0.0, 0.0]]))[0].numpy()
    np.testing.assert_allclose(c2w[:3, 2], [0.0, -1.0, 0.0], atol=1e-6)  # forward
    np.testing.assert_allclose(c2w[:3, 0], [1.0, 0.0, 0.0], atol=1e-6)  # right
    np.testing.assert_allclose(c2w[:3, 1], [0.0, 0.0, 1.0], atol=1e-6)  # down
    # rx = -30, ry = 45: forward = (-sin ry cos rx, sin rx, -cos ry cos rx)
    c2w = maya_c2w_opencv(np.zeros((1, 3)), np.array([[-30.0, 45.0, 0.0]]))[0].numpy()
    expect = [-np.sin(np.pi / 4) * np.cos(np.pi / 6), -0.5, -np.cos(np.pi / 4) * np.cos(np.pi / 6)]
    np.testing.assert_allclose(c2w[:3, 2], expect, atol=1e-6)
    angles = look_at_angles(np.array([[3.0, 4.0, 5.0]]), np.array([[0.0, 1.0, -2.0]]))
    fwd = maya_c2w_opencv(np.array([[3.0, 4.0, 5.0]]), angles)[0, :3, 2].double().numpy()
    target = np.array([-3.0, -3.0, -7.0]) / np.linalg.norm([3.0, 3.0, 7.0])
    np.testing.assert_allclose(fwd, target, atol=1e-6)


def test_terminal_velocity_and_drop_sizes():
    assert terminal_velocity(np.array([1e-3]))[0] == pytest.approx(200 * np.sqrt(1e-3))
    rng = np.random.default_rng(0)
    light = sample_radii(20000, RainConfig(rain_rate_mm_h=2.0), rng)
    heavy = sample_radii(20000, RainConfig(rain_rate_mm_h=50.0), rng)
    assert light.min() >= 0.5e-3 and heavy.max() <= 3e-3
    assert heavy.mean() > light.mean()  # Marshall-Palmer: heavier rain, bigger drops
    counts, _ = np.histogram(light, bins=5, range=(0.5e-3, 3e-3))
    assert np.all(np.diff(counts) < 0)  # exponential: fewer big drops


def test_wind_angle_and_two_direction_mixture():
    cfg = RainConfig(density=2.0, wind_deg=30.0, wind_azimuth_deg=0.0, wind2_deg=30.0,
                     wind2_azimuth_deg=180.0, mix=0.4, jitter=0.0)
    field = make_drop_field(np.zeros(3), np.full(3, 10.0), cfg, seed=1)
    v = field.velocities
    assert np.all(v[:, 1] < 0)
    to_left = np.mean(v[:, 0] < 0)
    assert to_left == pytest.approx(0.4, abs=0.05)
    right = v[v[:, 0] > 0]
    median_fall = terminal_velocity(np.array([1.75e-3]))[0]
    assert np.allclose(right[:, 0], median_fall * np.tan(np.radians(30)))


def _one_drop(pos, vel, radius=2e-3) -> DropField:
    return DropField(np.array([pos], float), np.array([vel], float), np.array([radius]), np.ones(1),
                     np.array([-100.0, 0.0, -100.0]), np.array([100.0, 100.0, 100.0]))


def _alpha_centroid_and_axis(alpha: np.ndarray):
    ys, xs = np.nonzero(alpha > 0)
    wgt = alpha[ys, xs]
    c = np.array([np.sum(xs * wgt), np.sum(ys * wgt)]) / wgt.sum() + 0.5
    d = np.stack([xs + 0.5 - c[0], ys + 0.5 - c[1]], 1)
    cov = (d * wgt[:, None]).T @ d / wgt.sum()
    return c, np.linalg.eigh(cov)[1][:, -1]


def test_static_rain_streak_is_where_the_drop_projects_in_every_view(tiny_scene_dir):
    scene = MayaCsvParser(MayaCsvConfig(normalize=False)).parse(tiny_scene_dir)
    cams = scene.cameras
    cfg = RainConfig(size_scale=100.0, opacity=1.0, exposure_s=0.1)
    drop = _one_drop([0.3, 3.0, 2.0], [1.5, -6.0, 0.0])
    start, end = drop.segments(0.0, cfg.exposure_s)
    sky = np.full((cams.height, cams.width), np.inf)
    for view in (0, 5, 11):
        layer = render_rain(drop, cams, view, sky, 0.0, cfg, np.ones(3))
        assert layer.alpha.max() > 0.3
        uv, _ = cams[view].project(torch.from_numpy(np.stack([start[0], end[0]])).float())
        a, b = uv[0].numpy()
        centroid, axis = _alpha_centroid_and_axis(layer.alpha)
        assert np.linalg.norm(centroid - (a + b) / 2) < 0.6
        seg = (b - a) / np.linalg.norm(b - a)
        assert abs(seg @ axis) > 0.99  # the streak runs along the projected motion
        blocked = render_rain(drop, cams, view, np.full_like(sky, 5.0), 0.0, cfg, np.ones(3))
        assert blocked.alpha.max() == 0.0  # hidden behind a nearer surface


def test_dynamic_rain_moves_between_frames(tiny_scene):
    cams = tiny_scene.cameras
    cfg = RainConfig(size_scale=40.0, opacity=1.0)
    drop = _one_drop([0.0, 0.5, 0.0], [0.0, -4.0, 0.0])
    sky = np.full((cams.height, cams.width), np.inf)
    first = render_rain(drop, cams, 4, sky, 0.0, cfg, np.ones(3))
    again = render_rain(drop, cams, 4, sky, 0.0, cfg, np.ones(3))
    later = render_rain(drop, cams, 4, sky, 1.0 / 24, cfg, np.ones(3))
    np.testing.assert_array_equal(first.alpha, again.alpha)  # one instant: one picture
    assert np.abs(first.alpha - later.alpha).max() > 0.3
    c0, _ = _alpha_centroid_and_axis(first.alpha)
    c1, _ = _alpha_centroid_and_axis(later.alpha)
    pts = torch.tensor([[0.0, 0.5, 0.0], [0.0, 0.5 - 4.0 / 24, 0.0]])
    uv, _ = cams[4].project(pts)
    np.testing.assert_allclose(c1 - c0, (uv[0, 1] - uv[0, 0]).numpy(), atol=0.6)


def test_generated_scene_is_consistent(tiny_scene, tiny_scene_dir):
    s = tiny_scene
    info = json.loads((tiny_scene_dir / "scene.json").read_text())
    assert info["mode"] == "static" and all(v["time_s"] == 0.0 for v in info["metrics"]["per_view"])
    rainy = s.images.float() / 255
    clean = s.clean_images.float() / 255
    # the rain layer is the additive rain I - B (to 8-bit rounding)
    assert (rainy - clean - s.rain_layers).abs().max() < 2.5 / 255
    assert s.rain_layers.abs().mean() > 1e-3  # visible rain
    assert (s.rain_layers.sum(-1) >= -1e-3).float().mean() > 0.9  # drops are brighter than the scene
    # the scene has real detail: blurring costs PSNR
    x = clean.permute(0, 3, 1, 2)
    blurred = F.avg_pool2d(F.pad(x, (1, 1, 1, 1), mode="replicate"), 3, stride=1)
    mse = ((blurred - x) ** 2).mean()
    assert -10 * torch.log10(mse) < 26.0


def test_dynamic_mode_times_and_video_trajectory(tmp_path):
    out = generate(tmp_path / "dyn", "demo", rows=1, cols=3, width=24, height=24, mode="dynamic",
                   trajectory="video", density=5.0)
    info = json.loads((out / "scene.json").read_text())
    times = [v["time_s"] for v in info["metrics"]["per_view"]]
    assert times == pytest.approx([0.0, 1 / 24, 2 / 24])
    assert sorted(p.name for p in (out / "images_rain").iterdir()) == ["001.png", "002.png", "003.png"]


def test_generate_refuses_non_empty_folder_and_bad_options(tmp_path):
    (tmp_path / "keep.txt").write_text("user data")
    with pytest.raises(DataError, match="not empty"):
        generate(tmp_path, "demo", rows=1, cols=1, width=8, height=8)
    assert (tmp_path / "keep.txt").read_text() == "user data"
    with pytest.raises(ConfigError, match="unknown rain option 'densty'"):
        generate(tmp_path / "x", "demo", densty=3)
    with pytest.raises(ConfigError, match="unknown preset"):
        generate(tmp_path / "x", "nope")
    with pytest.raises(ConfigError, match="mode"):
        generate(tmp_path / "x", "demo", mode="sometimes")


def test_density_beyond_the_drop_budget_is_refused(tmp_path):
    with pytest.raises(ConfigError, match="lower density"):  # within density's range, too many drops here
        generate(tmp_path / "x", "demo", rows=1, cols=1, width=8, height=8, density=1000)
    with pytest.raises(ConfigError, match="density: must be between 0 and 1000"):
        generate(tmp_path / "x", "demo", rows=1, cols=1, width=8, height=8, density=1e6)
    assert list(tmp_path.iterdir()) == []  # nothing left behind, staging folder included


@pytest.mark.slow  # two spawned processes each import torch
def test_worker_processes_write_the_same_scene(tmp_path):
    one = generate(tmp_path / "one", "yard", rows=1, cols=2, width=20, height=20, workers=1)
    two = generate(tmp_path / "two", "yard", rows=1, cols=2, width=20, height=20, workers=2)
    for sub in ("images_rain", "images_wo_rain", "rain"):
        for p in sorted((one / sub).iterdir()):
            assert p.read_bytes() == (two / sub / p.name).read_bytes()
    assert json.loads((two / "scene.json").read_text())["workers"] == 2
