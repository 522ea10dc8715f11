"""Normalised device coordinates for forward-facing captures (NeRF's LLFF mode).

NDC maps the frustum z in [near, inf) of a reference camera to [-1, 1), so a fixed number
of samples covers an unbounded forward-facing scene. Everything here is in the OpenCV
convention: the reference camera looks down +z, x right, y down.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor


def average_pose(c2w: Tensor) -> Tensor:
    """A camera-to-world 4x4 at the mean centre, looking along the mean optical axis."""
    forward = F.normalize(c2w[:, :3, 2].mean(0), dim=0)
    down = c2w[:, :3, 1].mean(0)
    right = F.normalize(torch.linalg.cross(down, forward), dim=0)
    down = torch.linalg.cross(forward, right)
    out = torch.eye(4, dtype=c2w.dtype, device=c2w.device)
    out[:3, 0], out[:3, 1], out[:3, 2] = right, down, forward
    out[:3, 3] = c2w[:, :3, 3].mean(0)
    return out


# NeRF's LLFF mode puts the NDC near plane at 3/4 of the nearest content's depth
NEAR_SHARE = 0.75


def ndc_near(frame: Tensor, points: Tensor | None, fallback: float) -> float:
    """The NDC near plane of a capture seen from the reference camera ``frame`` (4x4): 3/4 of
    the depth of its nearest sparse points (their 1 % quantile: a stray triangulation must not
    pull it in), else of ``fallback`` (the scene's near bound). A plane too close wastes most
    of NDC's depth range in front of the content (s = 1 - 2 near / z)."""
    if points is None or not len(points):
        return NEAR_SHARE * float(fallback)
    depth = (points.float() - frame[:3, 3]) @ frame[:3, 2]
    depth = depth[depth > 0]
    if not len(depth):
        return NEAR_SHARE * float(fallback)
    return NEAR_SHARE * float(depth.quantile(0.01))


def ndc_points(points: Tensor, scale_x: float, scale_y: float, near: float) -> Tensor:
    """NDC image (..., 3) of points (..., 3) in front of the reference camera."""
    z = points[..., 2].clamp_min(1e-6)
    return torch.stack([scale_x * points[..., 0] / z, scale_y * points[..., 1] / z, 1.0 - 2.0 * near / z], -1)


def ndc_rays(origins: Tensor, directions: Tensor, scale_x: float, scale_y: float,
             near: float) -> tuple[Tensor, Tensor, Tensor]:
    """Rays (in the reference camera's frame) -> NDC rays and the shift to the near plane.

    ``scale_x`` = 2 fx / W and ``scale_y`` = 2 fy / H of the reference camera. The NDC point
    o' + s d' for s in [0, 1) is the image of o + t d, t in [0, inf), where o was first moved
    along the ray to the plane z = near (returned as ``t_near``, the distance moved).
    The NDC parameter s and the distance t past that plane satisfy t = s near / (dz (1 - s)).
    """
    dz = directions[..., 2].clamp_min(1e-6)  # forward-facing: every ray moves away from the camera plane
    t_near = (near - origins[..., 2]) / dz
    o = origins + t_near[..., None] * directions
    ox_oz, oy_oz = o[..., 0] / o[..., 2], o[..., 1] / o[..., 2]
    o_ndc = torch.stack([scale_x * ox_oz, scale_y * oy_oz, 1.0 - 2.0 * near / o[..., 2]], -1)
    d_ndc = torch.stack([scale_x * (directions[..., 0] / dz - ox_oz),
                         scale_y * (directions[..., 1] / dz - oy_oz),
                         2.0 * near / o[..., 2]], -1)
    return o_ndc, d_ndc, t_near


def ndc_to_distance(s: Tensor, near: float, dz: Tensor) -> Tensor:
    """Distance t past the near plane for NDC parameter ``s`` (s -> 1 is infinitely far)."""
    return s * near / (dz.clamp_min(1e-6) * (1.0 - s).clamp_min(1e-6))
