"""RobustNeRF's trimmed least squares (Sabour et al., CVPR 2023): the loss of ``robust-nerf``.

Distractors (things present in some views only) are outliers of the photometric fit. The
loss is the squared error of the pixels judged inliers, over the batch's pixel count:

1. residual: the per-pixel squared error, averaged over the colour channels;
2. a pixel is an inlier when its residual is below the threshold T: the ``inlier_quantile``
   (0.8, the authors' 360 config) of the residuals of the *previous* batch of the paper's
   64 patches (1.0, i.e. everything, before the first batch), so a batch cannot lower its
   own bar. A smaller batch (the CPU recipe's 4 patches) pools the last batches up to 64
   patches: the quantile of 4 patches swung tenfold from step to step (0.008 to 0.13 on
   plaza-crowd), so what a patch kept depended on what the previous 4 showed;
3. 3 x 3 smoothing: also an inlier when more than ``smooth_threshold`` (0.5) of its 3 x 3
   neighbourhood is (zero padding at the window's border, as the authors' 'SAME'
   convolution), so isolated high residuals on fine texture still train;
4. patch decision: when more than ``patch_threshold`` (0.5) of a 16 x 16 training patch is
   inlier after step 3, its central ``inner_patch`` x ``inner_patch`` (8 x 8) pixels all are.

The mask of a pixel is the OR of the three decisions. The batch is made of 16 x 16 patches
(``methods/robust.py``): the decisions need each pixel's neighbours. Settings and order of
operations follow the authors' public code (multinerf ``internal/robustnerf.py``,
``configs/360_robustnerf.gin``); no code is taken from it.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

from rainyscape.components import Loss, LossContext
from rainyscape.config.schema import bounded
from rainyscape.errors import ConfigError


def squared_residuals(rendered: Tensor, target: Tensor) -> Tensor:
    """Per-pixel residual (B, 1, h, w): the squared error averaged over the channels."""
    return (rendered - target).pow(2).mean(dim=1, keepdim=True)


def neighbourhood_inliers(inlier: Tensor, size: int, threshold: float) -> Tensor:
    """Pixels (B, 1, h, w) more than ``threshold`` of whose ``size`` x ``size`` neighbourhood
    is inlier; outside the window counts as outlier (zero padding), as in RobustNeRF and
    SpotLessSplats. ``size`` <= 1: no smoothing (all zeros)."""
    if size <= 1:
        return torch.zeros_like(inlier)
    box = torch.full((1, 1, size, size), 1.0 / (size * size), device=inlier.device, dtype=inlier.dtype)
    pad = size // 2
    padded = F.pad(inlier, (pad, size - 1 - pad, pad, size - 1 - pad))
    return (F.conv2d(padded, box) > threshold).to(inlier.dtype)


def centre_square(height: int, width: int, inner: int, device=None) -> Tensor:
    """(1, 1, h, w) mask of the central ``inner`` x ``inner`` square of a window (the whole
    window when it is smaller)."""
    mask = torch.zeros(1, 1, height, width, device=device)
    ih, iw = min(inner, height), min(inner, width)
    y0, x0 = (height - ih) // 2, (width - iw) // 2
    mask[..., y0:y0 + ih, x0:x0 + iw] = 1.0
    return mask


def patch_inliers(inlier: Tensor, inner: int, threshold: float) -> Tensor:
    """Each window (one per batch entry) whose inlier fraction exceeds ``threshold`` marks its
    central ``inner`` x ``inner`` square inlier (B, 1, h, w); ``inner`` 0: no patch decision."""
    if inner <= 0:
        return torch.zeros_like(inlier)
    h, w = inlier.shape[-2:]
    whole = (inlier.mean(dim=(2, 3), keepdim=True) > threshold).to(inlier.dtype)
    return whole * centre_square(h, w, inner, inlier.device).to(inlier.dtype)


def robustnerf_mask(residuals: Tensor, threshold: float | Tensor, smooth_size: int = 3,
                    smooth_threshold: float = 0.5, inner_patch: int = 8,
                    patch_threshold: float = 0.5) -> Tensor:
    """RobustNeRF's binary inlier mask (B, 1, h, w) of a batch of windows' residuals."""
    inlier = (residuals < threshold).to(residuals.dtype)
    inlier = torch.maximum(inlier, neighbourhood_inliers(inlier, smooth_size, smooth_threshold))
    return torch.maximum(inlier, patch_inliers(inlier, inner_patch, patch_threshold))


class RobustNeRFLoss(Loss):
    """RobustNeRF's trimmed squared error: only the pixels judged inliers train."""

    description = "RobustNeRF: trimmed L2 over 16 x 16 patches (per-pixel test, 3 x 3 and patch smoothing)"
    phases = ()  # every phase of the method
    spatial = True

    @dataclass
    class Config:
        inlier_quantile: float = bounded(0.8, 0.0, 1.0)  # T: this quantile of the previous batch's residuals
        smooth_size: int = bounded(3, 1, 255)  # the neighbourhood of the smoothing decision (1: off)
        smooth_threshold: float = bounded(0.5, 0.0, 1.0)  # inlier if more than this share of the neighbourhood is
        inner_patch: int = bounded(8, 0, 4096)  # the patch decision marks this central square (0: off)
        patch_threshold: float = bounded(0.5, 0.0, 1.0)  # ... when more than this share of the patch is inlier
        initial_threshold: float = bounded(1.0, 0.0)  # T before the first batch (1.0: every pixel is inlier)
        pool_patches: int = bounded(64, 1)  # T is taken over the last this many patches (the paper's batch)

    def __init__(self, config: "RobustNeRFLoss.Config | None" = None):
        super().__init__(config or self.Config())
        c = self.config
        if not 0.0 < c.inlier_quantile <= 1.0:
            raise ConfigError(f"robust loss: inlier_quantile must be in (0, 1], got {c.inlier_quantile}")
        for key in ("smooth_threshold", "patch_threshold"):
            if not 0.0 <= getattr(c, key) < 1.0:
                raise ConfigError(f"robust loss: {key} must be in [0, 1), got {getattr(c, key)}")
        self.threshold = float(c.initial_threshold)
        self.pool: list[Tensor] = []  # the last batches' residuals, (patches, h * w) each

    def _pool_residuals(self, residuals: Tensor) -> Tensor:
        """Add this batch's residuals to the pool (dropping the oldest beyond ``pool_patches``
        patches) and return the pool's residuals."""
        self.pool.append(residuals.detach().flatten(1).float().cpu())
        while sum(len(r) for r in self.pool) - len(self.pool[0]) >= self.config.pool_patches:
            self.pool.pop(0)
        return torch.cat(self.pool)

    def mask(self, residuals: Tensor) -> Tensor:
        """This batch's inlier mask (B, 1, h, w) with the threshold learnt so far; then the
        threshold becomes this batch's quantile (used by the next batch)."""
        c = self.config
        with torch.no_grad():
            mask = robustnerf_mask(residuals, self.threshold, c.smooth_size, c.smooth_threshold,
                                   c.inner_patch, c.patch_threshold)
            used, self.threshold = self.threshold, quantile(self._pool_residuals(residuals), c.inlier_quantile)
        self.metrics = {"inlier_fraction": float(mask.mean()), "threshold": used}
        return mask

    def __call__(self, ctx: LossContext) -> Tensor:
        mask = self.mask(squared_residuals(ctx.rendered.detach(), ctx.target))
        sq = (ctx.rendered - ctx.target).pow(2)
        # over every pixel of the batch, as the authors' loss (trimmed pixels count as zero)
        return (sq * mask).mean()

    def state_dict(self) -> dict:
        return {"threshold": self.threshold, "pool": [r.clone() for r in self.pool]}

    def load_state_dict(self, state: dict) -> None:
        self.threshold = float(state.get("threshold", self.config.initial_threshold))
        self.pool = [r.clone() for r in state.get("pool", [])]


def quantile(values: Tensor, q: float) -> float:
    """The ``q`` quantile of ``values`` (a strided subset past torch.quantile's size limit)."""
    flat = values.detach().flatten().float()
    if flat.numel() > 1 << 24:
        flat = flat[:: flat.numel() // (1 << 24) + 1]
    return float(torch.quantile(flat, q))
