"""What every dataparser shares: common options and the final assembly of SceneData."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import Tensor

from rainyscape.cameras import Cameras
from rainyscape.config.schema import bounded
from rainyscape.errors import DataError, warn
from rainyscape.scene import (SceneData, apply_normalization, faces_forward, normalize_poses, points_box,
                              split_indices)

MIN_IMAGE_SIDE = 4  # smaller images are refused (nothing sensible trains on them)


@dataclass
class CommonParserConfig:
    """Options every dataparser accepts (each parser's Config subclasses this)."""

    holdout_every: int = bounded(8, 0, 100_000)  # every k-th view is held out for novel-view evaluation (0: none)
    # or a text file listing the held-out images, one a line: names, stems or paths relative
    # to the scene (as transforms.json writes them); a relative file path is looked up in the
    # working folder, then in the scene folder
    holdout_file: str = ""
    downscale: int = bounded(1, 1, 1024)  # integer image downscale factor (area averaging)
    normalize: bool = True  # centre where the cameras look; farthest camera at camera_radius
    camera_radius: float = bounded(3.0, hi=1e6, above=0.0)


class ImageIndex:
    """Finds an image by its name, its stem or its path relative to the scene folder (with or
    without extension, ``./`` or not), the ways held-out lists and transforms.json name them."""

    def __init__(self, names: list[str], files: list[Path] | None, root: Path | None):
        keys: dict[str, set[int]] = {}
        for i, name in enumerate(names):
            spellings = {name, Path(name).stem, Path(name).as_posix(), Path(name).with_suffix("").as_posix()}
            if files is not None:
                f = Path(files[i])
                spellings |= {f.name, f.stem, str(f.resolve())}
                if root is not None:
                    try:
                        rel = f.resolve().relative_to(Path(root).resolve())
                    except ValueError:
                        rel = None
                    if rel is not None:
                        spellings |= {rel.as_posix(), rel.with_suffix("").as_posix()}
            for key in spellings:
                keys.setdefault(key, set()).add(i)
        self.keys, self.root = keys, root

    def find(self, entry: str) -> int | None:
        """The index of ``entry``; None when no image matches; DataError when several do."""
        text = entry.strip().replace("\\", "/")
        candidates = [text, text[2:] if text.startswith("./") else text]
        if self.root is not None and not Path(text).is_absolute():
            candidates.append(str((Path(self.root) / text).resolve()))
        for c in candidates:
            for key in (c, str(Path(c).with_suffix("")) if Path(c).suffix else c):
                hits = self.keys.get(key)
                if hits and len(hits) > 1:
                    raise DataError(f"'{entry}' names {len(hits)} images; write its path relative to "
                                    "the scene folder")
                if hits:
                    return next(iter(hits))
        return None

    def indices(self, entries: list[str], where: str) -> list[int]:
        found = [(e, self.find(e)) for e in entries]
        missing = [e for e, i in found if i is None]
        if missing:
            raise DataError(f"{where}: not among the scene's images: {', '.join(missing[:5])}"
                            + (f" and {len(missing) - 5} more" if len(missing) > 5 else ""))
        return [i for _, i in found]


def holdout_file_path(option: str, root: Path | None) -> Path:
    """``dataparser.holdout_file``: as given, else relative to the scene folder."""
    path = Path(option).expanduser()
    if path.is_file() or path.is_absolute() or root is None:
        return path
    inside = Path(root) / option
    return inside if inside.is_file() else path


def read_holdout_file(path: Path, names: list[str], files: list[Path] | None = None,
                      root: Path | None = None) -> list[int]:
    """Indices of the images a held-out list names (see :class:`ImageIndex`)."""
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise DataError(f"{path}: no such held-out list (dataparser.holdout_file)") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise DataError(f"{path}: cannot read the held-out list "
                        f"({getattr(exc, 'strerror', None) or exc})") from None
    wanted = [line.strip() for line in text.splitlines() if line.strip() and not line.startswith("#")]
    return ImageIndex(names, files, root).indices(wanted, str(path))


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
                   points_source: str = "", near: float | None = None, far: float | None = None,
                   forward_facing: bool | None = None, metadata: dict | None = None,
                   image_files: list[Path] | None = None,
                   heldout: tuple[list[str], str] | None = None) -> SceneData:
    """Apply downscale, world normalisation and the held-out split; return SceneData.

    ``cameras`` must already be in the OpenCV convention. ``depths`` are z-depths in the
    input's world units; ``near`` / ``far`` likewise (estimated from cameras when None).
    ``points_source``: where ``points`` come from (SceneData.points_source).
    ``forward_facing``: None: from the cameras (``scene.faces_forward``).
    ``image_files``: the image files (held-out lists may name them by path). ``heldout``:
    the format's own held-out list (entries, where they come from), used unless
    ``holdout_file`` is set.
    """
    factor = max(1, int(config.downscale))
    h0, w0 = images.shape[1:3]
    if min(h0, w0) // factor < MIN_IMAGE_SIDE:
        raise DataError(f"{source}: the images are {w0}x{h0}; dataparser.downscale={factor} would make "
                        f"them {w0 // factor}x{h0 // factor} (at least {MIN_IMAGE_SIDE} pixels a side "
                        f"needed; largest downscale: {max(1, min(h0, w0) // MIN_IMAGE_SIDE)})"
                        if factor > 1 else
                        f"{source}: the images are {w0}x{h0}; at least {MIN_IMAGE_SIDE} pixels a side needed")
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
        box = points_box(points)
    else:
        # No points: cameras around the centre see content out to about their own distance
        # (a half-size cube cut off the street scenes' buildings and ground).
        r = cameras.centers.norm(dim=-1).max().item()
        box = torch.tensor([[-r, -r, -r], [r, r, r]], dtype=torch.float32)
    n = len(image_names)
    if config.holdout_file:
        path = holdout_file_path(config.holdout_file, source)
        held = read_holdout_file(path, image_names, image_files, source)
        train, held = split_indices(n, explicit=held)
        split_from = f"dataparser.holdout_file={config.holdout_file}"
    elif heldout is not None:
        entries, where = heldout
        held = ImageIndex(image_names, image_files, source).indices(entries, where)
        train, held = split_indices(n, explicit=held)
        split_from = where
    else:
        train, held = split_indices(n, every=config.holdout_every)
        split_from = f"dataparser.holdout_every={config.holdout_every}"
    if not train:
        raise DataError(f"{source}: {split_from} holds out every one of the {n} views: none is left "
                        "to train on" + (" (holdout_every=0 holds out none; 2 or more, every k-th)"
                                         if split_from.startswith("dataparser.holdout_every") else ""))
    if n == 1:
        warn(f"{source}: a single view: a 3D scene cannot be recovered from one image "
             "(training fits that view only)")
    return SceneData(
        name=name, images=images, cameras=cameras, image_names=image_names,
        train_indices=train, eval_indices=held, near=float(near), far=float(far),
        scene_box=box.float(), clean_images=clean_images, depths=depths,
        rain_layers=rain_layers, points=points, point_colors=point_colors,
        points_source=(points_source or "dataparser") if points is not None and len(points) else "none",
        forward_facing=faces_forward(cameras.c2w) if forward_facing is None else forward_facing,
        transform=transform, scale=scale, source=str(source),
        metadata=metadata or {})
