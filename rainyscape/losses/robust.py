"""RobustNeRF-style trimmed photometric loss: the unsupervised baseline for transient clutter.

Pixels whose residual exceeds the inlier threshold are left out of the loss. The threshold
is the ``inlier_quantile`` of per-pixel residuals, averaged over recent batches (the current
batch is masked with the threshold learnt *before* it, so a batch full of clutter cannot
lower its own bar). Three decisions are OR-ed, as in RobustNeRF (Sabour et al., 2023):
the pixel itself is an inlier; most of its 3 x 3 neighbourhood is (spatial smoothing, so
isolated false outliers on fine texture are kept); or most of its ``block_size`` block is
(patch-level decision, so mostly-clean patches train whole).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import torch
import torch.nn.functional as F
from torch import Tensor

from rainyscape.components import Loss, LossContext
from rainyscape.imaging.metrics import ssim_map


def pixel_residuals(rendered: Tensor, target: Tensor, kind: str) -> Tensor:
    """Per-pixel residual (B, 1, h, w): channel mean of squared (``l2``) or absolute (``l1``) error."""
    diff = rendered - target
    err = diff * diff if kind == "l2" else diff.abs()
    return err.mean(dim=1, keepdim=True)


def smoothed_inliers(inlier: Tensor, size: int, threshold: float) -> Tensor:
    """Pixels (B, 1, h, w) with more than ``threshold`` of their size x size neighbours inlier."""
    if size <= 1:
        return inlier
    box = torch.ones(1, 1, size, size, device=inlier.device, dtype=inlier.dtype) / (size * size)
    # Zero padding would count the outside as outliers and erode every border: replicate.
    pad = size // 2
    padded = F.pad(inlier, (pad, size - 1 - pad, pad, size - 1 - pad), mode="replicate")
    return (F.conv2d(padded, box) > threshold).to(inlier.dtype)


def block_inliers(inlier: Tensor, block: int, threshold: float) -> Tensor:
    """Whole ``block`` x ``block`` tiles (B, 1, h, w) marked inlier where more than ``threshold``
    of their pixels are; the ragged right / bottom tiles are decided on the pixels they have."""
    if block <= 0:
        return torch.zeros_like(inlier)
    h, w = inlier.shape[-2:]
    # With ceil_mode and no padding, a ragged tile is averaged over the pixels it has.
    fraction = F.avg_pool2d(inlier, block, ceil_mode=True)
    decided = (fraction > threshold).to(inlier.dtype)
    return F.interpolate(decided, scale_factor=block, mode="nearest")[..., :h, :w]


def robust_mask(residuals: Tensor, threshold: float | Tensor, smooth_size: int = 3,
                smooth_threshold: float = 0.5, block_size: int = 16,
                block_threshold: float = 0.9) -> Tensor:
    """Binary inlier mask (B, 1, h, w) from per-pixel residuals and an inlier threshold."""
    inlier = (residuals <= threshold).to(residuals.dtype)
    smooth = smoothed_inliers(inlier, smooth_size, smooth_threshold)
    blocks = block_inliers(inlier, block_size, block_threshold)
    return torch.maximum(torch.maximum(inlier, smooth), blocks)


class RobustPhotometric(Loss):
    """Trimmed photometric loss (RobustNeRF): ignores pixels the field cannot explain."""

    description = "RobustNeRF-style trimmed photometric loss (robust baseline)"
    phases = ()  # every phase of the method

    @dataclass
    class Config:
        residual: Literal["l2", "l1"] = "l2"  # l2 for NeRF, l1 for 3DGS (its L1 + D-SSIM loss)
        inlier_quantile: float = 0.8  # fraction of pixels assumed to be inliers
        history: int = 16  # the threshold is the mean quantile of this many recent batches
        smooth_size: int = 3  # neighbourhood of the spatial smoothing (1: off)
        smooth_threshold: float = 0.5  # inlier if more than this fraction of neighbours are
        block_size: int = 16  # patch-level decisions on tiles of this size (0: off)
        block_threshold: float = 0.9  # a tile trains whole if more than this fraction is inlier
        ssim_weight: float = 0.0  # > 0 adds this much masked D-SSIM (3DGS: 0.2, L1 gets 1 - it)

    def __init__(self, config: "RobustPhotometric.Config | None" = None):
        super().__init__(config or self.Config())
        c = self.config
        if not 0.0 < c.inlier_quantile <= 1.0:
            from rainyscape.errors import ConfigError

            raise ConfigError(f"robust loss: inlier_quantile must be in (0, 1], got {c.inlier_quantile}")
        if not 0.0 <= c.ssim_weight <= 1.0:
            from rainyscape.errors import ConfigError

            raise ConfigError(f"robust loss: ssim_weight must be in [0, 1], got {c.ssim_weight}")
        self.recent: list[float] = []

    def threshold(self) -> float | None:
        """The inlier threshold learnt from recent batches (None before the first batch)."""
        return sum(self.recent) / len(self.recent) if self.recent else None

    def _update(self, residuals: Tensor) -> None:
        flat = residuals.detach().flatten().float()
        if flat.numel() > 1 << 20:  # torch.quantile's size limit; a strided subset suffices
            flat = flat[:: flat.numel() // (1 << 20) + 1]
        self.recent.append(float(torch.quantile(flat, self.config.inlier_quantile)))
        del self.recent[: max(0, len(self.recent) - max(1, self.config.history))]

    def mask(self, rendered: Tensor, target: Tensor) -> Tensor:
        """Inlier mask (B, 1, h, w) for this batch; also advances the running threshold."""
        c = self.config
        with torch.no_grad():
            residuals = pixel_residuals(rendered.detach(), target, c.residual)
            if not self.recent:
                self._update(residuals)  # first batch: nothing learnt yet, use its own quantile
                thr = self.recent[-1]
            else:
                thr = self.threshold()
                self._update(residuals)
            mask = robust_mask(residuals, thr, c.smooth_size, c.smooth_threshold,
                               c.block_size, c.block_threshold)
        self.metrics = {"inlier_fraction": float(mask.mean()), "threshold": float(thr)}
        return mask

    def __call__(self, ctx: LossContext) -> Tensor:
        c = self.config
        mask = self.mask(ctx.rendered, ctx.target)
        denom = mask.sum().clamp_min(1.0)
        err = pixel_residuals(ctx.rendered, ctx.target, c.residual)
        loss = (err * mask).sum() / denom
        if c.ssim_weight > 0:
            # "same" padding: training patches may be smaller than the 11 x 11 window.
            d_ssim = 1.0 - ssim_map(ctx.rendered, ctx.target, padding="same").mean(1, keepdim=True)
            loss = (1.0 - c.ssim_weight) * loss + c.ssim_weight * (d_ssim * mask).sum() / denom
        return loss

    def state_dict(self) -> dict:
        return {"recent": list(self.recent)}

    def load_state_dict(self, state: dict) -> None:
        self.recent = [float(v) for v in state.get("recent", [])]
