"""Projection of 3D Gaussians to screen-space ellipses (EWA splatting), pure torch.

Follows the conventions of gsplat 1.x (and the 3DGS reference) so that the torch and the
CUDA paths agree: OpenCV camera (x right, y down, z forward), pixel centre of (row i,
column j) at (j + 0.5, i + 0.5), quaternions w x y z (normalised here), a 2D dilation
``eps2d`` added to the projected covariance, the Jacobian evaluated at the mean clamped
to 1.3 x the field of view (keeps off-screen Gaussians from exploding), and an
opacity-aware bounding box: a Gaussian contributes only where alpha >= 1/255.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

ALPHA_THRESHOLD = 1.0 / 255.0
MAX_EXTENT_SIGMA = 3.33  # exp(-3.33^2 / 2) < 1/255: no contribution beyond, whatever the opacity


@dataclass
class Projection:
    """Per camera and Gaussian; coordinates are window pixels (window origin at 0, 0)."""

    means2d: Tensor  # (C, N, 2) differentiable
    conics: Tensor  # (C, N, 3) inverse 2D covariance (a, b, c), differentiable
    depths: Tensor  # (C, N) camera-space z, differentiable
    opacities: Tensor  # (C, N) differentiable
    radii: Tensor  # (C, N, 2) int32 bounding-box half sizes in pixels; 0 where culled

    @property
    def visible(self) -> Tensor:
        return (self.radii > 0).all(-1)


def quat_to_rotmat(quats: Tensor) -> Tensor:
    """Rotation matrices (N, 3, 3) from quaternions (N, 4), w x y z, any norm."""
    w, x, y, z = torch.nn.functional.normalize(quats, dim=-1).unbind(-1)
    return torch.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ], -1).reshape(*quats.shape[:-1], 3, 3)


def covariance_factor(quats: Tensor, scales: Tensor) -> Tensor:
    """M = R S with Sigma = M M^T (N, 3, 3); scales are linear (not log)."""
    return quat_to_rotmat(quats) * scales[..., None, :]


@torch.no_grad()
def candidate_gaussians(means: Tensor, scales: Tensor, opacities: Tensor, viewmats: Tensor,
                        Ks: Tensor, width: int, height: int, window_x0: Tensor,
                        window_y0: Tensor, window_width: int, window_height: int,
                        near_plane: float = 0.01, far_plane: float = 1e10,
                        eps2d: float = 0.3) -> Tensor:
    """Indices of the Gaussians that may be visible in some camera's window: a cheap
    superset of :func:`project_gaussians`'s visible set, so that the costly differentiable
    projection, colour and compositing run on these only (a patch sees a few percent of a
    scene's Gaussians).

    The bound: a screen-space standard deviation is at most max(scale) times the norm of
    the Jacobian row, f / z sqrt(1 + t^2) at the clamped mean t (W is a rotation), and the
    box reaches ``MAX_EXTENT_SIGMA`` of them (plus the dilation); one pixel of slack.
    """
    dev, dt = means.device, means.dtype
    rot, trans = viewmats[:, :3, :3].to(dt), viewmats[:, :3, 3].to(dt)
    p = means @ rot.transpose(1, 2) + trans[:, None]  # (C, N, 3)
    x, y, z = p.unbind(-1)
    in_depth = (z > near_plane) & (z < far_plane)
    z_safe = torch.where(in_depth, z, torch.ones_like(z))
    fx, fy = Ks[:, 0, 0, None].to(dt), Ks[:, 1, 1, None].to(dt)
    cx, cy = Ks[:, 0, 2, None].to(dt), Ks[:, 1, 2, None].to(dt)
    xz, yz = x / z_safe, y / z_safe
    lim_x, lim_y = 0.3 * 0.5 * width / fx, 0.3 * 0.5 * height / fy
    tx = torch.clamp(xz, min=-(cx / fx + lim_x), max=(width - cx) / fx + lim_x)
    ty = torch.clamp(yz, min=-(cy / fy + lim_y), max=(height - cy) / fy + lim_y)
    s_max = scales.amax(-1)[None]
    sx = s_max * fx / z_safe * torch.sqrt(1 + tx * tx)
    sy = s_max * fy / z_safe * torch.sqrt(1 + ty * ty)
    rx = MAX_EXTENT_SIGMA * torch.sqrt(sx * sx + eps2d) + 1.0
    ry = MAX_EXTENT_SIGMA * torch.sqrt(sy * sy + eps2d) + 1.0
    mx = fx * xz + cx - window_x0.to(dev, dt)[:, None]
    my = fy * yz + cy - window_y0.to(dev, dt)[:, None]
    on_screen = ((mx + rx > 0) & (mx - rx < window_width)
                 & (my + ry > 0) & (my - ry < window_height))
    ok = in_depth & on_screen & (opacities >= ALPHA_THRESHOLD)
    return ok.any(0).nonzero().squeeze(1)


def project_gaussians(means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor,
                      viewmats: Tensor, Ks: Tensor, width: int, height: int,
                      window_x0: Tensor | None = None, window_y0: Tensor | None = None,
                      window_width: int | None = None, window_height: int | None = None,
                      near_plane: float = 0.01, far_plane: float = 1e10,
                      eps2d: float = 0.3) -> Projection:
    """Project N Gaussians into C cameras, in the coordinates of each camera's window.

    ``width`` / ``height`` are the full image size (they set the Jacobian clamp, so a
    window renders exactly as the same pixels of the full image); the window (per-camera
    offsets, shared size; default the whole image) sets the coordinates and the culling.
    """
    c = viewmats.shape[0]
    dev, dt = means.device, means.dtype
    win_w = width if window_width is None else window_width
    win_h = height if window_height is None else window_height
    x0 = torch.zeros(c, device=dev, dtype=dt) if window_x0 is None else window_x0.to(dev, dt)
    y0 = torch.zeros(c, device=dev, dtype=dt) if window_y0 is None else window_y0.to(dev, dt)
    if opacities.ndim == 1:
        opacities = opacities[None].expand(c, -1)

    rot = viewmats[:, :3, :3]
    p = torch.einsum("cij,nj->cni", rot, means) + viewmats[:, None, :3, 3]  # (C, N, 3)
    x, y, z = p.unbind(-1)
    in_depth = (z > near_plane) & (z < far_plane)
    z_safe = torch.where(in_depth, z, torch.ones_like(z))  # culled ones: finite, no gradient
    fx, fy = Ks[:, 0, 0, None], Ks[:, 1, 1, None]
    cx, cy = Ks[:, 0, 2, None], Ks[:, 1, 2, None]
    xz, yz = x / z_safe, y / z_safe
    means2d = torch.stack([fx * xz + cx - x0[:, None], fy * yz + cy - y0[:, None]], -1)

    # EWA: J W Sigma W^T J^T with the Jacobian J of the perspective map at the clamped mean.
    lim_x = 0.3 * 0.5 * width / fx
    lim_y = 0.3 * 0.5 * height / fy
    tx = torch.clamp(xz, min=-(cx / fx + lim_x), max=(width - cx) / fx + lim_x)
    ty = torch.clamp(yz, min=-(cy / fy + lim_y), max=(height - cy) / fy + lim_y)
    w0, w1, w2 = rot[:, None, 0], rot[:, None, 1], rot[:, None, 2]  # rows of W, (C, 1, 3)
    row_x = (fx / z_safe)[..., None] * (w0 - tx[..., None] * w2)  # rows of J W, (C, N, 3)
    row_y = (fy / z_safe)[..., None] * (w1 - ty[..., None] * w2)
    m = covariance_factor(quats, scales)  # (N, 3, 3)
    ax = torch.einsum("cni,nij->cnj", row_x, m)
    ay = torch.einsum("cni,nij->cnj", row_y, m)
    cov_a = (ax * ax).sum(-1) + eps2d
    cov_b = (ax * ay).sum(-1)
    cov_c = (ay * ay).sum(-1) + eps2d
    det = cov_a * cov_c - cov_b * cov_b
    det_ok = det > 0
    det_safe = torch.where(det_ok, det, torch.ones_like(det))
    conics = torch.stack([cov_c / det_safe, -cov_b / det_safe, cov_a / det_safe], -1)

    with torch.no_grad():
        op = opacities.detach()
        extent = torch.sqrt(2.0 * torch.log((op / ALPHA_THRESHOLD).clamp_min(1.0)))
        extent = extent.clamp(max=MAX_EXTENT_SIGMA)
        rx = torch.ceil(extent * cov_a.detach().sqrt())
        ry = torch.ceil(extent * cov_c.detach().sqrt())
        mx, my = means2d.detach().unbind(-1)
        on_screen = (mx + rx > 0) & (mx - rx < win_w) & (my + ry > 0) & (my - ry < win_h)
        keep = in_depth & det_ok & (op >= ALPHA_THRESHOLD) & ((rx > 0) | (ry > 0)) & on_screen
        radii = torch.stack([rx, ry], -1).to(torch.int32) * keep[..., None]
    return Projection(means2d, conics, z, opacities, radii)
