"""Reading COLMAP sparse models (binary or text) through pycolmap: where the model is, its
camera poses in the OpenCV camera-to-world form, pinhole intrinsics and sparse points.

COLMAP stores world-to-camera poses (``cam_from_world``) with OpenCV camera axes and puts the
centre of pixel (row i, column j) at (j + 0.5, i + 0.5), as rainyscape.cameras does, so only
the pose needs inverting.
"""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np

from rainyscape.errors import DataError

MODEL_FILES = ("cameras", "images", "points3D")


def model_files(folder: Path) -> list[str]:
    """Which of :data:`MODEL_FILES` ``folder`` holds (as .bin or .txt)."""
    return [name for name in MODEL_FILES
            if any((folder / f"{name}{ext}").is_file() for ext in (".bin", ".txt"))]


def is_model_dir(folder: Path) -> bool:
    return len(model_files(folder)) == len(MODEL_FILES)


def check_complete(folder: Path) -> None:
    """DataError naming what is missing when ``folder`` holds part of a model (a model with a
    file deleted is not silently skipped for another one)."""
    have = model_files(folder)
    if have and len(have) < len(MODEL_FILES):
        missing = [f"{n}.bin" for n in MODEL_FILES if n not in have]
        raise DataError(f"{folder / missing[0]}: missing, so the COLMAP model in {folder} is incomplete "
                        f"(it has {', '.join(have)}); restore it, or name a model with dataparser.sparse=")


def read_model(folder: Path):
    """A pycolmap Reconstruction from a model folder (binary preferred, else text). Binary
    files are checked whole first (:func:`check_binary_model`): pycolmap reads a truncated
    one as garbage sizes (a 1x1 camera, "out of memory")."""
    import pycolmap

    check_complete(folder)
    if not is_model_dir(folder):
        raise DataError(f"{folder}: not a COLMAP model (needs cameras, images and points3D "
                        ".bin or .txt)")
    if all((folder / f"{name}.bin").is_file() for name in MODEL_FILES):
        check_binary_model(folder)
    model = pycolmap.Reconstruction()
    try:
        model.read(folder)
    except (ValueError, RuntimeError, OSError, IndexError, KeyError) as exc:
        reason = str(exc).split("]", 1)[-1].strip() or type(exc).__name__
        raise DataError(f"{folder}: cannot read the COLMAP model ({reason})") from None
    return model


# Parameters per COLMAP camera model id (colmap/sensor/models.h)
CAMERA_PARAMS = {0: 3, 1: 4, 2: 4, 3: 5, 4: 8, 5: 8, 6: 12, 7: 5, 8: 4, 9: 5, 10: 12, 11: 16}


class _Reader:
    """Walks a binary model file, naming the file and the record when it ends too soon."""

    def __init__(self, path: Path):
        self.path, self.data, self.at = path, path.read_bytes(), 0

    def take(self, fmt: str, what: str) -> tuple:
        size = struct.calcsize(fmt)
        if self.at + size > len(self.data):
            raise DataError(f"{self.path}: truncated or damaged ({len(self.data)} bytes; it ends inside "
                            f"{what}); write the model again (rs-process-data, or COLMAP's model_converter)")
        out = struct.unpack_from(fmt, self.data, self.at)
        self.at += size
        return out

    def skip(self, size: int, what: str) -> None:
        if self.at + size > len(self.data):
            self.take(f"<{size}x", what)
        self.at += size

    def count(self, record: int, what: str) -> int:
        """The leading record count, checked against the file's size (``record``: the least
        bytes one record takes)."""
        (n,) = self.take("<Q", f"the count of {what}")
        if n * record > len(self.data) - self.at:
            raise DataError(f"{self.path}: truncated or damaged (it says {n} {what}, which need at least "
                            f"{n * record} bytes; it has {len(self.data) - self.at}); write the model again")
        return n

    def end(self) -> None:
        if self.at != len(self.data):
            raise DataError(f"{self.path}: damaged ({len(self.data) - self.at} bytes after its last record)")


def check_binary_model(folder: Path) -> None:
    """DataError naming the file when cameras.bin, images.bin or points3D.bin is truncated or
    damaged: each is walked record by record (COLMAP's binary layout) and must end exactly."""
    r = _Reader(folder / "cameras.bin")
    for k in range(r.count(24, "cameras")):
        _, model, width, height = r.take("<IiQQ", f"camera {k + 1}")
        if model not in CAMERA_PARAMS:
            raise DataError(f"{r.path}: damaged (camera {k + 1} has model id {model}, not a COLMAP model)")
        if not (0 < width < 1 << 20 and 0 < height < 1 << 20):
            raise DataError(f"{r.path}: damaged (camera {k + 1} is {width} x {height} pixels)")
        r.skip(8 * CAMERA_PARAMS[model], f"camera {k + 1}'s parameters")
    r.end()
    r = _Reader(folder / "images.bin")
    for k in range(r.count(73, "images")):
        r.skip(64, f"image {k + 1}")  # id, quaternion, translation, camera id
        end = r.data.find(b"\0", r.at)
        if end < 0:
            r.take(f"<{len(r.data) - r.at + 1}x", f"image {k + 1}'s name")
        r.at = end + 1
        (points,) = r.take("<Q", f"image {k + 1}'s point count")
        r.skip(24 * points, f"image {k + 1}'s {points} points")
    r.end()
    r = _Reader(folder / "points3D.bin")
    for k in range(r.count(51, "points")):
        r.skip(43, f"point {k + 1}")  # id, xyz, rgb, error
        (track,) = r.take("<Q", f"point {k + 1}'s track length")
        r.skip(8 * track, f"point {k + 1}'s track")
    r.end()


def find_model(root: Path, sparse: str = ""):
    """(folder, model): ``root/sparse`` if given, else the first of sparse/, colmap/sparse/ and
    the root that holds a model; among numbered sub-models (0, 1, ...) the one with the most
    registered images."""
    if sparse:
        folder = root / sparse
        return folder, read_model(folder)
    for base in (root / "sparse", root / "colmap" / "sparse", root):
        check_complete(base)
        if is_model_dir(base):
            return base, read_model(base)
        numbered = sorted(p for p in base.glob("*") if p.is_dir() and p.name.isdigit())
        for p in numbered:
            check_complete(p)
        subs = [p for p in numbered if is_model_dir(p)]
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
