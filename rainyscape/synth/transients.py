"""Transient distractors: objects present in one view only (people, cars, blowing leaves).

The setting the robust baselines were built for (RobustNeRF's and On-the-go's captures): a
static scene photographed while things move through it. Each view gets its own objects,
placed where that camera sees them (under random pixels: people and cars stand on the
ground, leaves float a few metres in front of the lens), drawn from a generator seeded by
the scene's seed and the view, so a view's transients never appear in another. They are
real geometry of that view's render: they occlude, are lit by the same sun and cast
shadows, and they are integrated over each pixel like the rest of the scene.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np
import trimesh

from rainyscape.errors import ConfigError
from rainyscape.synth.geometry import Part, blob, box
from rainyscape.synth.raycast import Camera
from rainyscape.synth.scenes import car

SHIRTS = [(0.85, 0.15, 0.12), (0.1, 0.35, 0.8), (0.95, 0.75, 0.1), (0.15, 0.6, 0.25), (0.9, 0.9, 0.88),
          (0.55, 0.2, 0.6), (0.95, 0.45, 0.1), (0.1, 0.1, 0.12)]
TROUSERS = [(0.12, 0.14, 0.22), (0.2, 0.2, 0.2), (0.35, 0.3, 0.25), (0.08, 0.08, 0.1)]
SKIN = [(0.85, 0.66, 0.52), (0.6, 0.42, 0.3), (0.4, 0.27, 0.2)]
CARS = [(0.8, 0.1, 0.1), (0.1, 0.25, 0.6), (0.9, 0.9, 0.9), (0.15, 0.15, 0.15), (0.95, 0.8, 0.1)]
LEAVES = [(0.85, 0.45, 0.08), (0.75, 0.2, 0.05), (0.9, 0.75, 0.15), (0.45, 0.55, 0.1)]


@dataclass(frozen=True)
class TransientConfig:
    """How many transients each view gets, and where they may be."""

    people: int = 0  # standing on the ground under random pixels of the view
    cars: int = 0
    leaves: int = 0  # floating in the air in front of the camera
    near_m: float = 3.0  # people and cars stand at least this far from the camera ...
    far_m: float = 30.0  # ... and at most this far
    leaf_near_m: float = 1.5  # leaves float between these distances
    leaf_far_m: float = 6.0

    @classmethod
    def of(cls, options: dict) -> "TransientConfig":
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(options) - known)
        if unknown:
            raise ConfigError(f"unknown transient option '{unknown[0]}'; options are {', '.join(sorted(known))}")
        cfg = cls(**options)
        if min(cfg.people, cfg.cars, cfg.leaves) < 0:
            raise ConfigError("transient counts must be >= 0")
        return cfg

    @property
    def any(self) -> bool:
        return self.people + self.cars + self.leaves > 0


def _pick(rng: np.random.Generator, palette: list) -> tuple:
    return tuple(palette[int(rng.integers(len(palette)))])


def person(x: float, z: float, yaw: float, rng: np.random.Generator, seed: int) -> list[Part]:
    """A standing figure about 1.75 m tall: legs, torso (a shirt colour) and head."""
    height = float(rng.uniform(1.55, 1.9))
    legs, torso = 0.48 * height, 0.34 * height
    width = float(rng.uniform(0.4, 0.52))
    return [
        Part(box(x, 0.0, z, width * 0.8, legs, 0.24, yaw), "paint", {"color": _pick(rng, TROUSERS)}, seed=seed),
        Part(box(x, legs, z, width, torso, 0.28, yaw), "paint", {"color": _pick(rng, SHIRTS)}, seed=seed + 1),
        Part(blob(x, legs + torso + 0.12, z, 0.12, 1.15, seed), "paint", {"color": _pick(rng, SKIN)}, seed=seed + 2),
    ]


def leaf(centre: np.ndarray, rng: np.random.Generator, seed: int) -> Part:
    """A tumbling leaf: a thin plate 12-25 cm across, turned at random."""
    size = float(rng.uniform(0.12, 0.25))
    mesh = trimesh.creation.box((size, 0.01, size * 0.7))
    mesh.apply_transform(trimesh.transformations.random_rotation_matrix(rng.random(3)))
    mesh.apply_translation(centre)
    return Part(mesh, "paint", {"color": _pick(rng, LEAVES)}, seed=seed)


def _ground_point(cam: Camera, rng: np.random.Generator, near: float, far: float,
                  tries: int = 50) -> np.ndarray | None:
    """Where the ray through a random pixel of the view's lower part meets the ground (y = 0),
    between ``near`` and ``far`` metres from the camera; None if no pixel gives one."""
    for _ in range(tries):
        px = rng.uniform(0.05, 0.95) * cam.width
        py = rng.uniform(0.35, 1.0) * cam.height
        d = cam.directions(np.array([px]), np.array([py]))[0]
        d = d / np.linalg.norm(d)
        if d[1] >= -1e-3:
            continue
        t = -cam.origin[1] / d[1]
        if near <= t <= far:
            return cam.origin + t * d
    return None


def view_transients(cfg: TransientConfig, cam: Camera, seed: int, view: int) -> list[Part]:
    """The transient parts of one view (the same for the same seed and view)."""
    rng = np.random.default_rng([int(seed), 7919, int(view)])
    base = 100_000 + 1000 * int(view)
    parts: list[Part] = []
    for i in range(cfg.people):
        p = _ground_point(cam, rng, cfg.near_m, cfg.far_m)
        if p is not None:
            parts += person(float(p[0]), float(p[2]), float(rng.uniform(0, 360)), rng, base + 10 * i)
    for i in range(cfg.cars):
        p = _ground_point(cam, rng, max(cfg.near_m, 5.0), cfg.far_m)
        if p is not None:
            parts += car(float(p[0]), float(p[2]), float(rng.uniform(0, 360)), _pick(rng, CARS), base + 500 + 10 * i)
    for i in range(cfg.leaves):
        px, py = rng.uniform(0, cam.width), rng.uniform(0, cam.height)
        d = cam.directions(np.array([px]), np.array([py]))[0]
        d = d / np.linalg.norm(d)
        parts.append(leaf(cam.origin + rng.uniform(cfg.leaf_near_m, cfg.leaf_far_m) * d, rng, base + 900 + i))
    return parts


def transient_mask(observed: np.ndarray, clean: np.ndarray, tolerance: float = 0.25 / 255.0) -> np.ndarray:
    """(H, W) pixels where the view with its transients (rendered with the clean view's
    samples) differs from the clean view by more than ``tolerance`` (a quarter of a grey
    level) in some channel: the objects, their shadows and the edges they touch."""
    return np.abs(observed - clean).max(-1) > tolerance
