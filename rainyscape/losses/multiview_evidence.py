"""Rain evidence from other views: what a pixel shows that its neighbours do not.

Rain streaks are bright, thin and differ from view to view; the scene does not. Every pixel
of a batch is lifted to 3D with the field's rendered depth, projected into the k nearest
training views, and compared with the median of what they see there: rain is where the
pixel is brighter than that median. A neighbour whose own depth at the projection is nearer
than the point (an occluder in front of it, judged by that view's last rendered depth) does
not vote; the median shrugs off the remaining odd neighbour (rainy itself). With a reach of r
pixels each neighbour offers the brightest it sees within r pixels of the projection: rain
only adds light, so a pixel is rain only where it is brighter than anything the neighbour
shows nearby, and an edge a rendered depth reprojects a pixel off reads as no rain. No
learning is involved, so the evidence is there from the first joint step. Pure functions on
tensors.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from rainyscape.cameras import Cameras, Window, window_rays


def neighbour_table(centers: Tensor, pool: list[int], k: int) -> Tensor:
    """(N, k') indices into the scene's views: for every view, its k nearest views of
    ``pool`` by camera centre (never itself); k' = min(k, len(pool) - 1)."""
    pool_t = torch.as_tensor(pool, dtype=torch.long, device=centers.device)
    dist = torch.cdist(centers.double(), centers[pool_t].double())  # (N, |pool|)
    dist[pool_t, torch.arange(len(pool_t), device=centers.device)] = float("inf")  # not itself
    k = max(0, min(k, len(pool_t) - 1))
    return pool_t[dist.argsort(dim=1)[:, :k]]


def backproject(cameras: Cameras, window: Window, depth: Tensor) -> Tensor:
    """World points (B, h, w, 3) of the window's pixels at z-depth ``depth`` (B, 1, h, w)."""
    rays = window_rays(cameras, window)
    t = depth[:, 0] / rays.z_scale
    return rays.origins + rays.directions * t[..., None]


def neighbour_colours(points: Tensor, neighbours: Tensor, cameras: Cameras, images: Tensor,
                      depths: Tensor | None = None, occlusion_tolerance: float = 0.05
                      ) -> tuple[Tensor, Tensor]:
    """What neighbour views see at ``points``.

    points (B, h, w, 3), neighbours (B, k) view indices, images (N, C, H, W) float.
    Returns colours (B, k, C, h, w) and validity (B, k, h, w): in front of the camera, inside
    its image and, with ``depths`` (N, 1, H, W) z-depths of every view (NaN where unknown), not
    hidden there: the view's depth at the projection is not nearer than the point's by more
    than ``occlusion_tolerance`` of it."""
    b, h, w, _ = points.shape
    k = neighbours.shape[1]
    height, width = images.shape[-2:]
    flat = points.reshape(b, 1, h * w, 3).expand(b, k, h * w, 3)
    uv, z = cameras[neighbours.reshape(-1)].project(flat.reshape(b * k, h * w, 3))  # (B k, P, 2)
    uv, z = uv.reshape(b, k, h * w, 2), z.reshape(b, k, h * w)
    grid = uv / uv.new_tensor([width, height]) * 2 - 1  # align_corners=False
    valid = (z > 1e-6) & (grid.abs() < 1).all(-1) & torch.isfinite(flat[..., 0])
    grid = torch.where(valid[..., None], grid, torch.zeros_like(grid)).reshape(b * k, h * w, 2)
    colours = sample_views(images, neighbours.reshape(-1), grid, "bilinear").reshape(b, k, -1, h, w)
    if depths is not None:
        seen = sample_views(depths, neighbours.reshape(-1), grid, "nearest").reshape(b, k, h * w)
        valid = valid & ~(seen < z * (1.0 - occlusion_tolerance))  # NaN (unknown) keeps the vote
    return colours, valid.reshape(b, k, h, w)


def brightest_within(images: Tensor, reach: int) -> Tensor:
    """``images`` (N, C, H, W) with every pixel the largest value, per channel, within ``reach``
    pixels of it (a (2 reach + 1)^2 window; the images themselves at 0)."""
    if reach <= 0:
        return images
    return F.max_pool2d(images, 2 * reach + 1, stride=1, padding=reach)


def with_brightest(images: Tensor, reach: int) -> Tensor:
    """``images`` (N, 3, H, W) with, at a reach above 0, their :func:`brightest_within` as
    channels 3:6, so that one sampling reads both."""
    return images if reach <= 0 else torch.cat([images, brightest_within(images, reach)], 1)


def sample_views(stack: Tensor, views: Tensor, grid: Tensor, mode: str) -> Tensor:
    """``stack`` (N, C, H, W) read at ``grid`` (M, P, 2; normalised, align_corners=False) in
    the views ``views`` (M,): (M, C, P). Each distinct view is sampled once with all its
    points, never copied per row: a batch of single rays has hundreds of rows (768 rays of 6
    neighbours gathered 4608 whole images a step, most of the grid field's joint step)."""
    m, p, _ = grid.shape
    distinct = views.unique()
    if len(distinct) == m:  # no view twice (whole views): one call over the gathered images
        return F.grid_sample(stack[views], grid[:, :, None], mode=mode, align_corners=False)[..., 0]
    out = grid.new_empty(m, stack.shape[1], p)
    for v in distinct.tolist():
        rows = (views == v).nonzero().squeeze(1)
        sampled = F.grid_sample(stack[v:v + 1], grid[rows].reshape(1, -1, 1, 2), mode=mode,
                                align_corners=False)  # (1, C, rows P, 1)
        out[rows] = sampled.reshape(stack.shape[1], len(rows), p).transpose(0, 1)
    return out


def neighbour_median(colours: Tensor, valid: Tensor, min_views: int = 2) -> tuple[Tensor, Tensor]:
    """The median (B, C, h, w) of what the valid neighbours see (colours (B, k, C, h, w), valid
    (B, k, h, w)), and where it is defined (B, 1, h, w): at least ``min_views`` of them (the
    median is NaN elsewhere)."""
    nan = torch.full_like(colours, float("nan"))
    ref = torch.where(valid[:, :, None], colours, nan).nanmedian(dim=1).values
    return ref, valid.sum(1, keepdim=True) >= min_views


def evidence_over(observed: Tensor, ref: Tensor, defined: Tensor) -> Tensor:
    """How much brighter ``observed`` (B, 3, h, w) is than the neighbours' median ``ref``, where
    that is ``defined`` (0 elsewhere)."""
    evidence = (observed - ref).clamp_min(0)
    return torch.where(defined & torch.isfinite(evidence), evidence, torch.zeros_like(evidence))


def evidence_with_reach(at_point: Tensor, within: Tensor, gain: float) -> Tensor:
    """The evidence against the neighbours' brightest within a reach (``within``), or with
    ``gain`` > 0 the evidence against what they see at the projection itself (``at_point``)
    capped at ``gain`` times it: a streak over a smooth background keeps its whole evidence,
    an edge reprojected a pixel off (next to nothing within the reach) keeps little."""
    return torch.minimum(at_point, gain * within) if gain > 0 else within


def rain_evidence(observed: Tensor, colours: Tensor, valid: Tensor, min_views: int = 2
                  ) -> tuple[Tensor, Tensor]:
    """How much brighter each pixel is than the median of its neighbours' views.

    observed (B, 3, h, w), colours (B, k, 3, h, w), valid (B, k, h, w). Returns the evidence
    (B, 3, h, w) >= 0 and where it is defined (B, 1, h, w): at least ``min_views`` valid
    neighbours."""
    ref, defined = neighbour_median(colours, valid, min_views)
    return evidence_over(observed, ref, defined), defined
