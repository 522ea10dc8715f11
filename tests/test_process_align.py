"""Umeyama similarity alignment and pose errors (rainyscape.process.align)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from rainyscape.process.align import aligned_pose_errors, rotation_angle_deg, trajectory_extent, umeyama


def random_similarity(seed: int):
    rng = np.random.default_rng(seed)
    return float(rng.uniform(0.2, 5.0)), Rotation.random(random_state=seed).as_matrix(), rng.normal(size=3)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_umeyama_recovers_a_known_similarity(seed):
    scale, rot, trans = random_similarity(seed)
    src = np.random.default_rng(seed + 10).normal(size=(20, 3))
    dst = scale * src @ rot.T + trans
    s, r, t = umeyama(src, dst)
    assert s == pytest.approx(scale, rel=1e-9)
    np.testing.assert_allclose(r, rot, atol=1e-9)
    np.testing.assert_allclose(t, trans, atol=1e-9)


def test_umeyama_never_returns_a_reflection():
    src = np.random.default_rng(3).normal(size=(10, 3))
    dst = src * np.array([1.0, 1.0, -1.0])  # a mirror image: best proper rotation only
    _, r, _ = umeyama(src, dst)
    assert np.linalg.det(r) == pytest.approx(1.0)


def test_umeyama_without_scale_keeps_unit_scale():
    src = np.random.default_rng(4).normal(size=(10, 3))
    s, _, _ = umeyama(src, 3 * src, with_scale=False)
    assert s == 1.0


def test_umeyama_rejects_too_few_points():
    with pytest.raises(ValueError):
        umeyama(np.zeros((2, 3)), np.zeros((2, 3)))


def test_rotation_angle():
    a = Rotation.from_euler("z", [[0], [10], [90]], degrees=True).as_matrix()
    b = np.repeat(np.eye(3)[None], 3, 0)
    np.testing.assert_allclose(rotation_angle_deg(a, b), [0, 10, 90], atol=1e-9)
    tiny = Rotation.from_euler("y", 1e-4, degrees=True).as_matrix()  # where arccos loses it
    np.testing.assert_allclose(rotation_angle_deg(a[1:2], a[1:2] @ tiny), [1e-4], rtol=1e-6)


def test_aligned_pose_errors_are_zero_for_a_similar_trajectory_and_see_noise():
    rng = np.random.default_rng(5)
    n = 12
    ref = np.tile(np.eye(4), (n, 1, 1))
    ref[:, :3, :3] = Rotation.random(n, random_state=5).as_matrix()
    ref[:, :3, 3] = rng.normal(size=(n, 3)) * 2
    scale, rot, trans = random_similarity(6)
    est = ref.copy()  # est = similarity^-1 applied to the reference
    est[:, :3, 3] = (ref[:, :3, 3] - trans) @ rot / scale
    est[:, :3, :3] = rot.T @ ref[:, :3, :3]
    clean = aligned_pose_errors(est, ref)
    assert clean.center_rmse < 1e-9 and clean.rotation_deg.max() < 1e-6
    assert clean.scale == pytest.approx(scale)
    assert clean.extent == pytest.approx(trajectory_extent(ref[:, :3, 3]))
    turned = est.copy()
    turned[0, :3, :3] = turned[0, :3, :3] @ Rotation.from_euler("x", 3, degrees=True).as_matrix()
    errors = aligned_pose_errors(turned, ref, axis_arm=0)  # centres unchanged: so is the alignment
    assert errors.rotation_deg[0] == pytest.approx(3.0, abs=1e-6)
    assert errors.rotation_deg[1:].max() < 1e-6
    errors = aligned_pose_errors(turned, ref)  # the axes pull the alignment a little towards it
    assert 2.5 < errors.rotation_deg[0] <= 3.0 and errors.rotation_deg[1:].max() < 0.5
    moved = est.copy()
    moved[1, :3, 3] += 0.5
    assert aligned_pose_errors(moved, ref).center_rmse > 0.01


def test_camera_axes_pin_the_rotation_about_a_straight_trajectory():
    n = 8
    ref = np.tile(np.eye(4), (n, 1, 1))
    ref[:, :3, :3] = Rotation.random(n, random_state=7).as_matrix()
    ref[:, 0, 3] = np.linspace(0, 10, n)  # centres on a line: a turn about it is invisible
    turn = Rotation.from_euler("x", 20, degrees=True).as_matrix()
    est = ref.copy()
    est[:, :3, :3] = turn @ ref[:, :3, :3]
    est[:, :3, 3] += np.random.default_rng(8).normal(scale=1e-3, size=(n, 3))
    assert aligned_pose_errors(est, ref).rotation_deg.max() < 0.1
