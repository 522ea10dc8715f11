"""The rain's colour, and how far a residual departs from it.

Rain is a translucent layer of one colour c over the scene, I = (1 - a) B + a c (the
simulator's model, and the usual one for real streaks, which take the light around them):
where a pixel is rain, the residual I - B points from the background B towards c. Detail the
field has not fitted yet (a bright leaf against a dark wall) leaves a residual in the
detail's own colour instead, off that line (docs/rain.md, "The field fitted without the
rain that has the rain's colour").
"""

from __future__ import annotations

import torch
from torch import Tensor

# the residual's length under which its direction is not read (a pixel the field fits)
FLAT = 1e-3
# a running fit of the colour: its sums forget this share a step
COLOUR_FORGET = 0.1


def _towards(background: Tensor, colour: Tensor) -> Tensor:
    return colour.view(1, 3, 1, 1) - background


def _amounts(residual: Tensor, towards: Tensor) -> Tensor:
    """(B, 1, H, W) the a >= 0 that best explains ``residual`` (B, 3, H, W) = a ``towards``."""
    return ((residual * towards).sum(1, keepdim=True)
            / (towards * towards).sum(1, keepdim=True).clamp_min(1e-6)).clamp_min(0)


def departure(residual: Tensor, background: Tensor, colour: Tensor) -> Tensor:
    """(B, H, W) the share of the residual's length off the line from the background towards
    the rain's colour: 0 for rain, 1 for a residual that points away from c; 0 where the
    residual is flat."""
    towards = _towards(background, colour)
    off = residual - _amounts(residual, towards) * towards
    length = residual.norm(dim=1)
    return torch.where(length > FLAT, off.norm(dim=1) / length.clamp_min(FLAT), torch.zeros_like(length))


def colour_sums(residual: Tensor, background: Tensor, colour: Tensor, where: Tensor) -> tuple[Tensor, Tensor]:
    """The sums of one least-squares step for c from the pixels ``where`` (B, H, W) whose
    residual is brighter in every channel: with each pixel's a from the current ``colour``,
    residual = a c - a B gives c = sum a (r + a B) / sum a^2. Returns (numerator (3,),
    denominator ()).

    Rain adds light: a residual darker in some channel (detail the field has not fitted, a
    field brighter than its input) is not rain, and counted it pulls c off the rain's colour
    towards its own. Each counted pixel's estimate B + r / a is then at least its background,
    so c cannot sink under the backgrounds it is fitted on; counted, such pixels took the
    fit from white to black within a run, after which no rain had the rain's colour
    (docs/rain.md, "The rain's colour fitted on the pixels rain brightens")."""
    where = where & (residual >= 0).all(1)
    a = _amounts(residual, _towards(background, colour))[:, 0][where]
    r = residual.permute(0, 2, 3, 1)[where]
    b = background.permute(0, 2, 3, 1)[where]
    return (a[:, None] * (r + a[:, None] * b)).sum(0), (a * a).sum()


def solved_colour(num: Tensor, den: Tensor, previous: Tensor) -> Tensor:
    """The colour (3,) from :func:`colour_sums`' sums; ``previous`` where no pixel was counted
    (``den`` 0), so that an empty batch cannot set it to black. No host sync."""
    return torch.where(den > 0, (num / torch.where(den > 0, den, torch.ones_like(den))).clamp(0, 1), previous)


def refit_colour(sums: Tensor, residual: Tensor, background: Tensor, colour: Tensor,
                 where: Tensor) -> tuple[Tensor, Tensor]:
    """One step of a running fit of the colour: ``sums`` (4,), the running numerator and
    denominator of :func:`colour_sums`, forget ``COLOUR_FORGET`` and take this batch's; returns
    the new sums and colour (``colour`` until a pixel it explains is counted: white at first)."""
    num, den = colour_sums(residual, background, colour, where)
    sums = sums * (1 - COLOUR_FORGET) + torch.cat([num, den[None]])
    return sums, solved_colour(sums[:3], sums[3], colour)


def fit_colour(residual: Tensor, background: Tensor, where: Tensor, steps: int = 100) -> Tensor:
    """The rain's colour (3,) fitted from white on the pixels ``where`` by ``steps`` of
    :func:`colour_sums` (alternating steps: slow along c itself, so many of them)."""
    colour = torch.ones(3, device=residual.device)
    for _ in range(steps):
        colour = solved_colour(*colour_sums(residual, background, colour, where), colour)
    return colour


def colour_weights(departed: Tensor, start: float) -> Tensor:
    """1 where the departure is under ``start``, falling to 0 at twice it."""
    return (2.0 - departed / start).clamp(0, 1)
