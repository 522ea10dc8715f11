"""Camera paths for videos: through the training views, or a spiral around the scene."""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor

from rainyscape.cameras import Cameras, world_up
from rainyscape.scene import normalize_poses


def interpolate_poses(c2w: Tensor, steps: int) -> Tensor:
    """Camera-to-world (N, 4, 4) -> a smooth path (steps * (N - 1) + 1, 4, 4) through them:
    spherical interpolation of the rotations, linear of the centres, ``steps`` per segment."""
    from scipy.spatial.transform import Rotation, Slerp

    n = c2w.shape[0]
    if n == 1 or steps <= 1:
        return c2w.clone()
    mats = c2w.double().cpu().numpy()
    times = np.arange(n, dtype=np.float64)
    query = np.linspace(0.0, n - 1.0, steps * (n - 1) + 1)
    rot = Slerp(times, Rotation.from_matrix(mats[:, :3, :3]))(query).as_matrix()
    centres = np.stack([np.interp(query, times, mats[:, i, 3]) for i in range(3)], -1)
    out = np.tile(np.eye(4), (len(query), 1, 1))
    out[:, :3, :3], out[:, :3, 3] = rot, centres
    return torch.from_numpy(out).to(c2w)


def look_at(centres: Tensor, target: Tensor, up: Tensor) -> Tensor:
    """OpenCV camera-to-world (M, 4, 4) at ``centres`` looking at ``target``; image-up is
    ``up`` projected (OpenCV's y axis points down, so y = -up)."""
    z = target[None] - centres
    z = z / z.norm(dim=-1, keepdim=True)
    x = torch.linalg.cross(z, up.expand_as(z))
    x = x / x.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    y = torch.linalg.cross(z, x)
    out = torch.eye(4, dtype=centres.dtype).repeat(len(centres), 1, 1)
    out[:, :3, 0], out[:, :3, 1], out[:, :3, 2], out[:, :3, 3] = x, y, z, centres
    return out


def spiral_poses(c2w: Tensor, frames: int, turns: float = 1.0) -> Tensor:
    """A circle (with a gentle vertical wave) around the mean camera, looking at the point all
    cameras look at; radius: the spread of the cameras around their mean."""
    transform, _ = normalize_poses(c2w)
    focus = -transform[:3, 3].to(c2w)
    centres = c2w[:, :3, 3]
    mean = centres.mean(0)
    up = world_up(c2w)
    view = focus - mean
    view = view / view.norm()
    right = torch.linalg.cross(view, up)
    right = right / right.norm().clamp_min(1e-12)
    true_up = torch.linalg.cross(right, view)
    radius = float((centres - mean).norm(dim=-1).mean().clamp_min(1e-3))
    t = torch.linspace(0, 2 * math.pi * turns, frames + 1, dtype=c2w.dtype)[:-1]
    path = (mean[None] + radius * torch.cos(t)[:, None] * right[None]
            + 0.5 * radius * torch.sin(t)[:, None] * true_up[None])
    return look_at(path, focus, up)


def path_cameras(cameras: Cameras, indices: list[int], kind: str, frames: int) -> Cameras:
    """``frames`` (about) cameras along ``kind`` = "views" (through ``indices`` in order) or
    "spiral"; intrinsics of the first view."""
    c2w = cameras.c2w[indices].cpu()
    if kind == "views":
        steps = max(1, round((frames - 1) / max(1, len(indices) - 1)))
        path = interpolate_poses(c2w, steps)
    elif kind == "spiral":
        path = spiral_poses(c2w, frames)
    else:
        raise ValueError(f"unknown camera path '{kind}' (views or spiral)")
    m = path.shape[0]
    first = indices[0]

    def rep(x: Tensor) -> Tensor:
        return x[first].cpu().expand(m).clone()

    return Cameras(path.float(), rep(cameras.fx), rep(cameras.fy), rep(cameras.cx), rep(cameras.cy),
                   cameras.width, cameras.height)
