"""Multi-view rain evidence: neighbours, back-projection, and the evidence itself on a
simulated scene with its true depth and rain layer."""

from __future__ import annotations

import torch
import torch.nn.functional as F

from rainyscape.cameras import Window
from rainyscape.losses.multiview_evidence import (backproject, brightest_within, evidence_with_reach,
                                                  neighbour_colours, neighbour_table, rain_evidence, sample_views)


def test_neighbours_are_the_nearest_other_views_of_the_pool():
    centers = torch.tensor([[0.0, 0, 0], [1, 0, 0], [3, 0, 0], [6, 0, 0]])
    table = neighbour_table(centers, [0, 1, 3], k=2)
    assert table.tolist() == [[1, 3], [0, 3], [1, 0], [1, 0]]  # never itself, only pool views


def test_backprojected_pixels_project_back_onto_their_centres(tiny_scene):
    view = 5
    cams = tiny_scene.cameras[[view]]
    window = Window(torch.tensor([7]), torch.tensor([3]), 20, 16)
    depth = torch.rand(1, 1, 16, 20) * 3 + 1
    points = backproject(cams, window, depth)
    uv, z = cams.project(points.reshape(-1, 3))
    xs, ys = window.pixel_grid()
    assert torch.allclose(uv[0, :, 0], xs.reshape(-1).float() + 0.5, atol=1e-3)
    assert torch.allclose(uv[0, :, 1], ys.reshape(-1).float() + 0.5, atol=1e-3)
    assert torch.allclose(z[0], depth.reshape(-1), atol=1e-4)


def test_evidence_finds_the_rain_with_the_true_depth(tiny_scene):
    scene = tiny_scene
    images = scene.images.permute(0, 3, 1, 2).float() / 255
    table = neighbour_table(scene.cameras.centers, list(scene.train_indices), 6)
    views = torch.tensor(scene.train_indices)
    window = Window.full(scene.cameras[views])
    depth = scene.depths[views][:, None]
    colours, valid = neighbour_colours(backproject(scene.cameras[views], window, depth), table[views],
                                       scene.cameras, images)
    evidence, defined = rain_evidence(images[views], colours, valid)
    true = scene.rain_layers[views].permute(0, 3, 1, 2)
    e, t = evidence.mean(1).flatten(), true.mean(1).flatten()
    corr = torch.corrcoef(torch.stack([e, t]))[0, 1]
    assert defined.float().mean() > 0.8
    assert corr > 0.45, float(corr)  # measured 0.61 here, 0.72 on the 128 px crossroad
    rainy_pixels = t > 0.05
    assert e[rainy_pixels].mean() > 4 * e[~rainy_pixels].mean()  # measured 8.9x: rain stands out


def test_occluded_neighbours_do_not_vote_and_the_evidence_finds_the_rain_better(tiny_scene):
    """A neighbour whose own depth at the projection is nearer than the point sees an
    occluder, not the point: without the test its colour joins the median (issue 28)."""
    s = tiny_scene
    images = s.images.permute(0, 3, 1, 2).float() / 255
    depths = s.depths[:, None].clone()  # ground-truth depth stands in for the rendered depth here
    depths[~torch.isfinite(depths)] = 1e6  # sky: far
    table = neighbour_table(s.cameras.centers, s.train_indices, 6)

    def correlation(a, b):
        a, b = a - a.mean(), b - b.mean()
        return float((a * b).sum() / (a.norm() * b.norm()))

    scores = {}
    for test in (False, True):
        per_view = []
        for v in s.train_indices:
            cams = s.cameras[[v]]
            points = backproject(cams, Window.full(cams), depths[[v]])
            colours, valid = neighbour_colours(points, table[[v]], s.cameras, images,
                                               depths if test else None)
            evidence, _ = rain_evidence(images[[v]], colours, valid)
            per_view.append(correlation(evidence.mean(1), s.rain_layers[v].mean(-1)))
        scores[test] = sum(per_view) / len(per_view)
    assert scores[True] > scores[False] + 0.01, scores


def test_brightest_within_spreads_a_bright_pixel_over_its_reach():
    images = torch.zeros(1, 3, 7, 7)
    images[0, 1, 3, 3] = 0.8
    assert brightest_within(images, 0) is images
    one = brightest_within(images, 1)
    assert torch.equal(one[0, 1, 2:5, 2:5], torch.full((3, 3), 0.8))
    assert int((one[0, 1] > 0).sum()) == 9 and float(one[0, 0].abs().sum()) == 0.0  # per channel
    assert int((brightest_within(images, 2)[0, 1] > 0).sum()) == 25


def test_the_evidence_at_the_point_is_capped_by_a_gain_times_the_reach_s():
    at_point = torch.tensor([0.20, 0.20, 0.05, 0.0])  # a streak on smooth ground, an edge a pixel off, a faint streak, dry
    within = torch.tensor([0.18, 0.01, 0.04, 0.0])
    assert torch.allclose(evidence_with_reach(at_point, within, 2.0), torch.tensor([0.20, 0.02, 0.05, 0.0]))
    assert torch.equal(evidence_with_reach(at_point, within, 0.0), within)  # no gain: the reach's alone


def test_a_reach_keeps_a_depth_error_from_reading_edges_as_rain(tiny_scene):
    """With a rendered depth 6 % off, edges reproject a pixel or so off and the evidence calls
    them rain; the neighbours' brightest within 1 px does not, and still finds the streaks."""
    s = tiny_scene
    images = s.images.permute(0, 3, 1, 2).float() / 255
    table = neighbour_table(s.cameras.centers, list(s.train_indices), 6)
    views = torch.tensor(s.train_indices)
    points = backproject(s.cameras[views], Window.full(s.cameras[views]), 1.06 * s.depths[views][:, None])
    rain = s.rain_layers[views].permute(0, 3, 1, 2).mean(1).flatten()
    found = {}
    for reach in (0, 1):
        colours, valid = neighbour_colours(points, table[views], s.cameras, brightest_within(images, reach))
        evidence = rain_evidence(images[views], colours, valid)[0].mean(1).flatten()
        found[reach] = (float(torch.corrcoef(torch.stack([evidence, rain]))[0, 1]),
                        float(evidence[rain < 0.02].mean()), float(evidence[rain > 0.05].mean()))
    assert found[1][0] > found[0][0] + 0.1, found  # measured 0.65 against 0.41
    assert found[1][1] < 0.25 * found[0][1], found  # on dry pixels 0.004 against 0.034
    assert found[1][2] > 10 * found[1][1], found  # the streaks still stand out (0.095)


def test_an_unknown_neighbour_depth_keeps_its_vote():
    from rainyscape.cameras import Cameras

    c2w = torch.eye(4)[None].repeat(2, 1, 1)
    cams = Cameras(c2w, torch.full((2,), 10.0), torch.full((2,), 10.0), torch.full((2,), 4.0),
                   torch.full((2,), 4.0), 8, 8)
    images = torch.rand(2, 3, 8, 8)
    points = torch.tensor([0.0, 0.0, 2.0]).expand(1, 1, 1, 3)  # the principal point at z = 2
    near = torch.full((2, 1, 8, 8), 1.0)  # an occluder at z = 1 in every view
    unknown = torch.full((2, 1, 8, 8), float("nan"))
    neighbours = torch.tensor([[1]])
    assert not neighbour_colours(points, neighbours, cams, images, near)[1].any()
    assert neighbour_colours(points, neighbours, cams, images, unknown)[1].all()


def test_gated_evidence_moves_the_rain_only_where_the_head_sees_rain():
    """mv-rain's ``where_rain``: the neighbours say how much rain there is where the head sees
    rain, never where it sees none (an edge the reprojection misses stays dry)."""
    from rainyscape.losses.multiview import evidence_error

    rain = torch.tensor([0.0, 0.1, 0.0]).view(1, 1, 1, 3).repeat(1, 3, 1, 1).requires_grad_()
    evidence = torch.full((1, 3, 1, 3), 0.3)
    defined = torch.tensor([True, True, False]).view(1, 1, 1, 3)
    ungated = evidence_error(rain, evidence, defined)
    assert torch.isclose(ungated, torch.tensor((0.3 ** 2 + 0.2 ** 2) / 2))
    (grad,) = torch.autograd.grad(ungated, rain)
    assert (grad[0, :, 0, :2] < 0).all() and (grad[0, :, 0, 2] == 0).all()  # both defined pixels rise

    (grad,) = torch.autograd.grad(evidence_error(rain, evidence, defined, where_rain=0.02), rain)
    assert (grad[0, :, 0, 0] == 0).all()  # dry to the head: the evidence does not make it rain
    assert torch.allclose(grad[0, :, 0, 1], -2 * 0.2 / 6 * torch.ones(3), rtol=1e-3)  # rain: as ungated
    assert (grad[0, :, 0, 2] == 0).all()


def test_sampling_each_view_once_matches_sampling_a_copy_per_row():
    """Rows that share a view (a batch of single rays) are read from one image, not from a
    copy per row; the colours and depths are the same to the bit."""
    g = torch.Generator().manual_seed(0)
    stack = torch.rand(5, 3, 9, 11, generator=g)
    for views in (torch.tensor([3, 1, 3, 3, 0, 1]), torch.tensor([4, 2, 0])):
        grid = torch.rand(len(views), 7, 2, generator=g) * 2.2 - 1.1  # some outside the image
        for mode in ("bilinear", "nearest"):
            copied = F.grid_sample(stack[views], grid[:, :, None], mode=mode, align_corners=False)[..., 0]
            assert torch.equal(sample_views(stack, views, grid, mode), copied)


def test_mv_rain_reads_the_brightest_within_its_reach_and_the_anchor_never_does(tiny_scene):
    from rainyscape.losses.multiview import MultiviewAnchor, MultiviewRain

    images = tiny_scene.images.permute(0, 3, 1, 2).float() / 255
    terms = [MultiviewRain(MultiviewRain.Config(reach=2)), MultiviewRain(), MultiviewAnchor()]
    for term in terms:
        term.setup(tiny_scene, torch.device("cpu"))
    for term, reach in zip(terms, (2, 0, 0)):
        expected = images if reach == 0 else torch.cat([images, brightest_within(images, reach)], 1)
        assert torch.equal(term.evidence.images, expected), type(term).__name__
