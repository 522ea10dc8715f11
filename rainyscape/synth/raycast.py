"""Clean-image rendering: embree ray casting (through trimesh) with sun, sky light and shadows,
integrated over each pixel's footprint.

A pixel's value is the mean radiance over its square footprint. Two things make that
integral accurate at a modest cost:

- **prefiltered textures**: every sample carries the footprint of its share of the pixel
  (ray differentials: the image cell mapped onto the hit surface, then into texture space)
  and the textures return their exact mean over it (:mod:`rainyscape.synth.filtering`);
  inside a surface, the samples of a regular ``n x n`` grid of cells then tile the pixel
  and their mean is the pixel integral, whatever the detail under it;
- **adaptive supersampling at edges**: where the samples of a pixel or of its neighbours
  see different surfaces (different planes or parts, sky, or a shadow boundary), the pixel
  and its 8 neighbours are re-rendered with ``edge x edge`` jittered stratified samples.

Depth is the z-depth of the pixel-centre ray (inf where it sees the sky); the z-depths of
the base samples are kept too (``sub_depth``): the rain uses them to hide streak parts
behind surfaces by the covered fraction of each pixel.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from trimesh.ray.ray_pyembree import RayMeshIntersector

from rainyscape.cameras import Cameras
from rainyscape.synth.filtering import Fp, fbm
from rainyscape.synth.geometry import surface_uv
from rainyscape.synth.scenes import SceneSpec
from rainyscape.synth.textures import TEXTURES

SMALL_IMAGE = 128  # images narrower than this get a 3 x 3 base grid (busy and cheap), else 2 x 2
EDGE_FACTOR = 4  # edge pixels: (EDGE_FACTOR * samples)^2 jittered samples (8 x 8 by default)
CHUNK = 262_144  # samples shaded at once (bounds the texture code's memory)


def default_samples(width: int, height: int) -> int:
    """Base samples per axis for an image size: 3 below SMALL_IMAGE px, else 2."""
    return 3 if max(width, height) < SMALL_IMAGE else 2


EDGE_SHARE = 0.2  # edge share above which edges get more samples (small, busy images)


def edge_samples(samples: int, factor: int, edge_share: float) -> int:
    """Edge samples per axis: ``factor * samples``, raised where edges are many (small
    images) so that their total error stays about that of a view with EDGE_SHARE of edge
    pixels (the error of jittered sampling across an edge falls as m^-1.5)."""
    m = samples * factor
    if factor <= 1:
        return m
    return max(m, int(round(m * (edge_share / EDGE_SHARE) ** (1 / 3))))


@dataclass
class ViewRender:
    rgb: np.ndarray  # (H, W, 3) float in [0, 1]: the pixel integral
    depth: np.ndarray  # (H, W) z-depth of the pixel-centre ray, inf where it sees the sky
    normal: np.ndarray  # (H, W, 3) world normal of the centre ray's surface, facing the camera (0: sky)
    sub_depth: np.ndarray  # (H, W, S) z-depths of the base samples (inf: sky)
    edge_fraction: float = 0.0  # share of pixels re-rendered with the edge samples


@dataclass
class Camera:
    """One view's pinhole: origin, rotation (columns: camera axes in the world), intrinsics."""

    origin: np.ndarray
    rot: np.ndarray
    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    @classmethod
    def of(cls, cameras: Cameras, index: int) -> "Camera":
        c2w = cameras.c2w[index].double().numpy()
        return cls(c2w[:3, 3].copy(), c2w[:3, :3].copy(), float(cameras.fx[index]), float(cameras.fy[index]),
                   float(cameras.cx[index]), float(cameras.cy[index]), cameras.width, cameras.height)

    def directions(self, xs: np.ndarray, ys: np.ndarray) -> np.ndarray:
        """Unnormalised world directions (camera z = 1) through image points (pixels)."""
        d = np.stack([(xs - self.cx) / self.fx, (ys - self.cy) / self.fy, np.ones_like(xs)], -1)
        return d @ self.rot.T

    @property
    def dx(self) -> np.ndarray:
        """Change of the unnormalised direction per pixel along x (and :attr:`dy` along y)."""
        return self.rot[:, 0] / self.fx

    @property
    def dy(self) -> np.ndarray:
        return self.rot[:, 1] / self.fy


@dataclass
class Shaded:
    rgb: np.ndarray  # (M, 3) radiance (not clipped)
    z: np.ndarray  # (M,) z-depth, inf for sky
    plane: np.ndarray  # (M,) plane id of the hit (-1: sky)
    shadow: np.ndarray  # (M,) bool: the sun is blocked
    normal: np.ndarray  # (M, 3) facing normal (0 for sky)


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
        # faces of one part on one plane shade alike: edges are where the plane changes
        offset = np.einsum("ij,ij->i", self.face_normals, self.plane_points)
        key = np.column_stack([owner, np.round(self.face_normals * 1e4), np.round(offset * 1e3)])
        self.plane_id = np.unique(key, axis=0, return_inverse=True)[1].ravel()

    def cast(self, origins: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """First hit per ray (unit ``dirs``): distance along the ray (inf on a miss) and triangle (-1)."""
        face = np.asarray(self.intersector.intersects_first(origins, dirs), np.int64)
        hit = face >= 0
        t = np.full(len(dirs), np.inf)
        # distance to the hit triangle's plane (cheaper than trimesh's location query)
        n = self.face_normals[face[hit]]
        t[hit] = (np.einsum("ij,ij->i", self.plane_points[face[hit]] - origins[hit], n)
                  / np.einsum("ij,ij->i", dirs[hit], n))
        return t, face

    # ----------------------------------------------------------------------- shading

    def _cloud_uv(self, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        d = d / np.linalg.norm(d, axis=-1, keepdims=True)
        k = 1.0 / np.maximum(d[:, 1], 0.05)
        return d[:, 0] * k, d[:, 2] * k

    def sky(self, d: np.ndarray, ddx: np.ndarray, ddy: np.ndarray) -> np.ndarray:
        """Overcast sky: horizon-to-zenith gradient with soft cloud banks, the clouds filtered
        over the footprint (unnormalised directions ``d`` and their change across the
        sample's cell, ``ddx``, ``ddy``)."""
        dn = d / np.linalg.norm(d, axis=-1, keepdims=True)
        up = np.clip(dn[:, 1], 0.0, 1.0)
        t = np.sqrt(up)[:, None]
        col = np.asarray(self.spec.sky_horizon) * (1 - t) + np.asarray(self.spec.sky_zenith) * t
        u, v = self._cloud_uv(d)
        ux, vx = self._cloud_uv(d + ddx)
        uy, vy = self._cloud_uv(d + ddy)
        fp = Fp(u, v, np.abs(ux - u), np.abs(uy - u), np.abs(vx - v), np.abs(vy - v))
        clouds = fbm(fp, 0.8, 4, 17)
        return col * (0.85 + 0.3 * clouds[:, None])

    def albedo(self, points: np.ndarray, normals: np.ndarray, faces: np.ndarray, dpx: np.ndarray,
               dpy: np.ndarray) -> np.ndarray:
        """Texture colour over each sample's footprint (``dpx``, ``dpy``: the surface
        displacement across the sample's cell along image x and y)."""
        part = self.owner[faces]
        u, v, up, gu, gv = surface_uv(points, normals, self.base_y[part], self.axis[part])
        fp = Fp(u, v, np.abs(np.einsum("ij,ij->i", gu, dpx)), np.abs(np.einsum("ij,ij->i", gu, dpy)),
                np.abs(np.einsum("ij,ij->i", gv, dpx)), np.abs(np.einsum("ij,ij->i", gv, dpy)))
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
                    out[sel] = TEXTURES[name](fp[sel], p.seed, **params)
        return out

    def shade(self, cam: Camera, xs: np.ndarray, ys: np.ndarray, cell: np.ndarray | float) -> Shaded:
        """Radiance of samples at image points (``xs``, ``ys``), each integrated over a square
        image cell of side ``cell`` pixels centred on it."""
        d = cam.directions(xs, ys)
        norm = np.linalg.norm(d, axis=-1)
        dirs = d / norm[:, None]
        origins = np.broadcast_to(cam.origin, dirs.shape)
        t, face = self.cast(origins, dirs)
        hit = face >= 0
        cell = np.broadcast_to(np.asarray(cell, np.float64), xs.shape)
        ddx, ddy = cam.dx[None] * cell[:, None], cam.dy[None] * cell[:, None]
        rgb = np.empty((len(xs), 3))
        miss = ~hit
        rgb[miss] = self.sky(d[miss], ddx[miss], ddy[miss])
        normals = np.zeros((len(xs), 3))
        shadow = np.zeros(len(xs), bool)
        z = t / norm
        plane = np.full(len(xs), -1, np.int64)
        if hit.any():
            fh = face[hit]
            plane[hit] = self.plane_id[fh]
            p = cam.origin + dirs[hit] * t[hit, None]
            n = self.face_normals[fh]
            dh = d[hit]
            dn = np.einsum("ij,ij->i", n, dh)
            n = np.where((dn > 0)[:, None], -n, n)
            dn = -np.abs(dn)
            dn = np.where(np.abs(dn) < 1e-9, -1e-9, dn)
            normals[hit] = n
            # ray differentials: where the neighbouring rays meet the hit plane
            zh = z[hit, None]
            dpx = zh * (ddx[hit] - (np.einsum("ij,ij->i", ddx[hit], n) / dn)[:, None] * dh)
            dpy = zh * (ddy[hit] - (np.einsum("ij,ij->i", ddy[hit], n) / dn)[:, None] * dh)
            ndotl = np.einsum("ij,j->i", n, self.sun)
            lit = ndotl > 0
            shadow_from = p[lit] + n[lit] * 2e-3
            blocked = self.intersector.intersects_any(shadow_from, np.broadcast_to(self.sun, shadow_from.shape))
            sun = np.zeros(len(p))
            sun[np.flatnonzero(lit)[~blocked]] = ndotl[lit][~blocked]
            sh = np.zeros(len(p), bool)
            sh[np.flatnonzero(lit)[blocked]] = True
            shadow[hit] = sh
            sky_light = 0.7 + 0.3 * n[:, 1]  # upward faces see more of the overcast sky
            light = (np.asarray(self.spec.ambient_rgb) * sky_light[:, None]
                     + np.asarray(self.spec.sun_rgb) * sun[:, None])
            rgb[hit] = self.albedo(p, n, fh, dpx, dpy) * light
        return Shaded(rgb, z, plane, shadow, normals)

    def _shade_chunked(self, cam: Camera, xs: np.ndarray, ys: np.ndarray, cell: float) -> Shaded:
        parts = [self.shade(cam, xs[i:i + CHUNK], ys[i:i + CHUNK], cell) for i in range(0, max(len(xs), 1), CHUNK)]
        return Shaded(*(np.concatenate([getattr(s, f) for s in parts]) for f in
                        ("rgb", "z", "plane", "shadow", "normal")))

    # ----------------------------------------------------------------------- views

    def render(self, cameras: Cameras, index: int, samples: int | None = None,
               edge_factor: int = EDGE_FACTOR, seed: int = 0, prefilter: bool = True,
               window: tuple[int, int, int, int] | None = None) -> ViewRender:
        """Render view ``index``: ``samples`` x ``samples`` prefiltered samples per pixel
        (default: :func:`default_samples` of the image size), and ``edge_factor * samples``
        squared (or more, see :func:`edge_samples`) jittered samples per pixel around edges.
        ``prefilter=False`` point-samples the textures (for measurements of the renderer);
        ``window=(x0, y0, x1, y1)`` renders only those pixels (a crop of the view)."""
        cam = Camera.of(cameras, index)
        x0, y0, x1, y1 = window if window is not None else (0, 0, cam.width, cam.height)
        h, w = y1 - y0, x1 - x0
        n = default_samples(cam.width, cam.height) if samples is None else int(samples)
        if n < 1:
            raise ValueError(f"samples must be at least 1, got {samples}")
        # base pass: a regular n x n grid of cells per pixel, each prefiltered over its cell;
        # a ring of pixels around the window too, so that edges at the border are found
        g = (np.arange(n) + 0.5) / n
        ii, jj = np.meshgrid(np.arange(y0 - 1, y1 + 1), np.arange(x0 - 1, x1 + 1), indexing="ij")
        sy, sx = np.meshgrid(g, g, indexing="ij")
        xs = (jj[:, :, None, None] + sx[None, None]).ravel()  # (h + 2, w + 2, n, n) order
        ys = (ii[:, :, None, None] + sy[None, None]).ravel()
        base = self._shade_chunked(cam, xs, ys, 1.0 / n if prefilter else 0.0)
        edge = self._edges(base, h + 2, w + 2, n)[1:-1, 1:-1]
        rgb = base.rgb.reshape(h + 2, w + 2, n * n, 3)[1:-1, 1:-1].mean(2)
        sub_depth = base.z.reshape(h + 2, w + 2, n * n)[1:-1, 1:-1]
        normals = base.normal.reshape(h + 2, w + 2, n * n, 3)[1:-1, 1:-1]
        m = edge_samples(n, int(edge_factor), float(edge.mean()))
        if m > n and edge.any():
            pi, pj = np.nonzero(edge)
            rng = np.random.default_rng([int(seed), int(index), m])
            cy, cx = np.meshgrid((np.arange(m)) / m, (np.arange(m)) / m, indexing="ij")
            jit = rng.random((len(pi), m * m, 2)) / m
            xs = (x0 + pj[:, None] + cx.ravel()[None] + jit[..., 0]).ravel()
            ys = (y0 + pi[:, None] + cy.ravel()[None] + jit[..., 1]).ravel()
            fine = self._shade_chunked(cam, xs, ys, 1.0 / m if prefilter else 0.0)
            rgb[pi, pj] = fine.rgb.reshape(len(pi), m * m, 3).mean(1)
        # depth and normal: the pixel-centre ray
        if n % 2 == 1:
            centre = (n * n) // 2
            depth = sub_depth[:, :, centre].copy()
            normal = normals[:, :, centre]
        else:
            depth, normal = self.centre_depth(cam, (x0, y0, x1, y1))
        return ViewRender(np.clip(rgb, 0.0, 1.0), depth, normal, sub_depth, float(edge.mean()))

    def _edges(self, base: Shaded, h: int, w: int, n: int) -> np.ndarray:
        """Pixels to supersample: both pixels holding two neighbouring base samples that see a
        different plane, the sky, or a different side of a shadow boundary."""
        key = (base.plane * 2 + base.shadow).reshape(h, w, n, n).transpose(0, 2, 1, 3).reshape(h * n, w * n)
        edge = np.zeros((h, w), bool)
        for axis in (0, 1):
            a = [slice(None), slice(None)]
            b = [slice(None), slice(None)]
            a[axis], b[axis] = slice(1, None), slice(None, -1)
            diff = key[tuple(a)] != key[tuple(b)]
            ry, rx = np.nonzero(diff)
            edge[ry // n, rx // n] = True
            if axis == 0:
                edge[(ry + 1) // n, rx // n] = True
            else:
                edge[ry // n, (rx + 1) // n] = True
        return edge


    def centre_depth(self, cam: Camera, window: tuple[int, int, int, int]) -> tuple[np.ndarray, np.ndarray]:
        x0, y0, x1, y1 = window
        h, w = y1 - y0, x1 - x0
        ii, jj = np.meshgrid(np.arange(y0, y1) + 0.5, np.arange(x0, x1) + 0.5, indexing="ij")
        d = cam.directions(jj.ravel(), ii.ravel())
        norm = np.linalg.norm(d, axis=-1)
        dirs = d / norm[:, None]
        t, face = self.cast(np.broadcast_to(cam.origin, dirs.shape), dirs)
        normal = np.zeros((h * w, 3))
        hit = face >= 0
        nrm = self.face_normals[face[hit]]
        flip = np.einsum("ij,ij->i", nrm, dirs[hit]) > 0
        normal[hit] = np.where(flip[:, None], -nrm, nrm)
        return (t / norm).reshape(h, w), normal.reshape(h, w, 3)
