"""Similarity alignment of two camera trajectories (Umeyama, 1991) and the pose errors after it.

SfM recovers cameras up to a similarity (scale, rotation, translation), so recovered poses are
compared with ground truth only after the best similarity maps one set of centres onto the other.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


def umeyama(src: np.ndarray, dst: np.ndarray, with_scale: bool = True
            ) -> tuple[float, np.ndarray, np.ndarray]:
    """Least-squares similarity ``dst ~ s * R @ src + t`` for corresponding points (N, 3).

    Returns (s, R, t) with R a proper rotation (det +1). Needs N >= 3 points that are not
    all on one line.
    """
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[0] < 3:
        raise ValueError(f"umeyama needs two (N >= 3, D) arrays of the same shape, got "
                         f"{src.shape} and {dst.shape}")
    mu_src, mu_dst = src.mean(0), dst.mean(0)
    a, b = src - mu_src, dst - mu_dst
    var_src = (a ** 2).sum() / len(src)
    cov = b.T @ a / len(src)
    u, d, vt = np.linalg.svd(cov)
    sign = np.ones(len(d))
    if np.linalg.det(u) * np.linalg.det(vt) < 0:  # reflection: flip the weakest axis
        sign[-1] = -1.0
    rot = u @ np.diag(sign) @ vt
    scale = float((d * sign).sum() / var_src) if with_scale else 1.0
    trans = mu_dst - scale * rot @ mu_src
    return scale, rot, trans


def rotation_angle_deg(rot_a: np.ndarray, rot_b: np.ndarray) -> np.ndarray:
    """Angle of the relative rotation between batches of rotations (N, 3, 3), in degrees."""
    rel = np.einsum("nji,njk->nik", rot_a, rot_b)  # R_a^T R_b
    cos = (np.trace(rel, axis1=1, axis2=2) - 1.0) / 2.0
    skew = rel - np.transpose(rel, (0, 2, 1))
    sin = np.linalg.norm(np.stack([skew[:, 2, 1], skew[:, 0, 2], skew[:, 1, 0]], -1), axis=-1) / 2.0
    return np.degrees(np.arctan2(sin, cos))  # accurate for small angles, unlike arccos


@dataclass
class PoseErrors:
    """Errors of estimated cameras after similarity alignment onto the reference."""

    center_rmse: float  # reference units
    extent: float  # largest distance between two reference centres
    rotation_deg: np.ndarray  # (N,) per camera
    scale: float  # the aligning similarity: ref = scale * R @ est + t
    rotation: np.ndarray
    translation: np.ndarray

    @property
    def center_rmse_fraction(self) -> float:
        return self.center_rmse / self.extent if self.extent > 0 else float("inf")


def trajectory_extent(centers: np.ndarray) -> float:
    """Largest pairwise distance between camera centres (N, 3)."""
    diff = centers[:, None, :] - centers[None, :, :]
    return float(np.sqrt((diff ** 2).sum(-1)).max())


def pose_points(c2w: np.ndarray, arm: float) -> np.ndarray:
    """Each camera's centre and the tips of its three axes ``arm`` away: (N * 4, 3)."""
    centers = c2w[:, None, :3, 3]
    tips = centers + arm * np.transpose(c2w[:, :3, :3], (0, 2, 1))  # rows: x, y, z axes
    return np.concatenate([centers, tips], 1).reshape(-1, 3)


def aligned_pose_errors(est_c2w: np.ndarray, ref_c2w: np.ndarray, axis_arm: float = 0.25) -> PoseErrors:
    """Align estimated camera-to-world poses (N, 4, 4) onto the reference; measure the errors.

    The similarity is Umeyama's on the camera centres and, with ``axis_arm`` > 0, on the tips
    of each camera's axes at that fraction of the trajectory extent (in each trajectory's own
    units, so an exactly similar trajectory still aligns exactly). The centres of a sweep lie
    near a plane or a line, which leaves the rotation about it loose; the axes pin it. Both
    poses must use the same camera-axis convention; rotation errors compare R @ R_est with R_ref.
    """
    est_c2w = np.asarray(est_c2w, dtype=np.float64)
    ref_c2w = np.asarray(ref_c2w, dtype=np.float64)
    extent = trajectory_extent(ref_c2w[:, :3, 3])
    if axis_arm > 0:
        src = pose_points(est_c2w, axis_arm * trajectory_extent(est_c2w[:, :3, 3]))
        dst = pose_points(ref_c2w, axis_arm * extent)
    else:
        src, dst = est_c2w[:, :3, 3], ref_c2w[:, :3, 3]
    scale, rot, trans = umeyama(src, dst)
    moved = scale * est_c2w[:, :3, 3] @ rot.T + trans
    rmse = float(np.sqrt(((moved - ref_c2w[:, :3, 3]) ** 2).sum(-1).mean()))
    rot_err = rotation_angle_deg(rot[None] @ est_c2w[:, :3, :3], ref_c2w[:, :3, :3])
    return PoseErrors(rmse, extent, rot_err, scale, rot, trans)
