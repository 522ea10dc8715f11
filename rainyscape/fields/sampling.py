"""Where along a ray to sample: stratified bins, inverse-CDF importance, ray-box clipping."""

from __future__ import annotations

import torch
from torch import Tensor


def stratified_samples(near: Tensor, far: Tensor, count: int, perturb: bool,
                       lindisp: bool = False) -> Tensor:
    """``count`` depths per ray between ``near`` and ``far`` (shape (R,) or scalars broadcast).

    Evenly spaced in depth (or in inverse depth with ``lindisp``); with ``perturb`` each
    sample is drawn uniformly inside its stratum, as in NeRF's training.
    """
    near, far = torch.broadcast_tensors(torch.as_tensor(near), torch.as_tensor(far))
    u = torch.linspace(0.0, 1.0, count, dtype=near.dtype, device=near.device)
    if lindisp:
        t = 1.0 / (1.0 / near[..., None] * (1.0 - u) + 1.0 / far[..., None] * u)
    else:
        t = near[..., None] * (1.0 - u) + far[..., None] * u
    if perturb:
        mids = 0.5 * (t[..., 1:] + t[..., :-1])
        upper = torch.cat([mids, t[..., -1:]], -1)
        lower = torch.cat([t[..., :1], mids], -1)
        t = lower + (upper - lower) * torch.rand_like(t)
    return t


def sample_pdf(bins: Tensor, weights: Tensor, count: int, deterministic: bool) -> Tensor:
    """Inverse-CDF samples from the piecewise-constant pdf ``weights`` over ``bins``.

    bins (R, M + 1) are bin edges, weights (R, M) >= 0; returns (R, count) depths,
    uniformly spread inside each bin in proportion to its weight. ``deterministic`` uses
    evenly spaced quantiles instead of random ones (NeRF's evaluation mode).
    """
    weights = weights + 1e-5  # an all-zero ray falls back to uniform sampling
    pdf = weights / weights.sum(-1, keepdim=True)
    cdf = torch.cat([torch.zeros_like(pdf[..., :1]), torch.cumsum(pdf, -1)], -1)
    cdf = cdf.clamp(max=1.0)
    shape = (*cdf.shape[:-1], count)
    if deterministic:
        u = torch.linspace(0.0, 1.0, count, dtype=cdf.dtype, device=cdf.device).expand(shape)
    else:
        u = torch.rand(shape, dtype=cdf.dtype, device=cdf.device)
    u = u.contiguous()
    above = torch.searchsorted(cdf.contiguous(), u, right=True)
    below = (above - 1).clamp(min=0)
    above = above.clamp(max=cdf.shape[-1] - 1)
    cdf_lo, cdf_hi = cdf.gather(-1, below), cdf.gather(-1, above)
    bin_lo, bin_hi = bins.gather(-1, below), bins.gather(-1, above)
    span = cdf_hi - cdf_lo
    span = torch.where(span < 1e-5, torch.ones_like(span), span)
    return bin_lo + (u - cdf_lo) / span * (bin_hi - bin_lo)


def ray_box_intersection(origins: Tensor, directions: Tensor, box: Tensor) -> tuple[Tensor, Tensor]:
    """Entry and exit distances (R,) of rays through the axis-aligned ``box`` (2, 3).

    A ray that misses the box gets entry >= exit.
    """
    tiny = torch.copysign(torch.full_like(directions, 1e-9), directions)
    safe = torch.where(directions.abs() < 1e-9, tiny, directions)
    inv = 1.0 / safe
    t0 = (box[0] - origins) * inv
    t1 = (box[1] - origins) * inv
    entry = torch.minimum(t0, t1).amax(-1)
    exit_ = torch.maximum(t0, t1).amin(-1)
    return entry, exit_
