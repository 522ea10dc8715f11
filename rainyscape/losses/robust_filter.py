"""SpotLessSplats' RobustFilter (Sabour, Goli et al. 2024): the weight-free robust loss of
``robust-3dgs``.

1. residual: the per-pixel absolute error averaged over the colour channels;
2. threshold: the ``percentile`` (0.7) of the errors seen so far, read from a running
   histogram (``bins`` bins over [0, 1], each step's histogram added to the old one times
   ``decay`` = 0.95); 1.0 (every pixel inlier) before the first step. The authors' code
   histograms the error's per-*column* means (a mean over the image rows, which puts the
   threshold near the mean error); that is the default here (``statistic="column"``), as it
   produced the published figures; ``"pixel"`` histograms the per-pixel residuals instead,
   as the method is described (on crossroad-traffic 1 dB lower: docs/benchmarks.md);
3. mask: a pixel is an inlier when its residual is below the threshold, or when more than
   half of its 3 x 3 neighbourhood is (zero padding at the border). That rule is kept as
   published; it also relabels thin outliers as inliers: a 1 px wide rain streak has at most
   3 of 9 neighbours in it, so its pixels become "clean" and train (docs/evaluation.md);
4. blend-in: the mask is drawn as Bernoulli(a + (1 - a) mask) with a = exp(beta floor((1 +
   step) / 1.5)), beta = -3e-3, in steps whatever the run's length (the scene is fitted at
   the same pace in a short run): at first every pixel trains;
5. loss: the masked L1 over every pixel (no D-SSIM: SpotLessSplats sets its weight to 0).

Its schedule changes to 3DGS go with it: no opacity resets (the method's field options), and
the view-dependent colour (``reset_group``, SH degrees above 0) is clamped to at most
``reset_max`` once, at ``reset_at`` of a ``reference_iters`` (30k) run stretched to the run,
as the 3DGS schedule is, its Adam moments restarted (:class:`ParamReset`, a callback of this
term). Settings and the order of operations follow the authors' public code (SpotLessSplats
``spotless_trainer.py``, also gsplat PR #304); no code is taken from it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import torch
from torch import Tensor

from rainyscape.components import Callback, Loss, LossContext, TrainState
from rainyscape.config.schema import bounded
from rainyscape.errors import ConfigError
from rainyscape.imaging.metrics import ssim_map
from rainyscape.losses.robust import neighbourhood_inliers


def absolute_residuals(rendered: Tensor, target: Tensor) -> Tensor:
    """Per-pixel residual (B, 1, h, w): the absolute error averaged over the channels."""
    return (rendered - target).abs().mean(dim=1, keepdim=True)


def residual_histogram(residuals: Tensor, bins: int) -> Tensor:
    """Counts (bins,) of residuals in ``bins`` equal bins over [0, 1] (larger ones in the last)."""
    return torch.histc(residuals.detach().float().clamp(0.0, 1.0).cpu(), bins=bins, min=0.0, max=1.0)


def histogram_percentile(hist: Tensor, q: float) -> float:
    """The left edge of the first bin at which the cumulative count reaches ``q`` of the total
    (SpotLessSplats' threshold); 1.0 for an empty histogram."""
    total = float(hist.sum())
    if total <= 0:
        return 1.0
    reached = torch.nonzero(torch.cumsum(hist.double(), 0) >= q * total)
    return float(reached[0, 0]) / len(hist)


def robust_filter_mask(residuals: Tensor, threshold: float, smooth_size: int = 3,
                       smooth_threshold: float = 0.5) -> Tensor:
    """RobustFilter's binary inlier mask (B, 1, h, w): below the threshold, or more than
    ``smooth_threshold`` of the 3 x 3 neighbourhood below it."""
    inlier = (residuals < threshold).to(residuals.dtype)
    return torch.maximum(inlier, neighbourhood_inliers(inlier, smooth_size, smooth_threshold))


def blend_weight(step: int, beta: float) -> float:
    """a in Bernoulli(a + (1 - a) mask): exp(beta floor((1 + step) / 1.5))."""
    return math.exp(beta * math.floor((1 + step) / 1.5))


def column_residuals(rendered: Tensor, target: Tensor) -> Tensor:
    """The absolute error averaged over each image column's pixels (B, 3, 1, w): the statistic
    SpotLessSplats' code histograms (a mean over the rows of its (1, H, W, 3) error)."""
    return (rendered - target).abs().mean(dim=2, keepdim=True)


class ParamReset(Callback):
    """Clamp one parameter group to at most ``value`` after the step at ``at`` of a
    ``reference_iters`` run (once), restarting its Adam moments; the group is found by name
    among the trainer's optimisers (a run without it is left alone)."""

    def __init__(self, group: str, at: int, value: float, reference_iters: int):
        self.group, self.at, self.value, self.reference_iters = group, at, value, reference_iters
        self.done = False

    def due(self, step: int, max_iters: int) -> bool:
        """Whether the reset follows completed step ``step`` + 1 (the at-th of the stretched run)."""
        return step + 1 == max(1, round(self.at * max_iters / self.reference_iters))

    @torch.no_grad()
    def after_step(self, state: TrainState) -> None:
        if self.done or not self.due(state.step, state.max_iters) or self.group not in state.optimizers:
            return
        opt = state.optimizers[self.group]
        for group in opt.param_groups:
            for p in group["params"]:
                p.clamp_(max=self.value)
                for key in ("exp_avg", "exp_avg_sq"):
                    if key in opt.state.get(p, {}):
                        opt.state[p][key].zero_()
        self.done = True

    def state_dict(self) -> dict:
        return {"done": self.done}

    def load_state_dict(self, state: dict) -> None:
        self.done = bool(state.get("done", False))


class RobustFilter(Loss):
    """SpotLessSplats' RobustFilter: masked L1, the mask from a running error percentile."""

    description = "SpotLessSplats' RobustFilter: L1 on pixels below a running 70th-percentile error (3 x 3 smoothed, blended in)"
    phases = ()  # every phase of the method
    spatial = True

    @dataclass
    class Config:
        percentile: float = bounded(0.7, 0.0, 1.0)  # the threshold: this quantile of the running error histogram
        bins: int = bounded(10_000, 2, 10_000_000)  # histogram bins over [0, 1]
        decay: float = bounded(0.95, 0.0, 1.0)  # the old histogram's weight at each step
        smooth_size: int = bounded(3, 1, 255)  # the neighbourhood rule (1: off)
        smooth_threshold: float = bounded(0.5, 0.0, 1.0)  # ... inlier if more than this share of it is
        # the threshold's statistic: "column" (the authors' code: per-column mean errors) or
        # "pixel" (per-pixel residuals, as the method is described)
        statistic: Literal["column", "pixel"] = "column"
        blend_in: bool = True  # Bernoulli blend-in of the mask ...
        blend_rate: float = bounded(-3e-3, -10.0, 0.0)  # ... a = exp(beta floor((1 + step) / 1.5)), in steps
        reference_iters: int = bounded(30_000, 1)  # reset_at is a step of a run this long (stretched to trainer.max_iters)
        ssim_weight: float = bounded(0.0, 0.0, 1.0)  # D-SSIM share (SpotLessSplats: 0), unmasked as in its code
        reset_group: str = "shN"  # parameter group clamped once ("" : no reset)
        reset_at: int = bounded(8002, 0)  # ... after this step of a reference_iters run
        reset_max: float = bounded(0.001, 0.0)  # ... to at most this value

    def __init__(self, config: "RobustFilter.Config | None" = None):
        super().__init__(config or self.Config())
        c = self.config
        if not 0.0 < c.percentile <= 1.0:
            raise ConfigError(f"robust-filter: percentile must be in (0, 1], got {c.percentile}")
        if c.bins < 2:
            raise ConfigError(f"robust-filter: bins must be at least 2, got {c.bins}")
        if not 0.0 <= c.decay <= 1.0:
            raise ConfigError(f"robust-filter: decay must be in [0, 1], got {c.decay}")
        if not 0.0 <= c.ssim_weight <= 1.0:
            raise ConfigError(f"robust-filter: ssim_weight must be in [0, 1], got {c.ssim_weight}")
        if c.reference_iters < 1:
            raise ConfigError(f"robust-filter: reference_iters must be at least 1, got {c.reference_iters}")
        self.hist = torch.zeros(c.bins)
        self.threshold = 1.0
        self.reset = ParamReset(c.reset_group, c.reset_at, c.reset_max, c.reference_iters) if c.reset_group else None

    def callbacks(self) -> list[Callback]:
        return [self.reset] if self.reset is not None else []

    def update(self, residuals: Tensor) -> None:
        """Add one step's residuals to the running histogram and read the new threshold."""
        c = self.config
        self.hist = c.decay * self.hist + residual_histogram(residuals, c.bins)
        self.threshold = histogram_percentile(self.hist, c.percentile)

    def mask(self, residuals: Tensor, step: int, statistic: Tensor | None = None) -> Tensor:
        """This step's (blended) mask (B, 1, h, w) with the threshold learnt so far; then the
        step's ``statistic`` (default: the residuals) goes into the histogram."""
        c = self.config
        with torch.no_grad():
            mask = robust_filter_mask(residuals, self.threshold, c.smooth_size, c.smooth_threshold)
            used = self.threshold
            self.metrics = {"inlier_fraction": float(mask.mean()), "threshold": used}
            if c.blend_in:
                a = blend_weight(step, c.blend_rate)
                mask = torch.bernoulli((a + (1.0 - a) * mask).clamp(0.0, 1.0))
                self.metrics["blend"] = a
            self.update(residuals if statistic is None else statistic)
        return mask

    def __call__(self, ctx: LossContext) -> Tensor:
        c = self.config
        rendered = ctx.rendered.detach()
        statistic = column_residuals(rendered, ctx.target) if c.statistic == "column" else None
        mask = self.mask(absolute_residuals(rendered, ctx.target), ctx.step, statistic)
        loss = ((ctx.rendered - ctx.target).abs() * mask).mean()  # over every pixel, as the authors'
        if c.ssim_weight > 0:
            d_ssim = 1.0 - ssim_map(ctx.rendered, ctx.target, padding="same").mean()
            loss = (1.0 - c.ssim_weight) * loss + c.ssim_weight * d_ssim
        return loss

    def state_dict(self) -> dict:
        return {"hist": self.hist.clone(), "threshold": self.threshold}

    def load_state_dict(self, state: dict) -> None:
        if "hist" in state:
            self.hist = state["hist"].detach().float().cpu().clone()
        self.threshold = float(state.get("threshold", 1.0))
