"""The compiled CPU rasteriser (csrc/, built by setup.py at install time): EWA projection,
binning and front-to-back compositing of Gaussians, forward and backward, in C++.

Drop-ins for :func:`projection.project_gaussians` and :func:`rasterize_torch.composite` on
float32 CPU tensors, with the same conventions: pixel centres, Jacobian clamp, dilation,
opacity-aware extent, alpha = min(0.999, o exp(-sigma)) with alpha <= 1/255 skipped, the
1e-4 transmittance stop, the alpha output. The backward passes give the gradients of the
means, quaternions and scales (projection) and of the 2D means, conics, opacities and
features (compositing), so that the 2D means' gradient that densification reads is there.
The compositing's cost is bounded for large Gaussians: each pixel stops on its own, a
Gaussian is listed only in the tiles its ellipse reaches and evaluated on its ellipse's
pixel span of each row (see csrc/kernel.cpp). Threads: ``torch.get_num_threads()``
(std::thread; no second OpenMP runtime next to torch's).
"""

from __future__ import annotations

import torch
from torch import Tensor

from rainyscape.fields.compiled import load
from rainyscape.fields.gaussians.projection import Projection
from rainyscape.fields.gaussians.rasterize_torch import AbsGrad

_ext, _IMPORT_ERROR = load("rainyscape.fields.gaussians._rasterize_cpp")

TILE_SIZE = 16  # fixed in csrc/kernel.h (kTile)


def cpp_available() -> bool:
    """Whether the compiled extension was built and imports."""
    return _ext is not None


def unavailable_reason() -> str:
    """Why the extension cannot be used ('' when it can)."""
    return "" if _ext is not None else f"the compiled rasteriser did not import ({_IMPORT_ERROR})"


def simd() -> str:
    """The build of the compositing that runs on this CPU (e.g. 'avx2 (8 lanes)')."""
    return _ext.simd() if _ext is not None else ""


def _ready(t: Tensor) -> Tensor:
    """A contiguous float32 CPU tensor with no autograd history (the kernel reads it by
    pointer; keeping a detached tensor keeps the memory alive without a graph cycle)."""
    t = t.detach()
    if t.device.type != "cpu" or t.dtype != torch.float32:
        raise ValueError("the cpp rasteriser takes float32 CPU tensors")
    return t.contiguous()


class _ProjectCpp(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means, quats, scales, opacities, views):
        arrays = [_ready(t) for t in (means, quats, scales, opacities)]
        views_arg, keep = views
        c, n = views_arg[3], means.shape[0]
        means2d = torch.empty(c, n, 2)
        conics = torch.empty(c, n, 3)
        depths = torch.empty(c, n)
        radii = torch.empty(c, n, 2, dtype=torch.int32)
        _ext.project(*(t.data_ptr() for t in arrays), n, views_arg, means2d.data_ptr(),
                     conics.data_ptr(), depths.data_ptr(), radii.data_ptr(),
                     torch.get_num_threads())
        ctx.arrays, ctx.views = arrays[:3], views
        ctx.mark_non_differentiable(radii)
        return means2d, conics, depths, radii

    @staticmethod
    def backward(ctx, g_means2d, g_conics, g_depths, _g_radii):
        means, quats, scales = ctx.arrays
        views_arg, _keep = ctx.views
        grads = [torch.zeros_like(t) for t in (means, quats, scales)]
        incoming = [(torch.zeros(shape) if g is None else _ready(g))
                    for g, shape in ((g_means2d, (views_arg[3], len(means), 2)),
                                     (g_conics, (views_arg[3], len(means), 3)),
                                     (g_depths, (views_arg[3], len(means))))]
        _ext.project_backward(means.data_ptr(), quats.data_ptr(), scales.data_ptr(), len(means),
                              views_arg, *(g.data_ptr() for g in incoming),
                              *(g.data_ptr() for g in grads), torch.get_num_threads())
        ctx.arrays = ctx.views = None
        return (*grads, None, None)


def project_cpp(means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor,
                viewmats: Tensor, Ks: Tensor, width: int, height: int, window_x0: Tensor,
                window_y0: Tensor, window_width: int, window_height: int,
                near_plane: float = 0.01, far_plane: float = 1e10,
                eps2d: float = 0.3) -> Projection:
    """As :func:`projection.project_gaussians` (opacities (N,); no gradient for the
    cameras), in C++."""
    if _ext is None:
        raise RuntimeError(unavailable_reason())
    c = viewmats.shape[0]
    offsets = torch.stack([window_x0, window_y0], -1).to(torch.float32).contiguous()
    cams = [_ready(viewmats), _ready(Ks), offsets]
    views = ((*(t.data_ptr() for t in cams), c, width, height, window_width, window_height,
              near_plane, far_plane, eps2d), cams)  # cams: keeps the pointed-to memory alive
    means2d, conics, depths, radii = _ProjectCpp.apply(means, quats, scales, opacities, views)
    return Projection(means2d, conics, depths, opacities[None].expand(c, -1), radii)


def _bin(proj: Projection, width: int, height: int, threads: int):
    """The kernel's binning of a projection: (binning, the arrays it points into)."""
    c, n = proj.radii.shape[:2]
    arrays = [_ready(t).reshape(c * n, k) for t, k in ((proj.means2d, 2), (proj.conics, 3),
                                                      (proj.opacities, 1), (proj.depths, 1))]
    radii = proj.radii.to(torch.int32).contiguous()
    means2d, conics, opacities, depths = arrays
    b = _ext.bin(means2d.data_ptr(), conics.data_ptr(), opacities.data_ptr(), radii.data_ptr(),
                 depths.data_ptr(), c, n, width, height, threads)
    return b, arrays


@torch.no_grad()
def binning_pairs(proj: Projection, width: int, height: int) -> int:
    """Gaussian-tile pairs of the kernel's binning (exact ellipse-tile test), for benchmarks."""
    proj = Projection(*(t.float() if t.is_floating_point() else t
                        for t in (proj.means2d, proj.conics, proj.depths, proj.opacities,
                                  proj.radii)))
    return _ext.pairs(_bin(proj, width, height, torch.get_num_threads())[0])


class _CompositeCpp(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means2d, conics, opacities, features, proj, width, height, absgrad):
        threads = torch.get_num_threads()
        b, arrays = _bin(proj, width, height, threads)
        feats = _ready(features)
        c = proj.radii.shape[0]
        out = torch.empty(c, height, width, feats.shape[1] + 1)
        _ext.forward(b, feats.data_ptr(), feats.shape[1], out.data_ptr(), threads)
        ctx.binning, ctx.arrays, ctx.features, ctx.absgrad = b, arrays, feats, absgrad
        return out

    @staticmethod
    def backward(ctx, g_out):
        _means2d, _conics, opacities, _depths = ctx.arrays
        feats = ctx.features
        g_out = _ready(g_out)
        m = feats.shape[0]
        grads = [torch.zeros(m, 2), torch.zeros(m, 3), torch.zeros(m), torch.zeros_like(feats)]
        absgrad = None if ctx.absgrad is None else torch.zeros(m, 2)
        _ext.backward(ctx.binning, opacities.data_ptr(), feats.shape[1], g_out.data_ptr(),
                      *(g.data_ptr() for g in grads), 0 if absgrad is None else absgrad.data_ptr(),
                      torch.get_num_threads())
        if absgrad is not None:
            ctx.absgrad.add(absgrad)
        ctx.binning = ctx.arrays = ctx.features = ctx.absgrad = None
        return (*grads, None, None, None, None)


def composite_cpp(proj: Projection, features: Tensor, width: int, height: int,
                  absgrad: AbsGrad | None = None) -> tuple[Tensor, Tensor]:
    """As :func:`rasterize_torch.composite`: (C, height, width, D) features and
    (C, height, width, 1) alpha of per-camera features (C, N, D), and the means' absolute
    gradient into ``absgrad``; float32 CPU only."""
    if _ext is None:
        raise RuntimeError(unavailable_reason())
    c, n = proj.radii.shape[:2]
    out = _CompositeCpp.apply(proj.means2d.reshape(c * n, 2), proj.conics.reshape(c * n, 3),
                              proj.opacities.reshape(c * n),
                              features.reshape(c * n, features.shape[-1]), proj, width, height,
                              absgrad)
    return out[..., :-1], out[..., -1:]
