"""maya-csv: the paper's Maya dataset layout (rs-synth writes it too; see docs/data.md).

A folder with ``cameras.csv`` (the paper's columns), rainy images (``images_rain/``, else
``images/``, else the folder itself), and optionally clean images (the authors' ``_rain`` ->
``_wo_rain`` sibling of the image folder, e.g. ``images_wo_rain/``), depth ``.mat`` files
(``depth/``) and the ground-truth rain layer (``rain/``, RGBA). Camera i of the CSV
(``cameraShape{i}``) is the image whose stem is the integer i (001.png), or else the i-th
image in natural order.
"""

from __future__ import annotations

import csv
import math
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from rainyscape.components import DataParser
from rainyscape.config.schema import bounded
from rainyscape.dataparsers.base import CommonParserConfig, assemble_scene
from rainyscape.dataparsers.depth import depth_bounds, points_from_depth, read_depth_mat
from rainyscape.dataparsers.images import clean_image_paths, list_images, read_stack
from rainyscape.dataparsers.truth import read_rain_layers, simulated_rain
from rainyscape.dataparsers.maya_math import MAYA_CSV_COLUMNS, maya_cameras
from rainyscape.errors import DataError
from rainyscape.scene import SceneData


GT_DEPTH_SOURCE = "ground-truth depth (dataparser.points_from_depth=true, not a real capture's)"


@dataclass
class MayaCsvConfig(CommonParserConfig):
    cameras: str = "cameras.csv"  # relative to the scene folder
    images: str = "auto"  # rainy images (what training sees); auto: images_rain/, images/ or .
    clean: str = "auto"  # clean images; auto: the `_rain` -> `_wo_rain` sibling; "": none
    depth: str = "depth"  # folder of <stem>.mat depth maps ("" or missing: none)
    depth_key: str = "depth"
    rain: str = "rain"  # folder of <stem>.png RGBA rain layers ("" or missing: none)
    # Sparse points for 3DGS back-projected from the GROUND-TRUTH depth maps: information no
    # capture has, so off by default (3DGS then starts from points triangulated from the rainy
    # training views) and refused by rs-bench. For studies of initialisation only.
    points_from_depth: bool = False
    max_points: int = bounded(20000, 0, 10_000_000)  # points_from_depth: at most this many
    check_units: bool = True  # reject radians / inches that would silently give wrong cameras


@dataclass
class MayaCamerasTable:
    names: list[str]
    positions: np.ndarray  # (N, 3)
    rotations: np.ndarray  # (N, 3) degrees
    focal_mm: np.ndarray
    h_aperture_mm: np.ndarray
    v_aperture_mm: np.ndarray


def read_cameras_csv(path: Path, check_units: bool = True) -> MayaCamerasTable:
    """Read and validate cameras.csv; every problem raises DataError naming the file."""
    try:
        with open(path, newline="", encoding="utf-8-sig") as fh:
            rows = [r for r in csv.reader(fh) if any(c.strip() for c in r)]
    except OSError as exc:
        raise DataError(f"{path}: cannot read the camera file ({exc.strerror})") from None
    except (csv.Error, UnicodeDecodeError) as exc:
        raise DataError(f"{path}: not a readable CSV file ({exc})") from None
    if not rows:
        raise DataError(f"{path}: empty camera file")
    header = [c.strip() for c in rows[0]]
    missing = [c for c in MAYA_CSV_COLUMNS if c not in header]
    extra = [c for c in header if c not in MAYA_CSV_COLUMNS]
    if missing or extra:
        parts = []
        if missing:
            parts.append(f"missing column(s) {', '.join(repr(c) for c in missing)}")
        if extra:
            parts.append(f"unexpected column(s) {', '.join(repr(c) for c in extra)}")
        raise DataError(f"{path}: {'; '.join(parts)}. Expected exactly: {', '.join(MAYA_CSV_COLUMNS)}")
    col = {c: header.index(c) for c in MAYA_CSV_COLUMNS}
    if len(rows) < 2:
        raise DataError(f"{path}: no camera rows")
    names, values = [], []
    for line, row in enumerate(rows[1:], start=2):
        if len(row) != len(header):
            raise DataError(f"{path}, line {line}: {len(row)} fields, the header has {len(header)}")
        name = row[col["Camera Name"]].strip()
        if not re.fullmatch(r"cameraShape\d+", name):
            raise DataError(f"{path}, line {line}: camera name '{name}' is not of the form cameraShapeN")
        numbers = []
        for c in MAYA_CSV_COLUMNS[1:]:
            text = row[col[c]].strip()
            try:
                x = float(text)
            except ValueError:
                raise DataError(f"{path}, line {line}: {c} '{text}' is not a number") from None
            if not math.isfinite(x):
                raise DataError(f"{path}, line {line}: {c} is {text} (not a finite number)")
            numbers.append(x)
        names.append(name)
        values.append(numbers)
    if len(set(names)) != len(names):
        dup = sorted({n for n in names if names.count(n) > 1})[0]
        raise DataError(f"{path}: camera '{dup}' appears more than once")
    v = np.asarray(values, np.float64)
    table = MayaCamerasTable(names, v[:, 0:3], v[:, 3:6], v[:, 6], v[:, 7], v[:, 8])
    _check_values(path, table, check_units)
    return table


def _check_values(path: Path, t: MayaCamerasTable, check_units: bool) -> None:
    for label, arr in (("Focal Length", t.focal_mm), ("Horizontal Aperture", t.h_aperture_mm),
                       ("Vertical Aperture", t.v_aperture_mm)):
        if (arr <= 0).any():
            i = int(np.argmax(arr <= 0))
            raise DataError(f"{path}: {label} of {t.names[i]} is {arr[i]:g}; it must be positive (mm)")
    if not check_units:
        return
    # Maya stores apertures in inches internally (a 36 mm film back is 1.417 in).
    for label, arr in (("Horizontal Aperture", t.h_aperture_mm), ("Vertical Aperture", t.v_aperture_mm)):
        if (arr < 2.0).any():
            i = int(np.argmax(arr < 2.0))
            raise DataError(f"{path}: {label} of {t.names[i]} is {arr[i]:g}, which looks like inches; "
                            "the column must be in mm (inches x 25.4), or pass check_units=false")
    if (t.focal_mm < 1.0).any():
        i = int(np.argmax(t.focal_mm < 1.0))
        raise DataError(f"{path}: Focal Length of {t.names[i]} is {t.focal_mm[i]:g}, which looks like "
                        "metres; the column must be in mm, or pass check_units=false")
    rot = np.abs(t.rotations)
    if len(t.names) > 2 and rot.max() <= math.pi + 1e-6 and rot.max() > 0.3:
        raise DataError(f"{path}: every rotation is within +-pi, which looks like radians; the "
                        "Rotation columns must be in degrees, or pass check_units=false")


def _match_images(csv_path: Path, folder: Path, names: list[str]) -> list[Path]:
    """Images for cameraShape1..N: by integer stem when every stem is an integer, else in order."""
    files = list_images(folder)
    if len(files) != len(names):
        raise DataError(f"{csv_path} lists {len(names)} cameras but {folder} holds {len(files)} images")
    numbers = [int(n[len("cameraShape"):]) for n in names]
    stems = [p.stem for p in files]
    if all(s.isdigit() for s in stems):
        by_number = {int(s): p for s, p in zip(stems, files)}
        absent = [f"cameraShape{k}" for k in numbers if k not in by_number]
        if absent:
            raise DataError(f"{folder}: no image numbered like {absent[0]} (images are named by "
                            "camera number, e.g. 001.png for cameraShape1)")
        return [by_number[k] for k in numbers]
    return files


def _sibling(root: Path, name: str) -> Path | None:
    if not name:
        return None
    folder = root / name
    return folder if folder.is_dir() else None


class MayaCsvParser(DataParser):
    """The paper's Maya layout: cameras.csv + images_rain/ (+ images_wo_rain/, depth/, rain/)."""

    description = "Maya camera CSV (the paper's dataset layout; what rs-synth writes)"
    Config = MayaCsvConfig

    def __init__(self, config: MayaCsvConfig | None = None):
        super().__init__(config or MayaCsvConfig())

    def parse(self, path: Path) -> SceneData:
        cfg: MayaCsvConfig = self.config
        root = Path(path)
        if not root.is_dir():
            raise DataError(f"{root}: no such scene folder")
        csv_path = root / cfg.cameras
        if not csv_path.is_file():
            raise DataError(f"{csv_path}: camera file not found")
        table = read_cameras_csv(csv_path, cfg.check_units)
        image_dir = self._image_dir(root)
        files = _match_images(csv_path, image_dir, table.names)
        images = read_stack(files, what="image")
        n, h, w = images.shape[:3]
        cameras = maya_cameras(table.positions, table.rotations, table.focal_mm, table.h_aperture_mm,
                               table.v_aperture_mm, w, h)
        clean = self._clean(root, image_dir, files, (w, h))
        depths = self._depths(root, files, (w, h))
        rain = self._rain(root, files, (w, h), clean)
        points = colors = None
        near = far = None
        # The depth maps are ground truth: only the explicit study option reads bounds from
        # them; otherwise near / far are those of any posed capture without points (a tight
        # near bound from the true depth hid 1.5 dB of near-camera floaters from `nerf`'s
        # held-out views: docs/benchmarks.md, "Ray bounds without the ground-truth depth")
        if depths is not None and cfg.points_from_depth:
            bounds = depth_bounds(depths)
            if bounds is not None:
                near, far = bounds
            if cfg.max_points > 0:
                points, colors = points_from_depth(cameras, depths, images, cfg.max_points)
        return assemble_scene(
            cfg, name=root.resolve().name, source=root, images=images, cameras=cameras,
            image_names=[p.name for p in files], clean_images=clean, depths=depths, rain_layers=rain,
            points=points, point_colors=colors, points_source=GT_DEPTH_SOURCE, near=near, far=far,
            image_files=files,
            metadata={"format": "maya-csv", "world": "Maya, Y up", "cameras_csv": str(csv_path),
                      **simulated_rain(root)})

    def _image_dir(self, root: Path) -> Path:
        if self.config.images != "auto":
            return root / self.config.images
        for name in ("images_rain", "images"):
            if (root / name).is_dir():
                return root / name
        return root

    def _clean(self, root: Path, image_dir: Path, files: list[Path], size: tuple[int, int]):
        paths = clean_image_paths(self.config.clean, root, image_dir, files)
        return None if paths is None else read_stack(paths, size, what="clean image")

    def _depths(self, root: Path, files: list[Path], size: tuple[int, int]):
        folder = _sibling(root, self.config.depth)
        if folder is None:
            return None
        arrays = []
        for f in files:
            p = folder / f"{f.stem}.mat"
            if not p.is_file():
                raise DataError(f"{p}: depth map missing (the folder has depth for some views only)")
            arrays.append(read_depth_mat(p, self.config.depth_key, size))
        return torch.from_numpy(np.stack(arrays))

    def _rain(self, root: Path, files: list[Path], size: tuple[int, int], clean):
        folder = _sibling(root, self.config.rain)
        if folder is None or clean is None:
            return None  # the additive rain I - B needs the clean image B
        return read_rain_layers(folder, files, size, clean)
