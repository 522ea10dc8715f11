"""Adaptive density control of 3DGS (Kerbl et al. 2023): clone, split, prune, opacity reset.

The policy and its defaults are the paper's (and gsplat's ``DefaultStrategy``'s); the
schedule is the paper's 30k-step one scaled to the run length. Every structural change
replaces the parameter tensors in place in the field's ``ParameterDict`` and carries the
Adam moments of surviving Gaussians over (new ones start at zero), so the trainer's
optimisers stay consistent.

Why not gsplat's ``DefaultStrategy`` itself: gsplat is an optional CUDA extra here, and
its strategy (checked on 1.5.3) never resets opacities (``step % reset_every == 0 & step
> 0`` parses as a chained comparison that is always false), normalises image-plane
gradients for full-image renders (we train on patches), and reads a ``radii`` layout that
changed between 1.4 and 1.5.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import torch
from torch import Tensor, nn

from rainyscape.fields.gaussians.projection import covariance_factor


@dataclass
class DensifySchedule:
    """Steps are 1-based counts of completed training steps, as in the 3DGS code."""

    start: int  # refine only after this many steps ...
    stop: int  # ... and up to this many (statistics and opacity resets stop too)
    every: int
    reset_every: int
    sh_every: int  # one more SH degree every this many steps

    def refines_at(self, it: int) -> bool:
        """Whether densification (grow + prune) runs after completed step ``it``."""
        return self.start < it < self.stop and it % self.every == 0

    def resets_at(self, it: int) -> bool:
        """Whether opacities are reset after completed step ``it``: every ``reset_every``
        steps, as long as a whole ``reset_every`` of densification follows before ``stop``
        (the densifier's time to recover; at the paper's 30k this is its 3k, 6k, 9k, 12k)."""
        return it % self.reset_every == 0 and it + self.reset_every <= self.stop

    def resets(self) -> list[int]:
        return [it for it in range(self.reset_every, self.stop, self.reset_every) if self.resets_at(it)]

    def sh_degree_at(self, step: int, max_degree: int) -> int:
        """The SH degree used at 0-based ``step``."""
        return min(max_degree, (step + 1) // self.sh_every)

    @staticmethod
    def scaled(max_iters: int, reference_iters: int, start: int, stop: int, every: int,
               reset_every: int, sh_every: int, min_reset_every: int = 0,
               min_every: int = 0, min_start: int = 0, min_sh_every: int = 0) -> "DensifySchedule":
        """The schedule given for a ``reference_iters`` run, stretched to ``max_iters``, with
        floors in steps where a fraction of a short run is too few steps.

        Opacity resets stay at least ``min_reset_every`` apart: after one, Adam needs a
        fixed number of steps (not a fraction of the run) to bring opacities back. For the
        same reason refinements stay at least ``min_every`` apart: new Gaussians need some
        steps to settle before their gradients say whether to split them again.
        ``min_start`` lets the initial Gaussians settle before the first refinement and
        ``min_sh_every`` keeps view-dependent colour from fitting before the geometry has
        formed. No floor moves the stop, which stays at its share of the run."""
        f = max_iters / reference_iters

        def s(x: int) -> int:
            return max(1, round(x * f))

        return DensifySchedule(max(s(start), min_start), s(stop), max(s(every), min_every),
                               max(s(reset_every), min_reset_every), max(s(sh_every), min_sh_every))


def replace_params(params: nn.ParameterDict, optimizers: dict[str, torch.optim.Optimizer],
                   new_value: Callable[[str, Tensor], Tensor],
                   new_state: Callable[[Tensor], Tensor], names: list[str] | None = None) -> None:
    """Swap each parameter for ``new_value(name, old)`` and map its Adam moments through
    ``new_state`` (the optimiser keyed by the parameter's name, one param group each)."""
    for name in names or list(params.keys()):
        old = params[name]
        new = nn.Parameter(new_value(name, old.detach()), requires_grad=old.requires_grad)
        params[name] = new
        opt = optimizers.get(name)
        if opt is None:
            continue
        state = opt.state.pop(old, None)
        opt.param_groups[0]["params"] = [new]
        if state:
            opt.state[new] = {k: (v if k == "step" else new_state(v)) for k, v in state.items()}


class Densifier:
    """Accumulates image-plane gradient statistics and grows / prunes Gaussians."""

    def __init__(self, grow_grad2d: float, grow_scale3d: float, prune_opacity: float,
                 prune_scale3d: float, max_gaussians: int, scene_extent: float):
        self.grow_grad2d = grow_grad2d
        self.grow_scale3d = grow_scale3d
        self.prune_opacity = prune_opacity
        self.prune_scale3d = prune_scale3d
        self.max_gaussians = max_gaussians
        self.extent = scene_extent
        self.grad2d: Tensor | None = None  # (N,) sum of per-view gradient norms
        self.count: Tensor | None = None  # (N,) views in which each Gaussian was visible

    def _ensure(self, n: int, device) -> None:
        if self.grad2d is None or len(self.grad2d) != n:
            self.grad2d = torch.zeros(n, device=device)
            self.count = torch.zeros(n, device=device)

    @torch.no_grad()
    def accumulate(self, means2d_grad: Tensor, radii: Tensor, scale_xy: Tensor) -> None:
        """Add one batch: ``means2d_grad`` (C, N, 2) in window pixels, ``radii`` (C, N, 2).

        ``scale_xy`` turns pixel gradients into the 3DGS statistic (normalised device
        coordinates of a full-image render with a per-image mean loss)."""
        self._ensure(means2d_grad.shape[1], means2d_grad.device)
        visible = (radii > 0).all(-1)  # (C, N)
        norms = (means2d_grad * scale_xy).norm(dim=-1) * visible
        self.grad2d += norms.sum(0).to(self.grad2d)
        self.count += visible.sum(0).to(self.count)

    def reset_stats(self) -> None:
        """Start a new accumulation window (sized at the next :meth:`accumulate`)."""
        self.grad2d = self.count = None

    @torch.no_grad()
    def grow(self, params: nn.ParameterDict, optimizers: dict) -> tuple[int, int]:
        """Clone small and split large Gaussians whose mean gradient exceeds the threshold.

        Returns (cloned, split). Splitting replaces one Gaussian by two samples from it
        with scales / 1.6. With ``max_gaussians`` set, only the highest-gradient
        candidates that fit are grown."""
        n = params["means"].shape[0]
        if self.grad2d is None or len(self.grad2d) != n:
            return 0, 0
        avg = self.grad2d / self.count.clamp_min(1)
        high = avg > self.grow_grad2d
        if self.max_gaussians > 0:
            room = max(self.max_gaussians - n, 0)
            if int(high.sum()) > room:
                chosen = torch.topk(torch.where(high, avg, -1.0), room).indices
                high = torch.zeros_like(high)
                high[chosen] = True
        small = params["scales"].exp().amax(-1) <= self.grow_scale3d * self.extent
        clone, split = high & small, high & ~small
        n_clone, n_split = int(clone.sum()), int(split.sum())
        if n_clone + n_split == 0:
            return 0, 0
        children = self._split_children(params, split)
        keep = ~split

        def value(name: str, p: Tensor) -> Tensor:
            return torch.cat([p[keep], p[clone], children.get(name, p[split].repeat_interleave(2, 0))])

        def state(v: Tensor) -> Tensor:
            fresh = torch.zeros((n_clone + 2 * n_split, *v.shape[1:]), device=v.device, dtype=v.dtype)
            return torch.cat([v[keep], fresh])

        replace_params(params, optimizers, value, state)
        return n_clone, n_split

    @staticmethod
    def _split_children(params: nn.ParameterDict, split: Tensor) -> dict[str, Tensor]:
        """Two samples per split Gaussian: positions drawn from it, scales / 1.6."""
        scales = params["scales"][split].exp()
        factor = covariance_factor(params["quats"][split], scales)  # (S, 3, 3)
        noise = torch.randn(len(scales), 2, 3, device=scales.device, dtype=scales.dtype)
        offsets = torch.einsum("sij,skj->ski", factor, noise)
        means = (params["means"][split][:, None] + offsets).reshape(-1, 3)
        return {"means": means,
                "scales": torch.log(scales / 1.6).repeat_interleave(2, 0)}

    @torch.no_grad()
    def prune(self, params: nn.ParameterDict, optimizers: dict, prune_large: bool) -> int:
        """Remove nearly transparent Gaussians (and, with ``prune_large``, ones larger than
        ``prune_scale3d`` x the scene extent); always keeps at least one."""
        drop = torch.sigmoid(params["opacities"]) < self.prune_opacity
        if prune_large:
            drop |= params["scales"].exp().amax(-1) > self.prune_scale3d * self.extent
        if bool(drop.all()):
            drop[torch.argmax(params["opacities"])] = False
        n_drop = int(drop.sum())
        if n_drop:
            keep = ~drop
            replace_params(params, optimizers, lambda name, p: p[keep], lambda v: v[keep])
        return n_drop

    @torch.no_grad()
    def reset_opacity(self, params: nn.ParameterDict, optimizers: dict, value: float) -> None:
        """Clamp every opacity to at most ``value``; its Adam moments restart from zero."""
        cap = float(torch.logit(torch.tensor(value)))
        replace_params(params, optimizers, lambda name, p: p.clamp(max=cap), torch.zeros_like,
                       names=["opacities"])

    def state_dict(self) -> dict:
        return {"grad2d": self.grad2d, "count": self.count}

    def load_state_dict(self, state: dict) -> None:
        self.grad2d, self.count = state.get("grad2d"), state.get("count")
