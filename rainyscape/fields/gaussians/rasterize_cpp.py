"""The compiled CPU rasteriser: binning and front-to-back compositing of projected
Gaussians, forward and backward, in C++ (csrc/, built by setup.py at install time).

A drop-in for :func:`rasterize_torch.composite` on float32 CPU tensors: the same pixel
centres, opacity-aware extent, alpha = min(0.999, o exp(-sigma)) with alpha <= 1/255
skipped, the 1e-4 transmittance stop and the alpha output; the backward pass gives the
gradients of the 2D means, conics, opacities and features. Its cost is bounded for large
Gaussians: each pixel stops on its own, a Gaussian is evaluated on its ellipse's pixel span
of each row only, and listed only in the tiles its ellipse reaches (see csrc/kernel.cpp).
Threads: ``torch.get_num_threads()`` (std::thread, no second OpenMP runtime).
"""

from __future__ import annotations

import torch
from torch import Tensor

from rainyscape.fields.gaussians.projection import Projection

try:
    from rainyscape.fields.gaussians import _rasterize_cpp as _ext
    _IMPORT_ERROR = ""
except ImportError as err:  # not built: no compiler at install time, or a stale install
    _ext = None
    _IMPORT_ERROR = str(err) or type(err).__name__

TILE_SIZE = 16  # fixed in csrc/kernel.h (kTile)


def cpp_available() -> bool:
    """Whether the compiled extension was built and imports."""
    return _ext is not None


def unavailable_reason() -> str:
    """Why the extension cannot be used ('' when it can)."""
    return "" if _ext is not None else f"the compiled rasteriser did not import ({_IMPORT_ERROR})"


def _flat(proj: Projection) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """Contiguous float32 means2d (M, 2), conics (M, 3), opacities (M,), int32 radii (M, 2)
    and the per-camera depth order (C, N) int64 (ties by index, as the torch path)."""
    c, n = proj.radii.shape[:2]
    order = torch.argsort(proj.depths.detach().reshape(c, n), dim=1, stable=True)
    return (proj.means2d.reshape(c * n, 2), proj.conics.reshape(c * n, 3),
            proj.opacities.reshape(c * n), proj.radii.reshape(c * n, 2).to(torch.int32).contiguous(),
            order.contiguous())


def _check(*tensors: Tensor) -> None:
    for t in tensors:
        if t.device.type != "cpu" or t.dtype != torch.float32 or not t.is_contiguous():
            raise ValueError("the cpp rasteriser takes contiguous float32 CPU tensors")


def _bin(means2d: Tensor, conics: Tensor, opacities: Tensor, radii: Tensor, order: Tensor,
         cameras: int, width: int, height: int, threads: int):
    _check(means2d, conics, opacities)
    return _ext.bin(means2d.data_ptr(), conics.data_ptr(), opacities.data_ptr(),
                    radii.data_ptr(), order.data_ptr(), cameras, order.shape[1], width, height,
                    threads)


@torch.no_grad()
def binning_pairs(proj: Projection, width: int, height: int) -> int:
    """Gaussian-tile pairs of the kernel's binning (exact ellipse-tile test), for benchmarks."""
    means2d, conics, opacities, radii, order = _flat(proj)
    arrays = [t.detach().float().contiguous() for t in (means2d, conics, opacities)]
    b = _bin(*arrays, radii, order, proj.radii.shape[0], width, height, torch.get_num_threads())
    return _ext.pairs(b)


class _CompositeCpp(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means2d, conics, opacities, features, radii, order, cameras, width, height):
        threads = torch.get_num_threads()
        # Detached views keep the arrays alive for the backward pass without a reference
        # cycle through the graph; the kernel reads them by pointer.
        arrays = [t.detach().contiguous() for t in (means2d, conics, opacities, features)]
        _check(*arrays)
        b = _bin(*arrays[:3], radii, order, cameras, width, height, threads)
        channels = features.shape[1]
        out = torch.empty(cameras, height, width, channels + 1)
        _ext.forward(b, arrays[3].data_ptr(), channels, out.data_ptr(), threads)
        ctx.binning, ctx.arrays, ctx.radii = b, arrays, radii
        return out

    @staticmethod
    def backward(ctx, g_out):
        means2d, conics, opacities, features = ctx.arrays
        g_out = g_out.to(torch.float32).contiguous()
        grads = [torch.zeros_like(t) for t in ctx.arrays]
        _ext.backward(ctx.binning, opacities.data_ptr(), features.data_ptr(), features.shape[1],
                      g_out.data_ptr(), *(g.data_ptr() for g in grads), torch.get_num_threads())
        ctx.binning = ctx.arrays = None
        return (*grads, None, None, None, None, None)


def composite_cpp(proj: Projection, features: Tensor, width: int,
                  height: int) -> tuple[Tensor, Tensor]:
    """As :func:`rasterize_torch.composite`: (C, height, width, D) features and
    (C, height, width, 1) alpha of per-camera features (C, N, D); float32 CPU only."""
    if _ext is None:
        raise RuntimeError(unavailable_reason())
    c, n = proj.radii.shape[:2]
    means2d, conics, opacities, radii, order = _flat(proj)
    out = _CompositeCpp.apply(means2d, conics, opacities,
                              features.reshape(c * n, features.shape[-1]), radii, order, c,
                              width, height)
    return out[..., :-1], out[..., -1:]
