"""RobustNeRF's trimmed least squares (Sabour et al., CVPR 2023): the loss of ``robust-nerf``.

Distractors (things present in some views only) are outliers of the photometric fit. The
loss is the squared error of the pixels judged inliers, over the batch's pixel count:

1. residual: the per-pixel squared error, averaged over the colour channels;
2. a pixel is an inlier when its residual is below the threshold T: the ``inlier_quantile``
   (0.8, the authors' 360 config) of the residuals of the *previous* batch of the paper's
   64 patches (1.0, i.e. everything, before the first batch), so a batch cannot lower its
   own bar. A smaller batch pools the last batches' residuals up to the paper's 16384
   pixels: the quantile of 4 patches swung tenfold from step to step (0.008 to 0.13 on
   plaza-crowd), so what a patch kept depended on what the previous 4 showed;
3. 3 x 3 smoothing: also an inlier when more than ``smooth_threshold`` (0.5) of its 3 x 3
   neighbourhood is (zero padding at the window's border, as the authors' 'SAME'
   convolution), so isolated high residuals on fine texture still train;
4. patch decision: when more than ``patch_threshold`` (0.5) of a 16 x 16 training patch is
   inlier after step 3, its central ``inner_patch`` x ``inner_patch`` (8 x 8) pixels all are.

The mask of a pixel is the OR of the three decisions. The paper's batch is made of 16 x 16
patches: the decisions need each pixel's neighbours. Settings and order of operations follow
the authors' public code (multinerf ``internal/robustnerf.py``, ``configs/360_robustnerf.gin``);
no code is taken from it.

``residual_map`` lets the batch be single rays instead. Each ray's residual is written to a
per-view map of the last residual seen at each pixel; the ray is given a virtual
``map_patch`` x ``map_patch`` patch with it at a uniformly random place (as a pixel of the
paper's random patches has), and the decisions above are made on that patch, its other
pixels read from the map. Pixels not rendered within the last pass over the training pixels
are left out of the shares. A grid field learns from a k x k patch about as much as from k
random rays (docs/benchmarks.md, "What a patch is worth to the grid field"), so at 1024 rays
a step the paper's 4 patches starve it.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from rainyscape.cameras import Window
from rainyscape.components import Loss, LossContext
from rainyscape.config.schema import bounded
from rainyscape.errors import ConfigError
from rainyscape.imaging.filters import box_sum


def squared_residuals(rendered: Tensor, target: Tensor) -> Tensor:
    """Per-pixel residual (B, 1, h, w): the squared error averaged over the channels."""
    return (rendered - target).pow(2).mean(dim=1, keepdim=True)


def neighbourhood_inliers(inlier: Tensor, size: int, threshold: float, known: Tensor | None = None) -> Tensor:
    """Pixels (B, 1, h, w) more than ``threshold`` of whose ``size`` x ``size`` neighbourhood
    is inlier; outside the window counts as outlier (zero padding), as in RobustNeRF and
    SpotLessSplats. With ``known`` (B, 1, h, w), unknown pixels inside the window do not
    count either way. ``size`` <= 1: no smoothing (all zeros)."""
    if size <= 1:
        return torch.zeros_like(inlier)
    counted = box_sum(known, size, value=1.0) if known is not None else size * size
    return (box_sum(inlier, size) > threshold * counted).to(inlier.dtype)


def centre_square(height: int, width: int, inner: int, device=None) -> Tensor:
    """(1, 1, h, w) mask of the central ``inner`` x ``inner`` square of a window (the whole
    window when it is smaller)."""
    mask = torch.zeros(1, 1, height, width, device=device)
    ih, iw = min(inner, height), min(inner, width)
    y0, x0 = (height - ih) // 2, (width - iw) // 2
    mask[..., y0:y0 + ih, x0:x0 + iw] = 1.0
    return mask


def patch_inliers(inlier: Tensor, inner: int, threshold: float, known: Tensor | None = None) -> Tensor:
    """Each window (one per batch entry) whose inlier fraction (of its ``known`` pixels)
    exceeds ``threshold`` marks its central ``inner`` x ``inner`` square inlier (B, 1, h, w);
    ``inner`` 0: no patch decision."""
    if inner <= 0:
        return torch.zeros_like(inlier)
    h, w = inlier.shape[-2:]
    counted = known.sum(dim=(2, 3), keepdim=True) if known is not None else h * w
    whole = (inlier.sum(dim=(2, 3), keepdim=True) > threshold * counted).to(inlier.dtype)
    return whole * centre_square(h, w, inner, inlier.device).to(inlier.dtype)


def robustnerf_mask(residuals: Tensor, threshold: float | Tensor, smooth_size: int = 3,
                    smooth_threshold: float = 0.5, inner_patch: int = 8,
                    patch_threshold: float = 0.5, known: Tensor | None = None) -> Tensor:
    """RobustNeRF's binary inlier mask (B, 1, h, w) of a batch of windows' residuals.
    ``known`` (B, 1, h, w): the pixels whose residual is known (default all); the others are
    left out of the smoothing's and the patch decision's shares."""
    inlier = (residuals < threshold).to(residuals.dtype)
    if known is not None:
        known = known.to(residuals.dtype)
        inlier = inlier * known
    smooth = neighbourhood_inliers(inlier, smooth_size, smooth_threshold, known)
    inlier = torch.maximum(inlier, smooth if known is None else smooth * known)
    return torch.maximum(inlier, patch_inliers(inlier, inner_patch, patch_threshold, known))


class ResidualMap:
    """The last residual seen at each pixel of each view, and the step it was seen at."""

    def __init__(self, views: int, height: int, width: int, device=None):
        self.residuals = torch.zeros(views, height, width, device=device)
        self.seen = torch.full((views, height, width), -1, dtype=torch.int32, device=device)

    @property
    def height(self) -> int:
        return self.residuals.shape[1]

    @property
    def width(self) -> int:
        return self.residuals.shape[2]

    def write(self, view_ids: Tensor, window: Window, residuals: Tensor, step: int) -> None:
        """Keep the residuals (B, 1, h, w) of ``window`` of the views (of a pixel given twice,
        the later)."""
        rows, cells = window.last_writes(view_ids, self.height, self.width, self.residuals.device)
        self.residuals.view(-1)[cells] = residuals.reshape(-1)[rows].to(self.residuals.dtype)
        self.seen.view(-1)[cells] = step

    def read(self, view_ids: Tensor, window: Window, since: int) -> tuple[Tensor, Tensor]:
        """The windows' residuals and whether each is known (seen at step ``since`` or
        later), (B, 1, h, w) each."""
        flat = window.table_indices(view_ids, self.height, self.width, self.residuals.device)
        known = (self.seen.view(-1)[flat] >= since)[:, None].to(self.residuals.dtype)
        return self.residuals.view(-1)[flat][:, None], known


def virtual_patches(window: Window, size: int, width: int, height: int,
                    generator: torch.Generator) -> tuple[Window, Tensor, Tensor]:
    """A ``size`` x ``size`` patch inside the view around each single-ray window, drawn
    uniformly from those that hold it (as the paper's random patches hold a pixel), and the
    ray's place in it: rows, columns."""
    def offsets(at: Tensor, length: int) -> Tensor:
        low = (at - (length - size)).clamp(min=0)  # the patch may not start past length - size
        high = at.clamp(max=size - 1)
        return low + (torch.rand(len(at), generator=generator) * (high - low + 1)).long().clamp(max=high - low)

    dy, dx = offsets(window.y0, height), offsets(window.x0, width)
    return Window(window.x0 - dx, window.y0 - dy, size, size), dy, dx


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
        pool_patches: int = bounded(64, 1)  # T is taken over the last this many 16 x 16 patches' pixels (the paper's batch)
        residual_map: bool = False  # neighbours read from a per-view map of the last residuals (batches of single rays)
        map_patch: int = bounded(16, 2, 255)  # with the map: each ray's virtual patch (the paper's training patch)

    def __init__(self, config: "RobustNeRFLoss.Config | None" = None):
        super().__init__(config or self.Config())
        c = self.config
        if not 0.0 < c.inlier_quantile <= 1.0:
            raise ConfigError(f"robust loss: inlier_quantile must be in (0, 1], got {c.inlier_quantile}")
        for key in ("smooth_threshold", "patch_threshold"):
            if not 0.0 <= getattr(c, key) < 1.0:
                raise ConfigError(f"robust loss: {key} must be in [0, 1), got {getattr(c, key)}")
        self.threshold = float(c.initial_threshold)
        self.pool: list[Tensor] = []  # the last batches' residuals, flat
        self.map: ResidualMap | None = None
        self.pixels = 0  # the training views' pixels (with the map)
        self.map_age = 0  # steps an entry of the map stays seen (one pass over the training pixels)

    def setup(self, scene, device: torch.device) -> None:
        if self.config.residual_map:
            self.map = ResidualMap(len(scene.images), scene.height, scene.width, device)
            self.pixels = scene.train_pixels

    def _pool_residuals(self, residuals: Tensor) -> Tensor:
        """Add this batch's residuals to the pool (dropping the oldest beyond ``pool_patches``
        16 x 16 patches' pixels) and return the pool's residuals."""
        self.pool.append(residuals.detach().flatten().float().cpu())
        while sum(len(r) for r in self.pool) - len(self.pool[0]) >= self.config.pool_patches * 16 * 16:
            self.pool.pop(0)
        return torch.cat(self.pool)

    def mask(self, residuals: Tensor, ctx: LossContext | None = None) -> Tensor:
        """This batch's inlier mask (B, 1, h, w) with the threshold learnt so far; then the
        threshold becomes this batch's quantile (used by the next batch). With the residual
        map, ``ctx`` says where the batch's pixels are."""
        c = self.config
        with torch.no_grad():
            if self.map is None:
                mask = robustnerf_mask(residuals, self.threshold, c.smooth_size, c.smooth_threshold,
                                       c.inner_patch, c.patch_threshold)
            else:
                mask = self._map_mask(residuals, ctx)
            used, self.threshold = self.threshold, quantile(self._pool_residuals(residuals), c.inlier_quantile)
        self.metrics = {"inlier_fraction": float(mask.mean()), "threshold": used}
        return mask

    def _map_mask(self, residuals: Tensor, ctx: LossContext) -> Tensor:
        """The paper's decisions on a virtual patch around each ray, its other pixels read
        from the residual map (this batch's rays written first)."""
        c, window = self.config, ctx.window
        if window.width != 1 or window.height != 1:
            raise ConfigError("robust loss: residual_map needs batches of single rays "
                              f"(phase patch_size=1), got {window.width} x {window.height} windows")
        self.map.write(ctx.view_ids, window, residuals, ctx.step)
        self.map_age = self.map_age or -(-self.pixels // residuals.numel())  # one pass over the pixels
        patches, dy, dx = virtual_patches(window, c.map_patch, self.map.width, self.map.height,
                                          torch.Generator().manual_seed(ctx.step))
        around, known = self.map.read(ctx.view_ids, patches, ctx.step - self.map_age)
        mask = robustnerf_mask(around, self.threshold, c.smooth_size, c.smooth_threshold, c.inner_patch,
                               c.patch_threshold, known)
        return mask[torch.arange(len(mask)), :, dy.to(mask.device), dx.to(mask.device)][:, :, None, None]

    def __call__(self, ctx: LossContext) -> Tensor:
        mask = self.mask(squared_residuals(ctx.rendered.detach(), ctx.target), ctx)
        sq = (ctx.rendered - ctx.target).pow(2)
        # over every pixel of the batch, as the authors' loss (trimmed pixels count as zero)
        return (sq * mask).mean()

    def state_dict(self) -> dict:
        state = {"threshold": self.threshold, "pool": [r.clone() for r in self.pool]}
        if self.map is not None:
            state["map"] = {"residuals": self.map.residuals.cpu(), "seen": self.map.seen.cpu()}
        return state

    def load_state_dict(self, state: dict) -> None:
        self.threshold = float(state.get("threshold", self.config.initial_threshold))
        self.pool = [r.clone() for r in state.get("pool", [])]
        if self.map is not None and "map" in state:
            self.map.residuals.copy_(state["map"]["residuals"])
            self.map.seen.copy_(state["map"]["seen"])


def quantile(values: Tensor, q: float) -> float:
    """The ``q`` quantile of ``values`` (a strided subset past torch.quantile's size limit)."""
    flat = values.detach().flatten().float()
    if flat.numel() > 1 << 24:
        flat = flat[:: flat.numel() // (1 << 24) + 1]
    return float(torch.quantile(flat, q))
