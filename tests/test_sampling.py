"""Sampling along rays: stratified bins, inverse-CDF importance sampling, box clipping,
contraction and the occupancy grid."""

from __future__ import annotations

import pytest
import torch

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


# ------------------------------------------------------------ the grid field's sampling space

from rainyscape.fields.marching import march  # noqa: E402
from rainyscape.fields.occupancy import EmaOccupancy  # noqa: E402
from rainyscape.fields.space import GridSpace, contract_to_cube, reach_half_size, shell_stretch  # noqa: E402

from _scenes import forward_facing_scene  # noqa: E402


def _rays(n=64, seed=0):
    gen = torch.Generator().manual_seed(seed)
    origins = torch.tensor([-3.0, 0.0, 0.0]) + 0.5 * (torch.rand(n, 3, generator=gen) - 0.5)
    directions = torch.nn.functional.normalize(torch.tensor([1.0, 0.0, 0.0]) + 0.1 * torch.randn(n, 3, generator=gen), dim=-1)
    t_a, t_b = ray_box_intersection(origins, directions, torch.tensor([[-1.0] * 3, [1.0] * 3]))
    return origins, directions, t_a, t_b


def test_march_through_empty_cells_tiles_the_occupied_part_of_every_ray():
    o, d, t_a, t_b = _rays()
    everywhere = march(o, d, t_a, t_b, None, torch.tensor(0.1), 4, 0,
                       lambda q: torch.ones(q.shape[:-1], dtype=torch.bool), jitter=True)
    # sorted by ray, then along the ray; intervals tile [t_a, t_b] exactly
    assert torch.all(everywhere.ray[1:] >= everywhere.ray[:-1])
    same = everywhere.ray[1:] == everywhere.ray[:-1]
    assert torch.all(everywhere.t0[1:][same] >= everywhere.t1[:-1][same] - 1e-6)
    assert torch.all((everywhere.t >= everywhere.t0) & (everywhere.t <= everywhere.t1))
    length = torch.zeros(len(o)).index_add(0, everywhere.ray, everywhere.t1 - everywhere.t0)
    assert torch.allclose(length, t_b - t_a, atol=1e-5)
    # only a slab x in [0.2, 0.4] occupied: samples only there, and all of it still covered
    slab = march(o, d, t_a, t_b, None, torch.tensor(0.1), 4, 0,
                 lambda q: (q[..., 0] >= 0.2) & (q[..., 0] <= 0.4), jitter=False)
    x = (o[slab.ray] + slab.t[:, None] * d[slab.ray])[:, 0]
    assert torch.all((x >= 0.2) & (x <= 0.4))
    inside = torch.zeros(len(o)).index_add(0, slab.ray, slab.t1 - slab.t0)
    enter, leave = (0.2 - o[:, 0]) / d[:, 0], (0.4 - o[:, 0]) / d[:, 0]
    expected = (torch.minimum(leave, t_b) - torch.maximum(enter, t_a)).clamp_min(0)
    assert torch.all(inside >= expected - 0.1 / 4 - 1e-6)  # at most half a fine step lost at each face
    assert len(slab) < len(everywhere) / 5


def test_march_far_part_is_even_in_inverse_distance():
    o, d, t_a, t_b = _rays(8)
    s = march(o, d, t_a, t_b, torch.full_like(t_a, 100.0), torch.tensor(0.2), 2, 16,
              lambda q: torch.ones(q.shape[:-1], dtype=torch.bool), jitter=False)
    far = s.select(s.far)
    for r in range(8):
        inv = 1.0 / far.t0[far.ray == r]
        steps = inv[:-1] - inv[1:]
        assert torch.allclose(steps, steps.mean().expand_as(steps), rtol=1e-4)
        assert torch.all(s.t0[(s.ray == r) & s.far] >= s.t1[(s.ray == r) & ~s.far].max() - 1e-6)


def test_contract_to_cube_gives_the_box_its_share_and_infinity_the_border():
    inner = 0.75
    q = torch.tensor([[0.5, -0.2, 0.9], [2.0, 0.0, 0.0], [0.0, -1e9, 0.0], [1.0, 1.0, -1.0]])
    g = contract_to_cube(q, inner)
    assert torch.allclose(g[0], inner * q[0])
    assert g[1, 0].item() == pytest.approx(inner + (1 - inner) * 0.5)
    assert g[2, 1].item() == pytest.approx(-1.0, abs=1e-6)
    assert torch.allclose(g[3], inner * q[3])  # the box's border stays where it is (continuous)
    # the stretch is the inverse derivative along a radius
    r = torch.tensor([1.5])
    eps = 1e-4
    dg = (contract_to_cube(torch.tensor([[1.5 + eps, 0, 0]]), inner)[0, 0]
          - contract_to_cube(torch.tensor([[1.5 - eps, 0, 0]]), inner)[0, 0]) / (2 * eps)
    gr = contract_to_cube(torch.stack([r, torch.zeros(1), torch.zeros(1)], -1), inner)
    assert shell_stretch(gr, inner).item() == pytest.approx(1.0 / dg.item(), rel=1e-3)


def test_rays_of_the_contracted_layout_end_where_the_shell_reaches_its_share():
    inner, reach = 0.5, 0.9
    r = reach_half_size(inner, reach)
    assert contract_to_cube(torch.tensor([[r, 0.3, -0.2]]), inner)[0, 0].item() == pytest.approx(reach)
    scene = forward_facing_scene()  # far 8: the scene's own bound, which the reach replaces
    space = GridSpace(scene, "contract", inner, shell_reach=reach)
    o = torch.tensor([[0.0, 0.0, 0.0], [1.0, -0.5, 0.2], [0.0, 0.0, 0.0]])
    d = torch.nn.functional.normalize(torch.tensor([[0.0, 0.0, 1.0], [0.3, 0.2, 1.0], [1.0, 1.0, 0.0]]), dim=-1)
    rays = space.sample_rays(o, d)
    ends = space.to_grid(rays.origins + rays.t_far[:, None] * rays.directions)
    assert torch.allclose(ends.abs().amax(-1), torch.full((3,), reach), atol=1e-5)
    assert torch.all(rays.t_far > scene.far)  # the scene's far (8 units) would cut the shell short
    assert torch.all(rays.t_b <= rays.t_far)
    plain = GridSpace(scene, "contract", inner).sample_rays(o, d)
    assert torch.all(plain.t_far == scene.far)


def test_ema_occupancy_keeps_surfaces_and_lets_emptied_cells_fade():
    occ = EmaOccupancy((16, 8, 12))
    ball = lambda g, c: (((g - torch.tensor(c)) ** 2).sum(-1) < 0.3 ** 2).float()
    occ.update(lambda g: ball(g, [0.0, 0.0, 0.0]), warmup=True, threshold=0.01, decay=0.5)
    assert occ.fraction() == 1.0  # nothing skipped during the warm-up
    occ.update(lambda g: ball(g, [0.0, 0.0, 0.0]), warmup=False, threshold=0.01, decay=0.5)
    assert 0.0 < occ.fraction() < 0.2
    assert bool(occ.lookup(torch.zeros(1, 3))[0])  # the ball's centre is kept
    assert not bool(occ.lookup(torch.tensor([[0.9, 0.9, 0.9]]))[0])
    assert not bool(occ.lookup(torch.tensor([[1.5, 0.0, 0.0]]))[0])  # outside the cube
    # the ball moves: its old cells fade over updates instead of at once
    centre_cell = torch.zeros(1, 3)
    for _ in range(3):
        occ.update(lambda g: ball(g, [0.6, 0.0, 0.0]), warmup=True, threshold=0.01, decay=0.5)
    value = occ.values.reshape(-1)[occ._index(centre_cell)].item()
    assert 0.0 < value <= 0.5 ** 3 + 1e-6
