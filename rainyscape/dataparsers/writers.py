"""Export a SceneData as an LLFF or a transforms.json scene (in the input's world frame).

The rainy images go to ``images_rain/`` and the clean ones (when known) to
``images_wo_rain/``, so the llff and transforms-json parsers find them by the authors'
``_rain`` / ``_wo_rain`` convention.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from rainyscape.dataparsers.images import write_png
from rainyscape.dataparsers.llff import opencv_to_llff
from rainyscape.dataparsers.transforms_json import transforms_content, write_transforms
from rainyscape.scene import SceneData

RAINY, CLEAN = "images_rain", "images_wo_rain"


def original_c2w(scene: SceneData) -> np.ndarray:
    """Camera-to-world (N, 4, 4) OpenCV in the input's world frame (normalisation undone)."""
    c2w = scene.cameras.c2w.double().clone()
    c2w[:, :3, 3] = scene.to_original(c2w[:, :3, 3].float()).double()
    return c2w.numpy()


def _write_images(scene: SceneData, out: Path) -> None:
    (out / RAINY).mkdir(parents=True, exist_ok=True)
    sets = [(RAINY, scene.images)]
    if scene.clean_images is not None:
        (out / CLEAN).mkdir(exist_ok=True)
        sets.append((CLEAN, scene.clean_images))
    for folder, images in sets:
        for name, img in zip(scene.image_names, images):
            write_png(out / folder / f"{Path(name).stem}.png", img.numpy())


def write_llff(scene: SceneData, out: str | Path) -> Path:
    """``poses_bounds.npy`` (standard LLFF columns: down, right, back) and the images.

    LLFF stores one focal length and a centred principal point; other cameras raise ValueError.
    """
    out = Path(out)
    cams = scene.cameras
    if not (torch.allclose(cams.fx, cams.fy, rtol=1e-4)
            and torch.allclose(cams.cx, torch.full_like(cams.cx, cams.width / 2), atol=1e-3)
            and torch.allclose(cams.cy, torch.full_like(cams.cy, cams.height / 2), atol=1e-3)):
        raise ValueError("LLFF needs fx == fy and a centred principal point")
    c2w = original_c2w(scene)
    mats = np.zeros((len(cams), 3, 5))
    mats[:, :, :3] = opencv_to_llff(c2w[:, :3, :3])
    mats[:, :, 3] = c2w[:, :3, 3]
    mats[:, :, 4] = np.stack([np.full(len(cams), cams.height), np.full(len(cams), cams.width),
                              cams.fx.double().numpy()], -1)
    bounds = _bounds(scene)
    _write_images(scene, out)
    np.save(out / "poses_bounds.npy", np.concatenate([mats.reshape(len(cams), 15), bounds], 1))
    return out


def _bounds(scene: SceneData) -> np.ndarray:
    """Per-view near / far in the input's units: from depth when known, else the scene's."""
    n = scene.num_images
    if scene.depths is not None:
        out = np.zeros((n, 2))
        for i, d in enumerate(scene.depths):
            finite = d[torch.isfinite(d)]
            if finite.numel():
                out[i] = [float(finite.min()) * 0.9, float(finite.max()) * 1.1]
            else:
                out[i] = [scene.near, scene.far]
        return out / scene.scale
    return np.tile([scene.near / scene.scale, scene.far / scene.scale], (n, 1))


def transforms_meta(scene: SceneData, file_paths: list[str]) -> dict:
    """nerfstudio ``transforms.json`` content: OpenGL camera-to-world in the input's world
    frame and per-frame pinhole intrinsics, one frame per view with ``file_paths``."""
    cams = scene.cameras
    intrinsics = [{"fl_x": float(cams.fx[i]), "fl_y": float(cams.fy[i]), "cx": float(cams.cx[i]),
                   "cy": float(cams.cy[i]), "w": cams.width, "h": cams.height} for i in range(len(cams))]
    return transforms_content(original_c2w(scene), intrinsics, file_paths, per_frame_intrinsics=True)


def write_transforms_json(scene: SceneData, out: str | Path) -> Path:
    """A transforms.json scene: the images plus ``transforms.json`` (see :func:`transforms_meta`)."""
    out = Path(out)
    meta = transforms_meta(scene, [f"{RAINY}/{Path(n).stem}.png" for n in scene.image_names])
    _write_images(scene, out)
    write_transforms(out / "transforms.json", meta)
    return out
