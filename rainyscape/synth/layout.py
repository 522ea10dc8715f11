"""Writing the paper's dataset layout (see docs/data.md).

```
images_rain/001.png ...     rainy views (8-bit RGB)
images_wo_rain/001.png ...  clean views
depth/001.mat ...           scipy .mat, key "depth": float32 z-depth in world units, inf = sky
rain/001.png ...            ground-truth rain (streaks only), 8-bit RGBA: RGB = rain colour C,
                            A = coverage; rainy = clean * (1 - A) + C * A
haze/001.png ...            only with the haze option: fog transmission T (grey); then
                            rainy = (clean * T + fog * (1 - T)) * (1 - A) + C * A
cameras.csv                 the paper's columns, Maya conventions
scene.json                  simulator parameters and rainy-vs-clean metrics
```
"""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import scipy.io

from rainyscape.dataparsers.images import write_png
from rainyscape.dataparsers.maya_math import MAYA_CSV_COLUMNS

RAINY_DIR, CLEAN_DIR, DEPTH_DIR, RAIN_DIR = "images_rain", "images_wo_rain", "depth", "rain"
HAZE_DIR = "haze"  # only with the haze option: fog transmission per pixel
DEPTH_KEY = "depth"


def view_names(n: int) -> list[str]:
    """Zero-padded 1-based stems: 001 ... (more digits past 999)."""
    digits = max(3, len(str(n)))
    return [f"{i + 1:0{digits}d}" for i in range(n)]


def to_uint8(img: np.ndarray) -> np.ndarray:
    return np.clip(np.round(img * 255.0), 0, 255).astype(np.uint8)


def make_dirs(out: Path) -> None:
    for sub in (RAINY_DIR, CLEAN_DIR, DEPTH_DIR, RAIN_DIR):
        (out / sub).mkdir(parents=True, exist_ok=True)


def write_view(out: Path, stem: str, rainy: np.ndarray, clean: np.ndarray, depth: np.ndarray | None,
               rain_alpha: np.ndarray, rain_color: np.ndarray, haze: np.ndarray | None = None) -> None:
    """Write one view's files (uint8 images; ``depth``: None when unknown
    (a real capture); ``haze``: fog transmission, if any)."""
    write_png(out / RAINY_DIR / f"{stem}.png", rainy)
    write_png(out / CLEAN_DIR / f"{stem}.png", clean)
    rgba = np.concatenate([to_uint8(rain_color), to_uint8(rain_alpha)[..., None]], -1)
    write_png(out / RAIN_DIR / f"{stem}.png", rgba)
    if depth is not None:
        scipy.io.savemat(out / DEPTH_DIR / f"{stem}.mat", {DEPTH_KEY: depth.astype(np.float32)},
                         do_compression=True)
    if haze is not None:
        (out / HAZE_DIR).mkdir(exist_ok=True)
        write_png(out / HAZE_DIR / f"{stem}.png", np.repeat(to_uint8(haze)[..., None], 3, -1))


def write_cameras_csv(path: Path, positions: np.ndarray, rotations: np.ndarray, focal_mm: np.ndarray,
                      h_aperture_mm: np.ndarray, v_aperture_mm: np.ndarray) -> None:
    """cameras.csv with the paper's columns; camera i is ``cameraShape{i}`` (1-based)."""
    with open(path, "w", newline="") as fh:
        writer = csv.writer(fh)
        writer.writerow(MAYA_CSV_COLUMNS)
        for i in range(len(positions)):
            values = [*positions[i], *rotations[i], focal_mm[i], h_aperture_mm[i], v_aperture_mm[i]]
            writer.writerow([f"cameraShape{i + 1}"] + [f"{float(v):.9g}" for v in values])


def write_scene_json(path: Path, info: dict) -> None:
    path.write_text(json.dumps(info, indent=2) + "\n")
