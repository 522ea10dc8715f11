"""Clean-image rendering: embree ray casting (through trimesh) with sun, sky light and shadows.

Per pixel the centre ray gives depth and normal (exact pixel-centre geometry, which the
reprojection tests rely on); colour averages the centre and four sub-pixel rays so edges
and texture detail are anti-aliased rather than sparkling.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from trimesh.ray.ray_pyembree import RayMeshIntersector

from rainyscape.cameras import Cameras
from rainyscape.synth.geometry import surface_uv
from rainyscape.synth.scenes import SceneSpec
from rainyscape.synth.textures import TEXTURES, fbm

# Centre first (depth / normal), then a rotated 2 x 2 grid (sub-pixel offsets in pixels).
SAMPLE_OFFSETS = np.array([[0.0, 0.0], [-0.125, -0.375], [0.375, -0.125], [0.125, 0.375], [-0.375, 0.125]])


@dataclass
class ViewRender:
    rgb: np.ndarray  # (H, W, 3) float in [0, 1]
    depth: np.ndarray  # (H, W) z-depth, inf where the ray sees the sky
    normal: np.ndarray  # (H, W, 3) world normal facing the camera (0 for sky)


def camera_rays(cameras: Cameras, index: int, offsets: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rays of every pixel for each sub-pixel offset: origins (3,), unit dirs (S, H*W, 3), z_scale.

    Same convention as :func:`rainyscape.cameras.pixel_rays`: pixel (i, j) centre at (j+.5, i+.5).
    """
    w, h = cameras.width, cameras.height
    c2w = cameras.c2w[index].double().numpy()
    fx, fy = float(cameras.fx[index]), float(cameras.fy[index])
    cx, cy = float(cameras.cx[index]), float(cameras.cy[index])
    jj, ii = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    xs = jj.ravel()[None] + offsets[:, :1]
    ys = ii.ravel()[None] + offsets[:, 1:]
    d = np.stack([(xs - cx) / fx, (ys - cy) / fy, np.ones_like(xs)], -1)
    norm = np.linalg.norm(d, axis=-1, keepdims=True)
    dirs = (d / norm) @ c2w[:3, :3].T
    return c2w[:3, 3], dirs, 1.0 / norm[..., 0]


class SceneRenderer:
    def __init__(self, spec: SceneSpec):
        self.spec = spec
        mesh, owner = spec.mesh()
        self.mesh = mesh
        self.owner = owner
        self.face_normals = np.asarray(mesh.face_normals, np.float64)
        self.plane_points = np.asarray(mesh.triangles[:, 0], np.float64)
        self.intersector = RayMeshIntersector(mesh)
        self.sun = np.asarray(spec.sun_dir, float) / np.linalg.norm(spec.sun_dir)
        parts = spec.parts
        self.base_y = np.array([p.base_y for p in parts])
        self.axis = np.array([p.axis if p.axis is not None else (np.nan, np.nan) for p in parts])

    def cast(self, origins: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """First hit per ray: distance along the ray (inf on a miss) and triangle (-1)."""
        face = np.asarray(self.intersector.intersects_first(origins, dirs), np.int64)
        hit = face >= 0
        t = np.full(len(dirs), np.inf)
        # distance to the hit triangle's plane (cheaper than trimesh's location query)
        n = self.face_normals[face[hit]]
        t[hit] = (np.einsum("ij,ij->i", self.plane_points[face[hit]] - origins[hit], n)
                  / np.einsum("ij,ij->i", dirs[hit], n))
        return t, face

    def sky(self, dirs: np.ndarray) -> np.ndarray:
        """Overcast sky: horizon-to-zenith gradient with soft cloud banks."""
        up = np.clip(dirs[:, 1], 0.0, 1.0)
        t = np.sqrt(up)[:, None]
        col = np.asarray(self.spec.sky_horizon) * (1 - t) + np.asarray(self.spec.sky_zenith) * t
        k = 1.0 / np.maximum(dirs[:, 1], 0.05)
        clouds = fbm(dirs[:, 0] * k, dirs[:, 2] * k, 0.8, 4, 17)
        return np.clip(col * (0.85 + 0.3 * clouds[:, None]), 0, 1)

    def albedo(self, points: np.ndarray, normals: np.ndarray, faces: np.ndarray) -> np.ndarray:
        part = self.owner[faces]
        u, v, up = surface_uv(points, normals, self.base_y[part], self.axis[part])
        out = np.empty((len(points), 3))
        order = np.argsort(part, kind="stable")
        bounds = np.searchsorted(part[order], np.arange(len(self.spec.parts) + 1))
        for k, p in enumerate(self.spec.parts):  # one vectorised texture call per part
            idx = order[bounds[k]:bounds[k + 1]]
            if not len(idx):
                continue
            top = up[idx] if p.top is not None else np.zeros(len(idx), bool)
            for mask, name, params in ((~top, p.texture, p.params), (top, p.top, p.top_params)):
                sel = idx[mask]
                if len(sel):
                    out[sel] = TEXTURES[name](u[sel], v[sel], p.seed, **params)
        return out

    def shade(self, origin: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Colour, distance and facing normal of rays from one origin."""
        origins = np.broadcast_to(origin, dirs.shape)
        t, face = self.cast(origins, dirs)
        hit = face >= 0
        rgb = np.empty_like(dirs)
        rgb[~hit] = self.sky(dirs[~hit])
        normals = np.zeros_like(dirs)
        if hit.any():
            p = origin + dirs[hit] * t[hit, None]
            n = self.face_normals[face[hit]]
            n = np.where((np.einsum("ij,ij->i", n, dirs[hit]) > 0)[:, None], -n, n)
            normals[hit] = n
            ndotl = np.einsum("ij,j->i", n, self.sun)
            lit = ndotl > 0
            shadow_from = p[lit] + n[lit] * 2e-3
            blocked = self.intersector.intersects_any(shadow_from, np.broadcast_to(self.sun, shadow_from.shape))
            sun = np.zeros(len(p))
            sun[np.flatnonzero(lit)[~blocked]] = ndotl[lit][~blocked]
            sky_light = 0.7 + 0.3 * n[:, 1]  # upward faces see more of the overcast sky
            light = (np.asarray(self.spec.ambient_rgb) * sky_light[:, None]
                     + np.asarray(self.spec.sun_rgb) * sun[:, None])
            rgb[hit] = np.clip(self.albedo(p, n, face[hit]) * light, 0, 1)
        return rgb, t, normals

    def render(self, cameras: Cameras, index: int, antialias: bool = True) -> ViewRender:
        h, w = cameras.height, cameras.width
        offsets = SAMPLE_OFFSETS if antialias else SAMPLE_OFFSETS[:1]
        origin, dirs, z_scale = camera_rays(cameras, index, offsets)
        s = len(offsets)
        rgb, t, normals = self.shade(origin, dirs.reshape(-1, 3))
        rgb = rgb.reshape(s, h * w, 3).mean(0)
        depth = (t[: h * w] * z_scale[0]).reshape(h, w)
        return ViewRender(rgb.reshape(h, w, 3), depth, normals[: h * w].reshape(h, w, 3))
