"""Run folders around a training run: create or reopen one, lock it, record its state,
restore it.

Run folder contents: config.yml (plain YAML), status.json (running / stopped / finished /
failed / interrupted; a running one names its pid and host), run.lock (held by the process
training there), log.jsonl (training curves), checkpoints/; evaluation adds metrics.json,
renders/ and report.html.
"""

from __future__ import annotations

import dataclasses
import json
import os
import socket
import sys
import time
import traceback
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterator

from rainyscape import config as config_mod
from rainyscape.config import PipelineConfig, with_run_length
from rainyscape.engine.checkpoint import (checkpoint_path, list_checkpoints, load_checkpoint,
                                          load_newest_valid, remove_partial_writes)
from rainyscape.engine.lock import RunLock, is_locked
from rainyscape.engine.pipeline import Pipeline, build_pipeline, load_scene, resolve_device
from rainyscape.engine.run_dir import (CHECKPOINTS, CONFIG_FILE, NewRunDir, check_output_dir,
                                       check_run_folder, new_run_dir)
from rainyscape.engine.snapshot import restore_models
from rainyscape.engine.trainer import Trainer, seed_everything
from rainyscape.errors import ConfigError, DataError, RainyScapeError
from rainyscape.formats.atomic import write_text_atomic
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
    def finished(self) -> bool:
        return self.trainer.step >= self.pipeline.config.trainer.max_iters

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
                    and self.created is not None and not list_checkpoints(self.run_dir / CHECKPOINTS)):
                self.created.remove()
        finally:
            self.close()


def write_status(run_dir: Path, state: str, **extra) -> None:
    """status.json, atomically; a "running" status names this process (pid, host)."""
    data = {"state": state, "time": time.strftime("%Y-%m-%d %H:%M:%S"), **extra}
    if state == "running":
        data.update(pid=os.getpid(), host=socket.gethostname())
    write_text_atomic(Path(run_dir) / "status.json", json.dumps(data, indent=2))


def read_status(run_dir: Path) -> dict:
    """status.json ({} when absent or unreadable). A "running" status whose process is gone
    (nobody holds the folder's lock: killed, crashed, power cut) is corrected to
    "interrupted" on disk and in the answer."""
    path = Path(run_dir) / "status.json"
    try:
        status = json.loads(path.read_text())
    except (OSError, ValueError):
        return {}
    if not isinstance(status, dict):
        return {}
    if status.get("state") == "running" and not is_locked(run_dir):
        owner = f"pid {status.get('pid', '?')}" + (f" on {status['host']}" if status.get("host") else "")
        status = {**status, "state": "interrupted",
                  "note": f"the training process ({owner}) ended without recording its end "
                          "(killed or crashed); resume with rs-train resume=RUN_DIR"}
        try:
            write_text_atomic(path, json.dumps(status, indent=2))
        except OSError:
            pass
    return status


@contextmanager
def recording_failures(run_dir: Path) -> Iterator[None]:
    """Whatever escapes the block is written to status.json (interrupted or failed)."""
    try:
        yield
    except KeyboardInterrupt:
        write_status(run_dir, "interrupted")
        raise
    except BaseException as exc:
        write_status(run_dir, "failed", error=f"{type(exc).__name__}: {exc}",
                     traceback=traceback.format_exc())
        raise


def scene_folder(cfg: PipelineConfig) -> Path:
    if not cfg.data:
        raise ConfigError("no scene folder (data=) in the config")
    return Path(cfg.data).expanduser()


def open_run(cfg: PipelineConfig, run_dir: Path | None = None,
             evaluator: Callable[[Pipeline], dict] | None = None,
             prepare_scene: Callable[[SceneData], SceneData] | None = None) -> Run:
    """A new run folder for ``cfg`` (or ``run_dir`` reopened to resume): locked, scene,
    pipeline and trainer built, checkpoint loaded. ``evaluator(pipeline)`` is the trainer's
    periodic evaluation; ``prepare_scene(scene)`` completes the parsed scene before the
    pipeline is built (the workflow adds sparse points there). Input errors surface before any
    folder is made; a folder another process trains in raises RunBusyError before anything in
    it changes, and so does anything that fails before training starts (a resume that does not
    fit leaves config.yml and status.json as they were). Close the run (``with open_run(...) as
    run``) to release the lock."""
    device = resolve_device(cfg.trainer.device)
    if run_dir is None:
        check_output_dir(cfg.trainer.output_dir)
    else:
        check_writable(run_dir, "a resume writes checkpoints, log.jsonl, status.json and config.yml there")
    lock, created = None, None
    if run_dir is not None:  # lock first: nothing in a busy folder may change
        lock = RunLock(run_dir, "rs-train").acquire()
    try:
        seed_everything(cfg.trainer.seed)
        scene = load_scene(cfg, scene_folder(cfg))
        if prepare_scene is not None:
            scene = prepare_scene(scene)
        cfg = with_run_length(cfg, len(scene.train_indices))
        if run_dir is None:
            created = new_run_dir(cfg.trainer.output_dir, scene.name, cfg.method)
            run_dir = created.path
            lock = RunLock(run_dir, "rs-train").acquire()
        run_dir = Path(run_dir)
        previous = read_status(run_dir)  # before it is overwritten: a dead owner shows here
        pipeline = build_pipeline(cfg, scene, device)
        evaluate = None if evaluator is None else (lambda: evaluator(pipeline))
        trainer = Trainer(pipeline, run_dir, evaluate)
        used = trainer.load() if any((run_dir / CHECKPOINTS).glob("step-*.pt")) else None
        # Everything is checked: only now does the folder change.
        remove_partial_writes(run_dir / CHECKPOINTS)
        config_mod.save_yaml(cfg, run_dir / CONFIG_FILE)
        write_status(run_dir, "running")
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
             data: str | Path | None = None) -> tuple[Pipeline, int]:
    """Rebuild a run's pipeline from config.yml and load its latest readable (or given)
    checkpoint. ``data`` replaces the scene folder config.yml names (a moved scene)."""
    run_dir = check_run_folder(Path(run_dir))
    cfg = config_mod.load_yaml(run_dir / CONFIG_FILE)
    if data:
        cfg = dataclasses.replace(cfg, data=str(data))
    dev = resolve_device(device)
    folder = scene_folder(cfg)
    if not folder.exists():
        hint = "pass data=NEW_FOLDER" if not data else "check data="
        raise DataError(f"{folder}: the run's scene folder is not there (moved?); {hint} "
                        f"(config.yml: {run_dir / CONFIG_FILE})")
    pipeline = build_pipeline(cfg, load_scene(cfg, folder), dev)
    ckpts = run_dir / CHECKPOINTS
    if step is not None:
        path = checkpoint_path(ckpts, step)
        if not path.is_file():
            have = ", ".join(str(int(p.stem.split("-")[1])) for p in sorted(ckpts.glob("step-*.pt")))
            raise RainyScapeError(f"{run_dir}: no checkpoint of step {step} (have: {have or 'none'})")
        state = load_checkpoint(path, dev)
    else:
        found = load_newest_valid(ckpts, dev)
        if found is None:
            raise RainyScapeError(f"{run_dir}: no checkpoint found (the run was stopped before its "
                                  f"first one; resume it with rs-train resume={run_dir})")
        path, state = found
    try:
        restore_models(state, pipeline.models())
    except (KeyError, IndexError, TypeError, ValueError, RuntimeError) as exc:
        reason = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise RainyScapeError(f"{path}: does not fit this run's config ({type(exc).__name__}: "
                              f"{reason[:300]})") from None
    for model in pipeline.models().values():
        model.eval()
    return pipeline, int(state["step"])
