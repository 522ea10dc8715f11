"""``rs-render``: per-view images and a camera-path video of a trained run.

Writes under ``RUN_DIR/renders/``:
  clean/<view>.png   the field's render (the de-rained scene)
  rain/<view>.png    the predicted rain layer (training views of runs with a rain head)
  error/<view>.png   |render - ground truth| on a fixed colour scale (scenes with clean images)
  depth/<view>.png   colour-mapped z-depth (near: bright), depth/<view>.npy the raw values
  strips/<view>.png  rainy | render | (post-processed) | ground truth | rain map
  path.mp4           a camera path through the training views (or a spiral)
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from rainyscape.engine.pipeline import Pipeline
from rainyscape.engine.run_folder import RunFolder
from rainyscape.eval.camera_path import path_cameras
from rainyscape.eval.images import depth_map, error_map, save_png, strip_panels, side_by_side, to_uint8
from rainyscape.eval.views import progress, render_cameras, view_images


@dataclass
class RenderOptions:
    views: str = "all"  # comma-separated view names / indices and all | train | heldout
    video: bool = True
    path: str = "views"  # views | spiral
    frames: int = 60
    fps: int = 15


def select_views(pipeline: Pipeline, which: str) -> list[int]:
    """View indices from a comma-separated list of view names / stems / indices and the
    groups ``all``, ``train`` and ``heldout`` (in the order given, without repeats)."""
    from rainyscape.errors import ConfigError

    scene = pipeline.scene
    groups = {"all": list(range(scene.num_images)), "train": list(scene.train_indices),
              "heldout": list(scene.eval_indices)}
    by_name = {n: i for i, n in enumerate(scene.image_names)}
    by_name.update({Path(n).stem: i for i, n in enumerate(scene.image_names)})
    out: list[int] = []
    for item in filter(None, (p.strip() for p in which.split(","))):
        if item in groups:
            out += groups[item]
        elif item in by_name:
            out.append(by_name[item])
        elif item.isdigit() and int(item) < scene.num_images:
            out.append(int(item))
        else:
            raise ConfigError(f"views: no view '{item}' in scene {scene.name} (views are "
                              f"{', '.join(scene.image_names[:6])}...; or all, train, heldout)")
    return list(dict.fromkeys(out))


@torch.no_grad()
def render_views(pipeline: Pipeline, out_dir: Path, indices: list[int]) -> dict[str, int]:
    """Per-view images for ``indices``; returns how many files of each kind were written."""
    counts: dict[str, int] = {}

    def put(kind: str, stem: str, image: np.ndarray) -> None:
        save_png(out_dir / kind / f"{stem}.png", image)
        counts[kind] = counts.get(kind, 0) + 1

    for i in progress(indices, "rendering views"):
        v = view_images(pipeline, i)
        stem = Path(v.name).stem
        put("clean", stem, to_uint8(v.rendered))
        if v.rain is not None:
            put("rain", stem, to_uint8(v.rain))
        if v.clean is not None:
            put("error", stem, error_map(v.rendered, v.clean))
        if v.depth is not None:
            put("depth", stem, depth_map(v.depth))
            np.save(out_dir / "depth" / f"{stem}.npy", v.depth[0].cpu().numpy())
        put("strips", stem, side_by_side(strip_panels(v)))
    return counts


def _even(frame: np.ndarray) -> np.ndarray:
    """Pad to even width and height (H.264 in yuv420p needs them)."""
    h, w = frame.shape[:2]
    return np.pad(frame, ((0, h % 2), (0, w % 2), (0, 0)), mode="edge")


def write_video(frames: list[np.ndarray], path: Path, fps: int) -> Path:
    import imageio.v2 as imageio

    path.parent.mkdir(parents=True, exist_ok=True)
    with imageio.get_writer(path, fps=fps, codec="libx264", quality=8, macro_block_size=1,
                            ffmpeg_log_level="error") as writer:
        for frame in frames:
            writer.append_data(_even(frame))
    return path


@torch.no_grad()
def render_path_video(pipeline: Pipeline, path: Path, kind: str = "views", frames: int = 60,
                      fps: int = 15) -> Path:
    """Render the field along a camera path (through the training views, or a spiral) to MP4."""
    scene = pipeline.scene
    indices = list(scene.train_indices) or list(range(scene.num_images))
    cams = path_cameras(scene.cameras, indices, kind, frames)
    images = [to_uint8(render_cameras(pipeline, cams[[k]]).rgb[0])
              for k in progress(list(range(len(cams))), "rendering the camera path", "frame")]
    return write_video(images, path, fps)


def render_run(pipeline: Pipeline, run_dir: Path, options: RenderOptions) -> dict:
    out_dir = RunFolder(run_dir).renders
    counts = render_views(pipeline, out_dir, select_views(pipeline, options.views))
    result: dict = {"folder": str(out_dir), "files": counts}
    if options.video:
        result["video"] = str(render_path_video(pipeline, out_dir / "path.mp4", options.path,
                                                options.frames, options.fps))
    return result
