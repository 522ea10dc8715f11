"""3D Gaussian Splatting as Markov chain Monte Carlo (Kheradmand et al. 2024), as a
densification strategy.

The Gaussians are samples of the scene's distribution: instead of cloning and splitting by
gradient, the strategy

- relocates dead Gaussians (opacity at most ``min_opacity``) onto live ones drawn in
  proportion to their opacity, and adds new ones the same way (``grow_rate`` more per
  refinement, up to ``cap``), rescaling the source and its copies so that together they
  render as the source did (:func:`relocated_opacity_scale`, the paper's Eq. 9-10);
- nudges every Gaussian's mean by noise shaped like its own covariance, strong for nearly
  transparent ones and vanishing for opaque ones (stochastic gradient Langevin dynamics);
- regularises opacities and scales (L1), so that unneeded Gaussians fade and get relocated.

The count never exceeds ``cap``, so a run's cost is known from its first step: what a CPU
budget needs. gsplat's ``MCMCStrategy`` has the same policy and defaults (read, not copied).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn

from rainyscape.components import TrainState
from rainyscape.fields.gaussians import ops
from rainyscape.fields.gaussians.densify import Strategy
from rainyscape.fields.gaussians.projection import covariance_factor

MAX_COPIES = 51  # a Gaussian shared by more copies than this is treated as this many


def relocated_opacity_scale(opacity: Tensor, scale: Tensor, copies: Tensor) -> tuple[Tensor, Tensor]:
    """Opacity and (linear) scale of each of ``copies`` (N,) Gaussians that together replace one
    of ``opacity`` (N,) and ``scale`` (N, 3) so that their composite matches it along any ray:

    o' = 1 - (1 - o)^(1/n),   s' = s * o / sum_{i=1..n} sum_{k=0..i-1} C(i-1, k) (-1)^k o'^(k+1) / sqrt(k+1)."""
    n = copies.clamp(1, MAX_COPIES).to(opacity.dtype)
    new_o = 1.0 - (1.0 - opacity).clamp_min(1e-12) ** (1.0 / n)
    k = torch.arange(MAX_COPIES, dtype=opacity.dtype, device=opacity.device)
    i = k[:, None]  # i - 1 in 0..MAX_COPIES-1, k in 0..i-1
    binom = torch.exp(torch.lgamma(i + 1) - torch.lgamma(k + 1) - torch.lgamma((i - k).clamp_min(0) + 1))
    signed = torch.where(k <= i, binom * (-1.0) ** k, torch.zeros_like(binom))  # (i, k)
    powers = new_o[:, None] ** (k + 1) / torch.sqrt(k + 1)  # (N, k)
    per_i = powers @ signed.T  # (N, i): the inner sum for each i
    used = (i[:, 0] < n[:, None]).to(opacity.dtype)  # i - 1 < n
    denom = (per_i * used).sum(-1)
    return new_o, scale * (opacity / denom.clamp_min(1e-12))[:, None]


class MCMCStrategy(Strategy):
    """Relocate dead Gaussians and add new ones every ``every`` steps from ``start`` to
    ``stop`` (fractions of the run via ``schedule``); noise and regularisation every step."""

    def __init__(self, schedule, cap: int, min_opacity: float = 0.005, grow_rate: float = 0.05,
                 noise_lr: float = 5e5, opacity_reg: float = 0.01, scale_reg: float = 0.01):
        self.schedule = schedule  # max_iters -> DensifySchedule (start, stop, every)
        self.cap = cap
        self.min_opacity = min_opacity
        self.grow_rate = grow_rate
        self.noise_lr = noise_lr
        self.opacity_reg = opacity_reg
        self.scale_reg = scale_reg

    def regularisation(self, params: nn.ParameterDict) -> dict[str, Tensor]:
        out = {}
        if self.opacity_reg > 0:
            out["opacity_reg"] = self.opacity_reg * torch.sigmoid(params["opacities"]).mean()
        if self.scale_reg > 0:
            out["scale_reg"] = self.scale_reg * params["scales"].exp().mean()
        return out

    def refine(self, state: TrainState, params: nn.ParameterDict) -> dict[str, int]:
        sched = self.schedule(state.max_iters)
        it = state.step + 1
        events: dict[str, int] = {}
        if sched.start < it < sched.stop and it % sched.every == 0:
            events = {"refinements": 1, "relocated": self.relocate(params, state.optimizers),
                      "added": self.add(params, state.optimizers)}
        self.inject_noise(params, float(state.optimizers["means"].param_groups[0]["lr"]))
        return events

    @staticmethod
    def _sample(opacity: Tensor, count: int) -> Tensor:
        """``count`` Gaussians drawn with replacement in proportion to their opacity."""
        return torch.multinomial(opacity.clamp_min(1e-12), count, replacement=True)

    @torch.no_grad()
    def _copies(self, params: nn.ParameterDict, optimizers: dict, sources: Tensor) -> dict[str, Tensor]:
        """Share each drawn source's opacity and size among it and its copies (the sources are
        updated in place, their moments restarted); returns every parameter of one copy per row
        of ``sources``."""
        n = params["means"].shape[0]
        extra = torch.bincount(sources, minlength=n)
        unique = extra.nonzero().squeeze(1)
        opacity = torch.sigmoid(params["opacities"][unique])
        new_o, new_s = relocated_opacity_scale(opacity, params["scales"][unique].exp(), extra[unique] + 1)
        new_o = new_o.clamp(self.min_opacity, 1.0 - 1e-6)
        updated = {name: p[unique].clone() for name, p in params.items()}
        updated["opacities"] = torch.log(new_o / (1.0 - new_o))
        updated["scales"] = torch.log(new_s.clamp_min(1e-12))
        lookup = torch.full((n,), -1, dtype=torch.long, device=sources.device)
        lookup[unique] = torch.arange(len(unique), device=sources.device)
        copies = {name: v[lookup[sources]] for name, v in updated.items()}
        ops.overwrite(params, optimizers, unique, updated)
        return copies

    @torch.no_grad()
    def relocate(self, params: nn.ParameterDict, optimizers: dict) -> int:
        """Move dead Gaussians onto live ones (drawn by opacity); returns how many moved."""
        opacity = torch.sigmoid(params["opacities"])
        dead = opacity <= self.min_opacity
        n_dead = int(dead.sum())
        alive = (~dead).nonzero().squeeze(1)
        if n_dead == 0 or len(alive) == 0:
            return 0
        sources = alive[self._sample(opacity[alive], n_dead)]
        copies = self._copies(params, optimizers, sources)
        ops.overwrite(params, optimizers, dead.nonzero().squeeze(1), copies)
        return n_dead

    @torch.no_grad()
    def add(self, params: nn.ParameterDict, optimizers: dict) -> int:
        """Add ``grow_rate`` more Gaussians (up to ``cap``), drawn by opacity; returns how many."""
        n = params["means"].shape[0]
        count = max(0, min(self.cap, int(math.floor((1.0 + self.grow_rate) * n))) - n)
        if count == 0:
            return 0
        sources = self._sample(torch.sigmoid(params["opacities"]), count)
        copies = self._copies(params, optimizers, sources)
        keep = torch.ones(n, dtype=torch.bool, device=sources.device)
        ops.append(params, optimizers, keep, copies)
        return count

    @torch.no_grad()
    def inject_noise(self, params: nn.ParameterDict, lr_means: float) -> None:
        """Move each mean by Sigma eps (its covariance times standard normal noise), times
        ``noise_lr`` x the means' learning rate, gated to the nearly transparent Gaussians
        (a steep sigmoid of 1 - opacity around 1 - min_opacity)."""
        opacity = torch.sigmoid(params["opacities"])
        gate = torch.sigmoid(100.0 * ((1.0 - opacity) - (1.0 - self.min_opacity)))
        factor = covariance_factor(params["quats"], params["scales"].exp())
        covariance = factor @ factor.transpose(1, 2)
        eps = torch.randn_like(params["means"])
        step = torch.einsum("nij,nj->ni", covariance, eps) * (gate * self.noise_lr * lr_means)[:, None]
        params["means"].add_(step)
