"""Alpha compositing of an occluding image layer over an image.

A layer that hides what lies behind it (a person walking through the view, a rain streak)
is a premultiplied colour D and a coverage alpha: the observed image is D + (1 - alpha) B
for the image B behind it (Porter and Duff's "over"). The simulator writes its rain layers
in this form (I = B (1 - A) + C A, that is D = C A) and DeSplat lays its per-view distractor
layer over the scene render the same way.
"""

from __future__ import annotations

from torch import Tensor


def split_rgba(layer: Tensor) -> tuple[Tensor, Tensor]:
    """(premultiplied colour (B, 3, h, w), alpha (B, 1, h, w)) of a layer (B, 4, h, w)."""
    if layer.shape[1] != 4:
        raise ValueError(f"an occluding layer has 4 channels (colour, alpha), got {layer.shape[1]}")
    return layer[:, :3], layer[:, 3:]


def over(layer: Tensor, below: Tensor) -> Tensor:
    """``layer`` (B, 4, h, w: premultiplied colour and alpha) laid over ``below`` (B, 3, h, w):
    D + (1 - alpha) below."""
    colour, alpha = split_rgba(layer)
    return colour + (1.0 - alpha) * below
