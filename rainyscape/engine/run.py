"""Run folders around a training run: create or reopen one, record its state, restore it.

Run folder contents: config.yml (plain YAML), status.json (running / stopped / finished /
failed / interrupted), log.jsonl (training curves), checkpoints/; evaluation adds
metrics.json, renders/ and report.html.
"""

from __future__ import annotations

import json
import time
import traceback
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterator

from rainyscape import config as config_mod
from rainyscape.config import PipelineConfig
from rainyscape.engine.checkpoint import checkpoint_path, latest_checkpoint, load_checkpoint
from rainyscape.engine.pipeline import Pipeline, build_pipeline, load_scene, resolve_device
from rainyscape.engine.run_dir import new_run_dir
from rainyscape.engine.snapshot import restore_models
from rainyscape.engine.trainer import Trainer, seed_everything
from rainyscape.errors import ConfigError, RainyScapeError


@dataclass
class RunResult:
    run_dir: Path
    metrics: dict


@dataclass
class Run:
    """A run folder with its pipeline and trainer, ready to train (resumed if it was)."""

    run_dir: Path
    pipeline: Pipeline
    trainer: Trainer

    @property
    def finished(self) -> bool:
        return self.trainer.step >= self.pipeline.config.trainer.max_iters


def write_status(run_dir: Path, state: str, **extra) -> None:
    data = {"state": state, "time": time.strftime("%Y-%m-%d %H:%M:%S"), **extra}
    tmp = run_dir / "status.json.tmp"
    tmp.write_text(json.dumps(data, indent=2))
    tmp.replace(run_dir / "status.json")


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
             evaluator: Callable[[Pipeline], dict] | None = None) -> Run:
    """A new run folder for ``cfg`` (or ``run_dir`` reopened to resume): scene, pipeline and
    trainer built, checkpoint loaded. ``evaluator(pipeline)`` is the trainer's periodic
    evaluation. Input errors surface before any folder is made."""
    device = resolve_device(cfg.trainer.device)
    seed_everything(cfg.trainer.seed)
    scene = load_scene(cfg, scene_folder(cfg))
    if run_dir is None:
        run_dir = new_run_dir(cfg.trainer.output_dir, scene.name, cfg.method)
    elif latest_checkpoint(Path(run_dir) / "checkpoints") is None:
        raise RainyScapeError(f"{run_dir}: no checkpoint to resume from")
    run_dir = Path(run_dir)
    config_mod.save_yaml(cfg, run_dir / "config.yml")
    write_status(run_dir, "running")
    with recording_failures(run_dir):
        pipeline = build_pipeline(cfg, scene, device)
        evaluate = None if evaluator is None else (lambda: evaluator(pipeline))
        trainer = Trainer(pipeline, run_dir, evaluate)
        if latest_checkpoint(run_dir / "checkpoints") is not None:
            trainer.load()
    return Run(run_dir, pipeline, trainer)


def load_run(run_dir: Path, device: str = "auto", step: int | None = None) -> tuple[Pipeline, int]:
    """Rebuild a run's pipeline from config.yml and load its latest (or given) checkpoint."""
    run_dir = Path(run_dir)
    if not (run_dir / "config.yml").is_file():
        raise RainyScapeError(f"{run_dir}: not a run folder (no config.yml)")
    cfg = config_mod.load_yaml(run_dir / "config.yml")
    dev = resolve_device(device)
    pipeline = build_pipeline(cfg, load_scene(cfg, scene_folder(cfg)), dev)
    folder = run_dir / "checkpoints"
    ckpt = checkpoint_path(folder, step) if step is not None else latest_checkpoint(folder)
    if ckpt is None or not ckpt.is_file():
        raise RainyScapeError(f"{run_dir}: no checkpoint found")
    state = load_checkpoint(ckpt, dev)
    restore_models(state, pipeline.models())
    for model in pipeline.models().values():
        model.eval()
    return pipeline, int(state["step"])
