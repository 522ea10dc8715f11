"""The weight-free robust baselines: ``robust-nerf`` (RobustNeRF) and ``robust-3dgs``
(SpotLessSplats' RobustFilter).

Each is its plain counterpart (``nerf``, ``3dgs``) with only what its paper changes, so the
comparison stays fair when the counterpart changes (the field, its options and the step
count are taken from it, never copied). No rain model: the whole run is one phase, ``fit``.
Plain data only: this module imports no torch.

- ``robust-nerf``: RobustNeRF's trimmed least squares (``losses/robust.py``) on the
  counterpart's batch of single rays, each ray's 3 x 3 and patch decisions made on a
  virtual 16 x 16 patch read from a map of the last residuals (``residual_map``). The
  paper's batch of real 16 x 16 patches (64 of them, 16384 rays) stays an option
  (``phases.fit.patches=4 phases.fit.patch_size=16 losses.robust.residual_map=false`` at
  ``nerf``'s 1024 rays); on the grid field a k x k patch trains about as much as k random
  rays, so at equal rays it starved the field (docs/benchmarks.md, "`robust-nerf` on single
  rays").
- ``robust-3dgs``: SpotLessSplats' RobustFilter (``losses/robust_filter.py``, L1 only) and
  its schedule changes to 3DGS: no opacity resets (its reset period is set past the run, as
  SpotLessSplats' 300k of 30k steps; large Gaussians are then not pruned either, as there),
  densification from step 1000 of 30k instead of 500, and the view-dependent colour clamped
  once at step 8002 of 30k (a callback of the loss term).
"""

from __future__ import annotations

import copy

from rainyscape.config import LossConfig, MethodSpec, PipelineConfig
from rainyscape.methods.gaussians import gaussians_3dgs
from rainyscape.methods.nerf import nerf

# SpotLessSplats' changes to the 3DGS schedule (its spotless_trainer.py defaults, 30k steps).
SPOTLESS_FIELD = {"reset_every": 300_000, "refine_start": 1000}


def _photometric_weight(base: MethodSpec) -> float:
    """The weight the counterpart gives its photometric term."""
    weights = [loss.weight for loss in base.config.losses.values() if "fit" in loss.phases]
    return weights[0] if len(weights) == 1 else 1.0


def _plain(base: MethodSpec, name: str) -> PipelineConfig:
    cfg = copy.deepcopy(base.config)
    cfg.method = name
    cfg.rain_head = None
    cfg.postprocess = {}
    return cfg


def _robust_nerf() -> PipelineConfig:
    cfg = _plain(nerf, "robust-nerf")
    cfg.losses = {"robust": LossConfig("robust", weight=_photometric_weight(nerf), phases=("fit",),
                                       options={"residual_map": True})}
    return cfg


def _robust_3dgs() -> PipelineConfig:
    cfg = _plain(gaussians_3dgs, "robust-3dgs")
    cfg.losses = {"robust": LossConfig("robust-filter", weight=_photometric_weight(gaussians_3dgs),
                                       phases=("fit",))}
    cfg.field.options = {**cfg.field.options, **SPOTLESS_FIELD}
    return cfg


robust_nerf = MethodSpec(
    name="robust-nerf",
    description="RobustNeRF on nerf's field: trimmed L2, its patch decisions from a residual map (weight-free robust baseline, no rain model)",
    config=_robust_nerf(),
    gpu=list(nerf.gpu),
)

robust_3dgs = MethodSpec(
    name="robust-3dgs",
    description="SpotLessSplats' RobustFilter on 3dgs: L1 on a running-percentile inlier mask, no opacity resets",
    config=_robust_3dgs(),
    gpu=list(gaussians_3dgs.gpu),
)
