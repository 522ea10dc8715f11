"""RainyScape on NeRF fields: ``rainyscape-nerf`` (fast grid field) and
``rainyscape-vanilla-nerf`` (the paper's NeRF and schedule).

Each is its plain counterpart (``nerf``, ``vanilla-nerf``: same field, data and iteration
budget, read from it, never copied) plus the rain module: warm-up with the photometric loss
alone, then the joint phase with the rain head, the four rain losses on 64 x 64 patches and
Langevin latent updates, and rain-mask fusion as post-processing. Plain data only: this
module imports no torch.
"""

from __future__ import annotations

import copy

from rainyscape.config import ComponentConfig, LossConfig, MethodSpec, PipelineConfig
from rainyscape.methods.nerf import nerf, vanilla_nerf

# The paper's loss weights (likelihood, reconstruction, tv, agr).
PAPER_WEIGHTS = {"likelihood": 0.1, "reconstruction": 500.0, "tv": 0.5, "agr": 1.0}


def rain_losses(weights: dict[str, float], agr: dict | None = None) -> dict[str, LossConfig]:
    """The photometric warm-up term and the four joint-phase rain terms."""
    return {
        "photometric": LossConfig("photometric", weight=1.0, phases=("warmup",)),
        "likelihood": LossConfig("likelihood", weight=weights["likelihood"]),
        "reconstruction": LossConfig("reconstruction", weight=weights["reconstruction"]),
        "tv": LossConfig("tv", weight=weights["tv"]),
        "agr": LossConfig("agr", weight=weights["agr"], options=dict(agr or {})),
    }


def with_rain_module(base: MethodSpec, name: str, *, weights: dict[str, float],
                     rain_head: dict, warmup_fraction: float, field: dict,
                     agr: dict | None = None, fusion: dict | None = None) -> PipelineConfig:
    """``base``'s config with the rain module added (its field options updated by ``field``)."""
    cfg = copy.deepcopy(base.config)
    cfg.method = name
    cfg.field.options = {**dict(cfg.field.options), **field}
    cfg.rain_head = ComponentConfig("rain-predictor", dict(rain_head))
    cfg.losses = rain_losses(weights, agr)
    cfg.postprocess = {"rain-mask-fusion": ComponentConfig("rain-mask-fusion", dict(fusion or {}))}
    t = cfg.trainer
    t.warmup_fraction = warmup_fraction
    t.joint_patches = 1  # the paper: one 64 x 64 patch (4096 rays) of one view per step
    t.joint_patch_size = 64
    return cfg


rainyscape_nerf = MethodSpec(
    name="rainyscape-nerf",
    description="RainyScape on the fast grid field: rain head + rain losses + Langevin latents (CPU minutes)",
    config=with_rain_module(
        nerf, "rainyscape-nerf",
        weights=PAPER_WEIGHTS,
        rain_head={"lowres_channels": (32, 32, 32, 32), "highres_channels": 16},
        warmup_fraction=0.5,
        field={},
    ),
)

rainyscape_vanilla_nerf = MethodSpec(
    name="rainyscape-vanilla-nerf",
    description="RainyScape as in the paper: NeRF MLP, half the run warm-up, NeRF lr 1e-6 afterwards",
    config=with_rain_module(
        vanilla_nerf, "rainyscape-vanilla-nerf",
        weights=PAPER_WEIGHTS,
        rain_head={},  # the paper-scale predictor (Config defaults)
        warmup_fraction=0.5,
        field={"lr_joint": 1e-6},
    ),
)
