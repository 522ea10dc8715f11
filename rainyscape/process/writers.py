"""Scene-folder side files: nerfstudio's ``transforms.json`` and ``sparse_pc.ply``, read from
the undistorted COLMAP model so that other tools can open the scene too.

nerfstudio wants camera-to-world with OpenGL camera axes (x right, y up, looking down -z); the
world frame is kept as COLMAP's, so ``applied_transform`` is the identity.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from rainyscape.dataparsers.colmap_model import (colmap_c2w, model_points, pinhole_intrinsics,
                                                 posed_images)
from rainyscape.formats.ply import write_ply


def transforms_json(model, image_prefix: str = "images", ply_name: str | None = "sparse_pc.ply") -> dict:
    """nerfstudio ``transforms.json`` content for the registered images of a pinhole model."""
    images = posed_images(model)
    intrinsics = {im.camera_id: pinhole_intrinsics(model.cameras[im.camera_id]) for im in images}
    shared = len({tuple(v.values()) for v in intrinsics.values()}) == 1
    gl_flip = np.diag([1.0, -1.0, -1.0, 1.0])  # OpenCV camera axes -> OpenGL
    frames = []
    for im in images:
        frame = {"file_path": f"{image_prefix}/{im.name}",
                 "transform_matrix": (colmap_c2w(im) @ gl_flip).tolist(),
                 "colmap_im_id": int(im.image_id)}
        if not shared:
            frame.update(intrinsics[im.camera_id])
        frames.append(frame)
    out: dict = {"camera_model": "OPENCV"}
    if shared:
        out.update(next(iter(intrinsics.values())))
    out.update({"k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0, "frames": frames,
                "applied_transform": np.eye(4)[:3].tolist()})
    if ply_name:
        out["ply_file_path"] = ply_name
    return out


def write_nerfstudio_files(model, scene_dir: Path) -> None:
    """``transforms.json`` and ``sparse_pc.ply`` in the scene folder."""
    xyz, rgb = model_points(model)
    write_ply(scene_dir / "sparse_pc.ply", {"x": xyz[:, 0].astype(np.float32), "y": xyz[:, 1].astype(np.float32),
                                            "z": xyz[:, 2].astype(np.float32), "red": rgb[:, 0],
                                            "green": rgb[:, 1], "blue": rgb[:, 2]})
    content = transforms_json(model)
    (scene_dir / "transforms.json").write_text(json.dumps(content, indent=2))
