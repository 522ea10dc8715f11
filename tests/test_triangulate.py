"""Sparse points from known poses (rainyscape.process.triangulate): the pure parts (pairs from
frustum overlap, ray angles, the point filter), the points on a small real capture (LLFF fern)
and on a simulated scene checked against its ground-truth depth (evaluation only)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch

from rainyscape.cameras import Cameras
from rainyscape.process.triangulate import (TriangulationOptions, epipolar_matches, frustum_overlap,
                                            fundamental_matrix, keep_points, max_ray_angles,
                                            overlap_pairs, sampson_errors, triangulate_views)


def look_at(centers: np.ndarray, target=(0.0, 0.0, 0.0)) -> torch.Tensor:
    """OpenCV camera-to-world matrices for cameras at ``centers`` looking at ``target``."""
    out = []
    for c in centers:
        z = np.asarray(target, float) - c
        z /= np.linalg.norm(z)
        x = np.cross(z, [0.0, 1.0, 0.0])
        if np.linalg.norm(x) < 1e-6:
            x = np.cross(z, [1.0, 0.0, 0.0])
        x /= np.linalg.norm(x)
        y = np.cross(z, x)
        m = np.eye(4)
        m[:3, :3] = np.stack([x, y, z], 1)
        m[:3, 3] = c
        out.append(m)
    return torch.tensor(np.stack(out), dtype=torch.float32)


def ring_cameras(n: int, radius: float = 3.0, size: int = 64, focal: float = 60.0) -> Cameras:
    angles = np.linspace(0, 2 * np.pi, n, endpoint=False)
    centers = np.stack([radius * np.cos(angles), np.zeros(n), radius * np.sin(angles)], 1)
    f = torch.full((n,), focal)
    return Cameras(look_at(centers), f, f, torch.full((n,), size / 2), torch.full((n,), size / 2), size, size)


def test_pairs_from_frustum_overlap_are_the_neighbours_on_a_ring():
    cams = ring_cameras(12)
    share = frustum_overlap(cams, near=2.0, far=4.0)
    assert np.allclose(share, share.T) and np.all(np.diag(share) == 0)
    # neighbours on the ring see more of each other than views across it
    assert share[0, 1] > share[0, 3] > share[0, 6]
    pairs = overlap_pairs(cams, 2.0, 4.0, neighbours=2)
    assert all(i < j for i, j in pairs)
    assert {(0, 1), (0, 11), (5, 6)} <= set(pairs)
    assert (0, 6) not in pairs  # the opposite view is never among two best neighbours
    # a view whose frustum no other view sees is paired with nothing
    away = cams.c2w.clone()
    away[3, :3, :3] = away[3, :3, :3] @ torch.diag(torch.tensor([-1.0, 1.0, -1.0]))  # turned to look outwards
    lonely = Cameras(away, cams.fx, cams.fy, cams.cx, cams.cy, cams.width, cams.height)
    assert not [p for p in overlap_pairs(lonely, 2.0, 4.0, neighbours=3) if 3 in p]


def test_known_poses_give_the_epipolar_geometry_and_the_matches():
    cams = ring_cameras(12)[[0, 1]]
    rng = np.random.default_rng(0)
    world = torch.tensor(rng.uniform(-0.8, 0.8, (40, 3)), dtype=torch.float32)
    uv, z = cams.project(world)
    assert bool((z > 0).all())
    x1, x2 = uv[0].double().numpy(), uv[1].double().numpy()
    f = fundamental_matrix(cams, 0, 1)
    h1, h2 = np.c_[x1, np.ones(40)], np.c_[x2, np.ones(40)]
    assert np.abs(np.einsum("ni,ij,nj->n", h2, f, h1)).max() < 1e-6 * np.abs(f).max() * 64 ** 2
    assert np.diag(sampson_errors(f, x1, x2)).max() < 1e-8
    # the same point's descriptor in both views (slightly perturbed); view 2 also holds an
    # exact copy of each descriptor off the epipolar line: the geometry must reject it
    desc = rng.normal(size=(40, 128))
    desc /= np.linalg.norm(desc, axis=1, keepdims=True)
    noisy = desc + 0.05 * rng.normal(size=desc.shape)
    noisy /= np.linalg.norm(noisy, axis=1, keepdims=True)
    decoys = x2 + np.array([0.0, 15.0])  # the baseline is horizontal: 15 px up leaves the line
    found = epipolar_matches(x1, desc, np.r_[x2, decoys], np.r_[noisy, desc], f, TriangulationOptions())
    assert sorted(map(tuple, found.tolist())) == [(i, i) for i in range(40)]
    # the decoys are the nearest descriptors: only the geometry keeps them out
    assert (np.argmax(desc @ np.r_[noisy, desc].T, 1) >= 40).all()


def test_max_ray_angle_of_a_track():
    centers = np.array([[-1.0, 0, 0], [1.0, 0, 0], [0.0, 0, 0]])
    point = np.array([[0.0, 0.0, 1.0]])
    assert max_ray_angles(centers, point, [np.array([0, 1])])[0] == pytest.approx(90.0)
    assert max_ray_angles(centers, point, [np.array([0, 2])])[0] == pytest.approx(45.0)
    assert max_ray_angles(centers, point, [np.array([0, 1, 2])])[0] == pytest.approx(90.0)


def test_point_filter_keeps_precise_well_seen_points():
    opts = TriangulationOptions(max_reprojection_error=2.0, min_track_length=3, min_angle=2.0)
    errors = np.array([0.5, 3.0, 0.5, 0.5, 0.5])
    tracks = np.array([3, 3, 2, 3, 5])
    angles = np.array([10.0, 10.0, 10.0, 1.0, 2.0])
    assert keep_points(errors, tracks, angles, opts, views=10).tolist() == [True, False, False, False, True]
    # in a set of fewer than five views two-view tracks are most of what there is: kept
    assert keep_points(errors, tracks, angles, opts, views=3).tolist() == [True, False, True, False, True]


def test_bad_options_are_refused():
    from rainyscape.errors import ConfigError

    with pytest.raises(ConfigError, match="max_features"):
        TriangulationOptions(max_features=8).validate()
    with pytest.raises(ConfigError):
        TriangulationOptions(min_track_length=1).validate()


# ------------------------------------------------------------------- real and simulated views


def shared_data() -> Path | None:
    here = Path(__file__).resolve().parents[1]
    for root in (here.parent / "shared" / "data", Path("/work/shared/data")):
        if root.is_dir():
            return root
    return None


@pytest.fixture(scope="module")
def fern():
    """LLFF fern at 252 x 189 (its images_8 shrunk by 2), 8 views of the sweep."""
    root = shared_data()
    if root is None or not (root / "real" / "fern" / "poses_bounds.npy").is_file():
        pytest.skip("the LLFF fern capture is not in ../shared/data/real/fern")
    from rainyscape.dataparsers.llff import LLFFConfig, LLFFParser

    scene = LLFFParser(LLFFConfig(downscale=16, holdout_every=0)).parse(root / "real" / "fern")
    views = list(range(0, 20, 20 // 8))[:8]
    bounds = np.load(root / "real" / "fern" / "poses_bounds.npy")[views, 15:17] * scene.scale
    return scene, views, bounds


def test_fern_points_lie_in_front_of_every_camera_within_the_capture_bounds(fern):
    scene, views, bounds = fern
    cams = scene.cameras[views]
    result = triangulate_views(scene.images[views].numpy(), cams, scene.near, scene.far,
                               TriangulationOptions(num_threads=1))
    report = result.report
    assert report.views == 8 and report.pairs == 28  # a small set: every pair
    assert report.points >= 200, report.summary()
    assert result.points.shape == (report.points, 3) and result.points.dtype == np.float32
    assert result.colors.shape == (report.points, 3) and result.colors.dtype == np.uint8
    assert result.colors.std() > 10  # coloured from the photos, not a constant
    assert report.mean_reprojection_error < 1.0 and report.mean_track_length >= 3.0
    uv, z = cams.project(torch.from_numpy(result.points))
    assert bool((z > 0).all())  # in front of every camera of the sweep
    # LLFF's bounds are the 0.1 / 99.9 percentiles of each view's COLMAP depths
    near = torch.tensor(bounds[:, :1], dtype=torch.float32)
    far = torch.tensor(bounds[:, 1:], dtype=torch.float32)
    inside = (z >= 0.9 * near) & (z <= 1.1 * far)
    assert inside.float().mean() > 0.98
    # each point reprojects onto the pixel it was measured at, within the filter's 2 px
    assert report.mean_reprojection_error <= TriangulationOptions().max_reprojection_error


def depth_errors(points: torch.Tensor, cameras: Cameras, depths: torch.Tensor) -> torch.Tensor:
    """Relative z-depth error of each point in each view it projects into, against the true
    depth of the closest of the 3 x 3 pixels about where it lands: SIFT features sit on corners,
    where one pixel's depth can jump to the background."""
    uv, z = cameras.project(points)
    out = []
    for k in range(len(cameras)):
        u, v = uv[k, :, 0], uv[k, :, 1]
        seen = (z[k] > 0) & (u >= 0) & (u < cameras.width) & (v >= 0) & (v < cameras.height)
        padded = torch.nn.functional.pad(depths[k][None, None], (1, 1, 1, 1), value=math.inf)[0, 0]
        iu, iv = u[seen].long() + 1, v[seen].long() + 1
        around = torch.stack([padded[iv + dy, iu + dx] for dy in (-1, 0, 1) for dx in (-1, 0, 1)], 1)
        rel = (z[k][seen][:, None] - around) / around
        best = rel.abs().nan_to_num(math.inf).argmin(1)
        rel = rel[torch.arange(len(rel)), best]
        out.append(rel[torch.isfinite(rel)])
    return torch.cat(out)


def test_simulated_points_agree_with_the_ground_truth_depth(tmp_path_factory):
    """Points from the rainy views of a simulated street agree with the simulator's depth
    (used here to evaluate them, never to make them)."""
    from rainyscape.dataparsers.maya_csv import MayaCsvConfig, MayaCsvParser
    from rainyscape.synth import generate

    folder = generate(tmp_path_factory.mktemp("tri") / "scene", "demo", rows=2, cols=4,
                      width=160, height=160, seed=0)
    scene = MayaCsvParser(MayaCsvConfig()).parse(folder)
    assert scene.points is None  # ground-truth depth gives no points unless asked
    train = scene.train_indices
    result = triangulate_views(scene.images[train].numpy(), scene.cameras[train], scene.near, scene.far,
                               TriangulationOptions(num_threads=1))
    assert result.report.points >= 60, result.report.summary()
    rel = depth_errors(torch.from_numpy(result.points), scene.cameras[train], scene.depths[train])
    assert len(rel) >= 5 * result.report.points  # each point lands in most views
    assert float(rel.abs().median()) < 0.02, float(rel.abs().median())
    assert float((rel.abs() < 0.05).float().mean()) > 0.8
