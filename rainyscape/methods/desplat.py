"""``desplat``: DeSplat (Wang et al., CVPR 2025) on the 3DGS field, a weight-free baseline.

``3dgs`` (its field, options, schedule and batch, taken from it) plus per-view distractor
Gaussians: a head (``distractor-gaussians``, in the pipeline's head slot) that renders each
training view's own Gaussians into a (colour, alpha) layer laid over the scene's render, and
DeSplat's loss on that composite (``losses/desplat.py``). Evaluation renders the field alone:
the static scene. No rain model. Plain data only: this module imports no torch.
"""

from __future__ import annotations

import copy

from rainyscape.config import ComponentConfig, LossConfig, MethodSpec, PipelineConfig
from rainyscape.methods.gaussians import gaussians_3dgs


def _desplat() -> PipelineConfig:
    cfg = copy.deepcopy(gaussians_3dgs.config)
    cfg.method = "desplat"
    cfg.rain_head = ComponentConfig("distractor-gaussians", {})
    cfg.postprocess = {}
    cfg.losses = {"desplat": LossConfig("desplat", weight=1.0, phases=tuple(cfg.phases))}
    for phase in cfg.phases.values():
        phase.heads = ("rain_head",)
    return cfg


desplat = MethodSpec(
    name="desplat",
    description="DeSplat on 3dgs: per-view distractor Gaussians laid over the render; the static scene is evaluated",
    config=_desplat(),
    gpu=list(gaussians_3dgs.gpu),
)
