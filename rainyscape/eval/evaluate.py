"""The evaluation protocol (DESIGN.md): rainy-input floor, de-raining on training views
(with and without post-processing) and novel held-out views; PSNR, SSIM, LPIPS (when its
weights are on this machine), the predicted rain angle and, for simulated scenes, how well
the predicted rain layer correlates with the true one.

``metrics.json`` keys (``summary``; every value a mean over views):
  rainy_input_{psnr,ssim,lpips}   rainy training inputs vs clean: the floor to beat
  train_{psnr,ssim,lpips}         renders at training views vs clean (the paper's numbers)
  train_<pp>_{psnr,ssim,lpips}    the same after post-process <pp> (the config's key)
  heldout_{psnr,ssim,lpips}       renders at held-out views vs clean (novel views)
  {train,heldout}_psnr_vs_rainy   renders vs the rainy images (how much rain was fitted)
  rain_angle_deg, rain_angle_true_deg, rain_angle_error_deg, rain_correlation
"""

from __future__ import annotations

import json
import math
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable

import torch
from torch import Tensor

from rainyscape.cameras import Cameras, Window
from rainyscape.components import RenderOutput
from rainyscape.engine.pipeline import Pipeline
from rainyscape.imaging.angles import (angle_difference_deg, estimate_rain_angles, mean_angle_deg,
                                       streak_angle)
from rainyscape.imaging.metrics import psnr, ssim
from rainyscape.eval.perceptual import LpipsMetric, load_lpips

STRIP_VIEWS = 3  # training views whose comparison strips evaluation saves for the report
ANGLE_KEYS = ("rain_angle_deg", "residual_angle_deg", "rain_angle_true_deg")
RAIN_KEYS = (*ANGLE_KEYS, "rain_correlation")  # training views only, kept without a split prefix


@torch.no_grad()
def render_cameras(pipeline: Pipeline, cameras: Cameras) -> RenderOutput:
    """Full-resolution render of one camera (fields chunk rays, so memory stays bounded)."""
    pipeline.field.eval()
    cams = cameras.to(pipeline.device)
    return pipeline.field.render(cams, Window.full(cams))


def render_view(pipeline: Pipeline, index: int) -> RenderOutput:
    return render_cameras(pipeline, pipeline.scene.cameras[[index]])


def render_image(pipeline: Pipeline, index: int) -> Tensor:
    """Full-resolution render (3, H, W) of view ``index``."""
    return render_view(pipeline, index).rgb[0].clamp(0, 1)


@torch.no_grad()
def predict_rain(pipeline: Pipeline, index: int, tile: int = 128) -> Tensor:
    """Predicted rain layer (3, H, W) of view ``index``, computed tile by tile (bounded memory)."""
    head = pipeline.rain_head
    head.eval()
    h, w = pipeline.scene.height, pipeline.scene.width
    out = torch.zeros(3, h, w, device=pipeline.device)
    ids = torch.tensor([index], device=pipeline.device)
    for y in range(0, h, tile):
        for x in range(0, w, tile):
            th, tw = min(tile, h - y), min(tile, w - x)
            win = Window(torch.tensor([x]), torch.tensor([y]), tw, th)
            out[:, y:y + th, x:x + tw] = head(ids, win)[0]
    return out


def progress(items: list, what: str, unit: str = "view") -> Iterable:
    """A console progress bar over ``items`` (only when stderr is a terminal)."""
    from tqdm import tqdm

    return tqdm(items, desc=what, unit=unit, file=sys.stderr, disable=None, leave=False)


def to_float(u8: Tensor, device) -> Tensor:
    """uint8 (H, W, 3) -> float (3, H, W) in [0, 1]."""
    return u8.to(device).permute(2, 0, 1).float() / 255.0


@dataclass
class ViewImages:
    """Everything evaluation and renders need for one view, (3, H, W) floats."""

    index: int
    name: str
    split: str  # "train" | "heldout"
    rainy: Tensor
    rendered: Tensor
    depth: Tensor | None  # (1, H, W)
    clean: Tensor | None = None
    rain: Tensor | None = None  # predicted rain layer (training views with a rain head)
    true_rain: Tensor | None = None
    post: dict[str, Tensor] = field(default_factory=dict)  # post-processed renders by key


@torch.no_grad()
def view_images(pipeline: Pipeline, index: int) -> ViewImages:
    scene, dev = pipeline.scene, pipeline.device
    split = "train" if index in set(scene.train_indices) else "heldout"
    out = render_view(pipeline, index)
    v = ViewImages(index, scene.image_names[index], split, to_float(scene.images[index], dev),
                   out.rgb[0].clamp(0, 1), None if out.depth is None else out.depth[0])
    if scene.clean_images is not None:
        v.clean = to_float(scene.clean_images[index], dev)
    if scene.rain_layers is not None:
        v.true_rain = scene.rain_layers[index].to(dev).permute(2, 0, 1).float()
    if split == "train" and pipeline.rain_head is not None:
        v.rain = predict_rain(pipeline, index)
        for key, post in pipeline.postprocess.items():
            v.post[key] = post(v.rendered, v.rain, v.rainy).clamp(0, 1)
    return v


# ------------------------------------------------------------------------ rain angles


def _agr_options(pipeline: Pipeline) -> dict:
    """Histogram settings of the run's AGR term (``k``: its rain directions per image), so
    evaluation measures angles as training did."""
    for cfg, _ in pipeline.losses.values():
        if cfg.name == "agr":
            opts = vars(cfg.options) if not isinstance(cfg.options, dict) else cfg.options
            out = {k: opts[k] for k in ("bins", "threshold", "smoothing", "kernel") if k in opts}
            return {**out, "k": int(opts.get("top_k", 1))}
    return {}


def streak_angles_deg(image: Tensor, options: dict) -> list[float]:
    """Directions the dominant streaks run along (``options["k"]`` of them, strongest first),
    degrees in [0, 180) from the image +x axis towards +y (down), estimated as the AGR loss
    does; empty if the image has no edges."""
    theta, valid = estimate_rain_angles(image[None], **{"k": 1, **options})
    return [math.degrees(float(streak_angle(t))) for t, ok in zip(theta[0], valid[0]) if bool(ok)]


def streak_angle_deg(image: Tensor, options: dict) -> float | None:
    """The dominant streak direction (see :func:`streak_angles_deg`), or None."""
    angles = streak_angles_deg(image, {**options, "k": 1})
    return angles[0] if angles else None


def correlation(a: Tensor, b: Tensor) -> float | None:
    """Pearson correlation of two images' grey levels (None when either is constant)."""
    x, y = a.double().mean(0).flatten(), b.double().mean(0).flatten()
    x, y = x - x.mean(), y - y.mean()
    den = float(x.norm() * y.norm())
    return float((x * y).sum()) / den if den > 0 else None


# ---------------------------------------------------------------------------- metrics


def image_metrics(pred: Tensor, target: Tensor, lpips: LpipsMetric) -> dict[str, float]:
    """PSNR, SSIM (and LPIPS when available) of two (3, H, W) images."""
    out = {"psnr": float(psnr(pred, target)), "ssim": float(ssim(pred[None], target[None]))}
    if lpips.available:
        out["lpips"] = float(lpips.fn(pred[None], target[None])[0])
    return out


def view_metrics(v: ViewImages, lpips: LpipsMetric, angle_options: dict) -> dict:
    row: dict = {"view": v.name, "split": v.split,
                 "psnr_vs_rainy": float(psnr(v.rendered, v.rainy))}
    if v.clean is not None:
        row.update(image_metrics(v.rendered, v.clean, lpips))
        if v.split == "train":
            row.update({f"rainy_input_{k}": x for k, x in image_metrics(v.rainy, v.clean, lpips).items()})
            for key, img in v.post.items():
                row.update({f"{key}_{k}": x for k, x in image_metrics(img, v.clean, lpips).items()})
    if v.rain is not None:
        angles = streak_angles_deg(v.rain, angle_options)  # strongest first
        row["rain_angle_deg"] = angles[0] if angles else None
        if angle_options.get("k", 1) > 1:  # multi-direction rain: every direction the AGR term uses
            row["rain_angles_deg"] = angles
        row["residual_angle_deg"] = streak_angle_deg(v.rainy - v.rendered, angle_options)
        if v.true_rain is not None:
            row["rain_correlation"] = correlation(v.rain, v.true_rain)
    if v.true_rain is not None and v.split == "train":
        row["rain_angle_true_deg"] = streak_angle_deg(v.true_rain, angle_options)
    return row


def _mean(values: list) -> float | None:
    values = [v for v in values if v is not None]
    return sum(values) / len(values) if values else None


def summarize(rows: list[dict]) -> dict[str, float]:
    """Means over views of every numeric per-view value, keyed ``<split>_<key>`` (the rainy
    floor and the rain statistics, defined on training views only, keep their own names)."""
    summary: dict[str, float] = {}
    for split in ("train", "heldout"):
        rows_s = [r for r in rows if r["split"] == split]
        keys = sorted({k for r in rows_s for k, x in r.items() if isinstance(x, float) or x is None})
        for k in keys:
            values = [r.get(k) for r in rows_s]
            value = mean_angle_deg([x for x in values if x is not None]) if k in ANGLE_KEYS else _mean(values)
            if k in RAIN_KEYS:  # None stays: "the predicted rain has no streaks", not "not measured"
                summary[k] = value
            elif value is None:
                continue
            elif k.startswith("rainy_input_"):
                summary[k] = value
            else:
                summary[f"{split}_{k}"] = value
    pairs = [(r["rain_angle_deg"], r["rain_angle_true_deg"]) for r in rows
             if r.get("rain_angle_deg") is not None and r.get("rain_angle_true_deg") is not None]
    if pairs:
        summary["rain_angle_error_deg"] = _mean([angle_difference_deg(a, b) for a, b in pairs])
    return dict(sorted(summary.items()))


def evaluate_views(pipeline: Pipeline, lpips: LpipsMetric | None = None, keep: int = 0
                   ) -> tuple[list[dict], list[ViewImages]]:
    """Per-view metrics of every view, and the images of the first ``keep`` training views."""
    lpips = lpips or load_lpips(pipeline.device)
    options = _agr_options(pipeline)
    scene = pipeline.scene
    rows, kept = [], []
    for i in progress(list(scene.train_indices) + list(scene.eval_indices), "evaluating views"):
        v = view_images(pipeline, i)
        rows.append(view_metrics(v, lpips, options))
        if v.split == "train" and len(kept) < keep:
            kept.append(v)
    return rows, kept


@torch.no_grad()
def evaluate_pipeline(pipeline: Pipeline, run_dir: Path | None = None) -> dict:
    """The whole protocol on a trained pipeline; with ``run_dir`` it also saves the comparison
    strips of a few training views under ``run_dir/renders/strips`` (used by the report)."""
    lpips = load_lpips(pipeline.device)
    rows, kept = evaluate_views(pipeline, lpips, keep=STRIP_VIEWS if run_dir is not None else 0)
    if run_dir is not None:
        from rainyscape.eval.images import save_strip

        for v in kept:
            save_strip(v, Path(run_dir) / "renders" / "strips" / f"{Path(v.name).stem}.png")
    scene = pipeline.scene
    return {
        "scene": scene.name,
        "method": pipeline.config.method,
        "has_clean": scene.clean_images is not None,
        "has_rain_head": pipeline.rain_head is not None,
        "postprocess": list(pipeline.postprocess),
        "views": {"train": len(scene.train_indices), "heldout": len(scene.eval_indices),
                  "width": scene.width, "height": scene.height},
        "lpips": lpips.describe(),
        "summary": summarize(rows),
        "per_view": rows,
    }


def write_metrics(run_dir: Path, metrics: dict) -> Path:
    """Write ``metrics.json`` atomically, then the run's ``report.html`` presenting it.

    A report that cannot be written is reported on stderr and does not fail the run (the
    metrics are safe; ``rs-eval RUN_DIR`` rebuilds it)."""
    path = Path(run_dir) / "metrics.json"
    tmp = path.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(metrics, indent=2))
    tmp.replace(path)
    try:
        from rainyscape.eval.report import write_report

        write_report(run_dir)
    except Exception as exc:  # the report is a view of the metrics; never lose a run over it
        print(f"rainyscape: warning: could not write {Path(run_dir) / 'report.html'}: "
              f"{type(exc).__name__}: {exc}", file=sys.stderr)
    return path
