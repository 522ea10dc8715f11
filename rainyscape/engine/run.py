"""A whole run: resolve the scene, build the pipeline, train, evaluate, write the run folder.

Run folder contents: config.yml (plain YAML), status.json (running / finished / failed /
interrupted), log.jsonl (training curves), checkpoints/, metrics.json, renders/.
"""

from __future__ import annotations

import json
import time
import traceback
from dataclasses import dataclass
from pathlib import Path

from rainyscape import config as config_mod
from rainyscape.config import PipelineConfig
from rainyscape.engine.checkpoint import latest_checkpoint
from rainyscape.engine.pipeline import Pipeline, build_pipeline, load_scene, resolve_device
from rainyscape.engine.run_dir import new_run_dir
from rainyscape.errors import RainyScapeError


@dataclass
class RunResult:
    run_dir: Path
    metrics: dict


def write_status(run_dir: Path, state: str, **extra) -> None:
    data = {"state": state, "time": time.strftime("%Y-%m-%d %H:%M:%S"), **extra}
    tmp = run_dir / "status.json.tmp"
    tmp.write_text(json.dumps(data, indent=2))
    tmp.replace(run_dir / "status.json")


def train_run(cfg: PipelineConfig, run_dir: Path | None = None) -> RunResult:
    """Train ``cfg`` in a new run folder, or resume the run in ``run_dir``."""
    from rainyscape.engine.trainer import Trainer, seed_everything

    cfg = config_mod.materialize(cfg)
    device = resolve_device(cfg.trainer.device)
    seed_everything(cfg.trainer.seed)
    scene = load_scene(cfg)  # input errors surface before any folder is made
    if run_dir is None:
        run_dir = new_run_dir(cfg.trainer.output_dir, scene.name, cfg.method)
    else:
        if latest_checkpoint(Path(run_dir) / "checkpoints") is None:
            raise RainyScapeError(f"{run_dir}: no checkpoint to resume from")
    config_mod.save_yaml(cfg, run_dir / "config.yml")
    write_status(run_dir, "running")
    try:
        pipeline = build_pipeline(cfg, scene, device)
        trainer = Trainer(pipeline, run_dir)
        if latest_checkpoint(run_dir / "checkpoints") is not None:
            trainer.load()
        trainer.train()
        metrics = {}
        if trainer.step >= cfg.trainer.max_iters:
            from rainyscape.eval.evaluate import evaluate_pipeline, write_metrics

            metrics = evaluate_pipeline(pipeline, run_dir)
            write_status(run_dir, "finished", step=trainer.step)  # before the report shows it
            write_metrics(run_dir, metrics)
        else:
            write_status(run_dir, "stopped", step=trainer.step)
    except KeyboardInterrupt:
        write_status(run_dir, "interrupted")
        raise
    except BaseException as exc:
        write_status(run_dir, "failed", error=f"{type(exc).__name__}: {exc}",
                     traceback=traceback.format_exc())
        raise
    return RunResult(run_dir, metrics)


def load_run(run_dir: Path, device: str = "auto", step: int | None = None) -> tuple[Pipeline, int]:
    """Rebuild a run's pipeline from config.yml and load its latest (or given) checkpoint."""
    from rainyscape.engine.checkpoint import checkpoint_path, load_checkpoint

    run_dir = Path(run_dir)
    if not (run_dir / "config.yml").is_file():
        raise RainyScapeError(f"{run_dir}: not a run folder (no config.yml)")
    cfg = config_mod.load_yaml(run_dir / "config.yml")
    dev = resolve_device(device)
    scene = load_scene(cfg)
    pipeline = build_pipeline(cfg, scene, dev)
    ckpt = checkpoint_path(run_dir / "checkpoints", step) if step is not None else latest_checkpoint(run_dir / "checkpoints")
    if ckpt is None or not ckpt.is_file():
        raise RainyScapeError(f"{run_dir}: no checkpoint found")
    state = load_checkpoint(ckpt, dev)
    pipeline.field.load_state_dict(state["field"])
    if pipeline.rain_head is not None and state.get("rain_head") is not None:
        pipeline.rain_head.load_state_dict(state["rain_head"])
    pipeline.field.eval()
    if pipeline.rain_head is not None:
        pipeline.rain_head.eval()
    return pipeline, int(state["step"])
