"""Where a grid field lives: world rays -> straight rays in a sampling space -> grid coordinates.

Three layouts, chosen by the kind of capture:

- ``box`` (bounded scenes): the scene box is the grid cube [-1, 1]^3; nothing outside it.
- ``contract`` (unbounded scenes): the box maps to the inner cube [-f, f]^3 of the grid and
  everything outside it to the shell up to [-1, 1]^3 (mip-NeRF 360's contraction with the max
  norm). ``f`` (``inner``) is the share of the grid given to the box: 0.5 is the classic
  contraction, more puts more of the lattice where the content is.
- ``ndc`` (forward-facing captures, LLFF): NeRF's normalised device coordinates of the average
  training camera, where a ray is straight and its far end is at s = 1; the NDC box that the
  training cameras' rays pass through is the grid cube.

In every layout a ray is a straight line q(t) = o + t d of the *sampling space* (box
coordinates, or NDC) with a linear part [t_a, t_b]: its stretch inside the box (``box``,
``ndc``), or from the near plane to where it leaves the box (``contract``), which adds the far
part [t_b, t_far] beyond it, which the marcher samples evenly in inverse distance; t_far is
the scene's far, or (``shell_reach``) where the ray's contracted point reaches that share of
the cube, so that the far part covers the shell whatever the cameras' reach. t is a world
distance (``box``, ``contract``) or the NDC parameter s in [0, 1] (``ndc``); quadrature uses
the interval lengths in those units (NDC lengths as NeRF's LLFF mode does).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import torch
from torch import Tensor, nn

from rainyscape.fields.ndc import average_pose, ndc_near, ndc_rays, ndc_to_distance
from rainyscape.fields.sampling import ray_box_intersection
from rainyscape.scene import SceneData

LAYOUTS = ("box", "contract", "ndc")


def reach_half_size(inner: float, reach: float) -> float:
    """The half size (box units) of the cube that ``contract_to_cube`` maps to the cube of half
    size ``reach`` (inner < reach < 1): solves inner + (1 - inner)(1 - 1/r) = reach."""
    return (1.0 - inner) / (1.0 - reach)


def contract_to_cube(q: Tensor, inner: float) -> Tensor:
    """Box coordinates (..., 3) -> grid coordinates in [-1, 1]: the unit cube to [-inner, inner],
    the rest of space to the shell, x -> (inner + (1 - inner)(1 - 1/r)) x / r with r = |x|_inf."""
    r = q.abs().amax(-1, keepdim=True).clamp_min(1e-9)
    shell = (inner + (1.0 - inner) * (1.0 - 1.0 / r)) * q / r
    return torch.where(r <= 1.0, inner * q, shell)


def shell_stretch(g: Tensor, inner: float) -> Tensor:
    """Box-coordinate length per grid length along a radius at grid points (..., 3): 1 / inner
    inside, (1 - inner) / (1 - r)^2 at max norm r in the shell (the inverse derivative of the
    contraction)."""
    r = g.abs().amax(-1).clamp(max=1.0 - 1e-3)
    return torch.where(r <= inner, torch.full_like(r, 1.0 / inner), (1.0 - inner) / (1.0 - r) ** 2)


@dataclass
class SampleRays:
    """Rays in the sampling space: q(t) = origins + t directions."""

    origins: Tensor  # (R, 3)
    directions: Tensor  # (R, 3)
    t_a: Tensor  # (R,) where the ray enters the box (or the near plane)
    t_b: Tensor  # (R,) where it leaves the box; t_b <= t_a: the ray misses it
    t_far: Tensor  # (R,) the end of the ray (the far part is [t_b, t_far] for ``contract``)
    length: Tensor  # (R,) world (or NDC) length per unit of t
    ndc_dz: Tensor | None = None  # (R,) for ``ndc``: the ray's z direction in the NDC frame
    ndc_shift: Tensor | None = None  # (R,) ... and its distance to the near plane


class GridSpace(nn.Module):
    """The layout of one scene (see the module docstring); all maps are pure tensor maths."""

    def __init__(self, scene: SceneData, layout: str, inner: float = 0.5, box_scale: float = 1.0,
                 box: Tensor | None = None, shell_reach: float | None = None):
        """``box`` (2, 3): the content's bounds for ``box`` and ``contract`` (default: the
        scene's box). ``shell_reach`` (``contract``): a ray ends where it reaches this
        contracted radius of the grid cube, instead of at the scene's ``far``."""
        super().__init__()
        if layout not in LAYOUTS:
            raise ValueError(f"layout must be one of {LAYOUTS}, got {layout}")
        self.layout = layout
        self.inner = float(inner) if layout == "contract" else 1.0
        self.near, self.far = float(scene.near), float(scene.far)
        self.reach_half = None
        if layout == "contract" and shell_reach is not None:
            if not self.inner < shell_reach < 1.0:
                raise ValueError(f"shell_reach must be in ({self.inner}, 1), got {shell_reach}")
            self.reach_half = reach_half_size(self.inner, shell_reach)
        train = scene.train_indices or list(range(len(scene.cameras)))
        cams = scene.cameras[train]
        frame = average_pose(cams.c2w.float())
        self.register_buffer("ndc_frame", frame, persistent=False)
        self.ndc_scale = (float(2 * cams.fx.mean() / cams.width), float(2 * cams.fy.mean() / cams.height))
        if layout == "ndc":
            self.near = ndc_near(frame, scene.points, scene.near)
            center, half = self._ndc_box(scene, train)
        else:
            box = (scene.scene_box if box is None else box).float()
            center, half = 0.5 * (box[0] + box[1]), 0.5 * (box[1] - box[0]) * box_scale
        self.register_buffer("box_center", center, persistent=False)
        self.register_buffer("box_half", half.clamp_min(1e-3), persistent=False)

    # ------------------------------------------------------------------ set-up

    def _ndc_box(self, scene: SceneData, train: list[int]) -> tuple[Tensor, Tensor]:
        """The NDC box the training views' corner and edge rays sweep for s in [0, 1]."""
        from rainyscape.cameras import pixel_rays

        cams = scene.cameras[train]
        w, h = scene.width, scene.height
        xs = torch.tensor([0.0, w / 2, w - 1.0, 0.0, w - 1.0, 0.0, w / 2, w - 1.0])
        ys = torch.tensor([0.0, 0.0, 0.0, h / 2, h / 2, h - 1.0, h - 1.0, h - 1.0])
        pts = []
        for i in range(len(cams)):
            rays = pixel_rays(cams[[i]], xs[None], ys[None])
            o, d = self._to_frame(rays.origins.reshape(-1, 3), rays.directions.reshape(-1, 3))
            o_ndc, d_ndc, _ = ndc_rays(o, d, *self.ndc_scale, self.near)
            s = torch.tensor([0.0, 1.0])
            pts.append((o_ndc[:, None] + s[None, :, None] * d_ndc[:, None]).reshape(-1, 3))
        pts = torch.cat(pts)
        lo, hi = pts.amin(0), pts.amax(0)
        return 0.5 * (lo + hi), 0.5 * (hi - lo) * 1.02  # a margin: no sample on the border

    def _to_frame(self, origins: Tensor, directions: Tensor) -> tuple[Tensor, Tensor]:
        frame = self.ndc_frame.to(origins)
        return (origins - frame[:3, 3]) @ frame[:3, :3], directions @ frame[:3, :3]

    # ----------------------------------------------------------------- mapping

    def extent(self) -> Tensor:
        """Half sizes (3,) of the box in its own units (world, or NDC): sets lattice aspect."""
        return self.box_half

    def sample_rays(self, origins: Tensor, directions: Tensor) -> SampleRays:
        """World rays (unit directions) -> rays of the sampling space with their intervals."""
        if self.layout == "ndc":
            o_ref, d_ref = self._to_frame(origins, directions)
            o, d, shift = ndc_rays(o_ref, d_ref, *self.ndc_scale, self.near)
            o, d = (o - self.box_center) / self.box_half, d / self.box_half
            entry, exit_ = ray_box_intersection(o, d, self._unit_box(o))
            t_a, t_b = entry.clamp(0.0, 1.0), exit_.clamp(0.0, 1.0)
            length = (d * self.box_half).norm(dim=-1)
            return SampleRays(o, d, t_a, t_b, torch.ones_like(t_a), length, d_ref[:, 2], shift)
        o, d = (origins - self.box_center) / self.box_half, directions / self.box_half
        entry, exit_ = ray_box_intersection(o, d, self._unit_box(o))
        far = torch.full_like(entry, self.far)
        if self.reach_half is not None:  # where the ray reaches the contracted radius shell_reach
            far = ray_box_intersection(o, d, self.reach_half * self._unit_box(o))[1].clamp_min(self.near)
        t_a, t_b = entry.clamp_min(self.near).minimum(far), exit_.clamp_min(self.near).minimum(far)
        if self.layout == "contract":
            # Everything from the near plane is scene: the linear part starts there (content
            # between a camera and the box lives in the shell too) and runs to the box exit;
            # a ray that misses the box starts its far part at its closest approach to it.
            closest = (-(o * d).sum(-1) / (d * d).sum(-1)).clamp_min(self.near).minimum(far)
            t_b = torch.where(t_b > t_a, t_b, closest)
            t_a = torch.full_like(t_a, self.near)
        return SampleRays(o, d, t_a, t_b, far, torch.ones_like(t_a))

    @staticmethod
    def _unit_box(like: Tensor) -> Tensor:
        return torch.tensor([[-1.0] * 3, [1.0] * 3], dtype=like.dtype, device=like.device)

    def to_grid(self, q: Tensor) -> Tensor:
        """Sampling-space points (..., 3) -> grid coordinates ([-1, 1] where the grid is)."""
        return contract_to_cube(q, self.inner) if self.layout == "contract" else q

    def world_to_grid(self, points: Tensor) -> Tensor:
        """World points (..., 3) of the normalised scene -> grid coordinates (for export)."""
        if self.layout == "ndc":
            from rainyscape.fields.ndc import ndc_points

            frame = self.ndc_frame.to(points)
            ref = (points - frame[:3, 3]) @ frame[:3, :3]
            return (ndc_points(ref, *self.ndc_scale, self.near) - self.box_center) / self.box_half
        return self.to_grid((points - self.box_center) / self.box_half)

    def density_at(self, points: Tensor, sigma: Callable[[Tensor], Tensor]) -> Tensor:
        """Density (P,) at world points (P, 3) from ``sigma`` of grid coordinates; zero outside
        the grid cube (NDC and box layouts; contracted space has no outside)."""
        g = self.world_to_grid(points)
        inside = (g.abs() <= 1.0).all(-1)
        values = sigma(g.clamp(-1.0, 1.0))
        return torch.where(inside, values, torch.zeros_like(values))

    def length_per_grid(self, g: Tensor) -> Tensor:
        """Sampling-space length (world or NDC units) per grid length at grid points (..., 3),
        averaged over axes: turns a density into an opacity per grid step."""
        scale = self.box_half.mean() / self.inner
        if self.layout == "contract":
            scale = scale * self.inner * shell_stretch(g, self.inner)
        return scale * torch.ones_like(g[..., 0])

    def end_distance(self, rays: SampleRays) -> Tensor:
        """World distance (R,) where each ray ends (the depth of the light that is left): its
        ``t_far``, or the scene's far for ``ndc`` (whose rays end at infinity)."""
        return torch.full_like(rays.t_far, self.far) if self.layout == "ndc" else rays.t_far

    def distance(self, rays: SampleRays, t: Tensor, ray: Tensor | None = None) -> Tensor:
        """World distance along the ray at parameters t (for depth): t (R, ...) of every ray,
        or t (S,) of packed samples of the rays ``ray`` (S,)."""
        if self.layout != "ndc":
            return t
        shift, dz = rays.ndc_shift, rays.ndc_dz
        if ray is not None:
            return shift[ray] + ndc_to_distance(t, self.near, dz[ray])
        shape = (-1,) + (1,) * (t.dim() - 1)
        return shift.view(shape) + ndc_to_distance(t, self.near, dz.view(shape))
