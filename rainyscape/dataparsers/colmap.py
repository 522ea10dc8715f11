"""``colmap`` dataparser: a COLMAP sparse model (binary or text) and its images.

Reads what rs-process-data writes (images/ + sparse/0/, already pinhole) and ordinary COLMAP
projects. Distorted cameras are undistorted on load with pycolmap; when undistortion (or one
camera per image) leaves images of different sizes, all are centre-cropped to the common size.
Sparse points and their colours go to SceneData for 3DGS initialisation.

Clean images (evaluation only): ``clean=FOLDER`` holds one per image of the model, named like
it (or its stem with another suffix); ``auto`` takes the ``_rain`` -> ``_wo_rain`` sibling of
the image folder when there is one. They are undistorted and cropped exactly as the rainy
images are.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from rainyscape.cameras import Cameras
from rainyscape.components import DataParser
from rainyscape.dataparsers.base import CommonParserConfig, assemble_scene
from rainyscape.dataparsers.images import clean_image_paths, read_rgb
from rainyscape.errors import DataError
from rainyscape.dataparsers.colmap_model import colmap_c2w, find_model, model_points, posed_images
from rainyscape.scene import SceneData

MAX_POINTS_FOR_BOUNDS = 20_000


def undistort_view(rgb: np.ndarray, camera) -> tuple[np.ndarray, object]:
    """Undistort one image with its COLMAP camera; returns the image and its pinhole camera."""
    import pycolmap

    bitmap, pinhole = pycolmap.undistort_image(pycolmap.UndistortCameraOptions(),
                                              pycolmap.Bitmap.from_array(rgb), camera)
    return np.ascontiguousarray(bitmap.to_array()[..., :3]), pinhole


def crop_to_common_size(images: list[np.ndarray], cx: np.ndarray, cy: np.ndarray
                        ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Centre-crop images of different sizes to the smallest width and height; shift cx, cy."""
    h = min(im.shape[0] for im in images)
    w = min(im.shape[1] for im in images)
    y0 = np.array([(im.shape[0] - h) // 2 for im in images])
    x0 = np.array([(im.shape[1] - w) // 2 for im in images])
    stack = np.stack([im[a:a + h, b:b + w] for im, a, b in zip(images, y0, x0)])
    return stack, cx - x0, cy - y0


def depth_bounds(cameras: Cameras, points: torch.Tensor) -> tuple[float, float] | None:
    """Near / far from the z-depths of the sparse points that project into each camera's image
    (None with too few points)."""
    if len(points) < 10:
        return None
    if len(points) > MAX_POINTS_FOR_BOUNDS:
        points = points[torch.randperm(len(points), generator=torch.Generator().manual_seed(0))
                        [:MAX_POINTS_FOR_BOUNDS]]
    uv, z = cameras.project(points)
    inside = ((z > 0) & (uv[..., 0] >= 0) & (uv[..., 0] < cameras.width)
              & (uv[..., 1] >= 0) & (uv[..., 1] < cameras.height))
    depths = z[inside]
    if depths.numel() < 10:
        return None
    # Margins around the bulk of the points: the scene has surfaces SfM left untextured.
    near = float(depths.quantile(0.01)) * 0.5
    far = float(depths.quantile(0.99)) * 1.5
    return near, far


def _f32(values) -> torch.Tensor:
    return torch.as_tensor(np.asarray(values, dtype=np.float32))


class ColmapParser(DataParser):
    description = "COLMAP sparse model (binary or text) with its images; rs-process-data output"

    @dataclass
    class Config(CommonParserConfig):
        images: str = "images"  # image folder, relative to the scene folder
        clean: str = "auto"  # clean images (evaluation only); auto: the `_rain` -> `_wo_rain` sibling; "": none
        sparse: str = ""  # model folder relative to the scene; empty: found automatically
        load_points: bool = True  # hand the sparse points to the field (3DGS initialisation)

    def __init__(self, config: "ColmapParser.Config | None" = None):
        super().__init__(config or ColmapParser.Config())

    def parse(self, path: Path) -> SceneData:
        cfg: ColmapParser.Config = self.config
        root = Path(path)
        model_dir, model = find_model(root, cfg.sparse)
        views = posed_images(model)
        if not views:
            raise DataError(f"{model_dir}: the COLMAP model has no registered images")
        image_dir = root / cfg.images
        if not image_dir.is_dir():
            raise DataError(f"{image_dir}: no image folder (set dataparser.images=FOLDER)")
        files = [image_dir / view.name for view in views]
        clean_files = clean_image_paths(cfg.clean, root, image_dir, files)
        images, cleans, fx, fy, cx, cy = [], [], [], [], [], []
        undistorted = False
        for k, (view, file) in enumerate(zip(views, files)):
            if not file.is_file():
                raise DataError(f"{file}: image '{view.name}' of the COLMAP model is missing")
            rgb = read_rgb(file)  # as stored, no EXIF turn: the pixels COLMAP measured
            clean = read_rgb(clean_files[k]) if clean_files is not None else None
            camera = model.cameras[view.camera_id]
            if (rgb.shape[1], rgb.shape[0]) != (camera.width, camera.height):
                raise DataError(f"{file}: image is {rgb.shape[1]}x{rgb.shape[0]} but its COLMAP "
                                f"camera {view.camera_id} is {camera.width}x{camera.height}")
            if clean is not None and clean.shape != rgb.shape:
                raise DataError(f"{clean_files[k]}: clean image is {clean.shape[1]}x{clean.shape[0]}, "
                                f"the rainy one {rgb.shape[1]}x{rgb.shape[0]} (clean=)")
            if not camera.is_undistorted():
                if clean is not None:  # the same camera: the same undistortion
                    clean, _ = undistort_view(clean, camera)
                rgb, camera = undistort_view(rgb, camera)
                undistorted = True
            images.append(rgb)
            cleans.append(clean)
            fx.append(camera.focal_length_x)
            fy.append(camera.focal_length_y)
            cx.append(camera.principal_point_x)
            cy.append(camera.principal_point_y)
        stack, cx_crop, cy_crop = crop_to_common_size(images, np.array(cx), np.array(cy))
        clean_stack = crop_to_common_size(cleans, np.array(cx), np.array(cy))[0] if clean_files else None
        cx, cy = cx_crop, cy_crop
        c2w = torch.from_numpy(np.stack([colmap_c2w(v) for v in views])).float()
        cameras = Cameras(c2w, _f32(fx), _f32(fy), _f32(cx), _f32(cy),
                          width=stack.shape[2], height=stack.shape[1])
        xyz, rgb = model_points(model)
        points, colors = torch.from_numpy(xyz).float(), torch.from_numpy(rgb)
        near, far = depth_bounds(cameras, points) or (None, None)
        if not cfg.load_points or len(points) == 0:
            points = colors = None
        metadata = {
            "colmap_model": str(model_dir),
            "camera_models": sorted({model.cameras[v.camera_id].model_name for v in views}),
            "undistorted_on_load": undistorted,
            "registered_images": len(views),
        }
        return assemble_scene(cfg, name=root.resolve().name, source=root,
                              images=torch.from_numpy(stack), cameras=cameras,
                              image_names=[v.name for v in views], points=points,
                              clean_images=None if clean_stack is None else torch.from_numpy(clean_stack),
                              point_colors=colors, points_source="colmap model", near=near, far=far,
                              metadata=metadata, image_files=files)
