"""LPIPS, only from weights already on this machine: never downloaded, never estimated.

LPIPS (Zhang et al., 2018) needs the ``lpips`` package (which ships its linear-layer
weights) and torchvision's AlexNet backbone weights in the torch hub cache. When either is
missing, :func:`load_lpips` says which, and evaluation reports LPIPS as unavailable.
"""

from __future__ import annotations

import importlib.util
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import torch
from torch import Tensor

ALEXNET_WEIGHTS = "alexnet-owt-7be5be79.pth"  # the file torchvision caches for AlexNet


@dataclass
class LpipsMetric:
    """``fn(pred, target) -> (B,)`` for (B, 3, H, W) images in [0, 1], or why there is none."""

    fn: Callable[[Tensor, Tensor], Tensor] | None
    reason: str = ""

    @property
    def available(self) -> bool:
        return self.fn is not None

    def describe(self) -> dict:
        return {"available": self.available, "net": "alex" if self.available else None,
                "reason": self.reason}


def backbone_path() -> Path:
    return Path(torch.hub.get_dir()) / "checkpoints" / ALEXNET_WEIGHTS


def load_lpips(device: torch.device | str = "cpu") -> LpipsMetric:
    """The LPIPS (AlexNet) metric if its weights are present locally."""
    if importlib.util.find_spec("lpips") is None:
        return LpipsMetric(None, "the 'lpips' package is not installed")
    path = backbone_path()
    if not path.is_file():
        return LpipsMetric(None, f"AlexNet weights not found at {path} (they are never downloaded "
                                 "during evaluation)")
    import lpips  # type: ignore[import-not-found]

    model = lpips.LPIPS(net="alex", verbose=False).to(device).eval()
    for p in model.parameters():
        p.requires_grad_(False)

    @torch.no_grad()
    def fn(pred: Tensor, target: Tensor) -> Tensor:
        return model(pred * 2 - 1, target * 2 - 1).flatten()

    return LpipsMetric(fn)
