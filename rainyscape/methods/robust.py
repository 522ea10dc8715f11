"""Robust-loss baselines: ``robust-nerf`` and ``robust-3dgs``.

Each is its plain counterpart (``nerf``, ``3dgs``) with the photometric loss replaced by
the RobustNeRF-style trimmed loss (:mod:`rainyscape.losses.robust`) and no rain head:
the whole run is one photometric phase, ``fit``. Field options
and the schedule are taken from the counterpart, never copied, so the comparison stays fair
when those change. Plain data only: this module imports no torch.
"""

from __future__ import annotations

import copy

from rainyscape.config import LossConfig, MethodSpec, PipelineConfig
from rainyscape.methods.gaussians import gaussians_3dgs
from rainyscape.methods.nerf import NERF_GPU, NERF_GPU_RAYS, nerf

# The robust decisions (smoothing, tiles) need neighbouring pixels: train on patches at least
# this wide, keeping the counterpart's rays per step.
MIN_PATCH = 16


def _patched_phase(base: PipelineConfig) -> None:
    """Whole images stay whole; smaller patches (or single rays) grow to MIN_PATCH squares."""
    fit = base.phases["fit"]
    if fit.patch_size == 0 or fit.patch_size >= MIN_PATCH:
        return
    rays = fit.patches * fit.patch_size ** 2
    fit.patch_size = MIN_PATCH
    fit.patches = max(1, round(rays / MIN_PATCH ** 2))


def _robust_config(base: MethodSpec, name: str, residual: str, ssim_weight: float,
                   weight: float) -> PipelineConfig:
    cfg = copy.deepcopy(base.config)
    cfg.method = name
    cfg.rain_head = None
    cfg.postprocess = {}
    cfg.losses = {"robust": LossConfig("robust", weight=weight, phases=("fit",),
                                       options={"residual": residual, "ssim_weight": ssim_weight})}
    _patched_phase(cfg)
    return cfg


def _photometric_weight(base: MethodSpec) -> float:
    """The weight the counterpart gives its photometric term."""
    weights = [loss.weight for loss in base.config.losses.values() if "fit" in loss.phases]
    return weights[0] if len(weights) == 1 else 1.0


def _dssim_fraction(base: MethodSpec) -> float:
    """The D-SSIM share of the counterpart's loss (3DGS: 0.2), read from its recipe options."""
    for loss in base.config.losses.values():
        if "fit" not in loss.phases:
            continue
        opts = loss.options  # a recipe: plain dicts
        if "ssim_weight" in opts:  # l1-ssim's D-SSIM share
            return float(opts["ssim_weight"])
    return 0.2  # the 3DGS paper's lambda when the counterpart does not say


robust_nerf = MethodSpec(
    name="robust-nerf",
    description="nerf with a RobustNeRF-style trimmed loss (robust baseline, no rain model)",
    config=_robust_config(nerf, "robust-nerf", "l2", 0.0, _photometric_weight(nerf)),
    gpu=NERF_GPU + [f"phases.fit.patches={NERF_GPU_RAYS // MIN_PATCH ** 2}"],  # nerf's rays in patches
)

robust_3dgs = MethodSpec(
    name="robust-3dgs",
    description="3dgs with a RobustNeRF-style trimmed L1 + D-SSIM loss (robust baseline)",
    config=_robust_config(gaussians_3dgs, "robust-3dgs", "l1", _dssim_fraction(gaussians_3dgs),
                          _photometric_weight(gaussians_3dgs)),
    gpu=list(gaussians_3dgs.gpu),
)
