"""What every dataparser shares: common options and the final assembly of SceneData."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import Tensor

from rainyscape.cameras import Cameras
from rainyscape.errors import DataError
from rainyscape.scene import SceneData, apply_normalization, normalize_poses, split_indices


@dataclass
class CommonParserConfig:
    """Options every dataparser accepts (each parser's Config subclasses this)."""

    holdout_every: int = 8  # every k-th view is held out for novel-view evaluation (0: none)
    holdout_file: str = ""  # or a text file listing held-out image names, one a line
    downscale: int = 1  # integer image downscale factor (area averaging)
    normalize: bool = True  # centre where the cameras look; farthest camera at camera_radius
    camera_radius: float = 3.0


def read_holdout_file(path: Path, names: list[str]) -> list[int]:
    try:
        wanted = [line.strip() for line in path.read_text().splitlines() if line.strip()]
    except OSError as exc:
        raise DataError(f"{path}: cannot read the held-out list ({exc.strerror})") from None
    index = {n: i for i, n in enumerate(names)}
    index.update({Path(n).stem: i for i, n in enumerate(names)})
    missing = [w for w in wanted if w not in index]
    if missing:
        raise DataError(f"{path}: names not among the images: {', '.join(missing[:5])}")
    return [index[w] for w in wanted]


def downscale_images(images: Tensor, factor: int) -> Tensor:
    """Area-average uint8 (N, H, W, C) by an integer factor (H, W cropped to multiples)."""
    if factor <= 1:
        return images
    n, h, w, c = images.shape
    h2, w2 = h // factor, w // factor
    x = images[:, : h2 * factor, : w2 * factor].permute(0, 3, 1, 2).float()
    x = F.avg_pool2d(x, factor)
    return x.round().clamp(0, 255).to(torch.uint8).permute(0, 2, 3, 1).contiguous()


def assemble_scene(config: CommonParserConfig, *, name: str, source: Path, images: Tensor,
                   cameras: Cameras, image_names: list[str], clean_images: Tensor | None = None,
                   depths: Tensor | None = None, rain_layers: Tensor | None = None,
                   points: Tensor | None = None, point_colors: Tensor | None = None,
                   near: float | None = None, far: float | None = None,
                   forward_facing: bool = False, metadata: dict | None = None) -> SceneData:
    """Apply downscale, world normalisation and the held-out split; return SceneData.

    ``cameras`` must already be in the OpenCV convention. ``depths`` are z-depths in the
    input's world units; ``near`` / ``far`` likewise (estimated from cameras when None).
    """
    factor = max(1, int(config.downscale))
    if factor > 1:
        images = downscale_images(images, factor)
        clean_images = downscale_images(clean_images, factor) if clean_images is not None else None
        if rain_layers is not None:
            rain_layers = F.avg_pool2d(rain_layers.permute(0, 3, 1, 2), factor).permute(0, 2, 3, 1)
        if depths is not None:
            depths = -F.max_pool2d(-depths[:, None], factor)[:, 0]  # keep the nearest surface
        cameras = cameras.scaled(images.shape[2] / cameras.width)
        cameras.width, cameras.height = images.shape[2], images.shape[1]
    transform, scale = torch.eye(4), 1.0
    if config.normalize:
        transform, scale = normalize_poses(cameras.c2w, config.camera_radius)
        cameras = Cameras(apply_normalization(cameras.c2w, transform, scale), cameras.fx,
                          cameras.fy, cameras.cx, cameras.cy, cameras.width, cameras.height)
        if points is not None:
            points = (points @ transform[:3, :3].T + transform[:3, 3]) * scale
        if depths is not None:
            depths = depths * scale
    if near is None or far is None:
        radius = cameras.centers.norm(dim=-1).max().item() if config.normalize else None
        near = near * scale if near is not None else 0.05 * (radius or 1.0)
        far = far * scale if far is not None else 2.5 * (radius or 1.0)
    else:
        near, far = near * scale, far * scale
    if points is not None and len(points):
        lo, hi = points.quantile(0.01, 0), points.quantile(0.99, 0)
        box = torch.stack([lo, hi])
    else:
        # No points: cameras around the centre see content out to about their own distance
        # (a half-size cube cut off the street scenes' buildings and ground).
        r = cameras.centers.norm(dim=-1).max().item()
        box = torch.tensor([[-r, -r, -r], [r, r, r]], dtype=torch.float32)
    if config.holdout_file:
        held = read_holdout_file(Path(config.holdout_file), image_names)
        train, held = split_indices(len(image_names), explicit=held)
    else:
        train, held = split_indices(len(image_names), every=config.holdout_every)
    return SceneData(
        name=name, images=images, cameras=cameras, image_names=image_names,
        train_indices=train, eval_indices=held, near=float(near), far=float(far),
        scene_box=box.float(), clean_images=clean_images, depths=depths,
        rain_layers=rain_layers, points=points, point_colors=point_colors,
        forward_facing=forward_facing, transform=transform, scale=scale, source=str(source),
        metadata=metadata or {})
