"""Cells that would train the same run: a plain field's ceiling on the clean views of a
capture's rain variants (``scenes=real``: one capture, three rains, the same clean photos).
One of them trains; the others take a copy of its run and evaluate it on their own scene,
whose rain (what the in-rain and dry columns split by) is its own."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

from rainyscape.comparison.matrix import Cell, cell_config


def training_digest(cell: Cell) -> str:
    """What a cell's training sees: its whole config but the scene folder's name, and the
    scene as its dataparser delivers it to training (images, cameras, split, bounds, points),
    never what is there for evaluation only (clean images, rain layers, depth)."""
    import numpy as np

    from rainyscape.config.yaml_io import to_dict
    from rainyscape.engine.scene_loading import load_scene

    cfg = cell_config(cell)
    conf = to_dict(cfg)
    for key in ("data", "rainyscape_version"):
        conf.pop(key, None)
    scene = load_scene(cfg, Path(cell.data))
    h = hashlib.sha1(json.dumps(conf, sort_keys=True, default=str).encode())
    cams = scene.cameras
    for value in (scene.images, cams.c2w, cams.fx, cams.fy, cams.cx, cams.cy, scene.scene_box,
                  scene.transform, scene.points, scene.point_colors):
        h.update(b"-" if value is None else np.ascontiguousarray(value.detach().cpu().numpy()).tobytes())
    h.update(repr((cams.width, cams.height, scene.train_indices, scene.eval_indices, scene.near, scene.far,
                   scene.forward_facing, scene.scale)).encode())
    return h.hexdigest()


def shared_runs(cells: list[Cell]) -> dict[str, str]:
    """Ceiling cell key -> the key of the earlier ceiling cell whose training is the same
    (:func:`training_digest`). Only ceilings are compared: they are the cells that repeat."""
    first: dict[str, str] = {}
    shared = {}
    for cell in cells:
        if not cell.clean:
            continue
        digest = training_digest(cell)
        if digest in first:
            shared[cell.key] = first[digest]
        else:
            first[digest] = cell.key
    return shared
