"""Named outdoor scenes (Y-up world, metres): geometry, textures, light and a camera rig.

Each builder returns a :class:`SceneSpec`; the camera rig (where the sphere cap is) belongs
to the scene because it depends on what is worth looking at.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np
import trimesh

from rainyscape.synth.geometry import Part, blob, box, hcylinder, hull, prism, vcylinder


@dataclass
class Rig:
    """Sphere cap of cameras around ``look_at``; azimuth 0 looks from +Z towards -Z."""

    look_at: tuple[float, float, float]
    radius: float
    elevation_deg: tuple[float, float]  # lowest and highest row
    azimuth_deg: tuple[float, float]  # first and last column


@dataclass
class SceneSpec:
    name: str
    parts: list[Part]
    rig: Rig
    sun_dir: tuple[float, float, float] = (-0.45, 0.75, 0.5)  # towards the sun
    sun_rgb: tuple[float, float, float] = (0.75, 0.72, 0.65)
    ambient_rgb: tuple[float, float, float] = (0.5, 0.53, 0.58)  # overcast sky light
    sky_zenith: tuple[float, float, float] = (0.55, 0.6, 0.68)
    sky_horizon: tuple[float, float, float] = (0.8, 0.82, 0.85)
    extras: dict = field(default_factory=dict)

    def mesh(self) -> tuple[trimesh.Trimesh, np.ndarray]:
        """All parts as one mesh, and each face's part index."""
        meshes = [p.mesh for p in self.parts]
        owner = np.concatenate([np.full(len(m.faces), i) for i, m in enumerate(meshes)])
        return trimesh.util.concatenate(meshes), owner


def ground_plane(size: float, seed: int, **params) -> Part:
    h = size / 2
    verts = np.array([[-h, 0, -h], [h, 0, -h], [h, 0, h], [-h, 0, h]], float)
    mesh = trimesh.Trimesh(verts, np.array([[0, 2, 1], [0, 3, 2]]), process=False)
    return Part(mesh, "ground", params, seed=seed)


def building(x: float, z: float, w: float, d: float, h: float, seed: int, wall=(0.55, 0.25, 0.18),
             kind: str = "brick", yaw: float = 0.0, shop: bool = True) -> list[Part]:
    body = Part(box(x, 0, z, w, h, d, yaw), "facade",
                {"wall": wall, "wall_kind": kind, "ground_shop": shop}, top="concrete", seed=seed)
    parapet = Part(box(x, h, z, w + 0.3, 0.4, d + 0.3, yaw), "concrete", seed=seed + 1)
    return [body, parapet]


def house(x: float, z: float, w: float, d: float, h: float, seed: int, wall=(0.82, 0.76, 0.62)) -> list[Part]:
    """Plastered house with a gable roof of clay tiles (ridge along X)."""
    body = Part(box(x, 0, z, w, h, d), "facade",
                {"wall": wall, "wall_kind": "plaster", "ground_shop": False, "bay_w": 2.6}, seed=seed)
    rise = 0.45 * d
    profile = np.array([[-d / 2 - 0.4, 0.0], [d / 2 + 0.4, 0.0], [0.0, rise]])
    roof = Part(prism(profile, w + 0.6, x, h, z, yaw=90.0), "roof", top="roof", seed=seed + 1)
    chimney = Part(box(x + w / 4, h, z - d / 6, 0.7, rise + 0.6, 0.7), "brick", seed=seed + 2)
    return [body, roof, chimney]


def tree(x: float, z: float, height: float, seed: int) -> list[Part]:
    trunk_h = 0.45 * height
    trunk = Part(vcylinder(x, 0, z, 0.18, trunk_h + 0.5, 10), "bark", axis=(x, z), seed=seed)
    crown_r = 0.32 * height
    crown = Part(blob(x, trunk_h + crown_r * 0.8, z, crown_r, 1.1, seed), "foliage", seed=seed + 1)
    return [trunk, crown]


def street_lamp(x: float, z: float, seed: int, arm_dir: float = -1.0, with_sign: bool = False) -> list[Part]:
    parts = [Part(vcylinder(x, 0, z, 0.08, 5.5, 12), "metal", axis=(x, z), seed=seed),
             Part(box(x, 5.3, z + arm_dir * 0.7, 0.1, 0.1, 1.4), "metal", seed=seed),
             Part(box(x, 5.15, z + arm_dir * 1.3, 0.35, 0.2, 0.6), "metal", {"color": (0.85, 0.85, 0.75)}, seed=seed)]
    if with_sign:
        parts.append(Part(box(x, 2.4, z, 1.5, 0.5, 0.05), "sign", seed=seed + 3))
    return parts


def car(x: float, z: float, yaw: float, color, seed: int) -> list[Part]:
    """A compound car along X (before ``yaw``): body, glass cabin, bumpers, four wheels."""
    rot = np.radians(yaw)

    def at(dx: float, dz: float) -> tuple[float, float]:
        return x + dx * np.cos(rot) + dz * np.sin(rot), z - dx * np.sin(rot) + dz * np.cos(rot)

    parts = [Part(box(x, 0.3, z, 4.2, 0.75, 1.8, yaw), "paint", {"color": color}, seed=seed)]
    cabin = np.array([[-1.3, 0], [1.0, 0], [0.55, 0.62], [-0.9, 0.62]])
    cx, cz = at(-0.2, 0)
    parts.append(Part(prism(cabin, 1.6, cx, 1.05, cz, yaw=yaw), "glass", seed=seed + 1))
    parts.append(Part(box(x, 1.66, z, 1.6, 0.04, 1.5, yaw), "paint", {"color": color}, seed=seed))
    for dx in (-2.15, 2.15):
        cx, cz = at(dx, 0)
        parts.append(Part(box(cx, 0.3, cz, 0.12, 0.3, 1.82, yaw), "metal", {"color": (0.2, 0.2, 0.2)}, seed=seed))
    for dx in (-1.35, 1.35):
        for dz in (-0.8, 0.8):
            cx, cz = at(dx, dz)
            parts.append(Part(hcylinder(cx, 0.34, cz, 0.34, 0.3, yaw + 90, 14), "rubber", seed=seed + 2))
    return parts


def bench(x: float, z: float, yaw: float, seed: int) -> list[Part]:
    return [Part(box(x, 0.42, z, 1.8, 0.06, 0.5, yaw), "planks", top="planks", seed=seed),
            Part(box(x, 0.0, z, 0.08, 0.42, 0.45, yaw), "metal", seed=seed)]


def _street(seed: int) -> SceneSpec:
    rng = np.random.default_rng(seed)
    parts = [ground_plane(300, seed, road_half_width=3.5, road_along_x=True, sidewalk=3.0, outer="paving")]
    walls = [(0.55, 0.25, 0.18), (0.8, 0.72, 0.58), (0.45, 0.3, 0.25), (0.7, 0.66, 0.62), (0.6, 0.35, 0.25)]
    x = -17.0
    k = 0
    while x < 17.0:
        w = float(rng.uniform(5.0, 7.5))
        h = float(rng.uniform(6.5, 13.0))
        kind = "brick" if k % 2 == 0 else "plaster"
        parts += building(x + w / 2, -10.0, w, 6.0, h, seed + 10 * k, walls[k % len(walls)], kind)
        x += w + 0.15
        k += 1
    for i, bx in enumerate((-22, -8, 6, 20)):  # a taller second row fills the sky gaps
        parts += building(bx, -26.0, 12.0, 8.0, 20.0 + 4 * i, seed + 300 + i, (0.62, 0.6, 0.58), "plaster", shop=False)
    for i, lx in enumerate((-12, -4, 4, 12)):
        parts += street_lamp(lx, -5.2, seed + 50 + i, arm_dir=1.0, with_sign=(i % 2 == 0))
    for i, tx in enumerate((-8.0, 8.0, 15.5)):
        parts += tree(tx, -5.6, float(rng.uniform(5.0, 6.5)), seed + 70 + i)
    parts += car(-3.0, -1.8, 0.0, (0.7, 0.1, 0.08), seed + 90)
    parts += car(6.5, 1.9, 180.0, (0.15, 0.3, 0.6), seed + 91)
    parts += car(-11.0, -1.8, 0.0, (0.85, 0.85, 0.82), seed + 92)
    parts += bench(2.0, 5.0, 0.0, seed + 95)
    parts.append(Part(box(-6.0, 0, 5.3, 1.2, 2.2, 1.2), "sign", {"color": (0.55, 0.1, 0.1)}, seed=seed + 96))
    return SceneSpec("street", parts, Rig((0.0, 2.5, -3.0), 18.0, (12.0, 38.0), (-55.0, 55.0)))


def _yard(seed: int) -> SceneSpec:
    parts = [ground_plane(300, seed, outer="grass")]
    parts.append(Part(box(0, 0, 0, 16, 0.02, 12), "paving", {"tile": 0.45}, top="paving",
                      top_params={"tile": 0.45}, seed=seed + 1))
    parts += house(0.0, -8.0, 11.0, 7.0, 5.5, seed + 10)
    parts += house(-13.0, -10.0, 8.0, 6.0, 4.5, seed + 20, wall=(0.7, 0.78, 0.82))
    for i in range(28):  # picket fence along the back of the yard
        parts.append(Part(box(-8.0 + i * 0.6, 0, -4.2, 0.12, 1.3, 0.05), "planks",
                          {"color": (0.8, 0.78, 0.72)}, seed=seed + 40))
    parts.append(Part(box(0.0, 0.9, -4.15, 16.8, 0.1, 0.04), "planks", {"color": (0.8, 0.78, 0.72)}, seed=seed + 41))
    parts += tree(-6.0, 1.5, 6.5, seed + 50)
    parts += tree(7.0, -1.0, 5.5, seed + 51)
    parts += tree(10.0, -9.0, 8.0, seed + 52)
    parts.append(Part(blob(4.0, 0.5, 3.5, 0.9, 0.7, seed + 53), "foliage", seed=seed + 53))
    parts.append(Part(blob(-3.5, 0.5, 4.5, 0.8, 0.7, seed + 54), "foliage", seed=seed + 54))
    parts += car(2.5, 0.5, 20.0, (0.2, 0.45, 0.25), seed + 60)
    parts += bench(-3.0, -2.5, 0.0, seed + 70)
    parts.append(Part(vcylinder(-1.0, 0, 2.5, 0.5, 0.8, 16), "concrete", axis=(-1.0, 2.5),
                      top="paving", seed=seed + 80))
    parts.append(Part(box(5.5, 0, -3.0, 1.0, 1.6, 0.1), "sign", {"color": (0.2, 0.2, 0.5)}, seed=seed + 81))
    return SceneSpec("yard", parts, Rig((0.0, 1.5, -2.0), 16.0, (15.0, 42.0), (-50.0, 50.0)),
                     sun_dir=(0.5, 0.7, 0.5))


def _bridge(seed: int) -> SceneSpec:
    parts = [ground_plane(300, seed, outer="grass", river_half_width=7.0)]
    parts.append(Part(box(0, 2.2, 0, 22.0, 0.6, 3.5), "concrete", top="planks",
                      top_params={"color": (0.45, 0.35, 0.25), "width": 0.25}, seed=seed + 1))
    for side in (-1.7, 1.7):
        parts.append(Part(box(0, 2.8, side, 22.0, 0.08, 0.08), "metal", seed=seed + 2))
        parts.append(Part(box(0, 3.6, side, 22.0, 0.1, 0.1), "metal", seed=seed + 2))
        for i in range(23):
            parts.append(Part(box(-11.0 + i, 2.8, side, 0.06, 0.8, 0.06), "metal", seed=seed + 3))
    for px in (-4.0, 4.0):
        parts.append(Part(vcylinder(px, -0.5, 0.0, 0.55, 2.7, 16), "concrete", axis=(px, 0.0), seed=seed + 4))
    hull_pts = np.array([[-2.6, 0.9, -1.0], [-2.6, 0.9, 1.0], [2.0, 0.9, -1.0], [2.0, 0.9, 1.0],
                         [3.2, 1.0, 0.0], [-2.4, -0.1, -0.7], [-2.4, -0.1, 0.7], [1.8, -0.1, -0.5],
                         [1.8, -0.1, 0.5], [2.8, 0.3, 0.0]])
    parts.append(Part(hull(hull_pts, 1.0, 0.0, 6.5, 25.0), "paint", {"color": (0.85, 0.82, 0.7)},
                      top="planks", seed=seed + 10))
    parts.append(Part(box(0.6, 0.9, 6.7, 1.6, 1.0, 1.3, 25.0), "facade",
                      {"wall": (0.9, 0.9, 0.88), "wall_kind": "plaster", "ground_shop": False,
                       "bay_w": 0.8, "floor_h": 1.0}, top="concrete", base_y=-0.9, seed=seed + 11))
    for i, z in enumerate((-16.0, -6.0)):  # on both banks, behind the bridge (cameras are at +Z)
        parts += building(-15.5, z, 6.0, 8.0, 8.0 + 3 * i, seed + 20 + i, (0.6, 0.3, 0.2) if i % 2 else (0.8, 0.75, 0.6),
                          "brick" if i % 2 else "plaster", yaw=90.0)
        parts += building(15.5, z + 3, 6.0, 8.0, 10.0 - 2 * i, seed + 30 + i, (0.7, 0.66, 0.62), "plaster", yaw=90.0)
    parts += tree(-10.0, 4.0, 6.0, seed + 40)
    parts += tree(10.0, -6.0, 6.5, seed + 41)
    parts += street_lamp(-9.0, 1.9, seed + 42, arm_dir=-1.0, with_sign=True)
    return SceneSpec("bridge", parts, Rig((0.0, 2.0, 0.0), 19.0, (14.0, 40.0), (-45.0, 45.0)),
                     sun_dir=(-0.3, 0.8, 0.55))


def _plaza(seed: int) -> SceneSpec:
    parts = [ground_plane(300, seed, outer="paving")]
    parts.append(Part(vcylinder(0, 0, 0, 3.0, 0.6, 40), "brick", {"color": (0.6, 0.58, 0.55)},
                      top="water", axis=(0.0, 0.0), seed=seed + 1))
    parts.append(Part(vcylinder(0, 0.6, 0, 0.35, 2.2, 16), "concrete", axis=(0.0, 0.0), seed=seed + 2))
    parts.append(Part(vcylinder(0, 2.8, 0, 1.0, 0.25, 24), "concrete", axis=(0.0, 0.0), seed=seed + 3))
    parts += building(0.0, -14.0, 20.0, 8.0, 15.0, seed + 10, (0.78, 0.74, 0.66), "plaster")
    parts += building(-15.0, -6.0, 8.0, 10.0, 11.0, seed + 11, (0.55, 0.28, 0.2), "brick", yaw=90.0)
    parts += building(15.0, -6.0, 8.0, 10.0, 9.0, seed + 12, (0.5, 0.5, 0.55), "brick", yaw=-90.0)
    parts += [Part(box(6.0, 0, -3.0, 3.0, 2.6, 2.2), "sign", {"color": (0.1, 0.3, 0.55)}, top="metal", seed=seed + 20)]
    for i, (bx, bz, yaw) in enumerate(((-4.5, 3.0, 30.0), (4.5, 3.5, -30.0), (-6.0, -3.5, 90.0))):
        parts += bench(bx, bz, yaw, seed + 30 + i)
    for i, (lx, lz) in enumerate(((-7.0, 5.0), (7.0, 5.5), (-8.0, -7.0), (8.0, -7.5))):
        parts += street_lamp(lx, lz, seed + 40 + i, with_sign=(i < 2))
    for i, (tx, tz) in enumerate(((-10.0, 2.0), (10.5, 1.0), (-3.0, -8.5), (3.5, -8.0))):
        parts += tree(tx, tz, 5.5 + i * 0.5, seed + 50 + i)
    parts += car(-9.5, 7.5, 70.0, (0.9, 0.75, 0.1), seed + 60)
    return SceneSpec("plaza", parts, Rig((0.0, 2.0, -1.0), 19.0, (16.0, 45.0), (-65.0, 65.0)),
                     sun_dir=(0.35, 0.8, 0.45))


def traffic_light(x: float, z: float, seed: int) -> list[Part]:
    return [Part(vcylinder(x, 0, z, 0.07, 3.3, 10), "metal", axis=(x, z), seed=seed),
            Part(box(x, 3.3, z, 0.32, 0.95, 0.32), "metal", {"color": (0.16, 0.16, 0.15)}, seed=seed + 1)]


def _crossroad(seed: int) -> SceneSpec:
    """Two roads crossing at the origin (along X and Z), zebra crossings on every arm, corner
    blocks of shops behind the junction, cars, traffic lights, lamps and trees."""
    rng = np.random.default_rng(seed)
    h, walk = 4.0, 3.0
    front = h + walk + 0.3
    parts = [ground_plane(300, seed, road_half_width=h, sidewalk=walk, outer="paving", cross=True)]
    walls = [(0.6, 0.32, 0.22), (0.82, 0.76, 0.64), (0.5, 0.34, 0.28), (0.74, 0.7, 0.66), (0.66, 0.4, 0.3)]
    k = 0
    for sx in (-1.0, 1.0):
        a = front
        while a < 30.0:  # along the X road, facing +Z
            w = float(rng.uniform(5.5, 8.0))
            ht = float(rng.uniform(7.0, 14.0))
            parts += building(sx * (a + w / 2), -front - 3.5, w, 7.0, ht, seed + 10 * k, walls[k % 5],
                              "brick" if k % 2 == 0 else "plaster")
            a += w + 0.2
            k += 1
        a = front + 7.2
        while a < 34.0:  # along the Z road, facing the road
            w = float(rng.uniform(5.5, 8.0))
            ht = float(rng.uniform(8.0, 15.0))
            parts += building(sx * (front + 3.5), -(a + w / 2), 7.0, w, ht, seed + 10 * k, walls[k % 5],
                              "plaster" if k % 2 == 0 else "brick", yaw=0.0)
            a += w + 0.2
            k += 1
    for i, bx in enumerate((-24.0, -9.0, 6.0, 21.0)):  # a taller back row fills the sky
        parts += building(bx, -40.0, 13.0, 8.0, 22.0 + 3 * i, seed + 400 + i, (0.64, 0.62, 0.6), "plaster", shop=False)
    for i, (lx, lz) in enumerate(((-(h + 0.6), -(h + 0.6)), ((h + 0.6), -(h + 0.6)), (-(h + 0.6), h + 0.6), (h + 0.6, h + 0.6))):
        parts += traffic_light(lx, lz, seed + 60 + 2 * i)
    for i, lx in enumerate((-16.0, 16.0)):
        parts += street_lamp(lx, -(h + 1.0), seed + 80 + i, arm_dir=1.0, with_sign=(i == 0))
    for i, (tx, tz) in enumerate(((-12.0, h + 1.6), (12.5, h + 1.6), (h + 1.6, -15.0), (-(h + 1.6), -19.0))):
        parts += tree(tx, tz, float(rng.uniform(5.0, 6.5)), seed + 90 + i)
    parts += car(-9.0, -2.0, 0.0, (0.75, 0.12, 0.1), seed + 100)
    parts += car(10.0, 2.0, 180.0, (0.9, 0.9, 0.88), seed + 101)
    parts += car(-2.0, 7.5, 90.0, (0.15, 0.3, 0.62), seed + 102)
    parts += car(2.0, -12.0, -90.0, (0.9, 0.7, 0.1), seed + 103)
    parts.append(Part(box(9.5, 0, 9.0, 2.4, 2.5, 2.0), "sign", {"color": (0.5, 0.12, 0.12)}, top="metal",
                      seed=seed + 110))
    parts += bench(-9.5, 8.5, 0.0, seed + 111)
    return SceneSpec("crossroad", parts, Rig((0.0, 1.5, -2.0), 20.0, (15.0, 42.0), (-50.0, 50.0)),
                     sun_dir=(0.4, 0.75, 0.45))


SCENES: dict[str, Callable[[int], SceneSpec]] = {
    "street": _street, "yard": _yard, "bridge": _bridge, "plaza": _plaza, "crossroad": _crossroad,
}


def build_scene(name: str, seed: int = 0) -> SceneSpec:
    return SCENES[name](seed)
