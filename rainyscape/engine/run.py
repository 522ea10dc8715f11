"""A training run in its folder: create or reopen one (locked, scene, pipeline and trainer
built, checkpoint loaded), and rebuild a trained run for evaluation. The folder's layout and
its questions are :class:`~rainyscape.engine.run_folder.RunFolder`'s."""

from __future__ import annotations

import dataclasses
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Sequence

from rainyscape.config import PipelineConfig, apply_overrides, parse_overrides, with_run_length
from rainyscape.engine.device import resolve_device
from rainyscape.engine.lock import RunLock
from rainyscape.engine.pipeline import Pipeline, build_pipeline
from rainyscape.engine.run_folder import NewRunDir, RunFolder, check_output_dir, new_run_dir, reached_end
from rainyscape.engine.scene_loading import load_scene
from rainyscape.engine.trainer import Trainer, seed_everything
from rainyscape.errors import ConfigError, DataError
from rainyscape.formats.output import check_writable
from rainyscape.scene import SceneData


@dataclass
class RunResult:
    run_dir: Path
    metrics: dict


@dataclass
class Run:
    """A run folder with its pipeline and trainer, ready to train (resumed if it was). It
    holds the folder's lock until :meth:`close` (or the end of a ``with`` block)."""

    run_dir: Path
    pipeline: Pipeline
    trainer: Trainer
    lock: RunLock | None = None
    created: NewRunDir | None = None  # a new run: the folder (and parents) this process made

    @property
    def folder(self) -> RunFolder:
        return RunFolder(self.run_dir)

    @property
    def trained(self) -> bool:
        """Whether training has reached the run's last step (then it is evaluated)."""
        return reached_end(self.trainer.step, self.pipeline.config.trainer.max_iters)

    def close(self) -> None:
        if self.lock is not None:
            self.lock.release()

    def __enter__(self) -> "Run":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        try:
            # A new run that failed before its first checkpoint holds nothing to resume or
            # keep: leave trainer.output_dir as it was. (Ctrl-C saves a checkpoint; a run with
            # checkpoints keeps its folder, status "failed", to be resumed.)
            if (exc_type is not None and not issubclass(exc_type, KeyboardInterrupt)
                    and self.created is not None and not self.folder.has_checkpoint()):
                self.created.remove()
        finally:
            self.close()


def scene_folder(cfg: PipelineConfig) -> Path:
    if not cfg.data:
        raise ConfigError("no scene folder (data=) in the config")
    return Path(cfg.data).expanduser()


def open_run(cfg: PipelineConfig, run_dir: Path | None = None,
             evaluator: Callable[[Pipeline], dict] | None = None,
             prepare_scene: Callable[[PipelineConfig, SceneData], SceneData] | None = None) -> Run:
    """A new run folder for ``cfg`` (or ``run_dir`` reopened to resume): locked, scene,
    pipeline and trainer built, checkpoint loaded. ``evaluator(pipeline)`` is the trainer's
    periodic evaluation; ``prepare_scene(cfg, scene)`` completes the parsed scene before the
    pipeline is built (the workflow adds sparse points there). Input errors surface before any
    folder is made; a folder another process trains in raises RunBusyError before anything in
    it changes, and so does anything that fails before training starts (a resume that does not
    fit leaves config.yml and status.json as they were). Close the run (``with open_run(...) as
    run``) to release the lock."""
    device = resolve_device(cfg.trainer.device)
    if run_dir is None:
        check_output_dir(cfg.trainer.output_dir)
    else:
        check_writable(run_dir, "a resume saves its training state, log, status and config there")
    lock: RunLock | None = None
    created = None
    if run_dir is not None:  # lock first: nothing in a busy folder may change
        lock = RunFolder(run_dir).lock("rs-train").acquire()
    try:
        seed_everything(cfg.trainer.seed)
        scene = load_scene(cfg, scene_folder(cfg))
        if prepare_scene is not None:
            scene = prepare_scene(cfg, scene)
        cfg = with_run_length(cfg, len(scene.train_indices), scene.train_pixels)
        if run_dir is None:
            created = new_run_dir(cfg.trainer.output_dir, scene.name, cfg.method)
            run_dir = created.path
            lock = RunFolder(run_dir).lock("rs-train").acquire()
        run_dir = Path(run_dir)
        folder = RunFolder(run_dir)
        previous = folder.status()  # before it is overwritten: a dead owner shows here
        pipeline = build_pipeline(cfg, scene, device)
        evaluate = None if evaluator is None else (lambda: evaluator(pipeline))
        trainer = Trainer(pipeline, folder, evaluate)
        used = trainer.load() if folder.has_checkpoint() else None
        # Everything is checked: only now does the folder change.
        folder.remove_partial_writes()
        folder.save_config(cfg)
        folder.set_status("running")
        if previous.get("state") == "interrupted" and previous.get("note"):
            print(f"rainyscape: {run_dir}: {previous['note'].split(';')[0]}", file=sys.stderr)
        if used is not None:
            print(f"resuming {run_dir} from {used.name} (step {trainer.step})", file=sys.stderr)
        elif previous:
            print(f"rainyscape: {run_dir}: no checkpoint yet; training again from step 0",
                  file=sys.stderr)
    except BaseException:
        if lock is not None:
            lock.release()
        if created is not None:
            created.remove()
        raise
    return Run(run_dir, pipeline, trainer, lock, created)


def load_run(run_dir: Path, device: str = "auto", step: int | None = None,
             data: str | Path | None = None,
             prepare_scene: Callable[[PipelineConfig, SceneData], SceneData] | None = None,
             postprocess: Sequence[str] = ()) -> tuple[Pipeline, int]:
    """Rebuild a run's pipeline from config.yml and load its latest readable (or given)
    checkpoint. ``data`` replaces the scene folder config.yml names (a moved scene);
    ``prepare_scene`` completes the scene as it did for training (see :func:`open_run`);
    ``postprocess`` overrides (``postprocess.NAME=on|none``, ``postprocess.NAME.KEY=V``)
    change the post-processes, which touch no checkpointed state."""
    folder = RunFolder.check(run_dir)
    cfg = folder.config()
    if postprocess:
        not_post = [o for o in postprocess if not o.startswith("postprocess.")]
        if not_post:
            raise ConfigError(f"'{not_post[0]}': a finished run takes only postprocess.* overrides "
                              f"(everything else is fixed by its checkpoint)")
        cfg = apply_overrides(cfg, parse_overrides(list(postprocess)))
    if data:
        cfg = dataclasses.replace(cfg, data=str(data))
    dev = resolve_device(device)
    scene_dir = scene_folder(cfg)
    if not scene_dir.exists():
        hint = "pass data=NEW_FOLDER" if not data else "check data="
        raise DataError(f"{scene_dir}: the run's scene folder is not there (moved?); {hint} "
                        f"(named in {folder.config_file})")
    scene = load_scene(cfg, scene_dir)
    if prepare_scene is not None:
        scene = prepare_scene(cfg, scene)
    pipeline = build_pipeline(cfg, scene, dev)
    return pipeline, folder.restore(pipeline, step)
