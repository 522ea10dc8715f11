"""Dense reference compositor: every pixel against every Gaussian, plain autograd.

The tiled rasteriser must reproduce it exactly (tests) and is measured against it
(benchmarks). Same per-pixel rules: depth order, alpha = min(0.999, o exp(-sigma)),
alpha < 1/255 skipped, stop before transmittance reaches 1e-4. No tiles, no bounding
boxes: only Gaussians outside the depth range are left out.
"""

from __future__ import annotations

import torch
from torch import Tensor

from rainyscape.fields.gaussians.projection import ALPHA_THRESHOLD, Projection
from rainyscape.fields.gaussians.rasterize_torch import MAX_ALPHA, T_MIN


def composite_pixels(mean: Tensor, conic: Tensor, opac: Tensor, feat: Tensor,
                      px: Tensor, py: Tensor) -> tuple[Tensor, Tensor]:
    """Depth-sorted Gaussians (V, ...) at pixel centres (P,): features (P, D), alpha (P,)."""
    dx = mean[:, 0, None] - px[None]
    dy = mean[:, 1, None] - py[None]
    sigma = 0.5 * conic[:, 0, None] * dx ** 2 + conic[:, 1, None] * dx * dy \
        + 0.5 * conic[:, 2, None] * dy ** 2
    raw = opac[:, None] * torch.exp(-sigma.clamp(max=20.0))  # no denormals; all far below 1/255
    alpha = raw.clamp(max=MAX_ALPHA) * (raw > ALPHA_THRESHOLD)
    t_incl = torch.cumprod(1.0 - alpha, 0)
    t_excl = torch.cat([torch.ones_like(t_incl[:1]), t_incl[:-1]], 0)
    weight = alpha * t_excl * (t_incl > T_MIN)
    return weight.T @ feat, weight.sum(0)


def composite_dense(proj: Projection, features: Tensor, width: int, height: int,
                    near_plane: float = 0.01, far_plane: float = 1e10,
                    pixel_chunk: int = 1 << 14) -> tuple[Tensor, Tensor]:
    """Same outputs as :func:`rasterize_torch.composite`: (C, h, w, D) and (C, h, w, 1)."""
    dev, dt = proj.means2d.device, proj.means2d.dtype
    ii, jj = torch.meshgrid(torch.arange(height, device=dev), torch.arange(width, device=dev),
                            indexing="ij")
    px, py = jj.reshape(-1).to(dt) + 0.5, ii.reshape(-1).to(dt) + 0.5
    feats, alphas = [], []
    for c in range(proj.means2d.shape[0]):
        z = proj.depths[c]
        idx = ((z > near_plane) & (z < far_plane)).nonzero().squeeze(1)
        idx = idx[torch.argsort(z.detach()[idx], stable=True)]
        parts = [composite_pixels(proj.means2d[c, idx], proj.conics[c, idx],
                                   proj.opacities[c, idx], features[c, idx], x, y)
                 for x, y in zip(px.split(pixel_chunk), py.split(pixel_chunk))]
        feats.append(torch.cat([p[0] for p in parts]).reshape(height, width, -1))
        alphas.append(torch.cat([p[1] for p in parts]).reshape(height, width, 1))
    return torch.stack(feats), torch.stack(alphas)
