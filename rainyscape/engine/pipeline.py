"""Assemble a pipeline from its typed config and scene: the field, the heads, the loss terms
(checked to have the layers they need in every phase they act in) and the post-processes."""

from __future__ import annotations

from dataclasses import dataclass

import torch

from rainyscape import registry
from rainyscape.components import Field, ImageHead, Loss, PostProcess
from rainyscape.config import LossConfig, PipelineConfig
from rainyscape.config.schema import require_typed
from rainyscape.engine.phases import PhaseSchedule
from rainyscape.errors import ConfigError
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


def build_pipeline(config: PipelineConfig, scene: SceneData, device: torch.device) -> Pipeline:
    require_typed(config, "the pipeline")
    field_cls = registry.load("field", config.field.name)
    field: Field = field_cls(config.field.options, scene).to(device)
    heads = {key: registry.load("rain_head", comp.name)(comp.options, scene).to(device)
             for key, comp in config.heads().items()}
    losses = {key: (cfg, registry.load("loss", cfg.name)(cfg.options)) for key, cfg in config.losses.items()}
    check_layers(config, heads, losses)
    field.request(render_extras(config, field, losses))
    for _, term in losses.values():
        term.setup(scene, device)
    post = {k: registry.load("postprocess", p.name)(p.options) for k, p in config.postprocess.items()}
    for key, process in post.items():
        if process.needs_rain and "rain_head" not in heads:
            raise ConfigError(f"postprocess.{key} fuses by the rain head's predicted rain, and this "
                              f"pipeline has no rain head; set rain_head=NAME, or use "
                              f"postprocess.streak-fusion=on (it needs none)")
    return Pipeline(config, scene, field, heads, losses, post, device)


def render_extras(config: PipelineConfig, field: Field, losses: dict[str, tuple[LossConfig, Loss]]) -> set[str]:
    """What the active loss terms read from the field's render beyond its images; a field
    that cannot give one is refused, naming the term."""
    wanted: set[str] = set()
    for key, (cfg, term) in losses.items():
        if not cfg.weight or not any(p in config.phases for p in cfg.phases):
            continue
        missing = [n for n in term.render_extras if n not in field.provides]
        if missing:
            raise ConfigError(f"losses.{key} reads the '{missing[0]}' of each ray from the field's render, "
                              f"and field={config.field.name} does not give it; use a field that does "
                              f"(grid), or drop the term (losses.{key}=none)")
        wanted.update(term.render_extras)
    return wanted


def check_layers(config: PipelineConfig, heads: dict[str, ImageHead],
                 losses: dict[str, tuple[LossConfig, Loss]]) -> None:
    """Every loss term must have, in each phase it acts in, the image layers it needs; a phase
    that trains heads on whole views must have heads, and one that refreshes their render
    cache must train them on whole views."""
    schedule = PhaseSchedule.of(config.phases, config.trainer.max_iters)
    for name, phase in config.phases.items():
        if schedule.length(name) == 0:
            continue
        if phase.head_views and not phase.heads:
            raise ConfigError(f"phases.{name}.head_views={phase.head_views}: the phase has no heads "
                              f"to learn on whole views (set phases.{name}.heads, or head_views=0)")
        if phase.refresh_every and not phase.head_views:
            raise ConfigError(f"phases.{name}.refresh_every={phase.refresh_every}: it refreshes the "
                              f"render cache that heads learn on with head_views, and the phase has "
                              f"none (set phases.{name}.head_views >= 1, or refresh_every=0)")
        if phase.heads and phase.rays and not phase.head_views:
            raise ConfigError(f"phases.{name}.rays={phase.rays}: those rays are fitted against the "
                              f"heads' last whole-view predictions, and the phase makes none "
                              f"(set phases.{name}.head_views >= 1)")
        layers = {heads[h].layer for h in phase.heads}
        for key, (cfg, term) in losses.items():
            missing = [n for n in term.needs if n not in layers] if name in cfg.phases and cfg.weight else []
            if missing:
                raise ConfigError(
                    f"losses.{key} needs the '{missing[0]}' layer in phase '{name}', and no head "
                    f"predicts it there; set rain_head=NAME and phases.{name}.heads, or drop the term "
                    f"(losses.{key}=none)")
