"""The CUDA path: gsplat's ``rasterization()`` (optional extra ``rainyscape[cuda]``).

Windows are rendered by shifting the principal point and rasterising a window-sized
image, so a patch costs a patch. Colours are passed post-activation (``rasterize()``
evaluates spherical harmonics in torch first, identically for both paths). Difference to the torch path: gsplat bounds
its Jacobian clamp by the rendered window rather than the full image, which changes
the footprint of large Gaussians centred more than ~15% of the window outside it.
"""

from __future__ import annotations

import importlib.util
from functools import lru_cache

import torch
from torch import Tensor


@lru_cache(maxsize=None)
def gsplat_installed() -> bool:
    return importlib.util.find_spec("gsplat") is not None


def rasterize_gsplat(means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor,
                     colors: Tensor, viewmats: Tensor, Ks: Tensor, x0: Tensor, y0: Tensor,
                     win_w: int, win_h: int, near_plane: float, far_plane: float,
                     eps2d: float) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """rgb (C, h, w, 3), alpha (C, h, w, 1), expected depth (C, h, w, 1), means2d
    (C, N, 2) in window pixels and radii (C, N, 2), for gsplat 1.x."""
    from gsplat import rasterization

    c = viewmats.shape[0]
    ks = Ks.clone()
    ks[:, 0, 2] -= x0.to(ks)
    ks[:, 1, 2] -= y0.to(ks)
    if colors.ndim == 2:
        colors = colors[None].expand(c, -1, -1)
    colors = colors.contiguous()
    render, alpha, meta = rasterization(
        means, quats, scales, opacities, colors, viewmats, ks, win_w, win_h,
        near_plane=near_plane, far_plane=far_plane, eps2d=eps2d, packed=False,
        render_mode="RGB+ED", rasterize_mode="classic", tile_size=16)
    radii = meta["radii"]
    if radii.ndim == 2:  # gsplat < 1.5: one radius per Gaussian
        radii = radii[..., None].expand(-1, -1, 2)
    return render[..., :3], alpha, render[..., 3:4], meta["means2d"], radii.to(torch.int32)
