"""3D Gaussian Splatting methods: ``3dgs`` and ``rainyscape-3dgs`` (the paper's Section V).

- ``3dgs``: the Gaussian field fitted to the rainy images with 3DGS's loss (0.8 L1 +
  0.2 D-SSIM) for the whole run: the paper's "3DGS" row.
- ``rainyscape-3dgs``: the same field and run, warm-up with that loss for the paper's
  4k of 30k steps, then the rain module (rain head, Langevin latents, the four rain losses,
  rain-mask fusion) with the authors' loss split: the Gaussians get 0.8 [L1(B + R, I) +
  L1(B, I)] + 0.2 (1 - SSIM(B + R, I)) with R detached, the rain generator gets the rain
  losses with B detached. TV acts on B (in the authors' code it was computed on a detached
  tensor and did nothing; the paper's loss has it).

The densification schedule and the position learning-rate decay are the 3DGS paper's,
scaled to ``trainer.max_iters``. Plain data only: this module imports no torch.
"""

from __future__ import annotations

import copy

from rainyscape.config import (ComponentConfig, LossConfig, MethodSpec, PhaseConfig, PipelineConfig,
                               TrainerConfig)
from rainyscape.methods.rainyscape_nerf import PAPER_RAIN_HEAD_GPU, PAPER_WEIGHTS

# CPU run length: 100 steps per training view, from 1500 to 3000 steps (a 17-view capture
# trains 1700 steps, a 30-view one or larger 3000: about 10 minutes on 2 cores at 240 px,
# docs/benchmarks.md "Fitting real captures"); the paper's is 30k (profile=gpu).
GS_ITERS, GS_ITERS_PER_VIEW, GS_MIN_ITERS = 3000, 100, 1500
PAPER_WARMUP = 4000 / 30000  # the paper's warm-up: 4k of 30k steps
# A smaller rain head than the paper's (same layout), as rainyscape-nerf uses on a CPU.
CPU_RAIN_HEAD = {"lowres_channels": (32, 32, 32, 32), "highres_channels": 16}
# CPU budget (docs/benchmarks.md, "Fitting real captures"): at most 50k Gaussians, and one
# per 5 training pixels on small scenes; refinements at least 50 steps apart in short runs;
# 20k points filled in at the depth of the nearest SfM points (small views give few).
CPU_GAUSSIANS = {"max_gaussians": 50_000, "pixels_per_gaussian": 5, "min_refine_every": 50, "init_fill": 20_000}
# The GPU recipe: the 3DGS paper's run, its schedule unscaled (densify from 500 to 15k every
# 100, resets every 3k), no Gaussian cap. Cut short, the refinements stay 100 steps apart (at
# 17, fern grew to 938k Gaussians in 2800 steps: docs/benchmarks.md, "The GPU recipes on an H200").
GS_GPU = ["trainer.max_iters=30000", "trainer.iters_per_view=0", "field.init_fill=0", "field.max_gaussians=0", "field.pixels_per_gaussian=0",
          "field.min_refine_every=100", "trainer.eval_every=5000", "trainer.checkpoint_every=5000"]

gaussians_3dgs = MethodSpec(
    name="3dgs",
    description="3D Gaussian Splatting fitted to the (rainy) images, 0.8 L1 + 0.2 D-SSIM (no rain model)",
    config=PipelineConfig(
        method="3dgs",
        dataparser=ComponentConfig("auto"),
        field=ComponentConfig("gaussians", dict(CPU_GAUSSIANS)),
        phases={"fit": PhaseConfig(patches=1, patch_size=0)},  # one whole view per step, as 3DGS
        losses={"photometric": LossConfig("l1-ssim", weight=1.0, phases=("fit",),
                                          options={"ssim_weight": 0.2})},
        trainer=TrainerConfig(
            max_iters=GS_ITERS,
            iters_per_view=GS_ITERS_PER_VIEW,
            min_iters=GS_MIN_ITERS,
            eval_every=500,
            checkpoint_every=1000,
        ),
    ),
    gpu=GS_GPU,
)


def _rainyscape_3dgs() -> PipelineConfig:
    cfg = copy.deepcopy(gaussians_3dgs.config)
    cfg.method = "rainyscape-3dgs"
    cfg.rain_head = ComponentConfig("rain-predictor", {**CPU_RAIN_HEAD, "latent_patch_size": 64})
    w = PAPER_WEIGHTS
    cfg.losses = {
        "photometric": LossConfig("l1-ssim", weight=1.0, phases=("warmup",),
                                  options={"ssim_weight": 0.2}),
        "gaussians": LossConfig("l1-ssim", weight=1.0, phases=("joint",), detach="rain",
                                options={"ssim_weight": 0.2, "with_rain": True, "render_l1": True}),
        "likelihood": LossConfig("likelihood", weight=w["likelihood"], detach="rendered"),
        "reconstruction": LossConfig("reconstruction", weight=w["reconstruction"], detach="rendered"),
        "tv": LossConfig("tv", weight=w["tv"]),
        "agr": LossConfig("agr", weight=w["agr"], detach="rendered"),
    }
    cfg.postprocess = {"rain-mask-fusion": ComponentConfig("rain-mask-fusion", {}),
                       "streak-fusion": ComponentConfig("streak-fusion", {})}
    # One whole view per joint step, as in the warm-up and `3dgs` (a 64 x 64 patch per step
    # left the Gaussians 2.5 dB behind `3dgs`); the latent updates use a 64 x 64 crop of it.
    cfg.phases = {"warmup": PhaseConfig(end=PAPER_WARMUP, patches=1, patch_size=0),
                  "joint": PhaseConfig(patches=1, patch_size=0, heads=("rain_head",))}
    return cfg


rainyscape_3dgs = MethodSpec(
    name="rainyscape-3dgs",
    description="RainyScape on 3D Gaussian Splatting: 3DGS warm-up, then the rain module (authors' loss split)",
    config=_rainyscape_3dgs(),
    gpu=GS_GPU + PAPER_RAIN_HEAD_GPU,
)
