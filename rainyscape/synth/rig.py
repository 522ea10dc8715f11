"""Camera placement: the paper's rows x columns array on a sphere cap, or a video-like path.

Cameras are returned as Maya quantities (positions, XYZ Euler degrees, film back), the
form ``cameras.csv`` stores; :func:`rainyscape.dataparsers.maya_math.maya_cameras` turns
them into :class:`~rainyscape.cameras.Cameras`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rainyscape.dataparsers.maya_math import look_at_angles, maya_cameras
from rainyscape.synth.scenes import Rig

FOCAL_MM = 35.0
H_APERTURE_MM = 36.0


@dataclass
class MayaRig:
    positions: np.ndarray  # (N, 3)
    rotations: np.ndarray  # (N, 3) degrees, XYZ order
    focal_mm: float
    h_aperture_mm: float
    v_aperture_mm: float
    width: int
    height: int

    def cameras(self):
        n = len(self.positions)
        return maya_cameras(self.positions, self.rotations, np.full(n, self.focal_mm),
                            np.full(n, self.h_aperture_mm), np.full(n, self.v_aperture_mm),
                            self.width, self.height)


def _on_sphere(rig: Rig, elevation_deg: np.ndarray, azimuth_deg: np.ndarray, radius: np.ndarray) -> np.ndarray:
    el, az = np.radians(elevation_deg), np.radians(azimuth_deg)
    offset = np.stack([np.sin(az) * np.cos(el), np.sin(el), np.cos(az) * np.cos(el)], -1) * radius[:, None]
    return np.asarray(rig.look_at) + offset


def sphere_cap(rig: Rig, rows: int, cols: int) -> tuple[np.ndarray, np.ndarray]:
    """Positions (rows*cols, 3) and look-at point, row-major: the top row first, each row left
    to right as seen from the cameras (001.png is the top-left camera)."""
    els = np.linspace(rig.elevation_deg[1], rig.elevation_deg[0], rows) if rows > 1 else np.array([np.mean(rig.elevation_deg)])
    azs = np.linspace(rig.azimuth_deg[0], rig.azimuth_deg[1], cols) if cols > 1 else np.array([np.mean(rig.azimuth_deg)])
    el, az = np.meshgrid(els, azs, indexing="ij")
    return _on_sphere(rig, el.ravel(), az.ravel(), np.full(el.size, rig.radius))


def video_path(rig: Rig, frames: int) -> np.ndarray:
    """A smooth hand-held-like sweep: azimuth across the cap, elevation and distance wavering."""
    s = np.linspace(0.0, 1.0, frames)
    az = rig.azimuth_deg[0] + (rig.azimuth_deg[1] - rig.azimuth_deg[0]) * s
    mid = np.mean(rig.elevation_deg)
    half = 0.5 * (rig.elevation_deg[1] - rig.elevation_deg[0])
    el = mid + 0.6 * half * np.sin(2 * np.pi * 1.5 * s)
    radius = rig.radius * (1.0 + 0.06 * np.sin(2 * np.pi * s + 0.7))
    return _on_sphere(rig, el, az, radius)


def make_rig(rig: Rig, rows: int, cols: int, width: int, height: int, trajectory: str = "sphere") -> MayaRig:
    if trajectory == "sphere":
        positions = sphere_cap(rig, rows, cols)
    elif trajectory == "video":
        positions = video_path(rig, rows * cols)
    else:
        raise ValueError(f"unknown trajectory '{trajectory}' (sphere, video)")
    rotations = look_at_angles(positions, np.broadcast_to(np.asarray(rig.look_at, float), positions.shape))
    v_aperture = H_APERTURE_MM * height / width  # square pixels
    return MayaRig(positions, rotations, FOCAL_MM, H_APERTURE_MM, v_aperture, width, height)
