"""The whole ``rs-train`` job: the scene (the embedded demo when none is given), training in a
run folder, and the evaluation protocol with its report when the run is complete.

It composes the layers below it (engine, eval, synth) so that none of them needs another:
the engine trains whatever it is given, evaluation evaluates a pipeline, the simulator
makes scenes. ``rs-train`` and ``rs-bench`` call :func:`train_and_evaluate`.

The evaluation at the end of training is bounded: ``trainer.final_eval_views`` views spread
over both splits, and no view started after ``trainer.final_eval_share`` of the training
time has gone into it. ``rs-eval RUN_DIR`` runs the protocol on every view.
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


def final_evaluation(run: Run, training_seconds: float | None) -> dict:
    """The protocol on the views ``trainer.final_eval_views`` / ``final_eval_share`` allow,
    with a line saying what it evaluates; ``training_seconds``: the whole run's estimated
    training time (None: unknown, no time limit)."""
    from rainyscape.eval.protocol import evaluate_pipeline
    from rainyscape.eval.views import choose_views

    t = run.pipeline.config.trainer
    scene = run.pipeline.scene
    views = choose_views(list(scene.train_indices), list(scene.eval_indices), t.final_eval_views)
    limit = t.final_eval_share * training_seconds if t.final_eval_share and training_seconds else None
    some = len(views) < scene.num_images or limit is not None
    print(f"evaluating {len(views)} of {scene.num_images} views"
          + (f" (at most {limit:.0f} s, {t.final_eval_share:.0%} of the training time)" if limit else "")
          + (f"; rs-eval {run.run_dir} evaluates every view" if some else ""), file=sys.stderr)
    metrics = evaluate_pipeline(run.pipeline, run.run_dir, views=views, time_limit=limit)
    done = metrics["evaluated"]
    print(f"evaluated {len(done['views'])} views in {done['seconds']:.1f} s", file=sys.stderr)
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
            first, started = run.trainer.step, time.perf_counter()
            run.trainer.train()
            steps = run.trainer.step - first
            per_step = (time.perf_counter() - started) / steps if steps else None
            if run.finished:
                total = per_step * run.pipeline.config.trainer.max_iters if per_step else None
                metrics = final_evaluation(run, total)
                metrics["step"] = run.trainer.step
                write_status(run.run_dir, "finished", step=run.trainer.step)  # before the report shows it
                write_metrics(run.run_dir, metrics)
            else:
                write_status(run.run_dir, "stopped", step=run.trainer.step)
    return RunResult(run.run_dir, metrics)
