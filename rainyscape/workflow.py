"""The whole ``rs-train`` job: the scene (the embedded demo when none is given), training in a
run folder, and the evaluation protocol with its report when the run is complete.

It composes the layers below it (engine, eval, synth) so that none of them needs another:
the engine trains whatever it is given, evaluation evaluates a pipeline, the simulator
makes scenes. ``rs-train`` and ``rs-bench`` call :func:`train_and_evaluate`.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

from rainyscape.config import PipelineConfig
from rainyscape.engine.run import RunResult, open_run, recording_failures, write_status


def with_scene(cfg: PipelineConfig) -> PipelineConfig:
    """``cfg`` with its scene folder set: the embedded demo scene (simulated once and cached)
    when ``data=`` is empty, so that config.yml names the folder the run used."""
    if cfg.data:
        return cfg
    from rainyscape.synth.demo import ensure_demo_scene

    return dataclasses.replace(cfg, data=str(ensure_demo_scene()))


def train_and_evaluate(cfg: PipelineConfig, run_dir: Path | None = None) -> RunResult:
    """Train ``cfg`` in a new run folder (or resume ``run_dir``); once the run is complete,
    evaluate it and write metrics.json and report.html."""
    from rainyscape.eval.protocol import evaluate_pipeline, write_metrics
    from rainyscape.eval.views import quick_eval

    run = open_run(with_scene(cfg), run_dir,
                   evaluator=lambda pipeline: quick_eval(pipeline, cfg.trainer.eval_views))
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
