"""Assemble a pipeline from its config: scene, field, rain head, loss terms, post-processes."""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import torch
from torch import Tensor

from rainyscape import registry
from rainyscape.components import (DataParser, Field, Loss, LossContext, PostProcess,
                                   RainHead)
from rainyscape.config import LossConfig, PipelineConfig, materialize
from rainyscape.errors import ConfigError, DataError
from rainyscape.scene import SceneData


@dataclass
class Pipeline:
    config: PipelineConfig
    scene: SceneData
    field: Field
    rain_head: RainHead | None
    losses: dict[str, tuple[LossConfig, Loss]]
    postprocess: dict[str, PostProcess]
    device: torch.device

    def loss_terms(self, phase: str) -> dict[str, tuple[LossConfig, Loss]]:
        return {k: v for k, v in self.losses.items() if phase in v[0].phases and v[0].weight != 0}


def resolve_device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    dev = torch.device(name)
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise ConfigError(f"trainer.device={name}, but CUDA is not available here")
    return dev


def resolve_data_path(config: PipelineConfig) -> Path:
    """The scene folder: ``data=`` or, when empty, the embedded demo scene (made once, cached)."""
    if config.data:
        path = Path(config.data).expanduser()
        if not path.exists():
            raise DataError(f"{path}: no such scene folder (data=)")
        return path
    from rainyscape.synth.demo import ensure_demo_scene

    return ensure_demo_scene()


def load_scene(config: PipelineConfig) -> SceneData:
    config = materialize(config)
    parser_cls = registry.load("dataparser", config.dataparser.name)
    parser: DataParser = parser_cls(config.dataparser.options)
    return parser.parse(resolve_data_path(config))


def build_pipeline(config: PipelineConfig, scene: SceneData, device: torch.device) -> Pipeline:
    config = materialize(config)
    field_cls = registry.load("field", config.field.name)
    field: Field = field_cls(config.field.options, scene).to(device)
    rain_head = None
    if config.rain_head is not None:
        head_cls = registry.load("rain_head", config.rain_head.name)
        rain_head = head_cls(config.rain_head.options, scene).to(device)
    losses = {}
    for key, loss_cfg in config.losses.items():
        losses[key] = (loss_cfg, registry.load("loss", loss_cfg.name)(loss_cfg.options))
    if rain_head is None:
        needs_rain = [k for k, (c, _) in losses.items() if "joint" in c.phases and c.weight != 0
                      and config.trainer.warmup_fraction < 1.0]
        if needs_rain:
            raise ConfigError(
                f"losses {', '.join(needs_rain)} run in the joint phase, which needs a rain head; "
                "set rain_head=NAME or trainer.warmup_fraction=1")
    post = {k: registry.load("postprocess", p.name)(p.options) for k, p in config.postprocess.items()}
    return Pipeline(config, scene, field, rain_head, losses, post, device)


def compute_losses(terms: dict[str, tuple[LossConfig, Loss]], ctx: LossContext
                   ) -> tuple[Tensor, dict[str, float]]:
    """Weighted sum of the loss terms; each term may stop gradients into B or R."""
    total = torch.zeros((), device=ctx.rendered.device)
    values: dict[str, float] = {}
    for key, (cfg, term) in terms.items():
        c = ctx
        if cfg.detach == "rendered":
            c = replace(ctx, rendered=ctx.rendered.detach())
        elif cfg.detach == "rain" and ctx.rain is not None:
            c = replace(ctx, rain=ctx.rain.detach())
        value = term(c)
        total = total + cfg.weight * value
        values[key] = float(value.detach())
    return total, values
