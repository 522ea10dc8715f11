"""Langevin dynamics on latent variables (the paper's latent update, Algorithm 1)."""

from __future__ import annotations

import torch
from torch import Tensor


@torch.no_grad()
def langevin_step(latents: list[Tensor], grads: list[Tensor | None], step: float,
                  prior_var: float, noise: bool, generator: torch.Generator | None = None) -> None:
    """In place: x <- x - step^2 / 2 * (grad E(x) + x / prior_var) [+ step * N(0, 1)].

    The x / prior_var term is the gradient of a N(0, prior_var) prior, so with no data
    gradient the latents shrink towards 0 and the noise keeps them spread (step 0.03 and
    prior 50 are the authors' values).
    """
    for x, g in zip(latents, grads):
        drift = x / prior_var if g is None else g + x / prior_var
        x.sub_(0.5 * step * step * drift)
        if noise:
            n = torch.randn(x.shape, generator=generator, device="cpu", dtype=x.dtype)
            x.add_(step * n.to(x.device))
