"""The evaluation protocol (docs/evaluation.md): rainy-input floor, de-raining on training
views (with and without post-processing) and novel held-out views; PSNR, SSIM, LPIPS (when its
weights are on this machine), the predicted rain angle and, for simulated scenes, how well the
predicted rain layer correlates with the true one. Every number is written under the key its
:class:`~rainyscape.eval.metric_keys.Metric` gives (the list: rainyscape/eval/metric_keys.py).
"""

from __future__ import annotations

import sys
from pathlib import Path

import torch
from torch import Tensor

from rainyscape.cameras import Cameras
from rainyscape.components import MaskFusion
from rainyscape.engine.pipeline import Pipeline
from rainyscape.engine.run_folder import RunFolder
from rainyscape.eval.images import save_strip
from rainyscape.eval.metric_keys import (COVERAGE, LPIPS, PSNR, PSNR_DRY, PSNR_IN_RAIN, PSNR_VS_RAINY, RAIN_KEPT,
                                         RAIN_RECOVERED, SSIM, Measure, Metric, control, post, rainy_input,
                                         render)
from rainyscape.eval.perceptual import LpipsMetric, load_lpips
from rainyscape.eval.rain_stats import angle_options, true_rain_directions, true_rain_falls, view_rain_stats
from rainyscape.eval.report import write_report
from rainyscape.eval.summary import summarize
from rainyscape.eval.views import ViewImages, progress, view_images
from rainyscape.imaging.metrics import masked_psnr, psnr, ssim

STRIP_VIEWS = 3  # training views whose comparison strips evaluation saves for the report
CONTROL_SEED = 7919  # the random-mask control of view i uses seed CONTROL_SEED + i
RAIN_PIXEL = 0.02  # a pixel is "in rain" where the true rain layer exceeds this (about 5 / 255)


def image_metrics(pred: Tensor, target: Tensor, lpips: LpipsMetric) -> dict[Measure, float]:
    """PSNR, SSIM (and LPIPS when available) of two (3, H, W) images."""
    out = {PSNR: float(psnr(pred, target)), SSIM: float(ssim(pred[None], target[None]))}
    if lpips.available:
        out[LPIPS] = float(lpips.fn(pred[None], target[None])[0])
    return out


def region_psnr(pred: Tensor, clean: Tensor, wet: Tensor) -> dict[Measure, float | None]:
    """PSNR of a (3, H, W) image vs clean on the pixels in rain (``wet``, (H, W)) and the others."""
    return {PSNR_IN_RAIN: masked_psnr(pred, clean, wet), PSNR_DRY: masked_psnr(pred, clean, ~wet)}


def rain_shares(rendered: Tensor, clean: Tensor, true_rain: Tensor, wet: Tensor,
                rain: Tensor | None = None) -> dict[Measure, float | None]:
    """Where a view's true rain went, on the pixels it covers (``wet``, (H, W)), as shares of
    its amount there (sum over wet pixels and channels): ``RAIN_KEPT`` is how much of it the
    render still shows (sum (B - clean) / sum rain: 1 = the rainy input, 0 = clean, below 0 =
    darker than clean), ``RAIN_RECOVERED`` how much of it the predicted rain holds (sum R /
    sum rain; only with ``rain``). None where the view has no rain."""
    m = wet.expand_as(true_rain)
    total = float(true_rain[m].double().sum())

    def share(layer: Tensor) -> float | None:
        return float(layer[m].double().sum()) / total if total > 0 else None

    out = {RAIN_KEPT: share(rendered - clean)}
    if rain is not None:
        out[RAIN_RECOVERED] = share(rain)
    return out


def region_metrics(image: Tensor, clean: Tensor, true_rain: Tensor, wet: Tensor,
                   rain: Tensor | None = None) -> dict[Measure, float | None]:
    """:func:`region_psnr` and :func:`rain_shares` of one image."""
    return {**region_psnr(image, clean, wet), **rain_shares(image, clean, true_rain, wet, rain)}


def keyed(values: dict[Measure, float | None], metric) -> dict[str, float | None]:
    """``values`` under the keys ``metric(measure)`` gives them (a per-view row's entries)."""
    return {metric(m).key: x for m, x in values.items()}


def fusion_controls(pipeline: Pipeline, v: ViewImages) -> dict[str, tuple[float, Tensor]]:
    """For each mask-fusion post-process of a training view (:class:`MaskFusion`): (coverage
    of its mask, the same fusion under a random mask of that coverage, placed with the view's
    seed). Other post-processes get none."""
    out: dict[str, tuple[float, Tensor]] = {}
    for key, post in pipeline.postprocess.items():
        if key in v.post and isinstance(post, MaskFusion):
            control = post.control(v.rendered, v.rain, v.rainy, CONTROL_SEED + v.index)
            out[key] = (control.coverage, control.control)
    return out


def view_metrics(v: ViewImages, lpips: LpipsMetric, angle_opts: dict,
                 controls: dict[str, tuple[float, Tensor]] | None = None, true_directions: int = 1,
                 falls: tuple[Cameras, Tensor] | None = None) -> dict:
    """One view's row of ``per_view``: its images against the clean and the rainy ones, the
    fusion controls (``controls``: post-process key -> (coverage, control image)), and its
    rain statistics (``true_directions`` and ``falls``: of the true rain, see
    :func:`view_rain_stats`)."""
    split, controls = v.split, controls or {}

    def at(m: Measure) -> Metric:
        return render(m, split)

    row: dict = {"view": v.name, "split": split, at(PSNR_VS_RAINY).key: float(psnr(v.rendered, v.rainy))}
    if v.clean is not None:
        row.update(keyed(image_metrics(v.rendered, v.clean, lpips), at))
        if split == "train":
            row.update(keyed(image_metrics(v.rainy, v.clean, lpips), rainy_input))
            for key, img in v.post.items():
                row.update(keyed(image_metrics(img, v.clean, lpips), lambda m: post(m, key)))
            for key, (_, img) in controls.items():
                row.update(keyed(image_metrics(img, v.clean, lpips), lambda m: control(m, key)))
    for key, (coverage, _) in controls.items():
        row[post(COVERAGE, key).key] = coverage
    if v.clean is not None and v.true_rain is not None:
        wet = v.true_rain.amax(0) > RAIN_PIXEL
        row.update(keyed(region_metrics(v.rendered, v.clean, v.true_rain, wet, v.rain), at))
        if split == "train":  # the input is exact on dry pixels: only its rain counts
            row[rainy_input(PSNR_IN_RAIN).key] = region_psnr(v.rainy, v.clean, wet)[PSNR_IN_RAIN]
            for key, img in v.post.items():
                row.update(keyed(region_metrics(img, v.clean, v.true_rain, wet), lambda m: post(m, key)))
    row.update(view_rain_stats(v, angle_opts, true_directions, falls))
    return row


def evaluate_views(pipeline: Pipeline, lpips: LpipsMetric | None = None, keep: int = 0,
                   views: list[int] | None = None) -> tuple[list[dict], list[ViewImages]]:
    """Per-view metrics of ``views`` (default: every view), and the images of the first
    ``keep`` training views."""
    lpips = lpips or load_lpips(pipeline.device)
    options, directions = angle_options(pipeline), true_rain_directions(pipeline)
    falls = true_rain_falls(pipeline.scene)
    scene = pipeline.scene
    rows, kept = [], []
    if views is None:
        views = list(scene.train_indices) + list(scene.eval_indices)
    for i in progress(views, "evaluating views"):
        v = view_images(pipeline, i)
        view_falls = None if falls is None else (scene.cameras[i], falls)
        rows.append(view_metrics(v, lpips, options, fusion_controls(pipeline, v), directions, view_falls))
        if v.split == "train" and len(kept) < keep:
            kept.append(v)
    return rows, kept


@torch.no_grad()
def evaluate_pipeline(pipeline: Pipeline, run_dir: Path | None = None, views: list[int] | None = None) -> dict:
    """The protocol on a trained pipeline, on ``views`` (default: every view); ``evaluated`` in
    the result says how many views were measured and names them. The result depends on the
    weights and the views only (no time, no clock): two evaluations of the same weights give
    the same metrics. With ``run_dir`` it also saves the comparison strips of a few training
    views in the run folder (used by the report), once every view is measured."""
    lpips = load_lpips(pipeline.device)
    rows, kept = evaluate_views(pipeline, lpips, keep=STRIP_VIEWS if run_dir is not None else 0, views=views)
    for v in kept:
        save_strip(v, RunFolder(run_dir).strips / f"{Path(v.name).stem}.png")
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
        "evaluated": {"views": [r["view"] for r in rows],
                      "train": sum(r["split"] == "train" for r in rows),
                      "heldout": sum(r["split"] == "heldout" for r in rows),
                      "all": len(rows) == scene.num_images},
        "summary": summarize(rows),
        "per_view": rows,
    }


def write_metrics(run_dir: Path, metrics: dict) -> Path:
    """Write the run's metrics atomically, then the report presenting them.

    A report that cannot be written is reported on stderr and does not fail the run (the
    metrics are safe; ``rs-eval RUN_DIR`` rebuilds it)."""
    folder = RunFolder(run_dir)
    path = folder.save_metrics(metrics)
    try:
        write_report(run_dir)
    except Exception as exc:  # the report is a view of the metrics; never lose a run over it
        print(f"rainyscape: warning: could not write {folder.report_file}: "
              f"{type(exc).__name__}: {exc}", file=sys.stderr)
    return path
