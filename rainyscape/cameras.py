"""Pinhole cameras in the OpenCV convention, image windows, and ray generation.

Convention (used everywhere inside the package):
- camera-to-world 4x4 ``c2w``; camera axes x right, y down, z forward (OpenCV / COLMAP);
- intrinsics fx, fy, cx, cy in pixels; continuous pixel coordinates put the centre of
  pixel (row i, column j) at (j + 0.5, i + 0.5), as COLMAP and gsplat do;
- every image of a scene has the same width and height.
Dataparsers convert other conventions (OpenGL / Maya / LLFF / nerfstudio) at the boundary.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from rainyscape.errors import ConfigError

# OpenGL-style camera axes (x right, y up, looking down -z) <-> OpenCV (x right, y down, z
# forward): the camera's y and z axes change sign, i.e. columns 1 and 2 of camera-to-world.
_GL_CV_SIGNS = (1.0, -1.0, -1.0, 1.0)


def opengl_to_opencv(c2w: Tensor | np.ndarray) -> Tensor | np.ndarray:
    """Camera-to-world (..., 4, 4), (..., 3, 4) or a rotation (..., 3, 3) with OpenGL camera
    axes -> OpenCV camera axes. An involution, so it also converts OpenCV -> OpenGL
    (:func:`opencv_to_opengl`). Takes a torch tensor or a numpy array and returns the same
    kind, dtype and device; the package's one conversion between the two conventions."""
    signs = _GL_CV_SIGNS[:c2w.shape[-1]]
    if isinstance(c2w, np.ndarray):
        return c2w * np.asarray(signs, dtype=c2w.dtype) + 0  # + 0: no -0.0 in written files
    return c2w * torch.tensor(signs, dtype=c2w.dtype, device=c2w.device) + 0


opencv_to_opengl = opengl_to_opencv  # the same sign flip, named for the direction written


@dataclass
class Cameras:
    c2w: Tensor  # (N, 4, 4) float32
    fx: Tensor  # (N,)
    fy: Tensor
    cx: Tensor
    cy: Tensor
    width: int
    height: int

    def __post_init__(self) -> None:
        if self.c2w.ndim != 3 or self.c2w.shape[-2:] != (4, 4):
            raise ValueError(f"c2w must be (N, 4, 4), got {tuple(self.c2w.shape)}")

    def __len__(self) -> int:
        return self.c2w.shape[0]

    def __getitem__(self, idx) -> "Cameras":
        if isinstance(idx, int):
            idx = [idx]
        if isinstance(idx, Tensor):
            idx = idx.to(self.c2w.device)
        return Cameras(self.c2w[idx], self.fx[idx], self.fy[idx], self.cx[idx], self.cy[idx],
                       self.width, self.height)

    def to(self, device) -> "Cameras":
        return Cameras(self.c2w.to(device), self.fx.to(device), self.fy.to(device),
                       self.cx.to(device), self.cy.to(device), self.width, self.height)

    @property
    def device(self) -> torch.device:
        return self.c2w.device

    @property
    def centers(self) -> Tensor:
        return self.c2w[:, :3, 3]

    def w2c(self) -> Tensor:
        """World-to-camera 4x4 (rigid inverse)."""
        rot = self.c2w[:, :3, :3]
        t = self.c2w[:, :3, 3:]
        out = torch.zeros_like(self.c2w)
        out[:, :3, :3] = rot.transpose(1, 2)
        out[:, :3, 3:] = -rot.transpose(1, 2) @ t
        out[:, 3, 3] = 1.0
        return out

    def K(self) -> Tensor:
        """Intrinsic matrices (N, 3, 3)."""
        k = torch.zeros(len(self), 3, 3, dtype=self.fx.dtype, device=self.fx.device)
        k[:, 0, 0], k[:, 1, 1] = self.fx, self.fy
        k[:, 0, 2], k[:, 1, 2] = self.cx, self.cy
        k[:, 2, 2] = 1.0
        return k

    def scaled(self, factor: float) -> "Cameras":
        """Cameras for images resized by ``factor`` (0.5 halves width and height)."""
        w, h = int(round(self.width * factor)), int(round(self.height * factor))
        sx, sy = w / self.width, h / self.height
        return Cameras(self.c2w.clone(), self.fx * sx, self.fy * sy, self.cx * sx, self.cy * sy, w, h)

    def project(self, points: Tensor) -> tuple[Tensor, Tensor]:
        """Project world points into the cameras: pixels (N, P, 2) and depths (N, P). ``points``
        (P, 3) go into every camera; (N, P, 3) are camera n's own points."""
        w2c = self.w2c()
        cam = (points if points.dim() == 3 else points[None]) @ w2c[:, :3, :3].transpose(1, 2) + w2c[:, None, :3, 3]
        z = cam[..., 2]
        u = self.fx[:, None] * cam[..., 0] / z + self.cx[:, None]
        v = self.fy[:, None] * cam[..., 1] / z + self.cy[:, None]
        return torch.stack([u, v], -1), z


def world_up(c2w: Tensor | np.ndarray) -> Tensor | np.ndarray:
    """The world's up (3,) as the cameras see it: minus their mean down (OpenCV +y) axis, unit
    length (a photographer holds the camera upright; a capture's frame has no known up).
    ``c2w`` (N, 3 or 4, 4), a torch tensor or a numpy array (the same kind comes back).
    Raises ConfigError when the cameras' down axes cancel out."""
    up = -c2w[:, :3, 1].mean(0)
    norm = float(np.linalg.norm(up) if isinstance(up, np.ndarray) else up.norm())
    if norm < 1e-6:
        raise ConfigError("the cameras' up axes cancel out: the scene has no common up (for the rain to fall along, for a camera path)")
    return up / norm


def level_up(c2w: Tensor) -> Tensor:
    """The world's up (3,) for cameras held level (no roll): the unit vector most nearly
    perpendicular to every camera's x axis (least squares), and of those the nearest to
    :func:`world_up` where the x axes leave it open (cameras that all face one way). Unlike the
    mean up it is not tilted by the cameras' pitch: an array looking down at a scene has mean
    image-up axes leaning towards the scene, its x axes stay horizontal."""
    mean = world_up(c2w).double()
    x = c2w[:, :3, 0].double()
    moments = x.T @ x / len(x)
    # (M + eps I)^-1 keeps the mean up's part along M's null space and shrinks the rest
    up = torch.linalg.solve(moments + 1e-6 * torch.eye(3, dtype=moments.dtype, device=moments.device), mean)
    return (up / up.norm()).to(c2w.dtype)


def down_directions(cameras: Cameras, up: Tensor | None = None) -> Tensor:
    """Per view (N,), the direction (radians in [0, pi), from the image +x axis towards +y, i.e.
    downwards) along which the world's down (``up`` reversed; default :func:`level_up`) runs
    through the image centre: where rain falls in each view, up to wind and perspective."""
    down = -(level_up(cameras.c2w) if up is None else up)
    d = cameras.c2w[:, :3, :3].transpose(1, 2) @ down  # in each camera's frame
    return torch.remainder(torch.atan2(cameras.fy * d[:, 1], cameras.fx * d[:, 0]), torch.pi)


def line_directions(cameras: Cameras, direction: Tensor) -> Tensor:
    """Per view and pixel (N, H, W), the direction (radians in [0, pi), from the image +x axis
    towards +y) in which a 3D line along ``direction`` (3,) (world frame) runs through the pixel's
    centre: towards the direction's vanishing point, so it is the same at any depth. A falling
    drop's streak through a pixel runs this way whatever its distance."""
    d = cameras.c2w[:, :3, :3].transpose(1, 2) @ direction.to(cameras.c2w)  # (N, 3), camera frame
    xs = torch.arange(cameras.width, dtype=d.dtype, device=d.device) + 0.5
    ys = torch.arange(cameras.height, dtype=d.dtype, device=d.device) + 0.5
    intrinsics = [v[:, None, None] for v in (cameras.fx, cameras.fy, cameras.cx, cameras.cy)]
    return projected_line_angles(d[:, None, None, :], *intrinsics, xs[None, None, :], ys[None, :, None])


def projected_line_angles(d: Tensor, fx: Tensor, fy: Tensor, cx: Tensor, cy: Tensor,
                          u: Tensor, v: Tensor) -> Tensor:
    """The image direction (radians in [0, pi), from +x towards +y) of a 3D line whose
    camera-frame direction is ``d`` (..., 3) through the pixel centre (``u``, ``v``); ``d``'s
    leading dimensions and the other arguments broadcast."""
    # d/dt of the projection of X + t d is, up to a positive factor 1 / z, (fx dx - (u - cx) dz,
    # fy dy - (v - cy) dz)
    dx, dy, dz = d.unbind(-1)
    du = fx * dx - (u - cx) * dz
    dv = fy * dy - (v - cy) * dz
    return torch.remainder(torch.atan2(dv, du), torch.pi)


@dataclass
class Window:
    """A rectangle of pixels per view: view b covers rows y0[b]:y0[b]+height, cols x0[b]:x0[b]+width."""

    x0: Tensor  # (B,) long
    y0: Tensor  # (B,) long
    width: int
    height: int

    @staticmethod
    def full(cameras: Cameras) -> "Window":
        zeros = torch.zeros(len(cameras), dtype=torch.long)
        return Window(zeros, zeros.clone(), cameras.width, cameras.height)

    def __len__(self) -> int:
        return self.x0.shape[0]

    def __getitem__(self, idx) -> "Window":
        if isinstance(idx, int):
            idx = [idx]
        return Window(self.x0[idx], self.y0[idx], self.width, self.height)

    def pixel_grid(self, device=None) -> tuple[Tensor, Tensor]:
        """Integer pixel coordinates (B, h, w) of every pixel in the window: xs, ys."""
        dev = device or self.x0.device
        jj = torch.arange(self.width, device=dev)
        ii = torch.arange(self.height, device=dev)
        ys = self.y0.to(dev)[:, None, None] + ii[None, :, None]
        xs = self.x0.to(dev)[:, None, None] + jj[None, None, :]
        return xs.expand(-1, self.height, -1), ys.expand(-1, -1, self.width)

    def random_subwindow(self, size: int, generator: torch.Generator) -> "Window":
        """A random ``size`` x ``size`` window inside each of these (image-absolute offsets)."""
        w, h = min(size, self.width), min(size, self.height)
        dx = torch.randint(self.width - w + 1, (len(self),), generator=generator)
        dy = torch.randint(self.height - h + 1, (len(self),), generator=generator)
        return Window(self.x0 + dx, self.y0 + dy, w, h)

    def table_values(self, table: Tensor, view_ids: Tensor) -> Tensor:
        """Cut the windows of the views ``view_ids`` out of a per-view table (N, H, W, C) ->
        (B, C, h, w), in the table's dtype."""
        xs, ys = self.pixel_grid(table.device)
        return table[view_ids.to(table.device)[:, None, None], ys, xs].permute(0, 3, 1, 2)

    def table_indices(self, view_ids: Tensor, height: int, width: int, device=None) -> Tensor:
        """Where each pixel of the windows of the views ``view_ids`` sits in a per-view table
        (views, ``height``, ``width``, ...) flattened over its first three dimensions: (B, h, w)."""
        xs, ys = self.pixel_grid(device)
        return (view_ids.to(xs.device)[:, None, None] * height + ys) * width + xs

    def last_writes(self, view_ids: Tensor, height: int, width: int, device=None) -> tuple[Tensor, Tensor]:
        """Writing the windows' pixels into such a table: which flattened batch rows to write
        and to which cells, of a cell given twice the later row (an assignment with repeated
        indices keeps either, by thread timing, and resumed runs would not match)."""
        flat = self.table_indices(view_ids, height, width, device).reshape(-1)
        order = torch.argsort(flat, stable=True)
        ranked = flat[order]
        last = torch.ones_like(ranked, dtype=torch.bool)
        last[:-1] = ranked[1:] != ranked[:-1]
        return order[last], ranked[last]

    def relative_to(self, outer: "Window") -> "Window":
        """This window in the pixel coordinates of ``outer`` (which contains it)."""
        return Window(self.x0 - outer.x0, self.y0 - outer.y0, self.width, self.height)

    def crop(self, images: Tensor) -> Tensor:
        """Cut the window out of per-view images (B, C, H, W) -> (B, C, h, w)."""
        xs, ys = self.pixel_grid(images.device)
        batch = torch.arange(len(self), device=images.device)[:, None, None]
        return images.permute(0, 2, 3, 1)[batch, ys, xs].permute(0, 3, 1, 2)


@dataclass
class Rays:
    origins: Tensor  # (..., 3)
    directions: Tensor  # (..., 3), unit length
    z_scale: Tensor  # (...,) cos of the angle to the optical axis: z-depth = t * z_scale


def pixel_rays(cameras: Cameras, xs: Tensor, ys: Tensor) -> Rays:
    """Rays through pixel centres. ``xs``, ``ys``: integer pixel indices (B, ...) for camera b."""
    shape = xs.shape
    b = shape[0]
    xs = xs.reshape(b, -1).to(cameras.c2w.dtype) + 0.5
    ys = ys.reshape(b, -1).to(cameras.c2w.dtype) + 0.5
    dirs_cam = torch.stack(
        [(xs - cameras.cx[:, None]) / cameras.fx[:, None],
         (ys - cameras.cy[:, None]) / cameras.fy[:, None],
         torch.ones_like(xs)], -1)  # (B, P, 3), z = 1
    norm = dirs_cam.norm(dim=-1, keepdim=True)
    dirs = (dirs_cam / norm) @ cameras.c2w[:, :3, :3].transpose(1, 2)
    origins = cameras.c2w[:, None, :3, 3].expand_as(dirs)
    return Rays(origins.reshape(*shape, 3), dirs.reshape(*shape, 3), (1.0 / norm[..., 0]).reshape(shape))


def window_rays(cameras: Cameras, window: Window) -> Rays:
    """Rays of every pixel of the window, shaped (B, h, w, 3)."""
    xs, ys = window.pixel_grid(cameras.device)
    return pixel_rays(cameras, xs, ys)
