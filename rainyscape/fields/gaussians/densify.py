"""Densification strategies: how the set of Gaussians changes during training (gsplat's
strategy objects, over the parameter surgery of ``ops.py``).

:class:`DefaultStrategy` is the adaptive density control of 3DGS (Kerbl et al. 2023): clone,
split, prune, opacity reset. The policy and its defaults are the paper's (and gsplat's
``DefaultStrategy``'s); the schedule is the paper's 30k-step one scaled to the run length.
``mcmc.py`` holds the other strategy (3DGS as Markov chain Monte Carlo).

Why not gsplat's ``DefaultStrategy`` itself: gsplat is an optional CUDA extra here, and
its strategy (checked on 1.5.3) never resets opacities (``step % reset_every == 0 & step
> 0`` parses as a chained comparison that is always false), normalises image-plane
gradients for full-image renders (we train on patches), and reads a ``radii`` layout that
changed between 1.4 and 1.5.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor, nn

from rainyscape.components import RenderOutput, TrainState
from rainyscape.fields.gaussians import ops


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


class Strategy:
    """How the Gaussians change during training. The field's training callback calls
    :meth:`observe` after each backward pass and :meth:`refine` after each optimiser step;
    :meth:`regularisation` adds loss terms of the strategy's own."""

    def observe(self, state: TrainState, output: RenderOutput) -> None: ...

    def refine(self, state: TrainState, params: nn.ParameterDict) -> dict[str, int]:
        """Change the Gaussians (and their optimisers' state) if this step calls for it;
        returns the counts of what changed ({} when nothing did)."""
        return {}

    def regularisation(self, params: nn.ParameterDict) -> dict[str, Tensor]:
        return {}

    def state_dict(self) -> dict:
        return {}

    def load_state_dict(self, state: dict) -> None: ...


def mean_grad2d_statistic(output: RenderOutput, absgrad: bool = False) -> tuple[Tensor, Tensor] | None:
    """The 3DGS densification statistic of one batch: per camera and Gaussian, the norm of
    the 2D mean's gradient in the NDC of one full image with a per-image mean loss (C, N),
    and where each Gaussian was visible (C, N); None when the render carried no gradient.
    ``absgrad``: of its absolute gradient instead (AbsGS; rendered with ``absgrad=True``)."""
    means2d = output.extras.get("means2d")
    if means2d is None or means2d.grad is None:
        return None
    grad = getattr(means2d, "absgrad", None) if absgrad else means2d.grad
    if grad is None:
        return None
    (width, height), (w, h) = output.extras["image_size"], output.extras["window_size"]
    # Pixel gradients of a batch of C windows with a mean loss -> the 3DGS statistic.
    area = means2d.shape[0] * w * h / (width * height)
    scale = torch.tensor([width / 2 * area, height / 2 * area], device=means2d.device)
    visible = (output.extras["radii"] > 0).all(-1)
    return (grad * scale).norm(dim=-1) * visible, visible


def ramped_cap(cap: int, progress: float, ramp: float) -> int:
    """The Gaussians allowed at ``progress`` (completed steps / the densification window's
    stop) when the cap ``cap`` rises in proportion over the first ``ramp`` of the window
    (0: the whole cap from the start; a cap of 0 stays none). The count then grows over the
    window, as the uncapped 3DGS schedule grows it, instead of filling the cap from the
    gradients of its first refinements (in a rain method, before its rain head starts)."""
    if cap <= 0 or ramp <= 0:
        return cap
    return int(cap * min(1.0, progress / ramp))


class DefaultStrategy(Strategy):
    """3DGS's adaptive density control: clone small and split large Gaussians whose mean
    image-plane gradient is high, prune transparent (and, after the first opacity reset,
    large) ones, reset opacities periodically; at most ``max_gaussians`` (0: no cap), or, with
    ``cap_ramp`` above 0, at most the cap's share that :func:`ramped_cap` allows at the step."""

    def __init__(self, schedule, grow_grad2d: float, grow_scale3d: float, prune_opacity: float,
                 prune_scale3d: float, max_gaussians: int, scene_extent: float, cap_ramp: float = 0.0):
        self.schedule = schedule  # max_iters -> DensifySchedule
        self.grow_grad2d = grow_grad2d
        self.grow_scale3d = grow_scale3d
        self.prune_opacity = prune_opacity
        self.prune_scale3d = prune_scale3d
        self.max_gaussians = max_gaussians
        self.cap_ramp = cap_ramp
        self.extent = scene_extent
        self.grad2d: Tensor | None = None  # (N,) sum of per-view gradient norms
        self.count: Tensor | None = None  # (N,) views in which each Gaussian was visible

    def _ensure(self, n: int, device) -> None:
        if self.grad2d is None or len(self.grad2d) != n:
            self.grad2d = torch.zeros(n, device=device)
            self.count = torch.zeros(n, device=device)

    def observe(self, state: TrainState, output: RenderOutput) -> None:
        if state.step + 1 >= self.schedule(state.max_iters).stop:
            return
        stat = mean_grad2d_statistic(output)
        if stat is not None:
            self.accumulate(*stat)

    @torch.no_grad()
    def accumulate(self, norms: Tensor, visible: Tensor) -> None:
        """Add one batch's statistic (C, N) and visibility (C, N)."""
        self._ensure(norms.shape[1], norms.device)
        self.grad2d += norms.sum(0).to(self.grad2d)
        self.count += visible.sum(0).to(self.count)

    def reset_stats(self) -> None:
        """Start a new accumulation window (sized at the next :meth:`accumulate`)."""
        self.grad2d = self.count = None

    def refine(self, state: TrainState, params: nn.ParameterDict) -> dict[str, int]:
        sched = self.schedule(state.max_iters)
        it = state.step + 1
        if it >= sched.stop:
            return {}
        events: dict[str, int] = {}
        if sched.refines_at(it):
            cap = ramped_cap(self.max_gaussians, it / sched.stop, self.cap_ramp)
            n_clone, n_split = self.grow(params, state.optimizers, cap)
            n_prune = self.prune(params, state.optimizers, prune_large=it > sched.reset_every)
            self.reset_stats()
            events.update(refinements=1, cloned=n_clone, split=n_split, pruned=n_prune)
        if sched.resets_at(it):
            self.reset_opacity(params, state.optimizers, 2 * self.prune_opacity)
            events["opacity_resets"] = 1
        return events

    @torch.no_grad()
    def grow(self, params: nn.ParameterDict, optimizers: dict, cap: int | None = None) -> tuple[int, int]:
        """Clone small and split large Gaussians whose mean gradient exceeds the threshold.

        Returns (cloned, split). Splitting replaces one Gaussian by two samples from it
        with scales / 1.6. Under a cap (``cap``, else ``max_gaussians``; 0: none), only the
        highest-gradient candidates that fit are grown."""
        cap = self.max_gaussians if cap is None else cap
        n = params["means"].shape[0]
        if self.grad2d is None or len(self.grad2d) != n:
            return 0, 0
        avg = self.grad2d / self.count.clamp_min(1)
        high = avg > self.grow_grad2d
        if cap > 0:
            room = max(cap - n, 0)
            if int(high.sum()) > room:
                chosen = torch.topk(torch.where(high, avg, -1.0), room).indices
                high = torch.zeros_like(high)
                high[chosen] = True
        small = params["scales"].exp().amax(-1) <= self.grow_scale3d * self.extent
        clone, split = high & small, high & ~small
        n_clone, n_split = int(clone.sum()), int(split.sum())
        if n_clone + n_split == 0:
            return 0, 0
        children = ops.split_samples(params, split.nonzero().squeeze(1))
        new = {name: torch.cat([p[clone], children[name]]) for name, p in params.items()}
        ops.append(params, optimizers, ~split, new)
        return n_clone, n_split

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
            ops.remove(params, optimizers, drop)
        return n_drop

    @torch.no_grad()
    def reset_opacity(self, params: nn.ParameterDict, optimizers: dict, value: float) -> None:
        """Clamp every opacity to at most ``value``; its Adam moments restart from zero."""
        ops.cap_opacity(params, optimizers, value)

    def state_dict(self) -> dict:
        return {"grad2d": self.grad2d, "count": self.count}

    def load_state_dict(self, state: dict) -> None:
        self.grad2d, self.count = state.get("grad2d"), state.get("count")
