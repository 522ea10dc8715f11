"""Assemble a pipeline from its typed config: scene, field, heads, loss terms, post-processes."""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import torch
from torch import Tensor

from rainyscape import registry
from rainyscape.components import DataParser, Field, ImageHead, Loss, LossContext, PostProcess
from rainyscape.config import LossConfig, PipelineConfig
from rainyscape.config.schema import is_materialized
from rainyscape.engine.phases import PhaseSchedule
from rainyscape.errors import ConfigError, DataError
from rainyscape.scene import SceneData


@dataclass
class Pipeline:
    config: PipelineConfig
    scene: SceneData
    field: Field
    heads: dict[str, ImageHead]  # by config key (e.g. "rain_head")
    losses: dict[str, tuple[LossConfig, Loss]]
    postprocess: dict[str, PostProcess]
    device: torch.device

    @property
    def rain_head(self) -> ImageHead | None:
        return self.heads.get("rain_head")

    def models(self) -> dict[str, torch.nn.Module]:
        """Everything with trainable parameters: the field first, then the heads."""
        return {"field": self.field, **self.heads}

    def loss_terms(self, phase: str) -> dict[str, tuple[LossConfig, Loss]]:
        return {k: v for k, v in self.losses.items() if phase in v[0].phases and v[0].weight != 0}


def resolve_device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        dev = torch.device(name)
    except RuntimeError:
        raise ConfigError(f"trainer.device={name}: not a device (auto, cpu, cuda or cuda:N)") from None
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise ConfigError(f"trainer.device={name}, but CUDA is not available here")
    if dev.type not in ("cpu", "cuda"):
        raise ConfigError(f"trainer.device={name}: only cpu and cuda are supported")
    return dev


def load_scene(config: PipelineConfig, path: Path) -> SceneData:
    """Parse the scene folder ``path`` with the config's dataparser."""
    _require_typed(config)
    if not Path(path).exists():
        raise DataError(f"{path}: no such scene folder (data=)")
    parser_cls = registry.load("dataparser", config.dataparser.name)
    parser: DataParser = parser_cls(config.dataparser.options)
    return parser.parse(Path(path))


def build_pipeline(config: PipelineConfig, scene: SceneData, device: torch.device) -> Pipeline:
    _require_typed(config)
    field_cls = registry.load("field", config.field.name)
    field: Field = field_cls(config.field.options, scene).to(device)
    heads = {key: registry.load("rain_head", comp.name)(comp.options, scene).to(device)
             for key, comp in config.heads().items()}
    losses = {key: (cfg, registry.load("loss", cfg.name)(cfg.options)) for key, cfg in config.losses.items()}
    _check_layers(config, heads, losses)
    for _, term in losses.values():
        term.setup(scene, device)
    post = {k: registry.load("postprocess", p.name)(p.options) for k, p in config.postprocess.items()}
    return Pipeline(config, scene, field, heads, losses, post, device)


def _require_typed(config: PipelineConfig) -> None:
    if not is_materialized(config):
        raise TypeError("the pipeline needs a typed config (from method_config or load_yaml)")


def _check_layers(config: PipelineConfig, heads: dict[str, ImageHead],
                  losses: dict[str, tuple[LossConfig, Loss]]) -> None:
    """Every loss term must have, in each phase it acts in, the image layers it needs."""
    schedule = PhaseSchedule.of(config.phases, config.trainer.max_iters)
    for name, phase in config.phases.items():
        if schedule.length(name) == 0:
            continue
        layers = {heads[h].layer for h in phase.heads}
        for key, (cfg, term) in losses.items():
            missing = [n for n in term.needs if n not in layers] if name in cfg.phases and cfg.weight else []
            if missing:
                raise ConfigError(
                    f"losses.{key} needs the '{missing[0]}' layer in phase '{name}', and no head "
                    f"predicts it there; set rain_head=NAME and phases.{name}.heads, or drop the term "
                    f"(losses.{key}=none)")


def compute_losses(terms: dict[str, tuple[LossConfig, Loss]], ctx: LossContext
                   ) -> tuple[Tensor, dict[str, float]]:
    """Weighted sum of the loss terms; each term may stop gradients into B or a layer."""
    total = torch.zeros((), device=ctx.rendered.device)
    values: dict[str, float] = {}
    for key, (cfg, term) in terms.items():
        c = ctx
        if cfg.detach == "rendered":
            c = replace(ctx, rendered=ctx.rendered.detach())
        elif cfg.detach in ctx.layers:
            c = replace(ctx, layers={**ctx.layers, cfg.detach: ctx.layers[cfg.detach].detach()})
        value = term(c)
        total = total + cfg.weight * value
        values[key] = float(value.detach())
    return total, values
