"""Sampling along rays: stratified bins, inverse-CDF importance sampling, box clipping,
contraction and the occupancy grid."""

from __future__ import annotations

import pytest
import torch

from rainyscape.fields.contraction import contract, contraction_stretch
from rainyscape.fields.encoding import encoded_dim, positional_encoding
from rainyscape.fields.occupancy import OccupancyGrid, cell_centers, occupied_cells
from rainyscape.fields.sampling import ray_box_intersection, sample_pdf, stratified_samples


def test_stratified_samples_fall_one_per_stratum():
    torch.manual_seed(0)
    near, far, n = torch.full((500,), 2.0), torch.full((500,), 6.0), 8
    t = stratified_samples(near, far, n, perturb=True)
    even = stratified_samples(near, far, n, perturb=False)
    assert torch.allclose(even[0], torch.linspace(2.0, 6.0, n))
    edges = torch.cat([torch.tensor([2.0]), 0.5 * (even[0, 1:] + even[0, :-1]), torch.tensor([6.0])])
    assert torch.all(t >= edges[:-1]) and torch.all(t <= edges[1:])
    assert torch.all(t[:, 1:] >= t[:, :-1])
    # Jitter covers each stratum uniformly: the mean lands mid-stratum.
    assert torch.allclose(t.mean(0), 0.5 * (edges[1:] + edges[:-1]), atol=0.05)


def test_lindisp_samples_are_even_in_inverse_depth():
    t = stratified_samples(torch.tensor([1.0]), torch.tensor([10.0]), 5, perturb=False, lindisp=True)
    inv = 1.0 / t[0]
    assert torch.allclose(inv[1:] - inv[:-1], torch.full((4,), (0.1 - 1.0) / 4), atol=1e-6)


def test_inverse_cdf_samples_follow_the_weights():
    torch.manual_seed(0)
    bins = torch.linspace(0.0, 1.0, 11)[None].expand(200, -1)  # 10 bins
    pdf = torch.tensor([0.0, 1.0, 4.0, 0.0, 0.0, 2.0, 0.0, 0.0, 3.0, 0.0])
    samples = sample_pdf(bins, pdf[None].expand(200, -1), 1000, deterministic=False)
    hist = torch.histc(samples, bins=10, min=0.0, max=1.0) / samples.numel()
    assert torch.allclose(hist, pdf / pdf.sum(), atol=0.01)
    # Inside a bin samples are uniform: bin 2's samples average to its centre.
    in_bin = samples[(samples >= 0.2) & (samples < 0.3)]
    assert in_bin.mean().item() == pytest.approx(0.25, abs=0.005)


def test_deterministic_inverse_cdf_hits_the_exact_quantiles():
    bins = torch.tensor([[0.0, 1.0, 3.0]])  # bins of width 1 and 2
    weights = torch.tensor([[1.0, 3.0]])  # cdf 0.25 at t = 1
    t = sample_pdf(bins, weights, 5, deterministic=True)[0]
    # Quantiles 0, .25, .5, .75, 1 of that density.
    expected = torch.tensor([0.0, 1.0, 1.0 + 2.0 / 3.0, 1.0 + 4.0 / 3.0, 3.0])
    assert torch.allclose(t, expected, atol=1e-3)


def test_ray_box_intersection_lands_on_the_faces():
    torch.manual_seed(0)
    box = torch.tensor([[-1.0, -2.0, -0.5], [1.0, 2.0, 0.5]])
    origins = torch.randn(256, 3) * 0.1 + torch.tensor([0.0, 0.0, 5.0])
    targets = torch.rand(256, 3) * (box[1] - box[0]) * 0.9 + box[0] * 0.9
    dirs = torch.nn.functional.normalize(targets - origins, dim=-1)
    entry, exit_ = ray_box_intersection(origins, dirs, box)
    assert torch.all(entry < exit_)
    for t in (entry, exit_):
        p = origins + t[:, None] * dirs
        on_face = ((p - box[0]).abs() < 1e-4) | ((p - box[1]).abs() < 1e-4)
        assert torch.all(on_face.any(-1))
        assert torch.all((p >= box[0] - 1e-4) & (p <= box[1] + 1e-4))
    away = torch.tensor([[0.0, 1.0, 0.0]]).expand(256, -1)  # up from above the box: misses
    entry, exit_ = ray_box_intersection(origins, away, box)
    assert torch.all(entry >= exit_)


def test_contraction_keeps_the_box_and_squeezes_the_rest_into_the_shell():
    torch.manual_seed(0)
    inside = torch.rand(100, 3) * 2 - 1
    assert torch.equal(contract(inside), inside)
    far = torch.randn(1000, 3) * 50
    c = contract(far)
    norm = c.abs().amax(-1)
    assert torch.all((norm > 1.0) & (norm < 2.0))
    assert contract(torch.tensor([[1e9, 0.0, 0.0]]))[0, 0].item() == pytest.approx(2.0)
    # Directions are kept and farther points go farther out.
    assert torch.allclose(torch.nn.functional.normalize(c, dim=-1), torch.nn.functional.normalize(far, dim=-1), atol=1e-5)
    assert torch.all(contract(far * 2).abs().amax(-1) > norm)


def test_contraction_stretch_matches_the_numerical_derivative():
    for r in (0.5, 1.5, 3.0, 10.0):
        x = torch.tensor([[r, 0.3 * r, -0.2 * r]], dtype=torch.float64)
        eps = 1e-6
        dc = contract(x * (1 + eps)) - contract(x)
        stretch = (x * eps).norm() / dc.norm()
        assert contraction_stretch(contract(x)).item() == pytest.approx(stretch.item(), rel=1e-4)


def test_occupancy_grid_looks_up_the_cell_of_a_point():
    occ = OccupancyGrid(8)
    mask = torch.zeros(8, 8, 8, dtype=torch.bool)
    mask[5, 2, 7] = True
    occ.set(mask)
    centers = cell_centers(8)
    assert occ.lookup(centers[5, 2, 7]).item()
    assert occ.lookup(centers).sum().item() == 1
    jittered = centers[5, 2, 7] + torch.tensor([0.24, -0.24, 0.2])  # cells are 0.5 wide
    assert occ.lookup(jittered).item()
    assert not occ.lookup(centers[5, 2, 6]).item()


def test_occupied_cells_dilate_by_one_cell():
    alpha = torch.zeros(6, 6, 6)
    alpha[3, 3, 3] = 0.5
    occ = occupied_cells(alpha, threshold=0.1, dilate=1)
    assert occ.sum().item() == 27
    assert occ[2:5, 2:5, 2:5].all()
    assert occupied_cells(alpha, threshold=0.6).sum().item() == 0


def test_positional_encoding_layout():
    x = torch.tensor([[0.5, -1.0, 2.0]])
    enc = positional_encoding(x, 3)
    assert enc.shape == (1, encoded_dim(3, 3)) == (1, 21)
    assert torch.equal(enc[0, :3], x[0])
    # Then per frequency 2^k: sin of the three coordinates, then cos.
    for k in range(3):
        block = enc[0, 3 + 6 * k: 9 + 6 * k]
        assert torch.allclose(block[:3], torch.sin(2.0 ** k * x[0]))
        assert torch.allclose(block[3:], torch.cos(2.0 ** k * x[0]))
