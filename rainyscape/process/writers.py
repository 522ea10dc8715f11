"""Scene-folder side files: nerfstudio's ``transforms.json`` and ``sparse_pc.ply``, read from
the undistorted COLMAP model so that other tools can open the scene too.

Both go through the package's one writer of each format (``dataparsers.transforms_json``,
``formats.ply``). The world frame is kept as COLMAP's, so ``applied_transform`` is the identity.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from rainyscape.dataparsers.colmap_model import (colmap_c2w, model_points, pinhole_intrinsics,
                                                 posed_images)
from rainyscape.dataparsers.transforms_json import transforms_content, write_transforms
from rainyscape.formats.ply import write_ply

PLY_NAME = "sparse_pc.ply"


def write_nerfstudio_files(model, scene_dir: Path, image_prefix: str = "images") -> None:
    """``transforms.json`` (the registered images of a pinhole model) and ``sparse_pc.ply``
    (its points: float x y z, uchar red green blue) in the scene folder."""
    xyz, rgb = model_points(model)
    columns = {axis: xyz[:, i].astype(np.float32) for i, axis in enumerate("xyz")}
    columns.update({channel: rgb[:, i] for i, channel in enumerate(("red", "green", "blue"))})
    write_ply(scene_dir / PLY_NAME, columns)
    images = posed_images(model)
    content = transforms_content(
        np.array([colmap_c2w(im) for im in images]).reshape(-1, 4, 4),
        [pinhole_intrinsics(model.cameras[im.camera_id]) for im in images],
        [f"{image_prefix}/{im.name}" for im in images],
        frame_extras=[{"colmap_im_id": int(im.image_id)} for im in images],
        ply_file_path=PLY_NAME, applied_transform=np.eye(4))
    write_transforms(scene_dir / "transforms.json", content)
