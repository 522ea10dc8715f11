"""DeSplat's adaptive density control of the per-view distractor Gaussians.

After each backward pass the norm of the 2D mean's absolute gradient (splatfacto's
statistic, which DeSplat's code uses; with ``absgrad=false`` the 3DGS net gradient) and
the largest screen radius of the rendered view's distractor Gaussians are accumulated. Every
``refine_every_views`` passes over the training views (DeSplat: 10, so each view has been
seen about ten times), until ``refine_stop`` of the run, each view's set is refined:
Gaussians larger on screen than ``split_screen`` x the image size are split in two (scales
/ 1.6), other ones whose mean gradient exceeds ``grow_grad2d`` are cloned, and those below
``cull_opacity`` or not seen since the last refinement are removed (DeSplat culls
transparent and invisible distractor Gaussians). Parameter surgery and the optimisers'
moments go through the Gaussian field's ``ops``.
"""

from __future__ import annotations

import torch
from torch import Tensor

from rainyscape.components import Callback, RenderOutput, TrainState
from rainyscape.fields.gaussians import ops
from rainyscape.fields.gaussians.densify import mean_grad2d_statistic


class DistractorDensify(Callback):
    """Per-view clone / split / cull of a :class:`DistractorGaussians` head's sets."""

    def __init__(self, head):
        self.head = head
        self.grad2d: dict[int, Tensor] = {}  # per view: (N,) summed gradient norms
        self.count: dict[int, Tensor] = {}  # per view: (N,) renders in which each was visible
        self.radius: dict[int, Tensor] = {}  # per view: (N,) largest screen radius (pixels)
        self.events = {"cloned": 0, "split": 0, "culled": 0}

    def _ensure(self, view: int, n: int, device) -> None:
        if view not in self.grad2d or len(self.grad2d[view]) != n:
            self.grad2d[view] = torch.zeros(n, device=device)
            self.count[view] = torch.zeros(n, device=device)
            self.radius[view] = torch.zeros(n, device=device)

    @torch.no_grad()
    def after_backward(self, state: TrainState, output: RenderOutput) -> None:
        for view, out, window_size in self.head.last:
            stats = RenderOutput(out.rgb, extras={"means2d": out.means2d, "radii": out.radii,
                                                  "image_size": (self.head.width, self.head.height),
                                                  "window_size": window_size})
            found = mean_grad2d_statistic(stats, absgrad=self.head.config.absgrad)
            if found is None:
                continue
            norms, visible = found
            self._ensure(view, norms.shape[1], norms.device)
            self.grad2d[view] += norms[0]
            self.count[view] += visible[0].to(self.count[view])
            self.radius[view] = torch.maximum(self.radius[view], out.radii[0].amax(-1).to(self.radius[view]))
        self.head.last = []

    def due(self, step: int, max_iters: int) -> bool:
        """Whether the sets are refined after completed step ``step`` + 1."""
        period = self.head.config.refine_every_views * len(self.head.views)
        it = step + 1
        return it % period == 0 and it <= self.head.config.refine_stop * max_iters

    def after_step(self, state: TrainState) -> None:
        if not self.due(state.step, state.max_iters):
            return
        optimizers = {a: state.optimizers[self.head.group_name(a)] for a in self.head.sets[str(self.head.views[0])]}
        for view in self.head.views:
            self.refine(view, optimizers)
        self.head.sync_param_groups()
        self.grad2d, self.count, self.radius = {}, {}, {}

    @torch.no_grad()
    def refine(self, view: int, optimizers: dict) -> None:
        """Grow, then cull, one view's distractor Gaussians."""
        c = self.head.config
        params = self.head.params_of(view)
        n = params["means"].shape[0]
        if view not in self.grad2d or len(self.grad2d[view]) != n:
            return  # not rendered since the last refinement
        avg = self.grad2d[view] / self.count[view].clamp_min(1)
        split = self.radius[view] > c.split_screen * max(self.head.width, self.head.height)
        clone = (avg > c.grow_grad2d) & ~split
        if c.max_per_view > 0:  # the highest gradients first, within the cap
            room = max(c.max_per_view - n, 0)
            grow = clone | split
            if int(grow.sum()) > room:
                keep = torch.topk(torch.where(grow, avg, -1.0), room).indices
                chosen = torch.zeros_like(grow)
                chosen[keep] = True
                clone, split = clone & chosen, split & chosen
        seen = self.count[view] > 0
        if bool(clone.any() | split.any()):
            children = ops.split_samples(params, split.nonzero().squeeze(1))
            new = {name: torch.cat([p[clone], children[name]]) for name, p in params.items()}
            ops.append(params, optimizers, ~split, new)
            # the survivors keep their visibility; clones and children are fresh (kept this time)
            seen = torch.cat([seen[~split], torch.ones(len(new["means"]), dtype=torch.bool, device=seen.device)])
        drop = (torch.sigmoid(params["opacities"]) < c.cull_opacity) | ~seen
        if bool(drop.all()):  # keep one (the rasteriser needs a Gaussian)
            drop[torch.argmax(params["opacities"])] = False
        if bool(drop.any()):
            ops.remove(params, optimizers, drop)
        self.events["cloned"] += int(clone.sum())
        self.events["split"] += int(split.sum())
        self.events["culled"] += int(drop.sum())

    def state_dict(self) -> dict:
        return {"grad2d": {str(k): v for k, v in self.grad2d.items()},
                "count": {str(k): v for k, v in self.count.items()},
                "radius": {str(k): v for k, v in self.radius.items()}, "events": dict(self.events)}

    def load_state_dict(self, state: dict) -> None:
        self.grad2d = {int(k): v for k, v in state.get("grad2d", {}).items()}
        self.count = {int(k): v for k, v in state.get("count", {}).items()}
        self.radius = {int(k): v for k, v in state.get("radius", {}).items()}
        self.events.update(state.get("events", {}))
