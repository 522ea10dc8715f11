"""The field's last render of every view, kept from the batches it renders, so that heads can
learn on whole views the field did not render this step (``phases.NAME.head_views``).

Why: a ray field renders about a thousand pixels a step on a CPU, so a rain head that learns
only where the field rendered sees each pixel of a view about once in a run, and learns
little rain (docs/rain.md, "The rain head on a ray field"). The cache holds, per pixel, the
colour and depth the field last rendered there (detached). Where it never rendered, the
nearest rendered pixels stand in (:func:`fill_holes`): after a warm-up of random rays about
half the pixels are known, and a background is smooth next to rain streaks a pixel wide.
Those renders are hundreds of steps old (docs/rain.md, "How old is the background the rain
head learns against"); ``phases.NAME.refresh_every`` has the trainer render whole views into
the cache in turn.

:class:`LayerCache` is the other way round: a head's last whole-view prediction, for a
field's single rays that the head does not predict on (``phases.NAME.rays``).
"""

from __future__ import annotations

import torch
from torch import Tensor

from rainyscape.cameras import Window
from rainyscape.components import RenderOutput
from rainyscape.imaging.filters import box_sum


def fill_holes(values: Tensor, known: Tensor) -> Tensor:
    """``values`` (B, C, h, w) where ``known`` (B, 1, h, w, bool); elsewhere the mean of the
    known pixels in the smallest square around each (3, 5, 9, ... pixels wide: normalised
    convolution) that holds one. Images with no known pixel stay as they are."""
    out = values.clone()
    missing = ~known
    weight = known.to(values.dtype)
    total = values * weight
    size = 3
    while bool(missing.any()):
        count = box_sum(weight, size)
        sums = box_sum(total.flatten(0, 1)[:, None], size).view_as(values)
        fill = missing & (count > 0)
        out = torch.where(fill, sums / count.clamp_min(1e-12), out)
        missing = missing & ~fill
        if size > 2 * max(values.shape[-2:]):
            break  # only images with no known pixel are left
        size = 2 * size - 1
    return out


class RenderCache:
    """Per view: the colour and depth the field last rendered at each pixel, and where it did."""

    def __init__(self, views: int, height: int, width: int, device: torch.device | str = "cpu"):
        # half precision: about a hundredth of a grey level, next to rain's tenths
        self.rgb = torch.zeros(views, height, width, 3, dtype=torch.float16, device=device)
        self.depth = torch.zeros(views, height, width, 1, dtype=torch.float16, device=device)
        self.known = torch.zeros(views, height, width, 1, dtype=torch.bool, device=device)

    @torch.no_grad()
    def write(self, view_ids: Tensor, window: Window, output: RenderOutput) -> None:
        """Keep the render of ``window`` of the views ``view_ids`` (the newest wins; of a pixel
        drawn twice in one batch, the later one: an assignment with repeated indices would
        keep either, by thread timing, and resumed runs would not match)."""
        height, width = self.known.shape[1:3]
        rows, cells = window.last_writes(view_ids, height, width, self.rgb.device)
        rgb = output.rgb.detach().permute(0, 2, 3, 1).reshape(-1, 3)
        self.rgb.view(-1, 3)[cells] = rgb[rows].to(self.rgb.dtype)
        if output.depth is not None:
            self.depth.view(-1)[cells] = output.depth.detach().reshape(-1)[rows].to(self.depth.dtype)
        self.known.view(-1)[cells] = True

    @torch.no_grad()
    def read(self, view_ids: Tensor, window: Window) -> RenderOutput:
        """The cached render of ``window`` of the views (B, C, h, w, float32), holes filled."""
        known = window.table_values(self.known, view_ids)
        both = torch.cat([window.table_values(self.rgb, view_ids),
                          window.table_values(self.depth, view_ids)], 1).float()
        filled = fill_holes(both, known)
        return RenderOutput(rgb=filled[:, :3], depth=filled[:, 3:])

    def state_dict(self) -> dict:
        return {"rgb": self.rgb, "depth": self.depth, "known": self.known}

    def load_state_dict(self, state: dict) -> None:
        for key in ("rgb", "depth", "known"):
            getattr(self, key).copy_(state[key])


class LayerCache:
    """Per view: a head's last whole-view prediction (detached), for rays it does not predict
    on (``phases.NAME.rays``). A view not yet predicted is predicted whole when first read."""

    def __init__(self, views: int, height: int, width: int, device: torch.device | str = "cpu"):
        self.size = (height, width)
        # (views, H, W, C), made at the first write (C is the head's); half precision, as the
        # render cache: rain is tenths, the rounding thousandths of it
        self.values: Tensor | None = None
        self.known = torch.zeros(views, dtype=torch.bool, device=device)

    @torch.no_grad()
    def write(self, view_ids: Tensor, layers: Tensor) -> None:
        """Keep whole-view predictions (B, C, H, W) of the views ``view_ids`` (of a view
        given twice, the later)."""
        if self.values is None:
            self.values = torch.zeros(len(self.known), *self.size, layers.shape[1], dtype=torch.float16,
                                      device=self.known.device)
        for i, v in enumerate(view_ids.tolist()):
            self.values[v] = layers[i].detach().permute(1, 2, 0).to(self.values.dtype)
            self.known[v] = True

    @torch.no_grad()
    def read(self, view_ids: Tensor, window: Window, predict) -> Tensor:
        """The cached layer (B, C, h, w, float32) at ``window`` of the views; views never
        predicted are first predicted whole by ``predict(view_ids, window)``."""
        views = view_ids.to(self.known.device)
        missing = torch.unique(views[~self.known[views]])
        if len(missing):
            zeros = torch.zeros(len(missing), dtype=torch.long)
            self.write(missing, predict(missing, Window(zeros, zeros.clone(), self.size[1], self.size[0])))
        return window.table_values(self.values, views).float()

    def state_dict(self) -> dict:
        return {"values": self.values, "known": self.known}

    def load_state_dict(self, state: dict) -> None:
        values = state["values"]
        self.values = None if values is None else values.to(self.known.device, torch.float16).clone()
        self.known.copy_(state["known"])
