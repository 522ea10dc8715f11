"""Maya camera conventions as pure functions (shared by the maya-csv parser and the simulator).

Maya: Y-up world, a camera looks down its local -Z with +Y up (OpenGL-like), Euler angles
in degrees with the default rotation order XYZ, i.e. the rotation applied to the camera is
R = Rz(rz) @ Ry(ry) @ Rx(rx) (column vectors: X first). Intrinsics come from film-back
apertures: f_px = focal_mm / aperture_mm * size_px, principal point at the image centre.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from rainyscape.cameras import Cameras, opengl_to_opencv


def rot_x(deg: np.ndarray) -> np.ndarray:
    a = np.radians(deg)
    c, s, o, z = np.cos(a), np.sin(a), np.ones_like(a), np.zeros_like(a)
    return np.stack([np.stack([o, z, z], -1), np.stack([z, c, -s], -1), np.stack([z, s, c], -1)], -2)


def rot_y(deg: np.ndarray) -> np.ndarray:
    a = np.radians(deg)
    c, s, o, z = np.cos(a), np.sin(a), np.ones_like(a), np.zeros_like(a)
    return np.stack([np.stack([c, z, s], -1), np.stack([z, o, z], -1), np.stack([-s, z, c], -1)], -2)


def rot_z(deg: np.ndarray) -> np.ndarray:
    a = np.radians(deg)
    c, s, o, z = np.cos(a), np.sin(a), np.ones_like(a), np.zeros_like(a)
    return np.stack([np.stack([c, -s, z], -1), np.stack([s, c, z], -1), np.stack([z, z, o], -1)], -2)


def euler_xyz_to_matrix(rotation_deg: np.ndarray) -> np.ndarray:
    """(N, 3) Maya XYZ Euler angles in degrees -> (N, 3, 3) rotations Rz @ Ry @ Rx."""
    r = np.asarray(rotation_deg, np.float64)
    return rot_z(r[:, 2]) @ rot_y(r[:, 1]) @ rot_x(r[:, 0])


def look_at_angles(position: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Maya (rx, ry, 0) in degrees that point a camera at ``position`` towards ``target``.

    With rz = 0 the camera's -Z axis is (-sin ry cos rx, sin rx, -cos ry cos rx).
    """
    f = np.asarray(target, np.float64) - np.asarray(position, np.float64)
    f /= np.linalg.norm(f, axis=-1, keepdims=True)
    rx = np.degrees(np.arcsin(np.clip(f[..., 1], -1, 1)))
    ry = np.degrees(np.arctan2(-f[..., 0], -f[..., 2]))
    return np.stack([rx, ry, np.zeros_like(rx)], -1)


def maya_c2w_opencv(position: np.ndarray, rotation_deg: np.ndarray) -> Tensor:
    """Camera-to-world (N, 4, 4) in the OpenCV camera convention (Maya's world axes kept)."""
    n = len(position)
    c2w = np.tile(np.eye(4), (n, 1, 1))
    c2w[:, :3, :3] = euler_xyz_to_matrix(rotation_deg)
    c2w[:, :3, 3] = position
    return opengl_to_opencv(torch.from_numpy(c2w)).float()


def maya_cameras(position: np.ndarray, rotation_deg: np.ndarray, focal_mm: np.ndarray,
                 h_aperture_mm: np.ndarray, v_aperture_mm: np.ndarray, width: int, height: int) -> Cameras:
    """Cameras (OpenCV convention) from Maya CSV quantities."""
    fx = torch.as_tensor(np.asarray(focal_mm) / np.asarray(h_aperture_mm) * width, dtype=torch.float32)
    fy = torch.as_tensor(np.asarray(focal_mm) / np.asarray(v_aperture_mm) * height, dtype=torch.float32)
    n = len(position)
    cx = torch.full((n,), width / 2.0)
    cy = torch.full((n,), height / 2.0)
    return Cameras(maya_c2w_opencv(position, rotation_deg), fx, fy, cx, cy, width, height)


# The paper's cameras.csv columns, in order (appendix "Camera Parameters").
MAYA_CSV_COLUMNS = ["Camera Name", "Position X", "Position Y", "Position Z", "Rotation X",
                    "Rotation Y", "Rotation Z", "Focal Length", "Horizontal Aperture", "Vertical Aperture"]
