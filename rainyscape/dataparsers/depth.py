"""Depth maps: reading ``.mat`` files, ray bounds and sparse points from depth."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import scipy.io
import torch
from torch import Tensor

from rainyscape.cameras import Cameras, pixel_rays
from rainyscape.errors import DataError


def read_depth_mat(path: Path, key: str, size: tuple[int, int]) -> np.ndarray:
    """(H, W) float32 z-depth; 0, negative and non-finite values mean "no surface" (inf)."""
    try:
        data = scipy.io.loadmat(path)
    except Exception as exc:  # scipy raises many types on a damaged file (struct, zlib, Type...)
        reason = str(exc).strip().splitlines()[0][:200] if str(exc).strip() else type(exc).__name__
        raise DataError(f"{path}: cannot read the depth .mat file (truncated or damaged? {reason})") from None
    if key not in data:
        keys = [k for k in data if not k.startswith("__")]
        if len(keys) != 1:
            raise DataError(f"{path}: no '{key}' array in the .mat file (found: {', '.join(keys) or 'none'})")
        key = keys[0]
    depth = np.asarray(data[key], np.float32)
    if depth.ndim == 3 and depth.shape[-1] == 1:
        depth = depth[..., 0]
    w, h = size
    if depth.shape != (h, w):
        raise DataError(f"{path}: depth is {depth.shape[1] if depth.ndim > 1 else '?'}x{depth.shape[0]}, "
                        f"the images are {w}x{h}")
    return np.where(np.isfinite(depth) & (depth > 0), depth, np.inf).astype(np.float32)


def depth_bounds(depths: Tensor) -> tuple[float, float] | None:
    """Near / far enclosing the finite depths with a margin (None when there are none)."""
    finite = depths[torch.isfinite(depths)]
    if finite.numel() == 0:
        return None
    sample = finite[torch.randperm(finite.numel(), generator=torch.Generator().manual_seed(0))[:200_000]]
    near = float(sample.min()) * 0.8
    far = float(torch.quantile(sample, 0.995)) * 1.2
    return near, far


def points_from_depth(cameras: Cameras, depths: Tensor, images: Tensor, max_points: int,
                      num_views: int = 8, seed: int = 0) -> tuple[Tensor, Tensor]:
    """Back-project a random sample of finite depth pixels of a few evenly spaced views.

    Returns world points (P, 3) and their colours (P, 3) uint8 from ``images``.
    """
    n = len(cameras)
    views = np.unique(np.linspace(0, n - 1, min(num_views, n)).round().astype(int))
    gen = torch.Generator().manual_seed(seed)
    per_view = max(1, max_points // len(views))
    pts, cols = [], []
    for v in views.tolist():
        d = depths[v]
        ys, xs = torch.nonzero(torch.isfinite(d), as_tuple=True)
        if len(ys) == 0:
            continue
        pick = torch.randperm(len(ys), generator=gen)[:per_view]
        ys, xs = ys[pick], xs[pick]
        rays = pixel_rays(cameras[v], xs[None], ys[None])
        t = d[ys, xs] / rays.z_scale[0]
        pts.append(rays.origins[0] + rays.directions[0] * t[:, None])
        cols.append(images[v, ys, xs])
    if not pts:
        return torch.zeros(0, 3), torch.zeros(0, 3, dtype=torch.uint8)
    return torch.cat(pts).float(), torch.cat(cols)
