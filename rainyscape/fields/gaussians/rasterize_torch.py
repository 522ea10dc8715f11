"""Tiled front-to-back alpha compositing of projected Gaussians, in vectorised torch.

The image (window) is cut into 16 x 16 tiles; every visible Gaussian is listed in each
tile its bounding box touches, the lists are sorted by depth, and all tiles are
composited together, ``slots`` Gaussians of every tile list at a time: one step works on
a (tiles, slots, 256 pixels) block, so there is no Python loop over Gaussians or pixels.
A tile leaves the sweep when its list ends or all its pixels are opaque (T < 1e-4).

Per pixel, as in gsplat and the 3DGS reference: alpha = min(0.999, o exp(-sigma)),
Gaussians with alpha < 1/255 are skipped, and compositing stops before the Gaussian
that would bring the transmittance to 1e-4 or below.

The backward pass is hand-written (:class:`_CompositeTiles`): it replays the forward
sweep and needs only the per-pixel results, so memory stays O(pixels + intersections)
instead of autograd's O(intersections x 256).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

from rainyscape.fields.gaussians.projection import ALPHA_THRESHOLD, Projection

TILE_SIZE = 16
MAX_ALPHA = 0.999
T_MIN = 1e-4
SLOTS = 32  # Gaussians per tile list handled in one step
BLOCK_ELEMENTS = 1 << 20  # bound on a (tiles, slots, pixels) step's size: memory stays flat


@dataclass
class Binning:
    """Gaussian-tile intersections, sorted by tile then depth."""

    gaussian_ids: Tensor  # (M,) index into the flattened (C * N) Gaussians
    tile_start: Tensor  # (C * tiles,) first entry of each tile's list
    tile_count: Tensor  # (C * tiles,) length of each tile's list
    tiles_x: int
    tiles_y: int
    tile_size: int


@torch.no_grad()
def bin_gaussians(proj: Projection, width: int, height: int, tile_size: int = TILE_SIZE) -> Binning:
    """List each visible Gaussian in every tile its bounding box overlaps, depth-sorted."""
    c, n = proj.radii.shape[:2]
    dev = proj.radii.device
    tiles_x, tiles_y = math.ceil(width / tile_size), math.ceil(height / tile_size)
    per_cam = tiles_x * tiles_y
    cam, gid = proj.visible.nonzero(as_tuple=True)
    mean = proj.means2d.detach()[cam, gid]
    rad = proj.radii[cam, gid].to(mean.dtype)
    lo = torch.floor((mean - rad) / tile_size)
    hi = torch.ceil((mean + rad) / tile_size)
    x0 = lo[:, 0].clamp(0, tiles_x).long()
    x1 = hi[:, 0].clamp(0, tiles_x).long()
    y0 = lo[:, 1].clamp(0, tiles_y).long()
    y1 = hi[:, 1].clamp(0, tiles_y).long()
    span = x1 - x0
    counts = span * (y1 - y0)
    rep = torch.repeat_interleave(torch.arange(len(counts), device=dev), counts)
    local = torch.arange(len(rep), device=dev) - (torch.cumsum(counts, 0) - counts)[rep]
    tile = (cam[rep] * per_cam + (y0[rep] + local // span[rep]) * tiles_x
            + x0[rep] + local % span[rep])
    # Depth rank of each visible Gaussian (ties broken by index): sort key = tile, rank.
    rank = torch.empty_like(cam)
    rank[torch.argsort(proj.depths.detach()[cam, gid], stable=True)] = torch.arange(
        len(cam), device=dev)
    order = torch.argsort(tile * max(len(cam), 1) + rank[rep])
    ids = (cam * n + gid)[rep][order]
    tile_count = torch.bincount(tile, minlength=c * per_cam)
    tile_start = torch.cumsum(tile_count, 0) - tile_count
    return Binning(ids, tile_start, tile_count, tiles_x, tiles_y, tile_size)


def _tile_geometry(binning: Binning, width: int, height: int, dtype, device):
    """Tile origins (tiles, 2), pixel-centre offsets inside a tile (s,) and which tile
    pixels fall inside the window (tiles, s * s)."""
    s = binning.tile_size
    per_cam = binning.tiles_x * binning.tiles_y
    t = torch.arange(len(binning.tile_count), device=device) % per_cam
    origin = torch.stack([t % binning.tiles_x, t // binning.tiles_x], -1) * s
    offs = torch.arange(s, device=device)
    centres = offs.to(dtype) + 0.5
    inside = (((origin[:, None, None, 0] + offs.view(1, 1, s)) < width)
              & ((origin[:, None, None, 1] + offs.view(1, s, 1)) < height))
    return origin.to(dtype), centres, inside.reshape(len(t), s * s)


def _chunk_alpha(means2d, conics, opacities, gid, slot_ok, origin, centres):
    """Alpha (A, P, K) of K Gaussians of A tiles at the tiles' P pixels, plus the per-slot
    quantities the backward pass needs. Slots are the last (contiguous) axis: the
    transmittance scans run along it, which is much faster than along a middle axis."""
    a, k = gid.shape
    s = len(centres)
    flat = gid.reshape(-1)
    mean = (means2d.index_select(0, flat).view(a, k, 2) - origin[:, None]).transpose(1, 2)
    con = conics.index_select(0, flat).view(a, k, 3).transpose(1, 2)  # (A, 3, K)
    op = opacities.index_select(0, flat).view(a, k) * slot_ok  # empty slots: opacity 0
    dx = mean[:, 0, None] - centres[:, None]  # (A, s, K): to each pixel column
    dy = mean[:, 1, None] - centres[:, None]  # (A, s, K): to each pixel row
    # -sigma = -(a dx^2 / 2 + c dy^2 / 2 + b dx dy): two separable terms and an outer product
    col = (-0.5 * con[:, 0, None] * dx * dx)[:, None]  # (A, 1, s, K)
    row = (-0.5 * con[:, 2, None] * dy * dy)[:, :, None]  # (A, s, 1, K)
    neg_sigma = torch.addcmul(col + row, (-con[:, 1, None] * dx)[:, None], dy[:, :, None])
    # Floor the exponent: far pixels would give float32 denormals, which are very slow to
    # compute; exp(-20) is far below the 1/255 threshold, so no kept alpha changes.
    raw = neg_sigma.clamp_(min=-20.0).exp_().mul_(op[:, None, None]).reshape(a, s * s, k)
    alpha = F.threshold(raw, ALPHA_THRESHOLD, 0.0).clamp_(max=MAX_ALPHA)
    return alpha, raw, op, con, dx, dy


def _transmittance(alpha: Tensor, t_start: Tensor) -> tuple[Tensor, Tensor, Tensor | None]:
    """Transmittance after each slot (A, P, K), blending weights (A, P, K), and the mask
    of kept slots when some pixel is or gets finished in this chunk (else None: all kept).

    ``t_start`` is 0 for finished pixels, which then get no weight and no gradient."""
    t_incl = torch.cumprod(torch.rsub(alpha, 1.0), -1).mul_(t_start[..., None])
    weight = torch.empty_like(t_incl)  # T_before * alpha = T_before - T_after
    torch.sub(t_start, t_incl[..., 0], out=weight[..., 0])
    torch.sub(t_incl[..., :-1], t_incl[..., 1:], out=weight[..., 1:])
    keep = None
    if bool((t_incl[..., -1] <= T_MIN).any()):
        keep = t_incl > T_MIN  # a prefix of each pixel's list
        weight.mul_(keep)
    return t_incl, weight, keep


def _sweep(means2d: Tensor, conics: Tensor, opacities: Tensor, features: Tensor,
           binning: Binning, width: int, height: int, upstream=None):
    """Composite all tiles front to back; with ``upstream`` also accumulate gradients.

    Forward: returns features and alpha, channels first: (tiles, D + 1, P).
    Backward (``upstream`` = (g_out, out), both (tiles, D + 1, P), last channel alpha):
    returns the gradients of means2d, conics, opacities and features.
    """
    dev, dt = means2d.device, means2d.dtype
    n_tiles = len(binning.tile_count)
    s = binning.tile_size
    npx = s * s
    origin, centres, inside = _tile_geometry(binning, width, height, dt, dev)
    feats = torch.cat([features, torch.ones_like(features[:, :1])], 1)  # alpha = sum of weights
    d1 = feats.shape[1]
    # Transmittance; 0 marks finished pixels (outside the window, or T would reach T_MIN).
    trans = inside.to(dt)
    ids_all = binning.gaussian_ids
    last = max(len(ids_all) - 1, 0)
    slot_range = torch.arange(SLOTS, device=dev)
    if upstream is None:
        acc = torch.zeros(n_tiles, d1, npx, device=dev, dtype=dt)
    else:
        g_out, out = upstream
        total = (g_out * out).sum(1)  # per pixel: sum over its whole list of w_k (g . f_k)
        prefix = torch.zeros(n_tiles, npx, device=dev, dtype=dt)
        grad_mean = torch.zeros_like(means2d)
        grad_conic = torch.zeros_like(conics)
        grad_opac = torch.zeros_like(opacities)
        grad_feat = torch.zeros_like(features)
    max_tiles = max(1, BLOCK_ELEMENTS // (SLOTS * npx))
    busy = (binning.tile_count > 0).nonzero().squeeze(1)
    for block in busy.split(max_tiles):
        active, start = block, 0
        while len(active):
            a = len(active)
            slot = start + slot_range
            count = binning.tile_count.index_select(0, active)
            slot_ok = slot[None] < count[:, None]  # (A, K)
            pos = (binning.tile_start.index_select(0, active)[:, None] + slot).clamp(max=last)
            gid = ids_all.index_select(0, pos.reshape(-1)).view(a, SLOTS)
            alpha, raw, op, con, dx, dy = _chunk_alpha(means2d, conics, opacities, gid, slot_ok,
                                                       origin.index_select(0, active), centres)
            t_start = trans.index_select(0, active)
            t_incl, weight, keep = _transmittance(alpha, t_start)
            flat = gid.reshape(-1)  # empty slots point at a real Gaussian, with zero gradient
            feat_t = feats.index_select(0, flat).view(a, SLOTS, d1).transpose(1, 2)  # (A, D+1, K)
            if upstream is None:
                acc.index_add_(0, active, torch.bmm(feat_t, weight.transpose(1, 2)))
            else:
                g = g_out.index_select(0, active)  # (A, D + 1, P)
                g_dot_f = torch.bmm(g.transpose(1, 2), feat_t)  # (A, P, K)
                run = weight * g_dot_f
                run[..., 0] += prefix.index_select(0, active)
                run = torch.cumsum(run, -1)
                prefix.index_copy_(0, active, run[..., -1])
                # dL/dalpha_k = (T_after_k (g . f_k) - sum_{j > k} w_j (g . f_j)) / (1 - alpha_k)
                g_alpha = (t_incl * g_dot_f).sub_(total.index_select(0, active)[..., None]).add_(run)
                g_alpha.div_(torch.rsub(alpha, 1.0))
                if keep is not None:
                    g_alpha.mul_(keep)
                # alpha = o exp(-sigma) where neither the threshold nor the clamp is active
                live = raw * ((alpha > 0) & (alpha < MAX_ALPHA))
                g_neg_sigma = g_alpha.mul_(live)  # dL/d(-sigma) = dL/dalpha * alpha
                grad_o = g_neg_sigma.sum(1) / op.clamp_min(1e-30)  # (A, K)
                gs = g_neg_sigma.reshape(a, s, s, SLOTS)  # rows, columns, slots
                col_sum, row_sum = gs.sum(1), gs.sum(2)  # (A, s, K)
                row_dx = (gs * dx[:, None]).sum(2)  # per row: sum over columns of g dx
                sx, sy = (col_sum * dx).sum(1), (row_sum * dy).sum(1)
                sxx, syy = (col_sum * dx * dx).sum(1), (row_sum * dy * dy).sum(1)
                sxy = (row_dx * dy).sum(1)
                ca, cb, cc = con.unbind(1)
                # d(-sigma)/d mean = -(a dx + b dy, b dx + c dy); d(-sigma)/d conic = -(dx^2/2, dx dy, dy^2/2)
                gm = -torch.stack([ca * sx + cb * sy, cb * sx + cc * sy], -1)
                gc = -torch.stack([0.5 * sxx, sxy, 0.5 * syy], -1)
                gf = torch.bmm(g[:, :-1], weight).transpose(1, 2)  # (A, K, D)
                grad_mean.index_add_(0, flat, gm.reshape(-1, 2))
                grad_conic.index_add_(0, flat, gc.reshape(-1, 3))
                grad_opac.index_add_(0, flat, grad_o.reshape(-1))
                grad_feat.index_add_(0, flat, gf.reshape(-1, d1 - 1))
            if keep is None:
                t_end = t_incl[..., -1]
            else:
                t_end = (t_start - weight.sum(-1)) * keep[..., -1]
            trans.index_copy_(0, active, t_end)
            start += SLOTS
            active = active[(count > start) & (t_end > 0).any(1)]
    if upstream is None:
        return acc
    return grad_mean, grad_conic, grad_opac, grad_feat


class _CompositeTiles(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means2d, conics, opacities, features, binning, width, height):
        out = _sweep(means2d, conics, opacities, features, binning, width, height)
        ctx.binning, ctx.size = binning, (width, height)
        ctx.save_for_backward(means2d, conics, opacities, features, out)
        return out

    @staticmethod
    def backward(ctx, g_out):
        means2d, conics, opacities, features, out = ctx.saved_tensors
        grads = _sweep(means2d, conics, opacities, features, ctx.binning, *ctx.size,
                       upstream=(g_out.contiguous(), out))
        return (*grads, None, None, None)


def _untile(x: Tensor, c: int, binning: Binning, width: int, height: int) -> Tensor:
    """(C * tiles, D, s * s) -> (C, height, width, D)."""
    s, tx, ty = binning.tile_size, binning.tiles_x, binning.tiles_y
    x = x.reshape(c, ty, tx, -1, s, s).permute(0, 1, 4, 2, 5, 3)
    return x.reshape(c, ty * s, tx * s, -1)[:, :height, :width]


def composite(proj: Projection, features: Tensor, width: int, height: int,
              tile_size: int = TILE_SIZE) -> tuple[Tensor, Tensor]:
    """Alpha-composite projected Gaussians into (C, height, width, D) features and
    (C, height, width, 1) alpha. ``features`` (C, N, D) are per-camera Gaussian values."""
    c, n = proj.radii.shape[:2]
    binning = bin_gaussians(proj, width, height, tile_size)
    out = _CompositeTiles.apply(
        proj.means2d.reshape(c * n, 2), proj.conics.reshape(c * n, 3),
        proj.opacities.reshape(c * n), features.reshape(c * n, features.shape[-1]), binning,
        width, height)
    out = _untile(out, c, binning, width, height)
    return out[..., :-1], out[..., -1:]
