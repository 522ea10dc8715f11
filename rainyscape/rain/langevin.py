"""Langevin dynamics on latent variables (the paper's latent update, Algorithm 1)."""

from __future__ import annotations

import torch
from torch import Tensor

from rainyscape.cameras import Window
from rainyscape.components import Energy


@torch.no_grad()
def langevin_step(latents: list[Tensor], grads: list[Tensor | None], step: float,
                  prior_var: float, noise: bool, generator: torch.Generator | None = None,
                  noise_scale: float = 1.0) -> None:
    """In place: x <- x - step^2 / 2 * (grad E(x) + x / prior_var) [+ noise_scale * step * N(0, 1)].

    The x / prior_var term is the gradient of a N(0, prior_var) prior, so with no data
    gradient the latents shrink towards 0 and the noise keeps them spread (step 0.03 and
    prior 50 are the authors' values).
    """
    for x, g in zip(latents, grads):
        drift = x / prior_var if g is None else g + x / prior_var
        x.sub_(0.5 * step * step * drift)
        if noise:
            n = torch.randn(x.shape, generator=generator, device="cpu", dtype=x.dtype)
            x.add_(noise_scale * step * n.to(x.device))


def langevin_update(latents: list[Tensor], predict, view_ids: Tensor, window: Window, energy: Energy,
                    generator: torch.Generator, steps: int, noise_steps: int, step: float,
                    prior_var: float, patch_size: int = 0, noise_scale: float = 1.0) -> None:
    """``steps`` Langevin steps of ``latents`` on ``energy(window, predict(view_ids, window))``,
    the first ``noise_steps`` with noise; with ``patch_size`` on a random crop of ``window``
    (a whole-view batch would make each step a whole-view prediction)."""
    if not latents or steps <= 0:
        return
    if 0 < patch_size < max(window.width, window.height):
        window = window.random_subwindow(patch_size, generator)
    for k in range(steps):
        value = energy(window, predict(view_ids, window))
        grads = torch.autograd.grad(value, latents, allow_unused=True)
        langevin_step(latents, list(grads), step, prior_var, noise=k < noise_steps, generator=generator,
                      noise_scale=noise_scale)
