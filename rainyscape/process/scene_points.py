"""Sparse points for a scene that ships none, from its training views at their known poses
(:mod:`rainyscape.process.triangulate`), cached in the package's cache folder.

Only the training views are used: they are what a user has (the rainy inputs), and held-out
views stay unseen. The cache key is a hash of those images, their cameras and the options,
so a changed view, pose, split or setting triangulates again; nothing is written into the
scene's folder.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import sys
import tempfile
from pathlib import Path

import numpy as np
import torch

from rainyscape.cameras import Cameras
from rainyscape.formats.atomic import write_text_atomic
from rainyscape.formats.cache import cache_root
from rainyscape.process.triangulate import (SparsePoints, TriangulationOptions, TriangulationReport,
                                            triangulate_views)
from rainyscape.scene import SceneData

SOURCE = "triangulated (pycolmap, known poses)"
CACHE_VERSION = 1  # bump when the triangulation changes what it returns for the same input
MIN_POINTS = 50  # fewer: the field starts as it would without points (a handful of points is worse than none)


def points_cache_dir() -> Path:
    return cache_root() / "sparse-points"


def cache_key(images: np.ndarray, cameras: Cameras, near: float, far: float,
              options: TriangulationOptions) -> str:
    """Hash of what the triangulation sees: the images, their cameras, the scene's bounds (they
    choose the view pairs) and the options."""
    h = hashlib.sha256(f"rainyscape-sparse-points-v{CACHE_VERSION}".encode())
    h.update(np.ascontiguousarray(images, np.uint8).tobytes())
    h.update(str(np.asarray(images).shape).encode())
    for t in (cameras.c2w, cameras.fx, cameras.fy, cameras.cx, cameras.cy):
        h.update(t.detach().cpu().to(torch.float64).numpy().tobytes())
    h.update(f"{cameras.width}x{cameras.height} {float(near)!r} {float(far)!r}".encode())
    opts = {k: v for k, v in dataclasses.asdict(options).items() if k != "num_threads"}  # threads change no result
    h.update(json.dumps(opts, sort_keys=True).encode())
    return h.hexdigest()[:24]


def load_cached(key: str) -> SparsePoints | None:
    """The cached points of ``key`` (None when absent or unreadable)."""
    folder = points_cache_dir()
    try:
        with np.load(folder / f"{key}.npz") as data:
            points, colors = data["points"].astype(np.float32), data["colors"].astype(np.uint8)
        report = TriangulationReport(**json.loads((folder / f"{key}.json").read_text()))
    except (OSError, ValueError, KeyError, TypeError):
        return None
    report.cached = True
    return SparsePoints(points, colors, report)


def save_cached(key: str, result: SparsePoints) -> None:
    """Write the points (npz, then the report that marks them complete), each atomically."""
    folder = points_cache_dir()
    folder.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{key}-", suffix=".npz", dir=folder)
    os.close(fd)
    try:
        np.savez(tmp, points=result.points, colors=result.colors)
        os.replace(tmp, folder / f"{key}.npz")
    finally:
        if os.path.exists(tmp):
            os.remove(tmp)
    report = {**dataclasses.asdict(result.report), "cached": False}
    write_text_atomic(folder / f"{key}.json", json.dumps(report, indent=2))


def training_view_points(scene: SceneData, options: TriangulationOptions | None = None,
                         use_cache: bool = True) -> SparsePoints:
    """Sparse points of ``scene`` from its training views (cached)."""
    options = options or TriangulationOptions()
    views = list(scene.train_indices)
    images = scene.images[views].cpu().numpy()
    cameras = scene.cameras[views].to("cpu")
    key = cache_key(images, cameras, scene.near, scene.far, options)
    if use_cache:
        found = load_cached(key)
        if found is not None:
            return found
    # said only when it runs (a cached result is instant), so that a command's own error
    # stays its only line
    print(f"sparse points: {scene.name} has none; triangulating them from its {len(views)} "
          "training views (pycolmap, known poses) ...", file=sys.stderr)
    result = triangulate_views(images, cameras, scene.near, scene.far, options)
    if use_cache:
        save_cached(key, result)
    return result


def with_sparse_points(scene: SceneData, options: TriangulationOptions | None = None,
                       use_cache: bool = True) -> SceneData:
    """``scene`` with points triangulated from its training views when it has none (and
    ``points_source`` / ``metadata["sparse_points"]`` saying so); unchanged when it has some.
    Fewer than ``MIN_POINTS`` points are not used (the report says so)."""
    if scene.points is not None and len(scene.points):
        return scene
    result = training_view_points(scene, options, use_cache)
    report = {"source": SOURCE, **result.report.to_json()}
    if result.report.points < MIN_POINTS:
        report["used"] = False
        return dataclasses.replace(scene, points_source=f"none ({SOURCE}: only {result.report.points} "
                                                        f"points, fewer than {MIN_POINTS})",
                                   metadata={**scene.metadata, "sparse_points": report})
    report["used"] = True
    return dataclasses.replace(scene, points=torch.from_numpy(result.points), point_colors=torch.from_numpy(result.colors),
                               points_source=SOURCE, metadata={**scene.metadata, "sparse_points": report})
