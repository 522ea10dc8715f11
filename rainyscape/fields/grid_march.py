"""The grid field's first pass: which samples light reaches, as a packed list.

:class:`LiveSamples` is what the render with gradients needs of a ray batch: the live samples
(inside an occupied cell, in front of the point where a ray turns opaque) sorted by ray and
along it. Two marchers make it: the dense torch path (``GridField._march_dense``, any device),
and :func:`march`, the compiled one (csrc/march.cpp, built by setup.py at install time; float32
CPU tensors, a vector-matrix density), which lays out the same samples ray by ray without the
(rays x slots) tensors. Threads: ``torch.get_num_threads()``.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from rainyscape.fields import vm_cpp
from rainyscape.fields.compiled import load

_ext, _IMPORT_ERROR = load("rainyscape.fields._march_cpp")


@dataclass
class LiveSamples:
    ray: Tensor  # (S,) long, non-decreasing
    t: Tensor  # (S,) ray parameter of the sample
    delta: Tensor  # (S,) interval length (world, or NDC, units)
    g: Tensor  # (S, 3) grid coordinates
    sigma: Tensor  # (S,) density (without gradient)
    rank: Tensor  # (S,) place among the ray's real samples (distortion's ray coordinate)
    slots: int  # sample slots a ray has (rank / slots is in [0, 1))
    evaluated: Tensor  # () samples whose density the pass evaluated (stats)


def cpp_available() -> bool:
    """Whether the compiled marcher was built and imports."""
    return _ext is not None


def unavailable_reason() -> str:
    """Why the compiled marcher cannot be used ('' when it can)."""
    return "" if _ext is not None else f"the compiled marcher did not import ({_IMPORT_ERROR})"


def usable(plane: Tensor, origins: Tensor) -> bool:
    """Whether :func:`march` can take these: float32 density tables and rays on the CPU."""
    return (_ext is not None and plane.device.type == "cpu" and plane.dtype == torch.float32
            and origins.device.type == "cpu" and origins.dtype == torch.float32)


def _f32(x: Tensor) -> Tensor:
    return x.detach().to(torch.float32).contiguous()


@torch.no_grad()
def march(plane: Tensor, line: Tensor, layout: tuple[int, ...], occupied: Tensor,
          origins: Tensor, directions: Tensor, t_a: Tensor, t_b: Tensor, t_far: Tensor,
          step: Tensor, jitter: Tensor, length: Tensor, n_lin: int, n_far: int, inner: float,
          last_delta: float, force_last: bool, density_scale: float, density_shift: float,
          threshold: float) -> LiveSamples:
    """The live samples of rays q = origins + t directions (R rays, all (R,) or (R, 3)).

    Linear part: t_a + (k + jitter) step for k < n_lin, where below t_b; then, with
    ``n_far`` > 0 (contracted), ``n_far`` samples evenly in 1 / t from t_b to t_far mapped
    into the cube by the contraction with ``inner``; else one sample at t_b. Intervals are
    the gaps times ``length``, the last ``last_delta`` times it. ``occupied`` (r, r, r) bool
    over [-2, 2]^3 holds 2 g. Density: ``density_scale`` softplus(VM sum + ``density_shift``)
    of the tables (plane, line, layout) as feature_grids.VMTables keeps them.
    """
    keep = [plane.detach().contiguous(), line.detach().contiguous(),
            occupied.detach().to(torch.bool).contiguous()]
    rays = [_f32(x) for x in (origins, directions, t_a, t_b, t_far, step, jitter, length)]
    ray, t, delta, g, sigma, rank, evaluated = _ext.march(
        tuple(int(v) for v in layout), keep[0].data_ptr(), keep[1].data_ptr(), keep[2].data_ptr(),
        keep[2].shape[0], *(x.data_ptr() for x in rays), origins.shape[0], n_lin, max(1, n_far),
        n_far > 0, float(inner), force_last, float(last_delta), float(density_scale),
        float(density_shift), float(threshold), torch.get_num_threads())

    def tensor(buf: bytearray, dtype: torch.dtype) -> Tensor:
        return torch.frombuffer(buf, dtype=dtype) if len(buf) else torch.empty(0, dtype=dtype)

    return LiveSamples(ray=tensor(ray, torch.int64), t=tensor(t, torch.float32),
                       delta=tensor(delta, torch.float32), g=tensor(g, torch.float32).view(-1, 3),
                       sigma=tensor(sigma, torch.float32),
                       rank=tensor(rank, torch.int32).long(), slots=n_lin + max(1, n_far),
                       evaluated=torch.tensor(evaluated))


class _PassDensity(torch.autograd.Function):
    """The pass's densities as the forward value, the tables' gradient in the backward:
    sigma = scale softplus(x), x = shift + the VM features' sum, so d sigma / d x =
    scale sigmoid(x) = scale (1 - exp(-sigma / scale)), spread over every feature."""

    @staticmethod
    def forward(ctx, plane: Tensor, line: Tensor, live: LiveSamples, layout: tuple, scale: float) -> Tensor:
        ctx.keep = (plane.detach().contiguous(), line.detach().contiguous(), live.g.contiguous(),
                    live.sigma, layout, scale)
        ctx.tables = (plane, line)
        return live.sigma.clone()

    @staticmethod
    def backward(ctx, grad: Tensor):
        plane, line, points, sigma, layout, scale = ctx.keep
        d_x = grad * scale * -torch.expm1(-sigma / scale)
        d_features = d_x[:, None].expand(-1, 3 * layout[0]).contiguous()
        return (*vm_cpp.tables_backward(ctx.tables, plane, line, points, d_features, layout),
                None, None, None)


def pass_density(plane: Tensor, line: Tensor, layout: tuple[int, ...], live: LiveSamples,
                 scale: float) -> Tensor:
    """The densities :func:`march` evaluated, differentiable in the density tables (plane,
    line): what GridField._sigma gives at the samples, without evaluating it again."""
    return _PassDensity.apply(plane, line, live, tuple(int(v) for v in layout), float(scale))
