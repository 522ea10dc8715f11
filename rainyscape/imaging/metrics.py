"""Image metrics on float images in [0, 1].

``ssim`` is the standard SSIM of Wang et al. (2004) as reported in papers: an 11 x 11
Gaussian window with sigma 1.5, K1 = 0.01, K2 = 0.03, data range 1, population
(co)variances, averaged over the valid region and the channels. It matches
``skimage.metrics.structural_similarity(gaussian_weights=True, sigma=1.5,
use_sample_covariance=False, data_range=1, channel_axis=...)`` and is differentiable,
so losses (L1 + D-SSIM) use the same function.
"""

from __future__ import annotations

from typing import Literal

import torch
import torch.nn.functional as F
from torch import Tensor

SSIM_WINDOW = 11
SSIM_SIGMA = 1.5
SSIM_K1 = 0.01
SSIM_K2 = 0.03


def psnr(pred: Tensor, target: Tensor) -> Tensor:
    """Peak signal-to-noise ratio in dB for images in [0, 1] (mean over all elements)."""
    mse = torch.mean((pred.float() - target.float()) ** 2)
    return -10.0 * torch.log10(mse.clamp_min(1e-12))


def masked_psnr(pred: Tensor, target: Tensor, mask: Tensor) -> float | None:
    """PSNR in dB over the pixels where ``mask`` (H, W) is set, every channel of images
    (C, H, W) in [0, 1]; None when the mask is empty."""
    return float(psnr(pred[:, mask], target[:, mask])) if bool(mask.any()) else None


def gaussian_kernel1d(size: int = SSIM_WINDOW, sigma: float = SSIM_SIGMA,
                      device=None, dtype=torch.float32) -> Tensor:
    """Normalised 1D Gaussian taps (size,)."""
    x = torch.arange(size, device=device, dtype=dtype) - (size - 1) / 2
    k = torch.exp(-0.5 * (x / sigma) ** 2)
    return k / k.sum()


def _blur(x: Tensor, kernel: Tensor, padding: int) -> Tensor:
    """Separable depthwise Gaussian blur of (B, C, H, W)."""
    c = x.shape[1]
    size = kernel.numel()
    kx = kernel.view(1, 1, 1, size).expand(c, 1, 1, size)
    ky = kernel.view(1, 1, size, 1).expand(c, 1, size, 1)
    x = F.conv2d(x, kx, padding=(0, padding), groups=c)
    return F.conv2d(x, ky, padding=(padding, 0), groups=c)


def ssim_map(pred: Tensor, target: Tensor, padding: Literal["valid", "same"] = "valid",
             window: int = SSIM_WINDOW, sigma: float = SSIM_SIGMA) -> Tensor:
    """Per-pixel SSIM (B, C, h, w) of images (B, C, H, W) in [0, 1].

    ``valid`` keeps only positions where the whole window lies inside the image (the
    standard); ``same`` zero-pads to the input size (what 3DGS's training loss does), which
    also works on patches smaller than the window.
    """
    if pred.shape != target.shape or pred.ndim != 4:
        raise ValueError(f"ssim needs two (B, C, H, W) images of one shape, got "
                         f"{tuple(pred.shape)} and {tuple(target.shape)}")
    if padding == "valid" and min(pred.shape[-2:]) < window:
        raise ValueError(f"ssim: images of {tuple(pred.shape[-2:])} are smaller than the "
                         f"{window}x{window} window (use padding='same')")
    pred, target = pred.float(), target.float()
    kernel = gaussian_kernel1d(window, sigma, pred.device)
    pad = (window - 1) // 2 if padding == "same" else 0
    mu_x, mu_y = _blur(pred, kernel, pad), _blur(target, kernel, pad)
    xx = _blur(pred * pred, kernel, pad) - mu_x ** 2
    yy = _blur(target * target, kernel, pad) - mu_y ** 2
    xy = _blur(pred * target, kernel, pad) - mu_x * mu_y
    c1, c2 = SSIM_K1 ** 2, SSIM_K2 ** 2
    num = (2 * mu_x * mu_y + c1) * (2 * xy + c2)
    den = (mu_x ** 2 + mu_y ** 2 + c1) * (xx + yy + c2)
    return num / den


def ssim(pred: Tensor, target: Tensor, padding: Literal["valid", "same"] = "valid",
         reduction: Literal["mean", "none"] = "mean") -> Tensor:
    """SSIM of (B, 3, H, W) images in [0, 1]: a scalar (``mean``) or one value per image.

    Images smaller than the 11 x 11 window (``valid``) are measured with the largest odd
    window that fits them (sigma scaled alike), so tiny images still get a score."""
    window, sigma = SSIM_WINDOW, SSIM_SIGMA
    side = min(pred.shape[-2:]) if pred.ndim == 4 else window
    if padding == "valid" and side < window:
        window = max(1, side if side % 2 else side - 1)
        sigma = SSIM_SIGMA * window / SSIM_WINDOW
    values = ssim_map(pred, target, padding, window=window, sigma=sigma)
    if reduction == "none":
        return values.mean(dim=(1, 2, 3))
    return values.mean()
