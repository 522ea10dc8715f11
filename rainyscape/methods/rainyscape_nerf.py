"""RainyScape on NeRF fields: ``rainyscape-nerf`` (fast grid field) and
``rainyscape-vanilla-nerf`` (the paper's NeRF and schedule).

Each is its plain counterpart (``nerf``, ``vanilla-nerf``: same field, data and iteration
budget, read from it, never copied) plus the rain module: warm-up with the photometric loss
alone, then the joint phase with the rain head, the four rain losses on square patches
and Langevin latent updates, and rain-mask fusion as post-processing. A joint step sees as
many rays as a warm-up step: on a CPU ``nerf``'s 1024 as 16 patches of 4 x 4 and 768 single
rays (the field fits those against the head's last whole-view R), on a GPU the paper's one
64 x 64 patch of 4096. Plain data only: this module imports no torch.
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


def joint_batch(warmup: PhaseConfig, patches: int, rays: int) -> dict:
    """A joint step's batch with the rays of a ``warmup`` step: ``patches`` square patches
    holding what ``rays`` single rays leave (the ``PhaseConfig`` fields it sets)."""
    patch_rays = warmup.patches * warmup.patch_size ** 2 - rays
    return {"patches": patches, "patch_size": square_patch(patch_rays // patches), "rays": rays}


def with_rain_module(base: MethodSpec, name: str, *, weights: dict[str, float],
                     rain_head: dict, warmup_fraction: float, joint_patches: int = 1,
                     joint_rays: int = 0, field_lr_joint: float | None = None,
                     head_views: int = 0, agr: dict | None = None,
                     fusion: dict | None = None) -> PipelineConfig:
    """``base``'s config with the rain module added: its one ``fit`` phase becomes the
    warm-up (same batches) followed by the joint phase, in which the rain head predicts R
    on ``joint_patches`` square patches per step holding the rays of a warm-up step (the
    paper: one patch, 64 x 64 = 4096), less ``joint_rays`` single rays that fit the field to
    the input less the head's last whole-view R (``phases.joint.rays``; needs
    ``head_views``). In the joint phase the field's rates are fixed at ``field_lr_joint``
    (the paper's NeRF: 1e-6) when given, else they go on; the rain head also learns on
    ``head_views`` whole views a step against the field's cached render
    (engine/render_cache.py)."""
    cfg = copy.deepcopy(base.config)
    cfg.method = name
    cfg.rain_head = ComponentConfig("rain-predictor", dict(rain_head))
    fit = cfg.phases["fit"]
    cfg.phases = {
        "warmup": PhaseConfig(end=warmup_fraction, patches=fit.patches, patch_size=fit.patch_size),
        "joint": PhaseConfig(**joint_batch(fit, joint_patches, joint_rays), heads=("rain_head",),
                             field_lr=field_lr_joint, head_views=head_views),
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
        # the joint phase from 35 % of the run (the paper: half; the GPU recipe keeps it): on
        # the cpu set's 2000 steps half left the rain head 1000 steps; 0.35 gained on every
        # scene of the cpu set and on fern (+0.24 / +0.34 and +0.18 / +0.25 dB;
        # docs/benchmarks.md, "The grid recipe at 3dgs's time")
        warmup_fraction=0.35,
        # nerf's 1024 rays as 16 patches of 4 x 4 and 768 single rays, not the paper's one
        # patch: the field fits the dry pixels from rays (patches cost a grid field up to
        # 3 dB), and TV and AGR, which need neighbours (4 x 4 for AGR's 3 x 3 gradients),
        # keep pushing static rain out of B on the patches (docs/rain.md, "Rays and patches
        # in the joint phase")
        joint_patches=16,
        joint_rays=768,
        # the field keeps its rates in the joint phase (not frozen, as the paper's NeRF: this
        # one is still fitting); 0.3x them was worth 0.6 dB only while the warm-up's loss
        # scale left Adam's steps too long after the switch (docs/rain.md, "The warm-up's scale")
        # a step's 1024 rays show the rain head each pixel about once a run: it also learns
        # on one whole view a step against the field's last render there (rain correlation
        # 0.07 -> 0.41 on real fern with heavy rain; docs/rain.md, "The rain head on a ray field")
        head_views=1,
    ),
    # nerf's GPU rays in both phases: the joint ones as one patch (the paper's 64 x 64; the
    # CPU recipe's rays not carried over unmeasured)
    gpu=NERF_GPU + PAPER_RAIN_HEAD_GPU + ["phases.warmup.end=0.5", f"phases.warmup.patches={NERF_GPU_RAYS}",
                                          "phases.joint.patches=1",
                                          f"phases.joint.patch_size={square_patch(NERF_GPU_RAYS)}",
                                          "phases.joint.rays=0"],
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
