"""Reading image folders for dataparsers: natural ordering, size checks, clear errors."""

from __future__ import annotations

import re
from pathlib import Path

import cv2
import numpy as np
import torch
from torch import Tensor

from rainyscape.errors import DataError

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".exr")


def natural_key(name: str) -> list:
    """Sort key that orders 2.png before 10.png."""
    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", name)]


def list_images(folder: Path) -> list[Path]:
    if not folder.is_dir():
        raise DataError(f"{folder}: no such image folder")
    files = [p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES
             and not p.name.startswith(".")]
    if not files:
        raise DataError(f"{folder}: no images (.png, .jpg) in the folder")
    return sorted(files, key=lambda p: natural_key(p.name))


def clean_sibling(image_dir: Path) -> Path | None:
    """The authors' convention: the last ``_rain`` in the path becomes ``_wo_rain``."""
    text = str(image_dir.resolve())
    pos = text.rfind("_rain")
    if pos < 0 or text[max(0, pos - 3):pos] == "_wo":
        return None
    candidate = Path(text[:pos] + "_wo_rain" + text[pos + len("_rain"):])
    return candidate if candidate.is_dir() else None


def clean_image_paths(option: str, root: Path, image_dir: Path, files: list[Path]) -> list[Path] | None:
    """The clean image for each rainy image in ``files``, or None where there are none.

    ``option`` is a parser's ``clean`` setting: "" (none), "auto" (the ``_wo_rain`` sibling of
    ``image_dir`` when it exists) or a folder relative to ``root`` that must hold them all.
    A clean image has the rainy one's name, or its stem with another suffix."""
    if not option:
        return None
    if option == "auto":
        folder = clean_sibling(image_dir)
        if folder is None:
            return None
    else:
        folder = root / option
        if not folder.is_dir():
            raise DataError(f"{folder}: clean image folder not found (clean=)")
    paths = []
    for f in files:
        p = folder / f.name
        if not p.is_file():
            matches = sorted(q for q in folder.glob(f"{f.stem}.*") if q.is_file())
            if not matches:
                raise DataError(f"{folder}: no clean image named like {f.name}")
            p = matches[0]
        paths.append(p)
    return paths


def read_rgb(path: Path) -> np.ndarray:
    """(H, W, 3) uint8 RGB; grey, alpha and 16-bit images are converted."""
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise DataError(f"{path}: cannot read the image (missing, corrupt or unsupported format)")
    if img.dtype == np.uint16:
        img = (img.astype(np.float32) / 257.0).round().astype(np.uint8)
    elif img.dtype != np.uint8:
        img = (np.clip(img.astype(np.float32), 0, 1) * 255).round().astype(np.uint8)
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, -1)
    if img.shape[-1] == 4:
        img = img[..., :3]
    return np.ascontiguousarray(img[..., ::-1])


def read_rgba(path: Path) -> np.ndarray:
    """(H, W, 4) uint8 RGBA (an opaque alpha is added to RGB files)."""
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise DataError(f"{path}: cannot read the image (missing, corrupt or unsupported format)")
    if img.dtype != np.uint8:
        raise DataError(f"{path}: expected an 8-bit image, got {img.dtype}")
    if img.ndim == 2 or img.shape[-1] != 4:
        raise DataError(f"{path}: expected an RGBA image (colour + alpha)")
    return np.ascontiguousarray(img[..., [2, 1, 0, 3]])


def read_stack(paths: list[Path], size: tuple[int, int] | None = None, what: str = "image") -> Tensor:
    """Read images into (N, H, W, 3) uint8; all must share one size (``size`` = (W, H) if given)."""
    arrays = []
    for p in paths:
        img = read_rgb(p)
        h, w = img.shape[:2]
        if size is None:
            size = (w, h)
        if (w, h) != size:
            raise DataError(f"{p}: {what} is {w}x{h}, expected {size[0]}x{size[1]} like {paths[0].name}")
        arrays.append(img)
    return torch.from_numpy(np.stack(arrays))


def write_png(path: Path, rgb_or_rgba: np.ndarray) -> None:
    """Write uint8 RGB or RGBA (H, W, 3|4) as PNG."""
    code = cv2.COLOR_RGBA2BGRA if rgb_or_rgba.shape[-1] == 4 else cv2.COLOR_RGB2BGR
    if not cv2.imwrite(str(path), cv2.cvtColor(np.ascontiguousarray(rgb_or_rgba), code)):
        raise OSError(f"{path}: could not write the image")
