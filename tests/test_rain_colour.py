"""imaging/colour.py and the rain head's field_colour: rain pulls a pixel towards one colour;
detail the field missed leaves a residual in its own colour."""

import torch

from rainyscape.imaging.colour import colour_weights, departure, fit_colour, solved_colour
from tests.test_rain_head import _head, _scene

RAIN = torch.tensor([0.9, 0.95, 1.0])


def _composite(background: torch.Tensor, alpha: torch.Tensor, colour: torch.Tensor = RAIN) -> torch.Tensor:
    return background * (1 - alpha) + colour.view(1, 3, 1, 1) * alpha


def test_departure_is_zero_on_rain_and_large_on_a_residual_in_another_colour():
    g = torch.Generator().manual_seed(0)
    background = torch.rand(1, 3, 8, 8, generator=g) * 0.6
    rain = _composite(background, torch.full((1, 1, 8, 8), 0.3)) - background
    assert float(departure(rain, background, RAIN).max()) < 1e-4
    # a green leaf the field rendered too dark: the residual is the leaf's own green
    leaf = torch.tensor([0.05, 0.3, 0.02]).view(1, 3, 1, 1).expand(1, 3, 8, 8)
    green = torch.tensor([0.1, 0.4, 0.1]).view(1, 3, 1, 1).expand(1, 3, 8, 8)
    assert float(departure(leaf, green, RAIN).min()) > 0.4
    # darker than the render: away from the rain's colour altogether
    assert torch.allclose(departure(-rain, background, RAIN), torch.ones(1, 8, 8))
    # a flat residual is not read
    assert float(departure(torch.zeros(1, 3, 8, 8), background, RAIN).abs().max()) == 0.0


def test_the_colour_fit_finds_the_rains_colour_from_white():
    g = torch.Generator().manual_seed(1)
    background = torch.rand(2, 3, 16, 16, generator=g) * 0.7
    alpha = torch.rand(2, 1, 16, 16, generator=g) * 0.8 + 0.1
    residual = _composite(background, alpha) - background
    colour = fit_colour(residual, background, torch.ones(2, 16, 16, dtype=torch.bool))
    assert torch.allclose(colour, RAIN, atol=2e-3)


def test_colour_weights_fall_from_one_to_zero_between_the_start_and_twice_it():
    w = colour_weights(torch.tensor([0.0, 0.1, 0.15, 0.2, 0.9]), 0.1)
    assert torch.allclose(w, torch.tensor([1.0, 1.0, 0.5, 0.0, 0.0]))


def test_the_field_is_fitted_without_the_rain_that_has_the_rains_colour_only():
    """field_colour: R over rain is kept for the field, R over a leaf's own-colour residual
    is not; off, R is returned whole; in training the head's colour moves towards the rain's."""
    scene = _scene(n=1, height=16, width=16)
    background = torch.tensor([0.1, 0.4, 0.1]).view(1, 3, 1, 1).repeat(1, 1, 16, 16)
    alpha = torch.zeros(1, 1, 16, 16)
    alpha[..., :8] = 0.3  # rain on the left half
    target = _composite(background, alpha)
    target[..., 8:] += torch.tensor([0.05, 0.3, 0.02]).view(1, 3, 1, 1)  # a missed leaf on the right
    residual = target - background
    layer = residual.clamp_min(0)  # the head took both for rain
    view = torch.tensor([0])
    assert _head(scene).for_field(layer, residual, view, background) is layer
    head = _head(scene, field_colour=0.1).train()
    kept = head.for_field(layer, residual, view, background)
    assert torch.allclose(kept[..., :8], layer[..., :8], atol=1e-5)
    assert float(kept[..., 8:].abs().max()) == 0.0
    assert float((head.rain_colour - RAIN).abs().max()) < 0.2  # from white, in one step
    assert "rain_colour" in head.state_dict() and "rain_colour" not in _head(scene).state_dict()


def test_residuals_darker_in_a_channel_leave_the_colour_fit_alone():
    """Rain adds light: detail brighter in red and darker in green and blue (a red edge the
    field missed) pulled the fitted colour off the rain's (to 0.89 / 0.88 / 0.93 here) and,
    within a run, to black; darker pixels alone leave no pixel to fit, and the colour stays."""
    g = torch.Generator().manual_seed(1)
    background = torch.rand(2, 3, 16, 16, generator=g) * 0.7
    alpha = torch.rand(2, 1, 16, 16, generator=g) * 0.8 + 0.1
    residual = _composite(background, alpha) - background
    residual[..., :8, :8] = torch.tensor([0.4, -0.1, -0.1]).view(1, 3, 1, 1)
    everywhere = torch.ones(2, 16, 16, dtype=torch.bool)
    assert torch.allclose(fit_colour(residual, background, everywhere), RAIN, atol=2e-3)
    assert torch.equal(fit_colour(-residual.abs(), background, everywhere), torch.ones(3))


def test_the_heads_colour_stays_white_until_a_pixel_is_rain():
    scene = _scene(n=1, height=16, width=16)
    head = _head(scene, field_colour=0.1).train()
    background = torch.full((1, 3, 16, 16), 0.5)
    residual = torch.full((1, 3, 16, 16), -0.2)  # a field brighter than its input
    head.for_field(torch.full((1, 3, 16, 16), 0.3), residual, torch.tensor([0]), background)
    assert torch.equal(head.rain_colour, torch.ones(3))


def test_the_solved_colour_is_the_sums_ratio_or_the_previous_one_when_nothing_counted():
    previous = torch.tensor([0.9, 0.8, 0.7])
    assert torch.allclose(solved_colour(torch.tensor([1.0, 2.0, 4.0]), torch.tensor(4.0), previous),
                          torch.tensor([0.25, 0.5, 1.0]))
    assert torch.equal(solved_colour(torch.zeros(3), torch.tensor(0.0), previous), previous)
