"""Turning tensors into pictures: uint8 conversion, colour maps, labelled side-by-side strips."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch
from torch import Tensor

from rainyscape.imaging.metrics import psnr

if TYPE_CHECKING:
    from rainyscape.eval.views import ViewImages

ERROR_VMAX = 0.25  # error maps: mean absolute error 0 .. 0.25 spans the colour map (fixed,
# so maps of different runs compare)
LABEL_HEIGHT = 18
MIN_PANEL_WIDTH = 128  # narrower panels are enlarged (nearest neighbour) so labels fit


def to_uint8(image: Tensor | np.ndarray) -> np.ndarray:
    """(C, H, W) tensor or (H, W[, C]) array in [0, 1] -> (H, W, 3) uint8."""
    if isinstance(image, Tensor):
        arr = image.detach().float().cpu().numpy()
        arr = arr.transpose(1, 2, 0) if arr.ndim == 3 else arr
    else:
        arr = np.asarray(image, dtype=np.float32)
    if arr.ndim == 2:
        arr = arr[..., None]
    if arr.shape[-1] == 1:
        arr = np.repeat(arr, 3, axis=-1)
    return (np.clip(arr, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


def colormap(values: np.ndarray, vmin: float, vmax: float, name: str) -> np.ndarray:
    """(H, W) values -> (H, W, 3) uint8 through a matplotlib colour map (NaN/inf: black)."""
    from matplotlib import colormaps

    v = np.asarray(values, dtype=np.float32)
    bad = ~np.isfinite(v)
    t = np.clip((np.where(bad, vmin, v) - vmin) / max(vmax - vmin, 1e-12), 0.0, 1.0)
    rgb = colormaps[name](t)[..., :3]
    rgb[bad] = 0.0
    return to_uint8(rgb)


def error_map(pred: Tensor, target: Tensor, vmax: float = ERROR_VMAX) -> np.ndarray:
    """Per-pixel mean absolute error, colour-mapped on a fixed scale [0, vmax]."""
    err = (pred - target).abs().mean(0).cpu().numpy()
    return colormap(err, 0.0, vmax, "inferno")


def depth_map(depth: Tensor) -> np.ndarray:
    """z-depth (1, H, W) colour-mapped between its 2nd and 98th percentiles (near: bright)."""
    d = depth[0].float().cpu().numpy()
    finite = d[np.isfinite(d)]
    if finite.size == 0:
        return np.zeros((*d.shape, 3), np.uint8)
    lo, hi = np.percentile(finite, [2, 98])
    return colormap(hi - d, 0.0, max(hi - lo, 1e-6), "turbo")


def enlarge(image: np.ndarray, min_width: int = MIN_PANEL_WIDTH) -> np.ndarray:
    """Integer nearest-neighbour upscaling of images narrower than ``min_width``."""
    factor = -(-min_width // image.shape[1])
    return image if factor <= 1 else image.repeat(factor, axis=0).repeat(factor, axis=1)


def labelled(image: np.ndarray, label: str) -> np.ndarray:
    """The image (enlarged if tiny) under a black band carrying ``label`` in white."""
    import cv2

    image = enlarge(image)
    h, w = image.shape[:2]
    band = np.zeros((LABEL_HEIGHT, w, 3), np.uint8)
    font, scale = cv2.FONT_HERSHEY_SIMPLEX, 0.4
    (text_w, _), _ = cv2.getTextSize(label, font, scale, 1)
    scale *= min(1.0, (w - 6) / max(text_w, 1))  # a long label shrinks to fit its panel
    cv2.putText(band, label, (3, LABEL_HEIGHT - 5), font, scale,
                (255, 255, 255), 1, cv2.LINE_AA)
    return np.concatenate([band, image], axis=0)


def side_by_side(panels: list[tuple[str, np.ndarray]], gap: int = 2) -> np.ndarray:
    """Labelled panels of one height in a row, separated by white gaps."""
    tiles = [labelled(img, label) for label, img in panels]
    spacer = np.full((tiles[0].shape[0], gap, 3), 255, np.uint8)
    row: list[np.ndarray] = []
    for tile in tiles:
        row += [tile, spacer]
    return np.concatenate(row[:-1], axis=1)


def grid(rows: list[list[tuple[str, np.ndarray]]], gap: int = 2) -> np.ndarray:
    """Rows of labelled panels stacked vertically (rows padded to the widest)."""
    strips = [side_by_side(r, gap) for r in rows]
    width = max(s.shape[1] for s in strips)
    padded = [np.pad(s, ((0, 0), (0, width - s.shape[1]), (0, 0)), constant_values=255) for s in strips]
    spacer = np.full((gap, width, 3), 255, np.uint8)
    out: list[np.ndarray] = []
    for s in padded:
        out += [s, spacer]
    return np.concatenate(out[:-1], axis=0)


RAIN_DISPLAY_MAX_GAIN = 4.0  # rain panels are brightened together, at most this much


def strip_panels(v: "ViewImages") -> list[tuple[str, np.ndarray]]:
    """``rainy | render | (post-processed) | clean | predicted rain | true rain`` for one view,
    each with its PSNR against the clean view (the rain panels: against the true rain) when
    the scene has them. Both rain panels are shown at one gain (written on them), so faint
    streaks stay visible and the two compare."""
    def score(image: Tensor, reference: Tensor | None) -> str:
        return "" if reference is None else f" {float(psnr(image, reference)):.1f} dB"

    panels = [("rainy input" + score(v.rainy, v.clean), to_uint8(v.rainy)),
              ("render" + score(v.rendered, v.clean), to_uint8(v.rendered))]
    panels += [(f"+ {key}" + score(img, v.clean), to_uint8(img)) for key, img in v.post.items()]
    if v.clean is not None:
        panels.append(("clean", to_uint8(v.clean)))
    if v.rain is not None:
        gain = rain_display_gain(v.true_rain if v.true_rain is not None else v.rain)
        shown = f" x{gain:.1f}" if gain > 1 else ""
        panels.append(("predicted rain" + score(v.rain, v.true_rain) + shown, to_uint8(v.rain * gain)))
        if v.true_rain is not None:
            panels.append(("true rain" + shown, to_uint8(v.true_rain * gain)))
    return panels


def rain_display_gain(rain: Tensor) -> float:
    """The brightening that puts the rain's 99.5th percentile at white (1 .. the cap)."""
    top = float(torch.quantile(rain.float().flatten()[::max(1, rain.numel() // 100_000)], 0.995))
    return float(min(RAIN_DISPLAY_MAX_GAIN, max(1.0, 1.0 / max(top, 1e-6))))


def save_png(path: Path, image: np.ndarray) -> Path:
    """Write a uint8 picture, making its folder."""
    from rainyscape.dataparsers.images import write_png

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    write_png(path, image)
    return path


def save_strip(v: "ViewImages", path: Path) -> Path:
    return save_png(path, side_by_side(strip_panels(v)))
