"""Rays: a pixel's ray passes through the 3D point that projects to that pixel, for every
camera convention the dataparsers read, and NDC keeps rays straight."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from rainyscape.errors import ConfigError
from rainyscape.cameras import Cameras, down_directions, level_up, opengl_to_opencv, pixel_rays, world_up
from rainyscape.fields.ndc import average_pose, ndc_points, ndc_rays, ndc_to_distance

W, H = 40, 30


def _random_rotation(gen: torch.Generator) -> torch.Tensor:
    q, r = torch.linalg.qr(torch.randn(3, 3, generator=gen, dtype=torch.float64))
    q = q * torch.sign(torch.diagonal(r))
    return q if torch.det(q) > 0 else -q


def _cameras(c2w: torch.Tensor) -> Cameras:
    n = c2w.shape[0]
    f = torch.full((n,), 35.0)
    return Cameras(c2w.float(), f, f * 1.1, torch.full((n,), 19.0), torch.full((n,), 16.5), W, H)


def _assert_rays_hit(cams: Cameras, cols: torch.Tensor, rows: torch.Tensor, points: torch.Tensor,
                     zdepth: torch.Tensor) -> None:
    """Camera b's ray through pixel (rows[b], cols[b]) reaches points[b] at z-depth zdepth[b]."""
    points, zdepth = points.float(), zdepth.float()
    rays = pixel_rays(cams, cols[:, None], rows[:, None])
    o, d, zs = rays.origins[:, 0], rays.directions[:, 0], rays.z_scale[:, 0]
    t = zdepth / zs
    assert torch.allclose(o + t[:, None] * d, points, atol=1e-4)
    pix, z = cams.project(points)
    idx = torch.arange(len(cams))
    assert torch.allclose(pix[idx, idx], torch.stack([cols + 0.5, rows + 0.5], -1).float(), atol=1e-3)
    assert torch.allclose(z[idx, idx], zdepth, atol=1e-4)


def _pixels_and_depths(gen: torch.Generator, n: int):
    cols = torch.randint(0, W, (n,), generator=gen)
    rows = torch.randint(0, H, (n,), generator=gen)
    depth = torch.rand(n, generator=gen, dtype=torch.float64) * 5 + 0.5
    return cols, rows, depth


def test_opencv_convention_colmap():
    """COLMAP / OpenCV: x right, y down, looking down +z; pixel centres at (j + .5, i + .5)."""
    gen = torch.Generator().manual_seed(0)
    n = 16
    c2w = torch.eye(4, dtype=torch.float64).repeat(n, 1, 1)
    for b in range(n):
        c2w[b, :3, :3] = _random_rotation(gen)
        c2w[b, :3, 3] = torch.randn(3, generator=gen, dtype=torch.float64) * 3
    cams = _cameras(c2w)
    cols, rows, depth = _pixels_and_depths(gen, n)
    # Independent back-projection with K^-1 in double precision.
    x = (cols + 0.5 - 19.0) / 35.0 * depth
    y = (rows + 0.5 - 16.5) / (35.0 * 1.1) * depth
    cam_pts = torch.stack([x, y, depth], -1)
    world = (c2w[:, :3, :3] @ cam_pts[..., None])[..., 0] + c2w[:, :3, 3]
    _assert_rays_hit(cams, cols, rows, world, depth)


def test_opengl_convention_llff_nerfstudio_maya():
    """OpenGL-style poses (x right, y up, looking down -z), converted at the parser boundary."""
    gen = torch.Generator().manual_seed(1)
    n = 16
    c2w_gl = torch.eye(4, dtype=torch.float64).repeat(n, 1, 1)
    for b in range(n):
        c2w_gl[b, :3, :3] = _random_rotation(gen)
        c2w_gl[b, :3, 3] = torch.randn(3, generator=gen, dtype=torch.float64) * 3
    cols, rows, depth = _pixels_and_depths(gen, n)
    # In an OpenGL camera, image rows grow downwards while y points up, and depth is -z.
    x = (cols + 0.5 - 19.0) / 35.0 * depth
    y = -(rows + 0.5 - 16.5) / (35.0 * 1.1) * depth
    cam_pts = torch.stack([x, y, -depth], -1)
    world = (c2w_gl[:, :3, :3] @ cam_pts[..., None])[..., 0] + c2w_gl[:, :3, 3]
    _assert_rays_hit(_cameras(opengl_to_opencv(c2w_gl)), cols, rows, world, depth)


def test_one_gl_cv_conversion_serves_torch_and_numpy():
    from rainyscape.cameras import opencv_to_opengl

    gen = torch.Generator().manual_seed(2)
    c2w = torch.eye(4, dtype=torch.float64).repeat(3, 1, 1)
    for b in range(3):
        c2w[b, :3, :3] = _random_rotation(gen)
        c2w[b, :3, 3] = torch.randn(3, generator=gen, dtype=torch.float64)
    flip = torch.diag(torch.tensor([1.0, -1.0, -1.0, 1.0], dtype=torch.float64))
    cv = opengl_to_opencv(c2w)
    assert isinstance(cv, torch.Tensor) and cv.dtype == torch.float64
    assert torch.equal(cv, c2w @ flip)
    assert torch.equal(opencv_to_opengl(cv), c2w)  # an involution
    as_np = opengl_to_opencv(c2w.numpy().astype(np.float32))
    assert isinstance(as_np, np.ndarray) and as_np.dtype == np.float32
    np.testing.assert_allclose(as_np, cv.numpy(), atol=1e-6)
    np.testing.assert_array_equal(opengl_to_opencv(c2w[:, :3].numpy()), cv[:, :3].numpy())  # 3 x 4
    np.testing.assert_array_equal(opengl_to_opencv(c2w[:, :3, :3].numpy()), cv[:, :3, :3].numpy())
    gl = opencv_to_opengl(np.eye(4))
    assert not np.signbit(gl[gl == 0]).any()  # no -0.0 written to files


def test_maya_camera_looks_at_its_target_with_y_up():
    from rainyscape.dataparsers.maya_math import look_at_angles, maya_c2w_opencv

    positions = np.array([[10.0, 4.0, 12.0], [-8.0, 6.0, 9.0], [3.0, 2.0, -11.0]])
    target = np.array([0.0, 1.5, -2.0])
    c2w = maya_c2w_opencv(positions, look_at_angles(positions, np.broadcast_to(target, positions.shape)))
    cams = _cameras(c2w.double())
    pts = torch.from_numpy(np.stack([target, target + [0.0, 1.0, 0.0]]))
    pix, z = cams.project(pts.float())
    assert torch.allclose(pix[:, 0], torch.tensor([19.0, 16.5]).expand(3, 2), atol=1e-3)
    assert torch.all(pix[:, 1, 1] < pix[:, 0, 1])  # world up (+Y) is up in the image
    assert torch.all(z > 0)


@pytest.mark.parametrize("fmt", ["maya-csv", "llff", "transforms-json"])
def test_dataparsers_agree_on_every_pixel_ray(fmt, tiny_scene, tiny_scene_dir, tmp_path):
    """Depth-lifted points of the simulator project to the same pixels whichever parser read
    the scene, and each parser's pixel ray reaches its lifted point."""
    from rainyscape import registry
    from rainyscape.dataparsers import writers

    if fmt == "maya-csv":
        path = tiny_scene_dir
    else:
        write = writers.write_llff if fmt == "llff" else writers.write_transforms_json
        path = write(tiny_scene, tmp_path / fmt)
    parser = registry.load("dataparser", fmt)
    scene = parser(parser.Config()).parse(path)
    ref = tiny_scene
    # Lift view 0's pixels with the simulator's depth (reference parse).
    depth = ref.depths[0]
    rows, cols = torch.nonzero(torch.isfinite(depth), as_tuple=True)
    keep = torch.arange(0, len(rows), 7)
    rows, cols = rows[keep], cols[keep]
    ref_rays = pixel_rays(ref.cameras[[0]], cols[None], rows[None])
    t = depth[rows, cols] / ref_rays.z_scale[0]
    ref_pts = ref_rays.origins[0] + t[:, None] * ref_rays.directions[0]
    original = ref.to_original(ref_pts)
    hom = torch.cat([original, torch.ones_like(original[:, :1])], -1)
    pts = scene.scale * (hom @ scene.transform.T)[:, :3]
    # The same pixels in every view, and view 0's rays reach the points.
    ref_pix, ref_z = ref.cameras.project(ref_pts)
    pix, z = scene.cameras.project(pts)
    in_front = ref_z > 0.1 * ref_z.amax()  # projection is ill-conditioned near a camera plane
    assert in_front.float().mean() > 0.5
    assert torch.allclose(pix[in_front], ref_pix[in_front], atol=2e-2)
    assert torch.allclose(pix[0], torch.stack([cols, rows], -1) + 0.5, atol=2e-2)
    rays = pixel_rays(scene.cameras[[0]], cols[None], rows[None])
    dist = torch.linalg.cross(pts - rays.origins[0], rays.directions[0]).norm(dim=-1)
    assert dist.max().item() < 1e-3 * scene.scale / ref.scale * max(1.0, float(z[0].max()))


def test_simulator_depth_is_consistent_across_views(tiny_scene):
    """A pixel's ray at the rendered depth hits the surface other views see there."""
    scene = tiny_scene
    depth = scene.depths[0]
    rows, cols = torch.nonzero(torch.isfinite(depth), as_tuple=True)
    rays = pixel_rays(scene.cameras[[0]], cols[None], rows[None])
    pts = rays.origins[0] + (depth[rows, cols] / rays.z_scale[0])[:, None] * rays.directions[0]
    pix, z = scene.cameras.project(pts)
    agree = []
    for v in range(1, scene.num_images):
        u = pix[v].floor().long()
        inside = (u[:, 0] >= 0) & (u[:, 0] < scene.width) & (u[:, 1] >= 0) & (u[:, 1] < scene.height) & (z[v] > 0)
        seen = scene.depths[v][u[inside, 1], u[inside, 0]]
        visible = (seen - z[v][inside]).abs() < 0.02 * z[v][inside]  # not occluded in view v
        agree.append(visible.float().mean().item())
    assert np.median(agree) > 0.8


def test_ndc_maps_rays_to_straight_rays():
    torch.manual_seed(0)
    origins = torch.randn(64, 3) * 0.2
    dirs = torch.nn.functional.normalize(torch.randn(64, 3) * 0.3 + torch.tensor([0.0, 0.0, 1.0]), dim=-1)
    near, sx, sy = 1.0, 1.8, 1.6
    o_ndc, d_ndc, t_near = ndc_rays(origins, dirs, sx, sy, near)
    for t in (0.5, 2.0, 10.0, 100.0):  # distances past the near plane
        p = origins + (t_near + t)[:, None] * dirs
        ndc = ndc_points(p, sx, sy, near)
        assert torch.allclose(ndc[:, :2], torch.stack([sx * p[:, 0], sy * p[:, 1]], -1) / p[:, 2:], atol=1e-5)
        assert torch.allclose(ndc[:, 2], 1 - 2 * near / p[:, 2], atol=1e-6)
        s = 1 - near / p[:, 2]  # NDC parameter of that point
        assert torch.allclose(o_ndc + s[:, None] * d_ndc, ndc, atol=1e-4)
        assert torch.allclose(ndc_to_distance(s, near, dirs[:, 2]), torch.full_like(s, t), rtol=1e-3)
    assert torch.allclose(o_ndc[:, 2], torch.full((64,), -1.0), atol=1e-6)  # the near plane


def test_average_pose_is_a_rotation_looking_along_the_mean_axis():
    angles = torch.tensor([-0.2, 0.0, 0.3])
    c2w = torch.eye(4).repeat(3, 1, 1)
    for i, a in enumerate(angles):  # rotations about y
        c, s = math.cos(a), math.sin(a)
        c2w[i, :3, :3] = torch.tensor([[c, 0, s], [0, 1, 0], [-s, 0, c]])
        c2w[i, :3, 3] = torch.tensor([float(i), 0.0, 0.0])
    avg = average_pose(c2w)
    rot = avg[:3, :3]
    assert torch.allclose(rot.T @ rot, torch.eye(3), atol=1e-6)
    assert torch.det(rot).item() == pytest.approx(1.0, abs=1e-6)
    assert torch.allclose(avg[:3, 3], torch.tensor([1.0, 0.0, 0.0]))
    assert rot[:, 2] @ torch.nn.functional.normalize(c2w[:, :3, 2].mean(0), dim=0) == pytest.approx(1.0, abs=1e-6)


def _look(azimuth_deg: float, pitch_deg: float, roll_deg: float = 0.0) -> torch.Tensor:
    """OpenCV camera-to-world of a camera turned by ``azimuth`` about the world's +y (up),
    pitched down by ``pitch`` and rolled by ``roll`` about its optical axis."""
    a, p, r = (math.radians(v) for v in (azimuth_deg, pitch_deg, roll_deg))
    yaw = torch.tensor([[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]])
    tilt = torch.tensor([[1, 0, 0], [0, math.cos(p), -math.sin(p)], [0, math.sin(p), math.cos(p)]])
    spin = torch.tensor([[math.cos(r), -math.sin(r), 0], [math.sin(r), math.cos(r), 0], [0, 0, 1]])
    flip = torch.diag(torch.tensor([1.0, -1.0, 1.0]))  # OpenCV: y down, so level cameras see +y as image-down
    c2w = torch.eye(4)
    c2w[:3, :3] = yaw @ tilt @ flip @ spin
    return c2w


def test_the_worlds_down_in_each_view():
    """An array looking down at a scene: its mean image-up leans towards the scene, the level
    cameras' up is the world's; the world's down runs straight down each level view and along
    the x axis of a view rolled by 90 degrees. Cameras that all face one way keep the mean up."""
    array = torch.stack([_look(az, 30.0) for az in (-40, -20, 0, 20, 40)])
    up = torch.tensor([0.0, 1.0, 0.0])
    assert float(world_up(array) @ up) < 0.95  # tilted by the pitch
    assert torch.allclose(level_up(array), up, atol=1e-4)
    assert np.allclose(world_up(array.numpy()), world_up(array).numpy())  # one rule for numpy and torch
    assert torch.allclose(down_directions(_cameras(array)), torch.full((5,), math.pi / 2), atol=1e-4)
    rolled = torch.cat([array, _look(10, 30.0, roll_deg=90.0)[None]])
    down = torch.rad2deg(down_directions(_cameras(rolled)))
    assert (down[:5] - 90).abs().max() < 5 and min(float(down[5]), 180 - float(down[5])) < 5
    facing = torch.stack([_look(0, 30.0)] * 3)
    facing[:, :3, 3] = torch.randn(3, 3)
    assert torch.allclose(level_up(facing), world_up(facing), atol=1e-4)
    with pytest.raises(ConfigError):
        world_up(torch.stack([torch.eye(4), torch.diag(torch.tensor([1.0, -1.0, -1.0, 1.0]))]))


def test_the_simulators_rain_falls_along_each_views_down(tiny_scene):
    """The simulator's rain falls along its world's -y (slanted by the wind); the level cameras'
    down is nearer each view's streaks than the mean up's in the tiny scene, an array looking
    down at a street."""
    from rainyscape.imaging.angles import angle_difference_deg, estimate_rain_angles, streak_angle

    theta, valid = estimate_rain_angles(tiny_scene.rain_layers.permute(0, 3, 1, 2).float().abs())
    ok = valid[:, 0]
    found = torch.rad2deg(streak_angle(theta[:, 0]))[ok].tolist()
    assert len(found) >= len(theta) // 2

    def error(down: torch.Tensor) -> float:
        return float(np.median([angle_difference_deg(a, b) for a, b in zip(found, torch.rad2deg(down)[ok].tolist())]))

    cams = tiny_scene.cameras
    level, mean = error(down_directions(cams)), error(down_directions(cams, world_up(cams.c2w)))
    # the demo preset's wind slants the streaks by 12 degrees; the mean up adds the array's pitch
    assert level < 15 and mean > level + 3
