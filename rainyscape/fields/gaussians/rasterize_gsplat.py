"""The CUDA path: gsplat's ``rasterization()`` (optional extra ``rainyscape[cuda]``).

Windows are rendered by shifting the principal point and rasterising a window-sized
image, so a patch costs a patch. Colours are passed post-activation (``rasterize()``
evaluates spherical harmonics in torch first, identically for both paths). Difference to the torch path: gsplat bounds
its Jacobian clamp by the rendered window rather than the full image, which changes
the footprint of large Gaussians centred more than ~15% of the window outside it.

First use: a gsplat installed from PyPI compiles its CUDA kernels on the first call (a
minute or more, cached afterwards); :func:`gsplat_usable` says so before it happens, then
loads the kernels and renders one Gaussian as a check. A missing or broken gsplat (no CUDA
toolkit, a failed build, a failing kernel) gives one warning and the torch rasteriser.
"""

from __future__ import annotations

import glob
import importlib
import importlib.util
import os
import sys
from functools import lru_cache
from typing import Callable

import torch
from torch import Tensor

BUILD_MESSAGE = "rainyscape: building gsplat's CUDA kernels (about a minute, once) ..."
INSTALL_HINT = "pip install 'rainyscape[cuda]'"


@lru_cache(maxsize=None)
def gsplat_installed() -> bool:
    return importlib.util.find_spec("gsplat") is not None


def _kernels_cached() -> bool:
    """Whether gsplat's kernels need no build: a prebuilt wheel (``gsplat.csrc``) or an
    earlier JIT build in torch's extension cache."""
    try:
        if importlib.util.find_spec("gsplat.csrc") is not None:
            return True
    except (ImportError, ValueError):
        pass
    try:  # torch's JIT cache: <root>/py<ver>_<cuda>/gsplat_cuda/ (looked up, never created)
        from torch.utils.cpp_extension import get_default_build_root

        root = os.environ.get("TORCH_EXTENSIONS_DIR") or get_default_build_root()
        return bool(glob.glob(os.path.join(root, "*", "gsplat_cuda", "gsplat_cuda.*"))
                    or glob.glob(os.path.join(root, "gsplat_cuda", "gsplat_cuda.*")))
    except Exception:  # when torch's layout moves, assume a build may be needed
        return False


def _smoke_test(device: torch.device) -> None:
    """One Gaussian through gsplat forward and backward on ``device``."""
    from gsplat import rasterization

    means = torch.tensor([[0.0, 0.0, 2.0]], device=device, requires_grad=True)
    quats = torch.tensor([[1.0, 0.0, 0.0, 0.0]], device=device)
    scales = torch.full((1, 3), 0.1, device=device)
    opac = torch.ones(1, device=device)
    colors = torch.ones(1, 1, 3, device=device)
    viewmats = torch.eye(4, device=device)[None]
    ks = torch.tensor([[[8.0, 0.0, 4.0], [0.0, 8.0, 4.0], [0.0, 0.0, 1.0]]], device=device)
    render, _, _ = rasterization(means, quats, scales, opac, colors, viewmats, ks, 8, 8)
    render.sum().backward()
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    if means.grad is None or not bool(torch.isfinite(render).all()):
        raise RuntimeError("the test render gave no gradient or a non-finite image")


def check_gsplat(device: torch.device, smoke_test: Callable[[torch.device], None] = _smoke_test,
                 stream=None) -> str:
    """Make gsplat ready on ``device`` (building its kernels on first use, with a message on
    ``stream``, default stderr); returns "" when usable, else why not (one line)."""
    stream = stream or sys.stderr
    if not gsplat_installed():
        return f"gsplat is not installed ({INSTALL_HINT})"
    try:
        importlib.import_module("gsplat")
    except Exception as exc:  # a broken install: any error at import
        return f"gsplat does not import ({type(exc).__name__}: {exc})"
    if not _kernels_cached():
        print(BUILD_MESSAGE, file=stream, flush=True)
    try:
        backend = importlib.import_module("gsplat.cuda._backend")
    except ModuleNotFoundError:
        backend = None  # another gsplat layout: the test render decides
    except Exception as exc:  # the build failed
        return f"gsplat's CUDA kernels did not build or load ({type(exc).__name__}: {exc})"
    if backend is not None and getattr(backend, "_C", True) is None:
        return "gsplat found no CUDA toolkit (nvcc) to build its kernels"
    try:
        smoke_test(device)
    except Exception as exc:
        return f"gsplat failed a test render ({type(exc).__name__}: {exc})"
    return ""


_usable: dict[str, bool] = {}


def gsplat_usable(device: torch.device, smoke_test: Callable[[torch.device], None] = _smoke_test,
                  stream=None) -> bool:
    """Whether gsplat renders on ``device`` (checked once per device type); when it does not,
    one warning on ``stream`` (default stderr) says why and that the torch rasteriser is used."""
    key = torch.device(device).type
    if key not in _usable:
        why = check_gsplat(torch.device(device), smoke_test, stream)
        if why:
            print(f"rainyscape: warning: {why}; the Gaussians render with the torch rasteriser "
                  f"instead (much slower on a GPU)", file=stream or sys.stderr, flush=True)
        _usable[key] = not why
    return _usable[key]


def forget_gsplat_checks() -> None:
    """Check again on the next use (tests; after installing gsplat in a running session)."""
    _usable.clear()
    gsplat_installed.cache_clear()


def rasterize_gsplat(means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor,
                     colors: Tensor, viewmats: Tensor, Ks: Tensor, x0: Tensor, y0: Tensor,
                     win_w: int, win_h: int, near_plane: float, far_plane: float,
                     eps2d: float, absgrad: bool = False) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """rgb (C, h, w, 3), alpha (C, h, w, 1), expected depth (C, h, w, 1), means2d
    (C, N, 2) in window pixels (with ``absgrad``: gsplat sets its ``.absgrad`` in the
    backward pass) and radii (C, N, 2), for gsplat 1.x."""
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
        render_mode="RGB+ED", rasterize_mode="classic", tile_size=16, absgrad=absgrad)
    radii = meta["radii"]
    if radii.ndim == 2:  # gsplat < 1.5: one radius per Gaussian
        radii = radii[..., None].expand(-1, -1, 2)
    return render[..., :3], alpha, render[..., 3:4], meta["means2d"], radii.to(torch.int32)
