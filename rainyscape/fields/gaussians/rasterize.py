"""One rasterisation entry point with a gsplat-like signature; picks the backend.

``backend="auto"`` uses gsplat (CUDA) when the tensors are on a CUDA device and gsplat
is installed, and the tiled torch rasteriser otherwise (CPU, or CUDA without gsplat).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from rainyscape.cameras import Window
from rainyscape.errors import ConfigError
from rainyscape.fields.gaussians.projection import project_gaussians
from rainyscape.fields.gaussians.rasterize_gsplat import gsplat_installed, rasterize_gsplat
from rainyscape.fields.gaussians.rasterize_torch import composite

BACKENDS = ("auto", "torch", "gsplat")


@dataclass
class Rasterized:
    rgb: Tensor  # (C, h, w, 3), background composited
    alpha: Tensor  # (C, h, w, 1)
    depth: Tensor  # (C, h, w, 1) expected z-depth (0 where nothing was hit)
    means2d: Tensor  # (C, N, 2) window pixels; its .grad drives densification
    radii: Tensor  # (C, N, 2) bounding-box half sizes; 0: not visible in the window


def resolve_backend(backend: str, device: torch.device) -> str:
    if backend not in BACKENDS:
        raise ConfigError(f"rasteriser backend '{backend}' is not one of {', '.join(BACKENDS)}")
    if backend == "auto":
        return "gsplat" if device.type == "cuda" and gsplat_installed() else "torch"
    if backend == "gsplat" and (device.type != "cuda" or not gsplat_installed()):
        raise ConfigError("backend=gsplat needs CUDA tensors and gsplat "
                          "(pip install 'rainyscape[cuda]'); use backend=auto or torch")
    return backend


def rasterize(means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor, colors: Tensor,
              viewmats: Tensor, Ks: Tensor, width: int, height: int,
              window: Window | None = None, *, backgrounds: Tensor | None = None,
              near_plane: float = 0.01, far_plane: float = 1e10, eps2d: float = 0.3,
              backend: str = "auto") -> Rasterized:
    """Render C cameras (or a window of each) of N Gaussians.

    means (N, 3), quats (N, 4) w x y z, scales (N, 3) linear, opacities (N,) in [0, 1],
    colors (N, 3) or (C, N, 3) post-activation, viewmats (C, 4, 4) world-to-camera
    (OpenCV), Ks (C, 3, 3); width / height: the full image. ``window``: per-camera offsets
    and one size (default: the whole image); only its pixels are computed.
    """
    c = viewmats.shape[0]
    if window is None:
        zeros = torch.zeros(c, dtype=torch.long)
        window = Window(zeros, zeros.clone(), width, height)
    x0, y0 = window.x0.to(means.device), window.y0.to(means.device)
    if resolve_backend(backend, means.device) == "gsplat":
        rgb, alpha, depth, means2d, radii = rasterize_gsplat(
            means, quats, scales, opacities, colors, viewmats, Ks, x0, y0, window.width,
            window.height, near_plane, far_plane, eps2d)
    else:
        proj = project_gaussians(means, quats, scales, opacities, viewmats, Ks, width, height,
                                 x0, y0, window.width, window.height, near_plane, far_plane, eps2d)
        if colors.ndim == 2:
            colors = colors[None].expand(c, -1, -1)
        features = torch.cat([colors, proj.depths[..., None]], -1)
        out, alpha = composite(proj, features, window.width, window.height)
        rgb = out[..., :3]
        depth = out[..., 3:] / alpha.clamp_min(1e-10)
        means2d, radii = proj.means2d, proj.radii
    if backgrounds is not None:
        rgb = rgb + (1.0 - alpha) * backgrounds.to(rgb).reshape(-1, 1, 1, 3)
    return Rasterized(rgb, alpha, depth, means2d, radii)
