"""The whole ``rs-train`` job: the scene (the embedded demo when none is given), training in a
run folder, and the evaluation protocol with its report when the run is complete.

It composes the layers below it (engine, eval, synth) so that none of them needs another:
the engine trains whatever it is given, evaluation evaluates a pipeline, the simulator
makes scenes. ``rs-train`` and ``rs-bench`` call :func:`train_and_evaluate`.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import torch

from rainyscape.config import PipelineConfig
from rainyscape.engine.pipeline import Pipeline
from rainyscape.engine.run import RunResult, open_run, recording_failures, write_status


def with_scene(cfg: PipelineConfig) -> PipelineConfig:
    """``cfg`` with its scene folder set: the embedded demo scene (simulated once and cached)
    when ``data=`` is empty, so that config.yml names the folder the run used."""
    if cfg.data:
        return cfg
    from rainyscape.synth.demo import ensure_demo_scene

    return dataclasses.replace(cfg, data=str(ensure_demo_scene()))


@torch.no_grad()
def quick_eval(pipeline: Pipeline) -> dict:
    """PSNR of a few training and held-out renders vs clean and rainy images (Fig. 2)."""
    from rainyscape.cameras import Window
    from rainyscape.imaging.metrics import psnr

    scene, dev = pipeline.scene, pipeline.device
    views = pipeline.config.trainer.eval_views
    out: dict[str, float] = {}
    for split, indices in {"train": scene.train_indices, "heldout": scene.eval_indices}.items():
        picked = indices[:views]
        if not picked:
            continue
        clean_vals, rainy_vals = [], []
        for i in picked:
            pipeline.field.eval()
            cams = scene.cameras[[i]].to(dev)
            rgb = pipeline.field.render(cams, Window.full(cams)).rgb.clamp(0, 1)
            rainy = scene.images[i].to(dev).permute(2, 0, 1)[None].float() / 255
            rainy_vals.append(float(psnr(rgb, rainy)))
            if scene.clean_images is not None:
                clean = scene.clean_images[i].to(dev).permute(2, 0, 1)[None].float() / 255
                clean_vals.append(float(psnr(rgb, clean)))
        out[f"{split}_psnr_rainy"] = sum(rainy_vals) / len(rainy_vals)
        if clean_vals:
            out[f"{split}_psnr_clean"] = sum(clean_vals) / len(clean_vals)
    return out


def train_and_evaluate(cfg: PipelineConfig, run_dir: Path | None = None) -> RunResult:
    """Train ``cfg`` in a new run folder (or resume ``run_dir``); once the run is complete,
    evaluate it and write metrics.json and report.html."""
    from rainyscape.eval.evaluate import evaluate_pipeline, write_metrics

    run = open_run(with_scene(cfg), run_dir, evaluator=quick_eval)
    metrics: dict = {}
    with recording_failures(run.run_dir):
        run.trainer.train()
        if run.finished:
            metrics = evaluate_pipeline(run.pipeline, run.run_dir)
            write_status(run.run_dir, "finished", step=run.trainer.step)  # before the report shows it
            write_metrics(run.run_dir, metrics)
        else:
            write_status(run.run_dir, "stopped", step=run.trainer.step)
    return RunResult(run.run_dir, metrics)
