"""Langevin latent update x <- x - d^2/2 (grad E + x / prior_var) [+ d N(0, 1)]."""

from __future__ import annotations

import pytest
import torch

from rainyscape.rain.langevin import langevin_step


def test_without_noise_the_prior_shrinks_the_latents_geometrically():
    x = torch.full((1000,), 5.0)
    d, prior = 0.03, 50.0
    for _ in range(100):
        langevin_step([x], [None], d, prior, noise=False)
    assert torch.allclose(x, torch.full_like(x, 5.0 * (1 - 0.5 * d * d / prior) ** 100))
    zero_grad = torch.full((1000,), 5.0)
    for _ in range(100):
        langevin_step([zero_grad], [torch.zeros(1000)], d, prior, noise=False)
    assert torch.allclose(zero_grad, x)


def test_one_noisy_step_has_the_step_size_as_noise_scale():
    x = torch.zeros(200_000)
    langevin_step([x], [None], 0.03, 50.0, noise=True, generator=torch.Generator().manual_seed(0))
    assert abs(float(x.mean())) < 0.03 * 0.02
    assert float(x.std()) == pytest.approx(0.03, rel=0.01)


def test_with_zero_data_gradient_the_latents_sample_the_prior():
    # x' = (1 - a) x + d n with a = d^2 / (2 prior): stationary mean 0 and variance
    # d^2 / (2a - a^2), i.e. the prior's variance up to the discretisation.
    d, prior = 1.0, 2.0
    a = d * d / (2 * prior)
    x = torch.full((100_000,), 3.0)
    g = torch.Generator().manual_seed(0)
    for _ in range(60):
        langevin_step([x], [None], d, prior, noise=True, generator=g)
    assert abs(float(x.mean())) < 0.02
    assert float(x.var()) == pytest.approx(d * d / (2 * a - a * a), rel=0.02)


def test_data_gradient_pulls_towards_the_minimum():
    # E = |x - 4|^2 / 2 with prior var 50: the noise-free fixed point is 4 * 50 / 51.
    x = torch.zeros(10)
    for _ in range(3000):
        langevin_step([x], [x - 4.0], 0.3, 50.0, noise=False)
    assert torch.allclose(x, torch.full_like(x, 4.0 * 50 / 51), atol=1e-4)


def test_updates_every_latent_in_place():
    s, v = torch.ones(4), torch.ones(3, 2)
    langevin_step([s, v], [torch.ones(4), None], 0.1, 1.0, noise=False)
    assert torch.allclose(s, torch.full((4,), 1 - 0.005 * 2))
    assert torch.allclose(v, torch.full((3, 2), 1 - 0.005))
