"""One rasterisation entry point with a gsplat-like signature; picks the backend.

``backend="auto"`` uses gsplat (CUDA) when the tensors are on a CUDA device and gsplat
works there; on the CPU the compiled kernel (``cpp``, rasterize_cpp.py) when it was built,
else the tiled torch rasteriser (also the one for CUDA without a working gsplat: one
warning says so).

The torch path first culls, cheaply and without gradients, the Gaussians that cannot be in
view, and projects, colours and composites the rest only. ``cpp`` projects all of them in
C++ (which culls as it goes, faster than subsetting the parameters in torch and routing
their gradients back), evaluates SH colours in torch for the Gaussians some camera sees,
and composites in C++. It runs float32 renders whose cameras need no gradient; others
(float64, which the tests use as the tight reference) fall back to the torch path.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from rainyscape.cameras import Window
from rainyscape.errors import ConfigError
from rainyscape.fields.gaussians.projection import candidate_gaussians, project_gaussians
from rainyscape.fields.gaussians.rasterize_gsplat import gsplat_usable, rasterize_gsplat
from rainyscape.fields.gaussians.rasterize_cpp import (composite_cpp, cpp_available,
                                                      project_cpp, unavailable_reason)
from rainyscape.fields.gaussians.rasterize_torch import AbsGrad, composite
from rainyscape.fields.gaussians.sh import sh_to_rgb

BACKENDS = ("auto", "torch", "cpp", "gsplat")


@dataclass
class Rasterized:
    rgb: Tensor  # (C, h, w, 3), background composited
    alpha: Tensor  # (C, h, w, 1)
    depth: Tensor  # (C, h, w, 1) expected z-depth (0 where nothing was hit)
    means2d: Tensor  # (C, N, 2) window pixels; its .grad drives densification
    radii: Tensor  # (C, N, 2) bounding-box half sizes; 0: not visible in the window


def resolve_backend(backend: str, device: torch.device) -> str:
    """The rasteriser for ``backend`` on ``device``. ``auto`` on CUDA uses gsplat when it works
    (the first use builds its kernels, with a message) and otherwise the torch rasteriser,
    after one warning; on the CPU the compiled kernel when it imports, else torch. An
    explicit ``gsplat`` or ``cpp`` that cannot run is a one-line ConfigError."""
    if backend not in BACKENDS:
        raise ConfigError(f"rasteriser backend '{backend}' is not one of {', '.join(BACKENDS)}")
    if backend == "auto":
        if device.type == "cuda":
            return "gsplat" if gsplat_usable(device) else "torch"
        return "cpp" if device.type == "cpu" and cpp_available() else "torch"
    if backend == "cpp" and device.type != "cpu":
        raise ConfigError("field.backend=cpp: it needs CPU tensors; use field.backend=auto or torch")
    if backend == "cpp" and not cpp_available():
        raise ConfigError(f"field.backend=cpp: {unavailable_reason()}; reinstall with a C++ "
                          "compiler present (pip install -e .) or use field.backend=auto or torch")
    if backend == "gsplat":
        why = ("it needs CUDA tensors" if device.type != "cuda"
               else "" if gsplat_usable(device) else "gsplat does not work here (see the warning above)")
        if why:
            raise ConfigError(f"field.backend=gsplat: {why}; use field.backend=auto or torch")
    return backend


def camera_centres(viewmats: Tensor) -> Tensor:
    """World positions (C, 3) of the cameras of world-to-camera matrices (C, 4, 4)."""
    rot = viewmats[:, :3, :3]
    return -(rot.transpose(1, 2) @ viewmats[:, :3, 3:])[..., 0]


def colors_from_sh(coeffs: Tensor, means: Tensor, viewmats: Tensor, sh_degree: int) -> Tensor:
    """Per-camera colours (C, N, 3) of SH coefficients (N, K, 3) seen from each camera."""
    dirs = torch.nn.functional.normalize(means[None] - camera_centres(viewmats)[:, None], dim=-1)
    return sh_to_rgb(coeffs, dirs, sh_degree)


def _project_torch(means, quats, scales, opacities, colors, args, sh_degree):
    """The torch path's projection and colours (C, N, 3), run on the Gaussians that may be
    in view only (a cheap superset, without gradients): a patch sees a few percent of them.
    Returns the projection of that subset, the full-size 2D means and radii, and the
    subset's indices (None: all N)."""
    viewmats, Ks, width, height, x0, y0, win_w, win_h, near_plane, far_plane, eps2d = args
    c, n = viewmats.shape[0], means.shape[0]
    ids = candidate_gaussians(means.detach(), scales.detach(), opacities.detach(), viewmats,
                              Ks, width, height, x0, y0, win_w, win_h, near_plane, far_plane,
                              eps2d)
    culled = len(ids) < n

    def take(t: Tensor, dim: int = 0) -> Tensor:
        return t.index_select(dim, ids) if culled else t

    sub_means = take(means)
    proj = project_gaussians(sub_means, take(quats), take(scales), take(opacities), *args)
    if sh_degree is not None:
        colors = colors_from_sh(take(colors), sub_means, viewmats, sh_degree)
    else:
        colors = take(colors, colors.ndim - 2)
    if colors.ndim == 2:
        colors = colors[None].expand(c, -1, -1)
    means2d, radii = proj.means2d, proj.radii
    if culled:
        # Densification reads the 2D means' gradient for all N Gaussians: route the
        # subset's means through a full-size tensor (zeros where culled).
        means2d = means2d.new_zeros(c, n, 2).index_copy(1, ids, means2d)
        proj.means2d = means2d.index_select(1, ids)
        radii = radii.new_zeros(c, n, 2).index_copy_(1, ids, radii)
    return proj, colors, means2d, radii, ids if culled else None


def _project_cpp(means, quats, scales, opacities, colors, args, sh_degree):
    """The compiled projection of all N Gaussians (it culls them itself, in ~50 ns each:
    cheaper than the torch path's subsetting and its backward) and their colours (C, N, 3);
    SH colours are evaluated for the Gaussians that some camera sees only."""
    proj = project_cpp(means, quats, scales, opacities, *args)
    c, n = proj.radii.shape[:2]
    if sh_degree is not None:
        seen = (proj.radii > 0).all(-1).any(0).nonzero().squeeze(1)
        if len(seen) < 0.9 * n:
            part = colors_from_sh(colors.index_select(0, seen), means.index_select(0, seen),
                                  args[0], sh_degree)
            colors = part.new_zeros(c, n, 3).index_copy(1, seen, part)
        else:
            colors = colors_from_sh(colors, means, args[0], sh_degree)
    if colors.ndim == 2:
        colors = colors[None].expand(c, -1, -1)
    return proj, colors


def rasterize(means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor, colors: Tensor,
              viewmats: Tensor, Ks: Tensor, width: int, height: int,
              window: Window | None = None, *, sh_degree: int | None = None,
              backgrounds: Tensor | None = None, near_plane: float = 0.01,
              far_plane: float = 1e10, eps2d: float = 0.3, backend: str = "auto",
              absgrad: bool = False) -> Rasterized:
    """Render C cameras (or a window of each) of N Gaussians.

    means (N, 3), quats (N, 4) w x y z, scales (N, 3) linear, opacities (N,) in [0, 1],
    colors (N, 3) or (C, N, 3) post-activation, or with ``sh_degree`` SH coefficients
    (N, K, 3) evaluated along camera centre -> mean (as gsplat), viewmats (C, 4, 4)
    world-to-camera (OpenCV), Ks (C, 3, 3); width / height: the full image. ``window``:
    per-camera offsets and one size (default: the whole image); only its pixels are
    computed. ``absgrad``: as gsplat's, after the backward pass ``means2d.absgrad`` (C, N, 2)
    holds the 2D means' absolute gradient (AbsGS: per pixel |dL/d mean2d|, summed).
    """
    c, n = viewmats.shape[0], means.shape[0]
    if window is None:
        zeros = torch.zeros(c, dtype=torch.long)
        window = Window(zeros, zeros.clone(), width, height)
    x0, y0 = window.x0.to(means.device), window.y0.to(means.device)
    name = resolve_backend(backend, means.device)
    if name == "gsplat":
        if sh_degree is not None:
            colors = colors_from_sh(colors, means, viewmats, sh_degree)
        rgb, alpha, depth, means2d, radii = rasterize_gsplat(
            means, quats, scales, opacities, colors, viewmats, Ks, x0, y0, window.width,
            window.height, near_plane, far_plane, eps2d, absgrad)
    else:
        # The compiled kernel takes float32 and gives no gradient to the cameras.
        use_cpp = (name == "cpp" and means.dtype == torch.float32
                   and not (viewmats.requires_grad or Ks.requires_grad))
        args = (viewmats, Ks, width, height, x0, y0, window.width, window.height, near_plane,
                far_plane, eps2d)
        if use_cpp:
            proj, colors = _project_cpp(means, quats, scales, opacities, colors, args, sh_degree)
            means2d, radii, ids = proj.means2d, proj.radii, None
        else:
            proj, colors, means2d, radii, ids = _project_torch(means, quats, scales, opacities,
                                                               colors, args, sh_degree)
        sink = None
        if absgrad:  # filled by the backward pass, as gsplat's means2d.absgrad
            means2d.absgrad = means2d.new_zeros(c, n, 2)
            rows = None if ids is None else (torch.arange(c, device=ids.device)[:, None] * n + ids).reshape(-1)
            sink = AbsGrad(means2d.absgrad.view(c * n, 2), rows)
        features = torch.cat([colors, proj.depths[..., None]], -1)
        out, alpha = (composite_cpp if use_cpp else composite)(
            proj, features, window.width, window.height, absgrad=sink)
        rgb = out[..., :3]
        depth = out[..., 3:] / alpha.clamp_min(1e-10)
    if backgrounds is not None:
        rgb = rgb + (1.0 - alpha) * backgrounds.to(rgb).reshape(-1, 1, 1, 3)
    return Rasterized(rgb, alpha, depth, means2d, radii)
