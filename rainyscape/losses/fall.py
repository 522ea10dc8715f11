"""One world direction for a scene's rain, fitted to the residual's gradients in every view.

Over its exposure a drop moves along one 3D line, its fall plus the wind, so one world
direction d fixes the streak's direction at every pixel of every view: towards d's vanishing
point (:func:`rainyscape.cameras.line_directions`). Read per view, the rain's direction
is a mode over streaks that fan out across the view (a rig looking down at a street sees them
spread over tens of degrees); fitted once over all views, the residual's scene edges, which
no one 3D direction explains in every view, are outvoted by the rain, which one does.

The fit scores candidate directions within ``max_tilt`` degrees of the world's down by how
many of the residual's gradients run across the candidate's streak at their own pixel (a
soft count: weight x exp(-(miss / tolerance)^2 / 2)), on a grid refined twice around its best.
Pure functions; the AGR term (``losses.agr.directions=world``) calls them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from rainyscape.cameras import Cameras, projected_line_angles
from rainyscape.imaging.angles import pixel_orientations


@dataclass
class GradientSamples:
    """Gradients of a residual at pixels of views: where (view index, pixel centre u, v), the
    gradient's direction ``phi`` (radians, across the structure it belongs to) and its weight."""

    view: Tensor  # (S,) long
    u: Tensor  # (S,)
    v: Tensor  # (S,)
    phi: Tensor  # (S,)
    weight: Tensor  # (S,)

    @staticmethod
    def cat(parts: "list[GradientSamples]") -> "GradientSamples":
        return GradientSamples(*(torch.cat([getattr(p, f) for p in parts]) for f in
                                 ("view", "u", "v", "phi", "weight")))


def gradient_samples(residual: Tensor, view: int, threshold: float, limit: int,
                     generator: torch.Generator | None = None, estimator: str = "gradient",
                     kernel: str = "scharr") -> GradientSamples:
    """Up to ``limit`` of the residual's (C, H, W) pixels whose gradient exceeds ``threshold``
    (Sobel gain, grey levels, as the AGR term's), drawn at random, each with its orientation and
    weight as ``estimator`` reads them (imaging/angles.py: ``pixel_orientations``)."""
    orientation, weight, magnitude = pixel_orientations(residual.float()[None], kernel, estimator)
    ys, xs = torch.nonzero(magnitude[0] > threshold, as_tuple=True)
    if len(xs) > limit:
        keep = torch.randperm(len(xs), generator=generator)[:limit].to(xs.device)
        ys, xs = ys[keep], xs[keep]
    # the valid 3x3 response at (y, x) is the pixel (y + 1, x + 1), whose centre is + 0.5
    return GradientSamples(torch.full_like(xs, view), xs.float() + 1.5, ys.float() + 1.5,
                           orientation[0, ys, xs], weight[0, ys, xs])


def tilted_directions(down: Tensor, tilts_deg: Tensor, azimuths_deg: Tensor) -> Tensor:
    """World directions (T * A, 3) leaning ``tilts_deg`` from ``down`` (3,) towards
    ``azimuths_deg`` (measured in a fixed frame around ``down``)."""
    down = down.double() / down.double().norm()
    helper = torch.eye(3, dtype=torch.float64)[int(torch.argmin(down.abs()))]
    e1 = torch.linalg.cross(down, helper)
    e1 = e1 / e1.norm()
    e2 = torch.linalg.cross(down, e1)
    t = torch.deg2rad(tilts_deg.double())[:, None, None]
    a = torch.deg2rad(azimuths_deg.double())[None, :, None]
    out = torch.cos(t) * down + torch.sin(t) * (torch.cos(a) * e1 + torch.sin(a) * e2)
    return out.reshape(-1, 3)


def fall_scores(cameras: Cameras, candidates: Tensor, samples: GradientSamples,
                tolerance_deg: float = 3.0, chunk: int = 64) -> Tensor:
    """Per candidate world direction (M, 3): the weighted soft count of the samples' gradients
    that run across the candidate's streak at their pixel."""
    rot = cameras.c2w[:, :3, :3].double().to(samples.u.device)  # (N, 3, 3), camera to world
    view = samples.view
    fx, fy, cx, cy = (t.double().to(view.device)[view] for t in (cameras.fx, cameras.fy, cameras.cx, cameras.cy))
    u, v, phi, w = samples.u.double(), samples.v.double(), samples.phi.double(), samples.weight.double()
    sigma = math.radians(tolerance_deg)
    scores = []
    for part in candidates.double().to(view.device).split(chunk):
        d_cam = torch.einsum("nji,mj->mni", rot, part)[:, view]  # (m, S, 3): R^T d per sample's view
        streak = projected_line_angles(d_cam, fx, fy, cx, cy, u, v)
        miss = torch.remainder(phi - streak, math.pi) - math.pi / 2  # 0 when the gradient runs across
        scores.append((w * torch.exp(-0.5 * (miss / sigma) ** 2)).sum(dim=1))
    return torch.cat(scores)


def fit_fall_direction(cameras: Cameras, samples: GradientSamples, down: Tensor,
                       max_tilt: float = 60.0, tolerance_deg: float = 3.0) -> Tensor:
    """The world direction (3,) within ``max_tilt`` degrees of ``down`` along which the most of
    the samples' gradients run across the streaks (see the module): a 3 x 10 degree grid of
    tilt and azimuth, then two finer grids around its best."""
    tilts = torch.arange(0.0, max_tilt + 1e-6, 3.0)
    azimuths = torch.arange(0.0, 360.0, 10.0)
    best_t, best_a = 0.0, 0.0
    for t_half, t_step, a_half, a_step in ((None, None, None, None), (3.0, 0.5, 10.0, 1.0), (0.5, 0.1, 1.0, 0.1)):
        if t_half is not None:
            tilts = (best_t + torch.arange(-t_half, t_half + 1e-6, t_step)).clamp(0.0, max_tilt).unique()
            azimuths = best_a + torch.arange(-a_half, a_half + 1e-6, a_step)
        scores = fall_scores(cameras, tilted_directions(down, tilts, azimuths), samples, tolerance_deg)
        i = int(torch.argmax(scores))
        best_t, best_a = float(tilts[i // len(azimuths)]), float(azimuths[i % len(azimuths)])
    return tilted_directions(down, torch.tensor([best_t]), torch.tensor([best_a]))[0].float()


def tilt_deg(direction: Tensor, down: Tensor) -> float:
    """Degrees between two world directions (3,), e.g. a fall and the world's down."""
    cos = float(direction.double() @ down.double() / (direction.double().norm() * down.double().norm()))
    return math.degrees(math.acos(max(-1.0, min(1.0, cos))))
