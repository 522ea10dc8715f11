"""llff: ``poses_bounds.npy`` + ``images/`` (or ``images_N/``), the format of the authors' release.

``poses_bounds.npy`` is (N, 17): per image a row-major 3 x 5 matrix [R | t | (H, W, f)] (a
camera-to-world rotation and centre, then height, width and focal length in pixels of the
full-resolution images) followed by the near and far depth bounds.

The rotation's columns are, in standard LLFF, the camera's (down, right, backwards) axes.
The authors' released scene stores OpenCV columns (right, down, forwards) instead.
``pose_convention=auto`` tells them apart for cameras that look at a common point (the
interpretation that puts that point in front of the cameras wins) and falls back to
standard LLFF for near-parallel (forward-facing) captures.

Clean images follow the authors' convention: the same path with ``_rain`` replaced by
``_wo_rain`` (``scene_rain/images`` -> ``scene_wo_rain/images``, ``images_rain`` ->
``images_wo_rain``), or a folder named by ``clean=``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from rainyscape.cameras import Cameras
from rainyscape.components import DataParser
from rainyscape.config.schema import choice
from rainyscape.dataparsers.base import CommonParserConfig, assemble_scene
from rainyscape.dataparsers.images import clean_image_paths, list_images, read_stack
from rainyscape.errors import DataError
from rainyscape.scene import SceneData

POSE_CONVENTIONS = ("auto", "llff", "opencv")


@dataclass
class LLFFConfig(CommonParserConfig):
    images: str = "auto"  # image folder; auto: images/, else images_rain/
    clean: str = "auto"  # auto: the `_rain` -> `_wo_rain` sibling if it exists; "": none
    pose_convention: str = choice("auto", POSE_CONVENTIONS)  # auto, llff (down, right, back) or opencv (right, down, forward)
    use_prescaled: bool = True  # with downscale=N read images_N/ (or images_k/, k dividing N) when it exists (LLFF habit)


def read_poses_bounds(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(N, 3, 4) rotation|centre as stored, (N, 3) hwf, (N, 2) bounds; DataError on bad input."""
    if not path.is_file():
        raise DataError(f"{path}: file not found")
    try:
        arr = np.load(path, allow_pickle=False)
    except (OSError, ValueError) as exc:
        raise DataError(f"{path}: not a readable .npy array ({exc})") from None
    if arr.ndim != 2 or arr.shape[1] != 17:
        raise DataError(f"{path}: expected an (N, 17) array, got shape {arr.shape}")
    if not np.isfinite(arr).all():
        row = int(np.argwhere(~np.isfinite(arr))[0, 0])
        raise DataError(f"{path}: row {row} holds non-finite numbers")
    mats = arr[:, :15].reshape(-1, 3, 5).astype(np.float64)
    bounds = arr[:, 15:17].astype(np.float64)
    if (mats[:, :, 4] <= 0).any():
        raise DataError(f"{path}: height, width and focal length (5th column) must be positive")
    if (bounds[:, 0] < 0).any() or (bounds[:, 1] <= bounds[:, 0]).any():
        raise DataError(f"{path}: bounds must satisfy 0 <= near < far")
    det = np.linalg.det(mats[:, :, :3])
    if (np.abs(det - 1.0) > 1e-2).any():
        raise DataError(f"{path}: the 3x3 blocks are not rotations (determinant {det[np.argmax(np.abs(det - 1))]:.3f})")
    return mats[:, :, :4], mats[:, :, 4], bounds


def llff_to_opencv(rot: np.ndarray) -> np.ndarray:
    """(down, right, back) columns -> OpenCV (right, down, forward), and back: an involution
    (:func:`opencv_to_llff`)."""
    return np.stack([rot[..., 1], rot[..., 0], -rot[..., 2]], -1)


opencv_to_llff = llff_to_opencv  # the same column swap, named for the direction written


def _focus_in_front(centers: np.ndarray, forward: np.ndarray) -> float | None:
    """Fraction of cameras with their axes' common point in front; None for parallel axes."""
    proj = np.eye(3)[None] - forward[:, :, None] * forward[:, None, :]
    a = proj.sum(0)
    if np.linalg.cond(a) > 1e4:
        return None
    focus = np.linalg.solve(a, (proj @ centers[:, :, None]).sum(0)[:, 0])
    return float(np.mean(np.einsum("ij,ij->i", focus - centers, forward) > 0))


def detect_convention(rot: np.ndarray, centers: np.ndarray) -> str:
    """'opencv' when the OpenCV reading makes the optical axes converge in front; else 'llff'."""
    cv_fwd = rot[..., 2]
    in_front = _focus_in_front(centers, cv_fwd)
    if in_front is None:
        return "llff"
    return "opencv" if in_front > 0.5 else "llff"


class LLFFParser(DataParser):
    """LLFF poses_bounds.npy + images/ (the authors' released scene format)."""

    description = "LLFF poses_bounds.npy + images/ (also the authors' _rain / _wo_rain folders)"
    Config = LLFFConfig

    def __init__(self, config: LLFFConfig | None = None):
        super().__init__(config or LLFFConfig())

    def _image_dir(self, root: Path) -> tuple[Path, int]:
        """Image folder and the factor its images are already downscaled by."""
        cfg: LLFFConfig = self.config
        if cfg.images != "auto":
            folder = root / cfg.images
            if not folder.is_dir():
                raise DataError(f"{folder}: image folder not found (images=)")
            return folder, 1
        factor = max(1, int(cfg.downscale))
        if factor > 1 and cfg.use_prescaled:
            # images_N itself, else the smallest images_k it can be made from (k divides N):
            # the authors' Yard ships images_2/ only, and downscale=8 reads it shrunk by 4
            for k in range(factor, 1, -1):
                if factor % k == 0 and (root / f"images_{k}").is_dir():
                    return root / f"images_{k}", k
        for name in ("images", "images_rain"):
            if (root / name).is_dir():
                return root / name, 1
        raise DataError(f"{root}: no images/ (or images_rain/) folder next to poses_bounds.npy")

    def parse(self, path: Path) -> SceneData:
        cfg: LLFFConfig = self.config
        if cfg.pose_convention not in POSE_CONVENTIONS:
            raise DataError(f"pose_convention must be one of {', '.join(POSE_CONVENTIONS)}, "
                            f"got '{cfg.pose_convention}'")
        root = Path(path)
        if not root.is_dir():
            raise DataError(f"{root}: no such scene folder")
        pb_path = root / "poses_bounds.npy"
        poses, hwf, bounds = read_poses_bounds(pb_path)
        image_dir, prescaled = self._image_dir(root)
        files = list_images(image_dir)
        if len(files) != len(poses):
            raise DataError(f"{pb_path} holds {len(poses)} poses but {image_dir} holds {len(files)} images")
        images = read_stack(files, what="image")
        h, w = images.shape[1:3]
        full_h, full_w = hwf[0, 0], hwf[0, 1]
        if abs(full_w / full_h - w / h) > 0.02:
            raise DataError(f"{image_dir}: images are {w}x{h}, but {pb_path} says {full_w:g}x{full_h:g} "
                            "(aspect ratios differ)")
        rot, centers = poses[:, :, :3], poses[:, :, 3]
        convention = cfg.pose_convention
        if convention == "auto":
            convention = detect_convention(rot, centers)
        rot_cv = rot if convention == "opencv" else llff_to_opencv(rot)
        c2w = np.tile(np.eye(4), (len(poses), 1, 1))
        c2w[:, :3, :3], c2w[:, :3, 3] = rot_cv, centers
        f = hwf[:, 2] * (w / full_w)
        cameras = Cameras(torch.from_numpy(c2w).float(), torch.tensor(f, dtype=torch.float32),
                          torch.tensor(f, dtype=torch.float32), torch.full((len(f),), w / 2.0),
                          torch.full((len(f),), h / 2.0), w, h)
        clean = self._clean(root, image_dir, files, (w, h))
        scene_cfg = cfg
        if prescaled > 1:  # images_k are already downscaled by k: shrink them by the rest only
            from dataclasses import replace

            scene_cfg = replace(cfg, downscale=max(1, int(cfg.downscale)) // prescaled)
        return assemble_scene(
            scene_cfg, name=root.resolve().name, source=root, images=images, cameras=cameras,
            image_names=[p.name for p in files], clean_images=clean,
            near=float(bounds[:, 0].min()), far=float(bounds[:, 1].max()),
            image_files=files,
            metadata={"format": "llff", "pose_convention": convention, "images": str(image_dir)})

    def _clean(self, root: Path, image_dir: Path, files: list[Path], size: tuple[int, int]):
        paths = clean_image_paths(self.config.clean, root, image_dir, files)
        return None if paths is None else read_stack(paths, size, what="clean image")
