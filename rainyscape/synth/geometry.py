"""Scene building blocks: textured trimesh parts in a Y-up world (metres).

A :class:`Part` is a mesh plus the texture of its side faces and, optionally, of its
upward faces (roofs, decks). Texture coordinates come from the surface itself (see
:func:`surface_uv`), so parts need no UV maps.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import trimesh


@dataclass
class Part:
    mesh: trimesh.Trimesh
    texture: str
    params: dict = field(default_factory=dict)
    top: str | None = None  # texture of faces whose normal points up (None: same as sides)
    top_params: dict = field(default_factory=dict)
    base_y: float = 0.0  # facade heights are measured from here
    axis: tuple[float, float] | None = None  # (x, z) of a vertical axis: cylindrical mapping
    seed: int = 0


def _place(mesh: trimesh.Trimesh, x: float, y: float, z: float, yaw_deg: float = 0.0) -> trimesh.Trimesh:
    rot = trimesh.transformations.rotation_matrix(np.radians(yaw_deg), [0, 1, 0])
    mesh.apply_transform(rot)
    mesh.apply_translation([x, y, z])
    return mesh


def box(x: float, y0: float, z: float, sx: float, sy: float, sz: float, yaw: float = 0.0) -> trimesh.Trimesh:
    """Axis-aligned box (before ``yaw`` about Y) with its bottom face at height ``y0``."""
    return _place(trimesh.creation.box((sx, sy, sz)), x, y0 + sy / 2, z, yaw)


def vcylinder(x: float, y0: float, z: float, radius: float, height: float, sections: int = 20) -> trimesh.Trimesh:
    """Vertical cylinder standing on height ``y0``."""
    mesh = trimesh.creation.cylinder(radius=radius, height=height, sections=sections)
    mesh.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [1, 0, 0]))
    return _place(mesh, x, y0 + height / 2, z)


def hcylinder(x: float, y: float, z: float, radius: float, length: float, yaw: float = 0.0,
              sections: int = 16) -> trimesh.Trimesh:
    """Horizontal cylinder along X (then ``yaw``) centred at (x, y, z): wheels, pipes, rails."""
    mesh = trimesh.creation.cylinder(radius=radius, height=length, sections=sections)
    mesh.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [0, 1, 0]))
    return _place(mesh, x, y, z, yaw)


def prism(profile: np.ndarray, length: float, x: float, y: float, z: float, yaw: float = 0.0) -> trimesh.Trimesh:
    """Extrude a convex 2D profile (P, 2) in the X-Y plane along Z by ``length`` (centred)."""
    n = len(profile)
    faces = np.array([[0, i, i + 1] for i in range(1, n - 1)])
    mesh = trimesh.creation.extrude_triangulation(profile, faces, length)
    mesh.apply_translation([0, 0, -length / 2])
    if mesh.volume < 0:
        mesh.invert()
    return _place(mesh, x, y, z, yaw)


def hull(points: np.ndarray, x: float, y: float, z: float, yaw: float = 0.0) -> trimesh.Trimesh:
    """Convex hull of points (a boat hull, a car nose)."""
    return _place(trimesh.convex.convex_hull(points), x, y, z, yaw)


def blob(x: float, y: float, z: float, radius: float, squash: float, seed: int) -> trimesh.Trimesh:
    """A lumpy sphere (tree crown, bush): an icosphere with radial noise on its vertices."""
    mesh = trimesh.creation.icosphere(subdivisions=2, radius=radius)
    rng = np.random.default_rng(seed)
    mesh.vertices *= (1.0 + 0.18 * rng.uniform(-1, 1, (len(mesh.vertices), 1)))
    mesh.vertices[:, 1] *= squash
    return _place(mesh, x, y, z)


def surface_uv(points: np.ndarray, normals: np.ndarray, base_y: np.ndarray,
               axis: np.ndarray | None = None) -> tuple[np.ndarray, ...]:
    """Texture coordinates (u, v) in metres, a mask of upward faces, and the gradients of u
    and v with respect to the surface point (M, 3) each (for footprints).

    Upward faces map (x, z); walls map (horizontal distance along the wall, height above
    ``base_y``); parts with a vertical ``axis`` (M, 2) map (arc length, height).
    """
    m = len(points)
    up = normals[:, 1] > 0.7
    tangent = np.stack([normals[:, 2], np.zeros(m), -normals[:, 0]], 1)
    tangent /= np.maximum(np.linalg.norm(tangent, axis=1, keepdims=True), 1e-9)
    u = np.einsum("ij,ij->i", points, tangent)
    v = points[:, 1] - base_y
    grad_u = tangent.copy()
    grad_v = np.tile([0.0, 1.0, 0.0], (m, 1))
    if axis is not None:
        has_axis = ~np.isnan(axis[:, 0])
        dx, dz = points[:, 0] - axis[:, 0], points[:, 2] - axis[:, 1]
        radius = np.hypot(dx, dz)
        r_map = np.maximum(radius, 0.05)
        u = np.where(has_axis, np.arctan2(dz, dx) * r_map, u)
        r2 = np.maximum(radius * radius, 1e-12)
        arc = np.stack([-dz, np.zeros(m), dx], 1) * (r_map / r2)[:, None]
        grad_u = np.where(has_axis[:, None], arc, grad_u)
    u = np.where(up, points[:, 0], u)
    v = np.where(up, points[:, 2], v)
    grad_u = np.where(up[:, None], np.array([1.0, 0.0, 0.0]), grad_u)
    grad_v = np.where(up[:, None], np.array([0.0, 0.0, 1.0]), grad_v)
    return u, v, up, grad_u, grad_v
