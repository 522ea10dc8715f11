"""The whole ``rs-train`` job: the scene (the embedded demo when none is given), training in a
run folder, and the evaluation protocol with its report when the run is complete.

It composes the layers below it (engine, eval, synth, process) so that none of them needs
another: the engine trains whatever it is given, evaluation evaluates a pipeline, the
simulator makes scenes, process triangulates sparse points for a field that starts from them
when the scene has none. ``rs-train`` and ``rs-bench`` call :func:`train_and_evaluate`.

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
from rainyscape.engine.pipeline import Pipeline
from rainyscape.engine.run import Run, RunResult, load_run, open_run
from rainyscape.errors import warn
from rainyscape.eval.report import POINTS_RECORD, points_line
from rainyscape.scene import SceneData


def with_scene(cfg: PipelineConfig) -> PipelineConfig:
    """``cfg`` with its scene folder set: the embedded demo scene (simulated once and cached)
    when ``data=`` is empty, so that config.yml names the folder the run used."""
    if cfg.data:
        return cfg
    from rainyscape.synth.demo import ensure_demo_scene

    return dataclasses.replace(cfg, data=str(ensure_demo_scene()))


def wants_sparse_points(cfg: PipelineConfig, forward_facing: bool = False) -> bool:
    """Whether the run's field needs the scene's sparse points: it starts from them (the
    Gaussian field's ``init`` is ``auto`` or ``points``; ``random`` or ``frustum`` do not), or
    bounds its grids by them (the grid fields' ``box`` ``points`` or ``auto``, and their NDC
    layout, whose near plane sits in front of the nearest points; ``auto`` is NDC on
    forward-facing scenes)."""
    options = cfg.field.options
    layout = getattr(options, "layout", None)
    ndc = layout == "ndc" or (layout == "auto" and forward_facing)
    by_points = ("auto", "points")
    return getattr(options, "init", None) in by_points or getattr(options, "box", None) in by_points or ndc


def complete_scene(cfg: PipelineConfig, scene: SceneData) -> SceneData:
    """The scene as the run's field needs it (rs-train, rs-eval, rs-render and rs-export all
    build the field from it): for a field that starts from or is bounded by sparse points,
    points triangulated from the training views (cached) when the scene has none."""
    if not wants_sparse_points(cfg, scene.forward_facing) or (scene.points is not None and len(scene.points)):
        return scene
    if len(scene.train_indices) < 2:
        return scene
    import torch

    from rainyscape.process.scene_points import with_sparse_points
    from rainyscape.process.triangulate import TriangulationOptions

    try:
        return with_sparse_points(scene, TriangulationOptions(num_threads=torch.get_num_threads()))
    except (RuntimeError, ValueError, OSError) as exc:  # a failed SfM step must not stop training
        warn(f"triangulating sparse points failed ({type(exc).__name__}: {exc}); the field "
             "starts without them")
        return dataclasses.replace(scene, points_source=f"none (triangulation failed: {exc})")


def load_trained(run_dir: Path, device: str = "auto", step: int | None = None,
                 data: str | Path | None = None, postprocess=()) -> tuple[Pipeline, int]:
    """A trained run's pipeline and checkpoint step, its scene completed as training completed
    it (:func:`complete_scene`: a grid field's box or a Gaussian field's start from points
    triangulated when the scene has none, else the lattice would not fit the checkpoint).
    What rs-eval, rs-render, rs-export, rs-bench and the benchmark scripts load runs with."""
    return load_run(Path(run_dir), device, step, data=data, prepare_scene=complete_scene,
                    postprocess=postprocess)


def points_record(cfg: PipelineConfig, scene: SceneData) -> dict:
    """What the log and the report say of the points the field started from."""
    count = 0 if scene.points is None else int(len(scene.points))
    record = {"points": count, "source": scene.points_source,
              "field_init": getattr(cfg.field.options, "init", None)}
    details = scene.metadata.get("sparse_points")
    if details:
        record["triangulation"] = details
    return record


def log_points(run: Run) -> None:
    """One console line and, on a fresh run, one log.jsonl record (step 0) about the field's
    starting points; nothing for a field that does not start from points."""
    cfg = run.pipeline.config
    if getattr(cfg.field.options, "init", None) is None:
        return
    record = points_record(cfg, run.pipeline.scene)
    print(f"sparse points: {points_line(record)}", file=sys.stderr)
    if run.trainer.step == 0 and not any(POINTS_RECORD in r for r in run.folder.log_records()):
        run.folder.append_log({"step": 0, POINTS_RECORD: record})


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
                  evaluator=lambda pipeline: quick_eval(pipeline, cfg.trainer.eval_views),
                  prepare_scene=complete_scene) as run:
        log_points(run)
        with run.folder.recording_failures():
            run.trainer.train()
            if run.trained:
                metrics = final_evaluation(run)
                metrics["step"] = run.trainer.step
                run.folder.set_status("finished", step=run.trainer.step)  # before the report shows it
                write_metrics(run.run_dir, metrics)
            else:
                run.folder.set_status("stopped", step=run.trainer.step)
    return RunResult(run.run_dir, metrics)
