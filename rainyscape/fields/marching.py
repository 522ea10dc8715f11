"""Ray marching through an occupancy grid into a packed list of samples.

Two levels, all vectorised: coarse steps of about half an occupancy cell along every ray are
looked up in the occupancy grid; only the coarse intervals that touch an occupied cell are
cut into ``fine`` sub-intervals, and only the sub-intervals whose sample lies in an occupied
cell are kept. Candidates are therefore counted in cells, not in voxels, and samples exist
only where density may be (nerfacc's empty-space skipping, without its CUDA kernels).

The result is *packed*: one row per sample, sorted by ray and then by distance, with its
ray index, interval [t0, t1] and its position u0 / u1 in coarse steps from the ray's start
(a normalised ray coordinate for the distortion loss).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import torch
from torch import Tensor


@dataclass
class PackedSamples:
    ray: Tensor  # (S,) long, non-decreasing
    t0: Tensor  # (S,) interval start
    t1: Tensor  # (S,) interval end
    t: Tensor  # (S,) where the sample is taken, in [t0, t1]
    u0: Tensor  # (S,) interval in coarse steps (normalised ray coordinate * total steps)
    u1: Tensor
    far: Tensor  # (S,) bool: in the far part (beyond the box)

    def __len__(self) -> int:
        return self.ray.shape[0]

    def select(self, keep: Tensor) -> "PackedSamples":
        return PackedSamples(self.ray[keep], self.t0[keep], self.t1[keep], self.t[keep],
                             self.u0[keep], self.u1[keep], self.far[keep])


def _coarse_linear(t_a: Tensor, t_b: Tensor, step: Tensor) -> tuple[Tensor, Tensor]:
    """Edges (R, K + 1) of coarse intervals of length ``step`` (R,) from t_a, clipped at t_b,
    and which intervals are real (R, K)."""
    step = step.expand_as(t_a)
    span = (t_b - t_a).clamp_min(0.0)
    count = max(1, int(torch.ceil((span / step).max()).item()) if span.numel() else 1)
    k = torch.arange(count + 1, device=t_a.device, dtype=t_a.dtype)
    edges = torch.minimum(t_a[:, None] + k * step[:, None], t_b[:, None])
    return edges, edges[:, :-1] < t_b[:, None]


def _coarse_inverse(t_a: Tensor, t_b: Tensor, count: int) -> tuple[Tensor, Tensor]:
    """Edges (R, count + 1) of ``count`` coarse intervals evenly spaced in 1 / t between t_a
    and t_b, and which are real (R, count)."""
    k = torch.arange(count + 1, device=t_a.device, dtype=t_a.dtype) / count
    edges = 1.0 / ((1.0 - k) / t_a[:, None] + k / t_b[:, None])
    return edges, (t_b > t_a)[:, None].expand(-1, count)


def march(origins: Tensor, directions: Tensor, t_a: Tensor, t_b: Tensor, t_far: Tensor | None,
          step: Tensor, fine: int, far_steps: int, occupied: Callable[[Tensor], Tensor],
          jitter: bool, generator: torch.Generator | None = None, far_fine: int = 1) -> PackedSamples:
    """Samples of rays q = o + t d (R rays) in occupied space.

    [t_a, t_b]: the linear part, coarse steps of length ``step`` (R,); [t_b, t_far] (when
    ``t_far`` is given): the far part, ``far_steps`` coarse steps even in 1 / t. Each coarse
    interval with an edge in an occupied cell (``occupied(points) -> bool``) is cut into
    equal sub-intervals, ``fine`` in the linear part and ``far_fine`` in
    the far part; a sample sits at a uniformly random place in its sub-interval (``jitter``)
    or at its middle, and is kept where occupied.
    """
    edges, valid = _coarse_linear(t_a, t_b, step)
    n_lin = valid.shape[1]
    parts = [_fine(origins, directions, edges, valid, 0, fine, occupied, jitter, generator, False)]
    if t_far is not None and far_steps > 0:
        edges, valid = _coarse_inverse(t_b.clamp_min(1e-6), torch.maximum(t_far, t_b), far_steps)
        parts.append(_fine(origins, directions, edges, valid, n_lin, far_fine, occupied, jitter,
                           generator, True))
        # one order: by ray, then along it (the far part comes after the linear part)
        cat = PackedSamples(*[torch.cat([getattr(p, f) for p in parts]) for f in
                              ("ray", "t0", "t1", "t", "u0", "u1", "far")])
        order = torch.argsort(cat.ray * 2 + cat.far.long(), stable=True)
        return cat.select(order)
    return parts[0]


def _fine(origins: Tensor, directions: Tensor, edges: Tensor, valid: Tensor, first: int,
          fine: int, occupied: Callable[[Tensor], Tensor], jitter: bool,
          generator: torch.Generator | None, far: bool) -> PackedSamples:
    """The kept fine samples of the coarse intervals between ``edges`` (R, K + 1) (``first``:
    the index of the first coarse step, for the ray coordinate u). An interval is live when
    an occupied cell holds either of its edges."""
    at_edge = occupied(origins[:, None] + edges[..., None] * directions[:, None])  # (R, K + 1)
    live = valid & (at_edge[:, :-1] | at_edge[:, 1:])
    rays, k = live.nonzero(as_tuple=True)
    lo, hi = edges[rays, k], edges[rays, k + 1]
    k = k + first
    j = torch.arange(fine, device=lo.device, dtype=lo.dtype)
    t0 = lo[:, None] + (hi - lo)[:, None] * j / fine
    t1 = lo[:, None] + (hi - lo)[:, None] * (j + 1) / fine
    if jitter:
        frac = torch.rand(t0.shape, device=t0.device, dtype=t0.dtype, generator=generator)
    else:
        frac = torch.full_like(t0, 0.5)
    t = t0 + (t1 - t0) * frac
    u0 = k[:, None].to(lo.dtype) + j / fine
    rays = rays[:, None].expand_as(t0)
    rays, t0, t1, t, u0 = [x.reshape(-1) for x in (rays, t0, t1, t, u0)]
    keep = occupied(origins[rays] + t[:, None] * directions[rays])
    flags = torch.full_like(rays, far, dtype=torch.bool)
    return PackedSamples(rays, t0, t1, t, u0, u0 + 1.0 / fine, flags).select(keep)
