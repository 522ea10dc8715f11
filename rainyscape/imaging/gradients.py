"""Small image operators shared by the rain losses and rain-angle estimation.

Images are (B, C, h, w) float tensors. Gradient operators use "valid" convolution (no
padding): a padded border would invent strong horizontal / vertical edges that bias the
orientation histogram and the directional losses.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor

# ITU-R BT.601 luma, as cv2 / PIL grayscale.
_LUMA = (0.299, 0.587, 0.114)

# 3x3 derivative kernels along x (to the right); y (downwards, image rows) is the transpose.
# Scharr is scaled to Sobel's gain (a unit step gives 4, a unit-per-pixel ramp 8) so the same
# thresholds apply to both. Sobel's orientation is biased by up to ~3 degrees on thin streaks
# (at 20-30 degrees off the axes); Scharr's by under ~1 (docs/rain.md).
_KERNELS_X = {
    "sobel": ((-1.0, 0.0, 1.0), (-2.0, 0.0, 2.0), (-1.0, 0.0, 1.0)),
    "scharr": ((-0.75, 0.0, 0.75), (-2.5, 0.0, 2.5), (-0.75, 0.0, 0.75)),
}
GRADIENT_KERNELS = tuple(_KERNELS_X)


def grayscale(images: Tensor) -> Tensor:
    """(B, 3, h, w) -> (B, 1, h, w) luma; single-channel input is returned unchanged."""
    if images.shape[1] == 1:
        return images
    weights = images.new_tensor(_LUMA).view(1, 3, 1, 1)
    return (images * weights).sum(1, keepdim=True)


def image_gradients(images: Tensor, kernel: str = "scharr") -> tuple[Tensor, Tensor]:
    """Raw 3x3 derivative responses (gx, gy), each (B, C, h-2, w-2), channel by channel.

    Sobel gain: a unit step across the kernel gives 4, a unit-per-pixel ramp 8 (divide by 8
    for a derivative per pixel). ``kernel``: "scharr" (default) or "sobel".
    """
    if kernel not in _KERNELS_X:
        raise ValueError(f"unknown gradient kernel '{kernel}'; choose one of {GRADIENT_KERNELS}")
    b, c, h, w = images.shape
    kx = images.new_tensor(_KERNELS_X[kernel])
    kernels = torch.stack([kx, kx.T])[:, None]  # (2, 1, 3, 3): gx, gy
    out = F.conv2d(images.reshape(b * c, 1, h, w), kernels)
    out = out.reshape(b, c, 2, h - 2, w - 2)
    return out[:, :, 0], out[:, :, 1]


def steer(gx: Tensor, gy: Tensor, angle: Tensor) -> Tensor:
    """Derivative along ``angle`` (radians): cos(angle) gx + sin(angle) gy.

    ``angle`` covers the leading dimensions of ``gx`` (e.g. (B,) for (B, C, h, w)) and is
    broadcast over the rest. Steering the two derivative responses gives the directional
    derivative of the smoothed image without resampling it by a rotation.
    """
    a = angle.to(gx.dtype).reshape(*angle.shape, *([1] * (gx.ndim - angle.ndim)))
    return torch.cos(a) * gx + torch.sin(a) * gy


def directional_derivative(images: Tensor, angle: Tensor, kernel: str = "scharr") -> Tensor:
    """Per-pixel derivative of ``images`` along ``angle`` (B,), valid region (h-2, w-2)."""
    gx, gy = image_gradients(images, kernel)
    return steer(gx, gy, angle) / 8.0


def gradient_orientation(images: Tensor, kernel: str = "scharr") -> tuple[Tensor, Tensor]:
    """Orientation in [0, pi) and raw magnitude of the gradient of the grey image.

    Returns (orientation, magnitude), each (B, h-2, w-2); orientation is measured from the
    +x axis (image columns) towards +y (image rows, downwards).
    """
    gx, gy = image_gradients(grayscale(images), kernel)
    orientation = torch.remainder(torch.atan2(gy, gx), math.pi)[:, 0]
    magnitude = torch.hypot(gx, gy)[:, 0]
    return orientation, magnitude


def structure_orientation(images: Tensor, kernel: str = "scharr",
                          sigma: float = 2.0) -> tuple[Tensor, Tensor, Tensor]:
    """Orientation in [0, pi) of the structure tensor's leading eigenvector (the direction the
    grey image varies most in around each pixel, pooled by a Gaussian of ``sigma`` pixels),
    its coherent strength lambda1 - lambda2, and the pooled gradient magnitude sqrt(trace),
    each (B, h-2, w-2) in the units of :func:`image_gradients`.

    Pooling before taking the angle lets a streak's two sides and its length agree on one
    direction, where a pixel's own 3x3 gradient at a 1 to 3 px streak leans towards the pixel
    grid's axes and diagonals."""
    gx, gy = image_gradients(grayscale(images), kernel)
    radius = max(1, int(math.ceil(3 * sigma)))
    taps = torch.exp(-0.5 * (torch.arange(-radius, radius + 1, device=gx.device, dtype=gx.dtype) / sigma) ** 2)
    taps = taps / taps.sum()
    moments = torch.cat([gx * gx, gy * gy, gx * gy], 1)  # (B, 3, h-2, w-2)
    padded = F.pad(moments, (radius,) * 4, mode="replicate")
    pooled = F.conv2d(F.conv2d(padded, taps.view(1, 1, 1, -1).expand(3, 1, 1, -1), groups=3),
                      taps.view(1, 1, -1, 1).expand(3, 1, -1, 1), groups=3)
    jxx, jyy, jxy = pooled.unbind(1)
    orientation = torch.remainder(0.5 * torch.atan2(2 * jxy, jxx - jyy), math.pi)
    coherent = torch.sqrt((jxx - jyy) ** 2 + 4 * jxy ** 2)
    return orientation, coherent, torch.sqrt((jxx + jyy).clamp_min(0))
