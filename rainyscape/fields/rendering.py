"""Volume-rendering quadrature (NeRF, Max 1995) on samples laid out densely per ray.

A ray's samples are intervals [t_i, t_i + delta_i) of constant density sigma_i and colour
c_i. Then alpha_i = 1 - exp(-sigma_i delta_i), T_i = exp(-sum_{j<i} sigma_j delta_j) and
C = sum_i T_i alpha_i c_i, which is exact for piecewise-constant density and colour.
"""

from __future__ import annotations

from typing import Callable

import torch
from torch import Tensor

FAR_DELTA = 1e10  # the last NeRF sample reaches to infinity: it absorbs what light is left


def sample_deltas(t: Tensor, last: float | Tensor = FAR_DELTA) -> Tensor:
    """Interval lengths t_{i+1} - t_i, the last one ``last`` (NeRF: 1e10)."""
    last_t = torch.as_tensor(last, dtype=t.dtype, device=t.device).expand_as(t[..., :1])
    return torch.cat([t[..., 1:] - t[..., :-1], last_t], -1)


def compositing_weights(sigma: Tensor, deltas: Tensor) -> tuple[Tensor, Tensor]:
    """Weights T_i alpha_i and transmittance T_i (both (..., N)) from densities and lengths."""
    optical = sigma * deltas
    alpha = 1.0 - torch.exp(-optical)
    # Exclusive cumulative sum (not cumsum - optical: the 1e10 last interval would swamp it).
    before = torch.cat([torch.zeros_like(optical[..., :1]), torch.cumsum(optical[..., :-1], -1)], -1)
    transmittance = torch.exp(-before)
    return transmittance * alpha, transmittance


def densities_until_opaque(live: Tensor, deltas: Tensor, density: Callable[[Tensor, Tensor], Tensor],
                           threshold: float, chunk: int = 32) -> tuple[Tensor, Tensor]:
    """Densities (R, N) of the ``live`` samples (R, N), evaluated front to back ``chunk``
    samples at a time, and which were evaluated (R, N); ``density(rays, samples)`` gives them
    at index pairs. A ray is no longer evaluated once its transmittance past a chunk is below
    ``threshold``: the samples behind stay 0. Up to there the densities, so the transmittance
    of :func:`compositing_weights`, are those of evaluating every live sample (the optical
    depth is summed sample by sample in the same order); behind it no sample passes the
    threshold either way. Occluded space costs nothing then: behind a surface most of a ray's
    live samples lie in space no view has carved."""
    sigma = torch.zeros(live.shape, dtype=deltas.dtype, device=deltas.device)
    evaluated = torch.zeros_like(live)
    active = torch.ones(live.shape[0], dtype=torch.bool, device=live.device)
    before = torch.zeros(live.shape[0], dtype=deltas.dtype, device=deltas.device)  # optical depth so far
    for start in range(0, live.shape[1], chunk):
        end = min(start + chunk, live.shape[1])
        evaluated[:, start:end] = live[:, start:end] & active[:, None]
        rays, cols = evaluated[:, start:end].nonzero(as_tuple=True)
        if len(rays):
            sigma[rays, cols + start] = density(rays, cols + start)
        if end == live.shape[1]:
            break
        optical = sigma[:, start:end] * deltas[:, start:end]
        before = torch.cumsum(torch.cat([before[:, None], optical], -1), -1)[:, -1]
        active &= torch.exp(-before) > threshold
        if not bool(active.any()):
            break
    return sigma, evaluated


def composite(weights: Tensor, values: Tensor) -> Tensor:
    """sum_i w_i v_i: (..., N) weights with (..., N, C) values -> (..., C)."""
    return (weights[..., None] * values).sum(-2)


def near_gradient_scale(distance: Tensor, reference: float) -> Tensor:
    """Per-sample gradient scale (d / reference)^2, at most 1 (Philip and Deschaintre, "Floaters
    No More", 2023): space close to a camera is seen by few pixels of few views, so its
    samples get outsized gradients per volume and grow floaters there."""
    return (distance / reference).square().clamp(max=1.0)


def scale_gradient(x: Tensor, scale: Tensor) -> Tensor:
    """``x`` unchanged in the forward pass; its gradient multiplied by ``scale`` (broadcast)."""
    return x.detach() + (x - x.detach()) * scale  # exactly x: x - x.detach() is 0
