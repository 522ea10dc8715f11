"""Ground truth a scene folder may carry for evaluation (never for training): the true rain
layers (``rain/NNN.png``) and what a simulator's ``scene.json`` says of the rain."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from rainyscape.dataparsers.images import read_rgba
from rainyscape.errors import DataError


def read_rain_layers(folder: Path, files: list[Path], size: tuple[int, int], clean: Tensor) -> Tensor:
    """The additive rain I - B (N, H, W, 3) float32 of each image in ``files``, from the RGBA
    ``folder/<stem>.png`` (RGB the rain's colour C, A its coverage: I = B (1 - A) + C A, so
    I - B = A (C - B) needs the clean images ``clean``)."""
    layers = []
    for i, f in enumerate(files):
        p = folder / f"{f.stem}.png"
        if not p.is_file():
            raise DataError(f"{p}: rain layer missing")
        rgba = read_rgba(p)
        if rgba.shape[1::-1] != size:
            raise DataError(f"{p}: rain layer is {rgba.shape[1]}x{rgba.shape[0]}, the images are "
                            f"{size[0]}x{size[1]}")
        a = rgba[..., 3:].astype(np.float32) / 255.0
        c = rgba[..., :3].astype(np.float32) / 255.0
        b = clean[i].numpy().astype(np.float32) / 255.0
        layers.append(a * (c - b))
    return torch.from_numpy(np.stack(layers))


def simulated_rain(root: Path) -> dict:
    """What the simulator's ``scene.json`` says of the true rain that evaluation needs: the
    number of directions it falls in (``mix`` > 0: two) and, where it records them, those
    directions in the folder's world frame (``rain_falls``, (K, 3) unit vectors; the true
    streak angles come from them); {} for a folder rs-synth did not write."""
    try:
        info = json.loads((root / "scene.json").read_text())
        out = {"rain_directions": 2 if float(info["rain"].get("mix", 0.0)) > 0 else 1}
        falls = info.get("rain_falls")
        if falls is not None:
            falls = np.asarray(falls, dtype=np.float64)
            if falls.ndim == 2 and falls.shape[1] == 3 and np.isfinite(falls).all():
                out["rain_falls"] = falls.tolist()
        return out
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        return {}
