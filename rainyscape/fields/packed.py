"""Volume rendering on packed samples: rows sorted by ray, any number of samples per ray.

The quadrature is NeRF's, C = sum_i T_i (1 - exp(-sigma_i delta_i)) c_i with
T_i = exp(-sum_{j<i} sigma_j delta_j), computed per ray with one cumulative sum over all
rows minus each ray's offset (in float64: the running sum over a whole batch is large next
to one ray's part of it). The distortion loss is mip-NeRF 360's, in its linear-time form.
"""

from __future__ import annotations

import torch
from torch import Tensor


def ray_starts(ray: Tensor, n_rays: int) -> Tensor:
    """Index (S,) of the first row of each row's ray, for rows sorted by ray."""
    counts = torch.bincount(ray, minlength=n_rays)
    first = torch.cumsum(counts, 0) - counts
    return first[ray]


def exclusive_cumsum(x: Tensor, starts: Tensor) -> Tensor:
    """Per-ray sum of the rows before each row (float64)."""
    x = x.double()
    before = torch.cumsum(x, 0) - x
    return before - before[starts]


def ray_sum(x: Tensor, ray: Tensor, n_rays: int) -> Tensor:
    """Per-ray sum (R, ...) of rows (S, ...)."""
    out = torch.zeros((n_rays, *x.shape[1:]), dtype=x.dtype, device=x.device)
    return out.index_add(0, ray, x)


def packed_weights(sigma: Tensor, deltas: Tensor, ray: Tensor, n_rays: int,
                   starts: Tensor | None = None) -> tuple[Tensor, Tensor, Tensor]:
    """Weights T_i alpha_i and transmittance T_i (S,) of packed samples, and the light left
    behind each ray's last sample (R,)."""
    starts = ray_starts(ray, n_rays) if starts is None else starts
    optical = sigma * deltas
    # A ray's last row never lies in front of one of its own: left out of the running sum,
    # its interval (NeRF's last one is 1e10 long) does not swamp the rays after it.
    last = torch.ones_like(ray, dtype=torch.bool)
    last[:-1] = ray[1:] != ray[:-1]
    before = exclusive_cumsum(torch.where(last, torch.zeros_like(optical), optical), starts)
    transmittance = torch.exp(-before).to(sigma.dtype)
    weights = transmittance * (1.0 - torch.exp(-optical))
    left = torch.exp(-ray_sum(optical.double(), ray, n_rays)).to(sigma.dtype)
    return weights, transmittance, left


def distortion(weights: Tensor, s0: Tensor, s1: Tensor, ray: Tensor, n_rays: int,
               starts: Tensor | None = None) -> Tensor:
    """mip-NeRF 360's distortion loss per ray (R,): sum_ij w_i w_j |m_i - m_j| + 1/3 sum_i
    w_i^2 (s1_i - s0_i) over intervals [s0, s1] of a normalised ray coordinate (midpoints m).

    The double sum is 2 sum_i w_i (m_i W_i - (wm)_i) with W_i, (wm)_i the sums of w and w m
    over the samples before i (samples sorted along the ray).
    """
    starts = ray_starts(ray, n_rays) if starts is None else starts
    mid = 0.5 * (s0 + s1)
    w_before = exclusive_cumsum(weights, starts).to(weights.dtype)
    wm_before = exclusive_cumsum(weights * mid, starts).to(weights.dtype)
    pairs = 2.0 * weights * (mid * w_before - wm_before)
    self_term = weights ** 2 * (s1 - s0) / 3.0
    return ray_sum(pairs + self_term, ray, n_rays)


def front_weight(weights: Tensor, distance: Tensor, ray: Tensor, n_rays: int,
                 starts: Tensor | None = None, margin: float = 0.1) -> Tensor:
    """Per ray (R,): the weight of its samples nearer than ``1 - margin`` times its median
    depth (the first sample where half its weight is reached; a floater short of half does
    not move it), with the gradient into every weight. Rows sorted by ray, then distance."""
    starts = ray_starts(ray, n_rays) if starts is None else starts
    with torch.no_grad():
        w = weights.double()
        cum = exclusive_cumsum(w, starts) + w
        below = (cum < 0.5 * ray_sum(w, ray, n_rays)[ray]).long()
        last = starts + torch.bincount(ray, minlength=n_rays)[ray] - 1
        median = distance[torch.minimum(starts + ray_sum(below, ray, n_rays)[ray], last)]
    return ray_sum(weights * (distance < (1.0 - margin) * median), ray, n_rays)
