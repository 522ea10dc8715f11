"""Image metrics against known values and against scikit-image."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from skimage.metrics import structural_similarity

from rainyscape.imaging.metrics import psnr, ssim, ssim_map


def _image(seed: int, h: int = 48, w: int = 56) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    coarse = torch.rand(1, 3, h // 8, w // 8, generator=g)
    smooth = torch.nn.functional.interpolate(coarse, size=(h, w), mode="bilinear", align_corners=False)
    return (0.6 * smooth + 0.2 * torch.rand(1, 3, h, w, generator=g)).clamp(0, 1)


@pytest.mark.parametrize("sigma", [0.01, 0.05, 0.1])
def test_psnr_of_a_known_noise_level(sigma):
    target = _image(0) * 0.6 + 0.2  # inside [0.2, 0.8]: +-sigma never clips
    signs = torch.randint(0, 2, target.shape, generator=torch.Generator().manual_seed(1)) * 2 - 1
    noisy = target + sigma * signs  # every squared error is exactly sigma^2
    assert float(psnr(noisy, target)) == pytest.approx(-10 * math.log10(sigma ** 2), abs=1e-3)


def test_ssim_of_identical_images_is_one():
    img = _image(2)
    assert float(ssim(img, img)) == pytest.approx(1.0, abs=1e-6)
    assert float(ssim(img, img, padding="same")) == pytest.approx(1.0, abs=1e-6)


def _skimage(a: torch.Tensor, b: torch.Tensor) -> float:
    return structural_similarity(a[0].permute(1, 2, 0).numpy().astype(np.float64),
                                 b[0].permute(1, 2, 0).numpy().astype(np.float64),
                                 gaussian_weights=True, sigma=1.5, use_sample_covariance=False,
                                 data_range=1.0, channel_axis=2)


@pytest.mark.parametrize("noise", [0.02, 0.1, 0.3])
def test_ssim_matches_scikit_image_on_a_reference_pair(noise):
    a = _image(3)
    b = (a + noise * torch.randn(a.shape, generator=torch.Generator().manual_seed(4))).clamp(0, 1)
    ours = float(ssim(a, b))
    assert ours == pytest.approx(_skimage(a, b), abs=1e-5)
    assert ours < 1.0


def test_ssim_per_image_and_gradients():
    a, b = _image(5), _image(6)
    pair = ssim(torch.cat([a, a]), torch.cat([a, b]), reduction="none")
    assert pair.shape == (2,) and float(pair[0]) == pytest.approx(1.0, abs=1e-6)
    assert float(pair[1]) == pytest.approx(_skimage(a, b), abs=1e-5)
    x = b.clone().requires_grad_(True)
    (1 - ssim(x, a)).backward()
    assert x.grad is not None and float(x.grad.abs().sum()) > 0


def test_ssim_window_and_padding():
    small = _image(7, 8, 8)
    with pytest.raises(ValueError, match="smaller than"):
        ssim_map(small, small * 0.5)
    # ssim (the metric) measures images smaller than its window with a window that fits (8 x 8: 7)
    assert float(ssim(small, small)) == pytest.approx(1.0, abs=1e-6)
    assert float(ssim(small, small * 0.5)) < 0.99
    assert ssim_map(small, small * 0.5, padding="same").shape == small.shape
    assert ssim_map(_image(8), _image(9)).shape == (1, 3, 48 - 10, 56 - 10)
