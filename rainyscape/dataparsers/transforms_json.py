"""transforms-json: nerfstudio / instant-ngp / Blender ``transforms.json``, read and written.

Camera-to-world matrices are OpenGL (x right, y up, looking down -z). Intrinsics come from
``fl_x`` / ``fl_y`` / ``cx`` / ``cy`` / ``w`` / ``h`` (top level, overridable per frame) or
Blender's ``camera_angle_x`` (and ``camera_angle_y``). Distortion (``k1 k2 k3 k4 p1 p2``,
``camera_model`` OPENCV or OPENCV_FISHEYE) is removed from the images with OpenCV, keeping
the pinhole intrinsics. Clean images: a folder named by ``clean=`` holding the same file
names, or (``auto``) the authors' ``_rain`` -> ``_wo_rain`` sibling of the image folder.
nerfstudio's ``train_filenames`` / ``val_filenames`` / ``test_filenames`` give the held-out
split when present (val and test are held out; ``dataparser.holdout_file`` overrides them).

Checked on reading: every ``transform_matrix`` is a rigid motion (its 3 x 3 block a
rotation), field-of-view angles lie in (0, 180) degrees, and lens distortion is plausible
(the radial factor stays within [1/5, 5] and the undistorted radius keeps growing out to the
image corners).

:func:`transforms_content` is the package's one writer of the format (pinhole cameras):
rs-process-data's scene folders, SceneData exports and rs-export all go through it.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Mapping, Sequence

import cv2
import numpy as np
import torch

from rainyscape.cameras import Cameras, opencv_to_opengl, opengl_to_opencv
from rainyscape.components import DataParser
from rainyscape.dataparsers.base import CommonParserConfig, ImageIndex, assemble_scene
from rainyscape.dataparsers.images import IMAGE_SUFFIXES, clean_image_paths, read_rgb
from rainyscape.dataparsers.truth import read_rain_layers, simulated_rain
from rainyscape.errors import DataError
from rainyscape.scene import SceneData

PINHOLE_KEYS = ("fl_x", "fl_y", "cx", "cy", "w", "h")  # what the writer stores per camera
INTRINSIC_KEYS = ("fl_x", "fl_y", "cx", "cy", "w", "h", "k1", "k2", "k3", "k4", "p1", "p2",
                  "camera_angle_x", "camera_angle_y", "camera_model")


def transforms_content(c2w: np.ndarray, intrinsics: Sequence[Mapping[str, float]],
                       file_paths: Sequence[str], *, per_frame_intrinsics: bool = False,
                       frame_extras: Sequence[Mapping] | None = None, ply_file_path: str | None = None,
                       applied_transform: np.ndarray | None = None) -> dict:
    """``transforms.json`` content for N pinhole cameras (``camera_model`` PINHOLE).

    ``c2w``: (N, 4, 4) camera-to-world with OpenCV camera axes (the package's convention),
    written with OpenGL axes. ``intrinsics``: per frame ``fl_x fl_y cx cy`` (pixels) and
    ``w h``. A key with one value for every frame is written once at the top level, else per
    frame; with ``per_frame_intrinsics`` ``fl_x fl_y cx cy`` stay per frame regardless.
    ``frame_extras``: more keys per frame (e.g. ``colmap_im_id``). ``ply_file_path``: the
    sparse points, relative to the JSON. ``applied_transform``: the world transform applied
    to the input's poses (nerfstudio's key), 3 x 4 or 4 x 4, written as 3 x 4.
    """
    c2w = np.asarray(c2w, dtype=np.float64).reshape(-1, 4, 4)
    n = len(c2w)
    extras = list(frame_extras) if frame_extras is not None else [{}] * n
    if not len(intrinsics) == len(file_paths) == len(extras) == n:
        raise ValueError(f"transforms_content: {n} poses, {len(intrinsics)} intrinsics, "
                         f"{len(file_paths)} file paths and {len(extras)} frame extras")
    values = {k: [int(cam[k]) if k in ("w", "h") else float(cam[k]) for cam in intrinsics]
              for k in PINHOLE_KEYS}
    shared = [k for k in PINHOLE_KEYS if n and len(set(values[k])) == 1
              and not (per_frame_intrinsics and k not in ("w", "h"))]
    c2w_gl = opencv_to_opengl(c2w)
    frames = []
    for i, path in enumerate(file_paths):
        frame = {"file_path": str(path), "transform_matrix": c2w_gl[i].tolist()}
        frame.update({k: values[k][i] for k in PINHOLE_KEYS if k not in shared})
        frame.update(extras[i])
        frames.append(frame)
    out: dict = {"camera_model": "PINHOLE", **{k: values[k][0] for k in shared}, "frames": frames}
    if applied_transform is not None:
        out["applied_transform"] = np.asarray(applied_transform, dtype=np.float64)[:3, :4].tolist()
    if ply_file_path:
        out["ply_file_path"] = str(ply_file_path)
    return out


def write_transforms(path: str | Path, content: dict) -> Path:
    """Write :func:`transforms_content` to ``path`` (indented JSON)."""
    path = Path(path)
    path.write_text(json.dumps(content, indent=2) + "\n")
    return path


@dataclass
class TransformsJsonConfig(CommonParserConfig):
    transforms: str = "transforms.json"  # file name inside the scene folder
    clean: str = "auto"  # folder of clean images matched by file name; auto: `_rain` -> `_wo_rain`
    images: str = ""  # read every frame's image by its file name from this folder instead ("": the frames' paths)
    rain: str = "auto"  # true rain layers (rs-synth's RGBA), by stem, for evaluation; auto: rain/ if present; "": none


@dataclass
class FrameCamera:
    c2w_gl: np.ndarray  # (4, 4)
    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    model: str
    dist: dict


def _number(value, where: str) -> float:
    try:
        x = float(value)
    except (TypeError, ValueError):
        raise DataError(f"{where} is '{value}', not a number") from None
    if not math.isfinite(x):
        raise DataError(f"{where} is {value} (not a finite number)")
    return x


def resolve_image(root: Path, file_path: str) -> Path:
    """A frame's image; Blender omits the extension ('./train/r_0')."""
    p = (root / file_path).resolve()
    if p.is_file():
        return p
    for suffix in IMAGE_SUFFIXES:
        q = p.with_name(p.name + suffix)
        if q.is_file():
            return q
    raise DataError(f"{root / file_path}: image listed in transforms.json not found")


def frame_camera(meta: dict, frame: dict, where: str, image_size: tuple[int, int]) -> FrameCamera:
    """Intrinsics and pose of one frame; per-frame keys override the top level."""
    get = {k: frame.get(k, meta.get(k)) for k in INTRINSIC_KEYS}
    width = int(_number(get["w"], f"{where}: w")) if get["w"] is not None else image_size[0]
    height = int(_number(get["h"], f"{where}: h")) if get["h"] is not None else image_size[1]
    if get["fl_x"] is not None:
        fx = _number(get["fl_x"], f"{where}: fl_x")
        fy = _number(get["fl_y"], f"{where}: fl_y") if get["fl_y"] is not None else fx
    elif get["camera_angle_x"] is not None:
        fx = 0.5 * width / math.tan(0.5 * _angle(get["camera_angle_x"], f"{where}: camera_angle_x"))
        fy = (0.5 * height / math.tan(0.5 * _angle(get["camera_angle_y"], f"{where}: camera_angle_y"))
              if get["camera_angle_y"] is not None else fx)
    else:
        raise DataError(f"{where}: no focal length (fl_x or camera_angle_x)")
    if fx <= 0 or fy <= 0:
        raise DataError(f"{where}: focal length must be positive (fl_x={fx:g}, fl_y={fy:g})")
    cx = _number(get["cx"], f"{where}: cx") if get["cx"] is not None else width / 2.0
    cy = _number(get["cy"], f"{where}: cy") if get["cy"] is not None else height / 2.0
    if "transform_matrix" not in frame:
        raise DataError(f"{where}: no transform_matrix")
    try:
        mat = np.asarray(frame["transform_matrix"], dtype=np.float64)
    except (TypeError, ValueError):
        raise DataError(f"{where}: transform_matrix is not a matrix of numbers") from None
    if mat.shape == (3, 4):
        mat = np.vstack([mat, [0, 0, 0, 1]])
    if mat.shape != (4, 4):
        raise DataError(f"{where}: transform_matrix must be 4x4 (or 3x4), got shape {mat.shape}")
    if not np.isfinite(mat).all():
        raise DataError(f"{where}: transform_matrix holds non-finite numbers")
    check_rigid(mat, where)
    dist = {k: _number(get[k], f"{where}: {k}") for k in ("k1", "k2", "k3", "k4", "p1", "p2") if get[k] is not None}
    model = str(get["camera_model"] or ("OPENCV" if dist else "PINHOLE")).upper()
    cam = FrameCamera(mat, fx, fy, cx, cy, width, height, model, dist)
    check_distortion(cam, where)
    return cam


def _angle(value, where: str) -> float:
    """A field-of-view angle in radians, in (0, pi)."""
    x = _number(value, where)
    if not 0 < x < math.pi:
        raise DataError(f"{where} is {value}: a field of view in radians must lie strictly between "
                        f"0 and pi (e.g. 0.69 for 40 degrees)")
    return x


def check_rigid(mat: np.ndarray, where: str, tol: float = 2e-2) -> None:
    """DataError unless ``mat`` (4x4) is a camera pose: a rotation (orthonormal, determinant
    +1) and a translation, bottom row 0 0 0 1."""
    rot = mat[:3, :3]
    if not np.allclose(mat[3], [0, 0, 0, 1], atol=1e-6):
        raise DataError(f"{where}: transform_matrix's last row is {mat[3].tolist()}, not [0, 0, 0, 1]")
    gram_err = float(np.abs(rot.T @ rot - np.eye(3)).max())
    det = float(np.linalg.det(rot))
    if gram_err > tol or det < 0:
        what = ("all zero" if not rot.any() else f"determinant {det:.3g}" if abs(det - 1) > tol
                else f"axes not orthonormal (off by {gram_err:.3g})")
        raise DataError(f"{where}: transform_matrix's 3x3 block is not a rotation ({what}); "
                        "expected a camera-to-world pose")


def check_distortion(cam: FrameCamera, where: str) -> None:
    """DataError for distortion no real lens has: the radial factor leaves [1/5, 5] or the
    distorted radius stops growing before the image corners (the undistortion would fold)."""
    d = cam.dist
    if not any(abs(v) > 0 for v in d.values()):
        return
    corner = max(math.hypot(x - cam.cx, y - cam.cy) for x in (0, cam.width) for y in (0, cam.height))
    r_max = corner / min(cam.fx, cam.fy)  # normalised radius of the farthest corner
    r = np.linspace(0.0, r_max, 256)
    if cam.model == "OPENCV_FISHEYE":
        theta = np.arctan(r)
        t2 = theta ** 2
        rd = theta * (1 + d.get("k1", 0) * t2 + d.get("k2", 0) * t2 ** 2 + d.get("k3", 0) * t2 ** 3
                      + d.get("k4", 0) * t2 ** 4)
    else:
        r2 = r ** 2
        rd = r * (1 + d.get("k1", 0) * r2 + d.get("k2", 0) * r2 ** 2 + d.get("k3", 0) * r2 ** 3)
    factor = rd[1:] / r[1:]
    named = ", ".join(f"{k}={v:g}" for k, v in d.items() if v)
    if factor.min() < 0.2 or factor.max() > 5 or (np.diff(rd) <= 0).any():
        raise DataError(f"{where}: lens distortion {named} is implausible for this camera (it "
                        f"would move image points by a factor of {factor.min():.2g} .. {factor.max():.2g}); "
                        "check the coefficients")


def undistort(image: np.ndarray, cam: FrameCamera, where: str) -> np.ndarray:
    """Remove lens distortion, keeping the pinhole intrinsics (fx, fy, cx, cy)."""
    if not any(abs(v) > 0 for v in cam.dist.values()):
        return image
    k = np.array([[cam.fx, 0, cam.cx], [0, cam.fy, cam.cy], [0, 0, 1]])
    d = cam.dist
    if cam.model == "OPENCV_FISHEYE":
        coeffs = np.array([d.get("k1", 0), d.get("k2", 0), d.get("k3", 0), d.get("k4", 0)])
        return cv2.fisheye.undistortImage(image, k, coeffs, Knew=k)
    if cam.model in ("OPENCV", "PINHOLE", "SIMPLE_RADIAL", "RADIAL"):
        coeffs = np.array([d.get("k1", 0), d.get("k2", 0), d.get("p1", 0), d.get("p2", 0), d.get("k3", 0)])
        return cv2.undistort(image, k, coeffs)
    raise DataError(f"{where}: camera_model {cam.model} is not supported (OPENCV, OPENCV_FISHEYE, PINHOLE)")


class TransformsJsonParser(DataParser):
    """nerfstudio / instant-ngp / Blender transforms.json (OpenGL camera-to-world)."""

    description = "nerfstudio / instant-ngp / Blender transforms.json"
    Config = TransformsJsonConfig

    def __init__(self, config: TransformsJsonConfig | None = None):
        super().__init__(config or TransformsJsonConfig())

    def parse(self, path: Path) -> SceneData:
        cfg: TransformsJsonConfig = self.config
        root = Path(path)
        json_path = root / cfg.transforms if root.is_dir() else root
        if root.is_file():
            root = root.parent
        if not json_path.is_file():
            raise DataError(f"{json_path}: file not found")
        try:
            meta = json.loads(json_path.read_text())
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise DataError(f"{json_path}: not a readable JSON file ({exc})") from None
        frames = meta.get("frames") if isinstance(meta, dict) else None
        if not frames or not isinstance(frames, list):
            raise DataError(f"{json_path}: no 'frames' list")
        images, cams, files, listed = [], [], [], []
        seen: dict[Path, int] = {}
        for i, frame in enumerate(frames):
            where = f"{json_path}, frame {i}"
            if not isinstance(frame, dict) or "file_path" not in frame:
                raise DataError(f"{where}: no file_path")
            listed.append(resolve_image(root, str(frame["file_path"])))
            if listed[-1] in seen:  # one photo, two poses: the views would contradict each other
                raise DataError(f"{json_path}: frames {seen[listed[-1]]} and {i} both use the image "
                                f"{frame['file_path']}; each frame needs its own image")
            seen[listed[-1]] = i
            file = self._moved(root / cfg.images, listed[-1]) if cfg.images else listed[-1]
            img = read_rgb(file)
            cam = frame_camera(meta, frame, where, (img.shape[1], img.shape[0]))
            if (img.shape[1], img.shape[0]) != (cam.width, cam.height):
                raise DataError(f"{file}: image is {img.shape[1]}x{img.shape[0]}, transforms.json says "
                                f"{cam.width}x{cam.height}")
            if cams and (cam.width, cam.height) != (cams[0].width, cams[0].height):
                raise DataError(f"{file}: image is {cam.width}x{cam.height}, expected "
                                f"{cams[0].width}x{cams[0].height} like {files[0].name}")
            images.append(undistort(img, cam, where))
            cams.append(cam)
            files.append(file)
        names = [f.name for f in files]
        if len(set(names)) != len(names):
            names = [str(f.relative_to(root)) if f.is_relative_to(root) else str(f) for f in files]
        w, h = cams[0].width, cams[0].height
        c2w = opengl_to_opencv(torch.from_numpy(np.stack([c.c2w_gl for c in cams]))).float()
        cameras = Cameras(c2w, *(torch.tensor([getattr(c, k) for c in cams], dtype=torch.float32)
                                 for k in ("fx", "fy", "cx", "cy")), w, h)
        clean = self._clean(root, files, cams)
        rain = self._rain(root, files, (w, h), clean)
        return assemble_scene(
            cfg, name=root.resolve().name, source=root, images=torch.from_numpy(np.stack(images)),
            cameras=cameras, image_names=names, clean_images=clean, rain_layers=rain, image_files=listed,
            heldout=self._split(meta, json_path, names, listed, root),  # lists name the frames by their paths
            metadata={"format": "transforms-json", "transforms": str(json_path), **simulated_rain(root)})

    @staticmethod
    def _moved(folder: Path, file: Path) -> Path:
        """The frame's image of the same file name in ``folder`` (dataparser.images=)."""
        if not folder.is_dir():
            raise DataError(f"{folder}: image folder not found (images=)")
        moved = folder / file.name
        if not moved.is_file():
            raise DataError(f"{moved}: no image named like the frame's {file.name} (images=)")
        return moved

    def _rain(self, root: Path, files: list[Path], size: tuple[int, int], clean):
        option = self.config.rain
        folder = root / ("rain" if option == "auto" else option) if option else None
        if folder is None or clean is None or (option == "auto" and not folder.is_dir()):
            return None  # the additive rain I - B needs the clean image B
        if not folder.is_dir():
            raise DataError(f"{folder}: rain layer folder not found (rain=)")
        return read_rain_layers(folder, files, size, clean)

    @staticmethod
    def _split(meta: dict, json_path: Path, names: list[str], files: list[Path],
               root: Path) -> tuple[list[str], str] | None:
        """nerfstudio's held-out views: val_filenames and test_filenames, or else every frame
        not in train_filenames (None when the file has none of these lists)."""
        lists = {}
        for key in ("train_filenames", "val_filenames", "test_filenames"):
            value = meta.get(key)
            if value is None:
                continue
            if not isinstance(value, list) or not all(isinstance(v, str) for v in value):
                raise DataError(f"{json_path}: {key} must be a list of file paths")
            lists[key] = value
        if not lists:
            return None
        held = lists.get("val_filenames", []) + lists.get("test_filenames", [])
        where = f"{json_path}: {' / '.join(k for k in lists if k != 'train_filenames') or 'train_filenames'}"
        if held or "train_filenames" not in lists:
            return held, where
        train = set(ImageIndex(names, files, root).indices(lists["train_filenames"], where))
        return [n for i, n in enumerate(names) if i not in train], where

    def _clean(self, root: Path, files: list[Path], cams: list[FrameCamera]):
        # Frames may sit in different folders: each looks for its own clean sibling.
        paths = [clean_image_paths(self.config.clean, root, f.parent, [f]) for f in files]
        if any(p is None for p in paths):
            return None
        out = []
        for [p], cam in zip(paths, cams):
            img = read_rgb(p)
            if (img.shape[1], img.shape[0]) != (cam.width, cam.height):
                raise DataError(f"{p}: clean image is {img.shape[1]}x{img.shape[0]}, the rainy one "
                                f"{cam.width}x{cam.height}")
            out.append(undistort(img, cam, str(p)))
        return torch.from_numpy(np.stack(out))
