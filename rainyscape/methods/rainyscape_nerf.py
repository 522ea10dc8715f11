"""RainyScape on NeRF fields: ``rainyscape-nerf`` (fast grid field) and
``rainyscape-vanilla-nerf`` (the paper's NeRF and schedule).

Each is its plain counterpart (``nerf``, ``vanilla-nerf``: same field, data and iteration
budget, read from it, never copied) plus the rain module: warm-up with the photometric loss
alone, then the joint phase with the rain head, the four rain losses on square patches
holding as many rays as a warm-up step (64 of 4 x 4 for ``nerf``'s 1024 on a CPU, the paper's
one 64 x 64 for 4096 on a GPU) and Langevin latent updates, and rain-mask fusion as
post-processing. Plain data only: this
module imports no torch.
"""

from __future__ import annotations

import copy
import math

from rainyscape.config import ComponentConfig, LossConfig, MethodSpec, PhaseConfig, PipelineConfig
from rainyscape.methods.nerf import NERF_GPU, NERF_GPU_RAYS, VANILLA_GPU, nerf, vanilla_nerf

# The paper's loss weights (likelihood, reconstruction, tv, agr).
PAPER_WEIGHTS = {"likelihood": 0.1, "reconstruction": 500.0, "tv": 0.5, "agr": 1.0}
# The paper's rain head (512/256/128/128 at latent resolution, 64 after PixelShuffle): GPU recipes.
PAPER_RAIN_HEAD_GPU = ["rain_head.lowres_channels=[512,256,128,128]", "rain_head.highres_channels=64"]


def rain_losses(weights: dict[str, float], agr: dict | None = None) -> dict[str, LossConfig]:
    """The photometric warm-up term and the four joint-phase rain terms. The warm-up term
    weighs the field's squared error as the joint phase's reconstruction term does: Adam
    takes the same steps either way, and its second moments then carry over the switch at
    the scale they will meet (at weight 1 the field's gradients jump 500x there, and for
    hundreds of steps its steps were up to 6x its rate: docs/rain.md, "The warm-up's scale")."""
    return {
        "photometric": LossConfig("photometric", weight=weights["reconstruction"], phases=("warmup",)),
        "likelihood": LossConfig("likelihood", weight=weights["likelihood"]),
        "reconstruction": LossConfig("reconstruction", weight=weights["reconstruction"]),
        "tv": LossConfig("tv", weight=weights["tv"]),
        "agr": LossConfig("agr", weight=weights["agr"], options=dict(agr or {})),
    }


def square_patch(rays: int) -> int:
    """The side of the one square patch a joint step sees: as many rays as the base method's
    step (1024 -> 32, 4096 -> 64), so that the rain method and its base train on equal budgets."""
    side = math.isqrt(rays)
    if side * side != rays:
        raise ValueError(f"{rays} rays per step make no square patch")
    return side


def with_rain_module(base: MethodSpec, name: str, *, weights: dict[str, float],
                     rain_head: dict, warmup_fraction: float, joint_patches: int = 1,
                     field_lr_joint: float | None = None,
                     head_views: int = 0, agr: dict | None = None,
                     fusion: dict | None = None) -> PipelineConfig:
    """``base``'s config with the rain module added: its one ``fit`` phase becomes the
    warm-up (same batches) followed by the joint phase, in which the rain head predicts R
    on ``joint_patches`` square patches per step holding the rays of a warm-up step (the
    paper: one patch, 64 x 64 = 4096). In the joint phase the field's rates are fixed at
    ``field_lr_joint`` (the paper's NeRF: 1e-6) when given, else they go on; the rain head
    also learns on ``head_views`` whole views a step against the field's cached render
    (engine/render_cache.py)."""
    cfg = copy.deepcopy(base.config)
    cfg.method = name
    cfg.rain_head = ComponentConfig("rain-predictor", dict(rain_head))
    fit = cfg.phases["fit"]
    cfg.phases = {
        "warmup": PhaseConfig(end=warmup_fraction, patches=fit.patches, patch_size=fit.patch_size),
        "joint": PhaseConfig(patches=joint_patches,
                             patch_size=square_patch(fit.patches * fit.patch_size ** 2 // joint_patches),
                             heads=("rain_head",), field_lr=field_lr_joint, head_views=head_views),
    }
    cfg.losses = rain_losses(weights, agr)
    cfg.postprocess = {"rain-mask-fusion": ComponentConfig("rain-mask-fusion", dict(fusion or {})),
                       "streak-fusion": ComponentConfig("streak-fusion", {})}
    return cfg


rainyscape_nerf = MethodSpec(
    name="rainyscape-nerf",
    description="RainyScape on the fast grid field: rain head + rain losses + Langevin latents (CPU minutes)",
    config=with_rain_module(
        nerf, "rainyscape-nerf",
        weights=PAPER_WEIGHTS,
        rain_head={"lowres_channels": (32, 32, 32, 32), "highres_channels": 16},
        warmup_fraction=0.5,
        # nerf's 1024 rays as 64 patches of 4 x 4, not the paper's one patch: the field fits
        # the dry pixels better from a batch as spread as the rain losses allow (AGR's 3 x 3
        # gradients need 4 x 4); the rain head sees whole views below (docs/rain.md, "The
        # warm-up's scale")
        joint_patches=64,
        # the field keeps its rates in the joint phase (not frozen, as the paper's NeRF: this
        # one is still fitting); 0.3x them was worth 0.6 dB only while the warm-up's loss
        # scale left Adam's steps too long after the switch (docs/rain.md, "The warm-up's scale")
        # a step's 1024 rays show the rain head each pixel about once a run: it also learns
        # on one whole view a step against the field's last render there (rain correlation
        # 0.07 -> 0.41 on real fern with heavy rain; docs/rain.md, "The rain head on a ray field")
        head_views=1,
    ),
    # nerf's GPU rays in both phases: the joint ones as one patch (the paper's 64 x 64)
    gpu=NERF_GPU + PAPER_RAIN_HEAD_GPU + [f"phases.warmup.patches={NERF_GPU_RAYS}", "phases.joint.patches=1",
                                          f"phases.joint.patch_size={square_patch(NERF_GPU_RAYS)}"],
)

rainyscape_vanilla_nerf = MethodSpec(
    name="rainyscape-vanilla-nerf",
    description="RainyScape as in the paper: NeRF MLP, half the run warm-up, NeRF lr 1e-6 afterwards",
    config=with_rain_module(
        vanilla_nerf, "rainyscape-vanilla-nerf",
        weights=PAPER_WEIGHTS,
        rain_head={},  # the paper-scale predictor (Config defaults)
        warmup_fraction=0.5,
        field_lr_joint=1e-6,  # the paper: NeRF nearly frozen after the warm-up
    ),
    gpu=VANILLA_GPU,
)
