"""The whole ``rs-train`` job: the scene (the embedded demo when none is given), training in a
run folder, and the evaluation protocol with its report when the run is complete.

It composes the layers below it (engine, eval, synth) so that none of them needs another:
the engine trains whatever it is given, evaluation evaluates a pipeline, the simulator
makes scenes. ``rs-train`` and ``rs-bench`` call :func:`train_and_evaluate`.

The evaluation at the end of training is bounded by views, never by time: a fixed subset of
``trainer.final_eval_views`` views over both splits (the same for every run of a scene), so
that two evaluations of the same weights give the same metrics.json. ``rs-eval RUN_DIR`` runs
the protocol on every view.
"""

from __future__ import annotations

import dataclasses
import sys
import time
from pathlib import Path

from rainyscape.config import PipelineConfig
from rainyscape.engine.run import Run, RunResult, open_run, recording_failures, write_status


def with_scene(cfg: PipelineConfig) -> PipelineConfig:
    """``cfg`` with its scene folder set: the embedded demo scene (simulated once and cached)
    when ``data=`` is empty, so that config.yml names the folder the run used."""
    if cfg.data:
        return cfg
    from rainyscape.synth.demo import ensure_demo_scene

    return dataclasses.replace(cfg, data=str(ensure_demo_scene()))


def final_evaluation(run: Run) -> dict:
    """The protocol on the fixed subset of views ``trainer.final_eval_views`` asks for, with a
    line saying which views it measures."""
    from rainyscape.eval.protocol import evaluate_pipeline
    from rainyscape.eval.views import choose_views

    scene = run.pipeline.scene
    views = choose_views(list(scene.train_indices), list(scene.eval_indices),
                         run.pipeline.config.trainer.final_eval_views)
    some = len(views) < scene.num_images
    print(f"evaluating {len(views)} of {scene.num_images} views"
          + (f" ({', '.join(scene.image_names[i] for i in views)}; a fixed subset: rs-eval "
             f"{run.run_dir} evaluates every view)" if some else ""), file=sys.stderr)
    started = time.perf_counter()
    metrics = evaluate_pipeline(run.pipeline, run.run_dir, views=views)
    print(f"evaluated {len(views)} views in {time.perf_counter() - started:.1f} s", file=sys.stderr)
    return metrics


def train_and_evaluate(cfg: PipelineConfig, run_dir: Path | None = None) -> RunResult:
    """Train ``cfg`` in a new run folder (or resume ``run_dir``); once the run is complete,
    evaluate it and write metrics.json and report.html. The folder is locked meanwhile."""
    from rainyscape.eval.protocol import write_metrics
    from rainyscape.eval.views import quick_eval

    metrics: dict = {}
    with open_run(with_scene(cfg), run_dir,
                  evaluator=lambda pipeline: quick_eval(pipeline, cfg.trainer.eval_views)) as run:
        with recording_failures(run.run_dir):
            run.trainer.train()
            if run.finished:
                metrics = final_evaluation(run)
                metrics["step"] = run.trainer.step
                write_status(run.run_dir, "finished", step=run.trainer.step)  # before the report shows it
                write_metrics(run.run_dir, metrics)
            else:
                write_status(run.run_dir, "stopped", step=run.trainer.step)
    return RunResult(run.run_dir, metrics)
