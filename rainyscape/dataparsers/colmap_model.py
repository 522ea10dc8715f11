"""Reading COLMAP sparse models (binary or text) through pycolmap: where the model is, its
camera poses in the OpenCV camera-to-world form, pinhole intrinsics and sparse points.

COLMAP stores world-to-camera poses (``cam_from_world``) with OpenCV camera axes and puts the
centre of pixel (row i, column j) at (j + 0.5, i + 0.5), as rainyscape.cameras does, so only
the pose needs inverting.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from rainyscape.errors import DataError

MODEL_FILES = ("cameras", "images", "points3D")


def is_model_dir(folder: Path) -> bool:
    return all(any((folder / f"{name}{ext}").is_file() for ext in (".bin", ".txt"))
               for name in MODEL_FILES)


def read_model(folder: Path):
    """A pycolmap Reconstruction from a model folder (binary preferred, else text)."""
    import pycolmap

    if not is_model_dir(folder):
        raise DataError(f"{folder}: not a COLMAP model (needs cameras, images and points3D "
                        ".bin or .txt)")
    model = pycolmap.Reconstruction()
    try:
        model.read(folder)
    except (ValueError, RuntimeError, OSError) as exc:
        reason = str(exc).split("]", 1)[-1].strip() or type(exc).__name__
        raise DataError(f"{folder}: cannot read the COLMAP model ({reason})") from None
    return model


def find_model(root: Path, sparse: str = ""):
    """(folder, model): ``root/sparse`` if given, else the first of sparse/, colmap/sparse/ and
    the root that holds a model; among numbered sub-models (0, 1, ...) the one with the most
    registered images."""
    if sparse:
        folder = root / sparse
        return folder, read_model(folder)
    for base in (root / "sparse", root / "colmap" / "sparse", root):
        if is_model_dir(base):
            return base, read_model(base)
        subs = sorted(p for p in base.glob("*") if p.is_dir() and p.name.isdigit() and is_model_dir(p))
        if subs:
            models = [(p, read_model(p)) for p in subs]
            return max(models, key=lambda pm: pm[1].num_reg_images())
    raise DataError(f"{root}: no COLMAP sparse model found (looked in sparse/, sparse/N/, "
                    "colmap/sparse/N/ and the folder itself); run rs-process-data first")


def colmap_c2w(image) -> np.ndarray:
    """Camera-to-world 4x4 (OpenCV axes) of a posed pycolmap Image."""
    w2c = np.eye(4)
    w2c[:3] = image.cam_from_world().matrix()
    return np.linalg.inv(w2c)


def posed_images(model) -> list:
    """The registered images of a model, sorted by name."""
    return sorted((model.images[i] for i in model.reg_image_ids()), key=lambda im: im.name)


def pinhole_intrinsics(camera) -> dict[str, float]:
    """fl_x, fl_y, cx, cy, w, h of an undistorted camera."""
    if not camera.is_undistorted():
        raise DataError(f"camera {camera.camera_id} ({camera.model_name}) still has distortion; "
                        "undistort the model first")
    return {"fl_x": float(camera.focal_length_x), "fl_y": float(camera.focal_length_y),
            "cx": float(camera.principal_point_x), "cy": float(camera.principal_point_y),
            "w": int(camera.width), "h": int(camera.height)}


def model_points(model) -> tuple[np.ndarray, np.ndarray]:
    """Sparse points (P, 3) float64 and their colours (P, 3) uint8, in point-id order."""
    points = [model.points3D[i] for i in sorted(model.point3D_ids())]
    xyz = np.array([p.xyz for p in points], dtype=np.float64).reshape(-1, 3)
    rgb = np.array([p.color for p in points], dtype=np.uint8).reshape(-1, 3)
    return xyz, rgb
