"""Volume-rendering quadrature against closed forms."""

from __future__ import annotations

import math

import pytest
import torch

from rainyscape.fields.rendering import (FAR_DELTA, composite, compositing_weights, densities_until_opaque,
                                         near_gradient_scale, sample_deltas, scale_gradient)

SIGMA, A, B = 1.7, 1.0, 2.5  # a constant-density slab [A, B)
COLOR = torch.tensor([0.2, 0.5, 0.9], dtype=torch.float64)
BACKGROUND = torch.tensor([1.0, 0.0, 0.3], dtype=torch.float64)


def slab_samples(count: int, far: float = 4.0) -> tuple[torch.Tensor, torch.Tensor]:
    """Samples (interval starts) over [0, far] and their densities: sigma inside the slab."""
    t = torch.linspace(0.0, far, count + 1, dtype=torch.float64)[:-1]
    sigma = torch.where((t >= A - 1e-12) & (t < B - 1e-12), SIGMA, 0.0)
    return t, sigma


def test_slab_colour_and_transmittance_are_exact():
    # Interval edges on the slab's faces: piecewise-constant quadrature is exact.
    t, sigma = slab_samples(count=80)  # spacing 0.05 puts edges at 1.0 and 2.5
    deltas = sample_deltas(t, last=4.0 - t[-1])
    weights, transmittance = compositing_weights(sigma, deltas)
    values = COLOR.expand(len(t), 3)
    opacity = 1.0 - math.exp(-SIGMA * (B - A))
    rgb = composite(weights, values) + (1.0 - weights.sum()) * BACKGROUND
    expected = COLOR * opacity + BACKGROUND * (1.0 - opacity)
    assert torch.allclose(rgb, expected, atol=1e-5)
    assert weights.sum().item() == pytest.approx(opacity, abs=1e-5)
    # T(t) = exp(-sigma * length of the slab before t), at every sample.
    closed = torch.exp(-SIGMA * (t.clamp(A, B) - A))
    assert torch.allclose(transmittance, closed, atol=1e-5)


def test_unaligned_samples_converge_to_the_closed_form():
    opacity = 1.0 - math.exp(-SIGMA * (B - A))
    errors = []
    for count in (37, 370, 3700):  # edges miss the slab faces
        t, sigma = slab_samples(count)
        weights, _ = compositing_weights(sigma, sample_deltas(t, last=4.0 - t[-1]))
        errors.append(abs(weights.sum().item() - opacity))
    assert errors[0] > errors[1] > errors[2]
    assert errors[2] < 1e-3


def test_expected_depth_of_a_half_space_is_entry_plus_mean_free_path():
    # Density sigma from A onwards: termination depth A + Exp(sigma), mean A + 1 / sigma.
    t = torch.linspace(0.0, 30.0, 300_001, dtype=torch.float64)
    sigma = torch.where(t >= A, SIGMA, 0.0)
    weights, _ = compositing_weights(sigma, sample_deltas(t))
    depth = (weights * t).sum().item()
    assert depth == pytest.approx(A + 1.0 / SIGMA, abs=1e-3)


def test_last_nerf_sample_absorbs_the_remaining_light():
    t = torch.tensor([[1.0, 2.0, 3.0, 4.0]])
    sigma = torch.tensor([[0.0, 0.7, 0.0, 3.0]])  # float32, as in training
    deltas = sample_deltas(t)
    assert deltas[0, -1].item() == FAR_DELTA
    weights, _ = compositing_weights(sigma, deltas)
    assert weights.sum().item() == pytest.approx(1.0)
    assert weights[0, 1].item() == pytest.approx(1 - math.exp(-0.7))
    assert weights[0, 3].item() == pytest.approx(math.exp(-0.7))  # not swamped by the 1e10 interval
    assert weights[0, 0].item() == 0.0 and weights[0, 2].item() == 0.0


def test_zero_density_is_fully_transparent_and_gradients_flow():
    t = torch.linspace(0.0, 1.0, 16)[None]
    sigma = torch.zeros_like(t, requires_grad=True)
    weights, transmittance = compositing_weights(sigma, sample_deltas(t, last=0.1))
    assert weights.abs().max().item() == 0.0
    assert torch.all(transmittance == 1.0)
    weights.sum().backward()
    assert torch.all(sigma.grad > 0)  # more density anywhere means more opacity


# ------------------------------------------------------------------ packed samples (grid field)

from rainyscape.fields.packed import distortion, packed_weights, ray_starts  # noqa: E402


def _ragged(counts, seed=0):
    """Packed rows for rays with ``counts`` samples each (some rays empty)."""
    gen = torch.Generator().manual_seed(seed)
    ray = torch.repeat_interleave(torch.arange(len(counts)), torch.tensor(counts))
    sigma = torch.rand(len(ray), generator=gen, dtype=torch.float64) * 5.0
    deltas = torch.rand(len(ray), generator=gen, dtype=torch.float64) * 0.3
    return ray, sigma, deltas


def test_packed_weights_match_the_dense_quadrature_ray_by_ray():
    counts = [5, 0, 1, 12, 3, 0, 7]
    ray, sigma, deltas = _ragged(counts)
    weights, transmittance, left = packed_weights(sigma, deltas, ray, len(counts))
    for r, n in enumerate(counts):
        rows = ray == r
        if n == 0:
            assert left[r] == 1.0  # an empty ray keeps all its light
            continue
        # the dense reference, with a final zero-length interval standing for "behind"
        w, t = compositing_weights(sigma[rows], deltas[rows])
        assert torch.allclose(weights[rows], w, atol=1e-12)
        assert torch.allclose(transmittance[rows], t, atol=1e-12)
        assert torch.isclose(weights[rows].sum() + left[r], torch.tensor(1.0, dtype=torch.float64))


def test_packed_slab_matches_the_closed_form():
    # one ray, 200 samples through a constant slab of optical depth sigma * L
    n, length = 200, B - A
    ray = torch.zeros(n, dtype=torch.long)
    sigma = torch.full((n,), SIGMA, dtype=torch.float64)
    weights, _, left = packed_weights(sigma, torch.full((n,), length / n, dtype=torch.float64), ray, 1)
    assert weights.sum().item() == pytest.approx(1.0 - math.exp(-SIGMA * length), abs=1e-12)
    assert left.item() == pytest.approx(math.exp(-SIGMA * length), abs=1e-12)


def test_ray_starts_points_at_each_rays_first_row():
    ray = torch.tensor([0, 0, 2, 2, 2, 3])
    assert ray_starts(ray, 5).tolist() == [0, 0, 2, 2, 2, 5]


def test_distortion_matches_the_double_sum():
    counts = [4, 0, 9, 1]
    ray, w, _ = _ragged(counts, seed=3)
    w = w / 10.0
    gen = torch.Generator().manual_seed(4)
    s0 = torch.zeros_like(w)
    s1 = torch.zeros_like(w)
    for r in range(len(counts)):  # sorted, non-overlapping intervals per ray
        rows = (ray == r).nonzero()[:, 0]
        edges = torch.sort(torch.rand(2 * len(rows), generator=gen, dtype=torch.float64)).values
        s0[rows], s1[rows] = edges[0::2], edges[1::2]
    got = distortion(w, s0, s1, ray, len(counts))
    for r in range(len(counts)):
        rows = ray == r
        wr, mr = w[rows], 0.5 * (s0[rows] + s1[rows])
        pairs = (wr[:, None] * wr[None, :] * (mr[:, None] - mr[None, :]).abs()).sum()
        single = (wr ** 2 * (s1[rows] - s0[rows])).sum() / 3.0
        assert got[r].item() == pytest.approx((pairs + single).item(), abs=1e-12)


def test_distortion_prefers_one_thin_surface_to_spread_weight():
    ray = torch.zeros(10, dtype=torch.long)
    s0 = torch.linspace(0, 0.9, 10, dtype=torch.float64)
    s1 = s0 + 0.1
    peaked = torch.zeros(10, dtype=torch.float64)
    peaked[4] = 1.0
    spread = torch.full((10,), 0.1, dtype=torch.float64)
    assert distortion(peaked, s0, s1, ray, 1) < distortion(spread, s0, s1, ray, 1) / 5


def test_near_gradient_scale_is_quadratic_up_to_the_reference_then_one():
    d = torch.tensor([0.0, 0.5, 1.0, 2.0, 4.0])
    assert torch.allclose(near_gradient_scale(d, 2.0), torch.tensor([0.0, 0.0625, 0.25, 1.0, 1.0]))


def test_scale_gradient_keeps_values_and_scales_only_the_gradient():
    x = torch.tensor([1.0, 2.0, 3.0], requires_grad=True)
    scale = torch.tensor([0.0, 0.5, 1.0])
    y = scale_gradient(x * 2.0, scale)
    assert torch.equal(y.detach(), torch.tensor([2.0, 4.0, 6.0]))
    y.sum().backward()
    assert torch.allclose(x.grad, torch.tensor([0.0, 1.0, 2.0]))


def test_densities_until_opaque_stop_where_the_light_is_gone_and_match_the_full_march():
    """Three rays of 100 samples: one through empty space, one into a thick wall at sample 10,
    one with a faint haze only. Marching in chunks of 8 evaluates the wall ray only up to the
    chunk where its transmittance falls under the threshold; every other density, and every
    transmittance above the threshold, is that of evaluating all live samples."""
    n = 100
    deltas = torch.full((3, n), 0.05)
    deltas[:, -1] = FAR_DELTA
    full = torch.zeros(3, n)
    full[1, 10:] = 400.0  # a wall: opaque within a sample
    full[2, :] = 0.2  # haze: transmittance stays above 1e-4 to the last sample but one
    live = torch.ones(3, n, dtype=torch.bool)
    live[0, 40:60] = False  # skipped by the occupancy grid
    calls = []

    def density(rays, samples):
        calls.append(len(rays))
        return full[rays, samples]

    sigma, evaluated = densities_until_opaque(live, deltas, density, threshold=1e-4, chunk=8)
    assert torch.equal(evaluated[1], torch.arange(n) < 16)  # the wall's chunk [8, 16), no further
    assert torch.equal(evaluated[0], live[0]) and evaluated[2].all()
    assert sum(calls) == int(evaluated.sum())
    _, t_full = compositing_weights(full * live, deltas)
    _, t_march = compositing_weights(sigma, deltas)
    lit = t_full > 1e-4
    assert torch.equal(t_march[lit], t_full[lit])
    assert not (t_march[1, 16:] > 1e-4).any()  # what was not evaluated still passes no threshold
