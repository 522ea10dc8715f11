"""Plain NeRF baselines (no rain model): the field fits the rainy images with a photometric loss.

- ``nerf``: the fast grid field, a schedule that finishes in minutes on a CPU.
- ``vanilla-nerf``: the paper's NeRF (nerf-pytorch's field and schedule; the paper's "NeRF" row).

The whole run is one photometric phase, ``fit``. Plain data only: this module imports no
torch.
"""

from __future__ import annotations

from rainyscape.config import (ComponentConfig, LossConfig, MethodSpec, PhaseConfig, PipelineConfig,
                               TrainerConfig)


def _photometric() -> dict[str, LossConfig]:
    return {"photometric": LossConfig("photometric", weight=1.0, phases=("fit",))}


# The run: about 7.5 rays a training pixel (1024 a step), from 2000 to 3000 steps; cheap coarse
# steps first (the field's growth sits at 10-80 % of them). The cpu set's 16 views of 128 px
# get 2000, within `3dgs`'s CPU time (93 s a scene against its 113; 3000 fitted 1.5 dB more
# in 1.5x that); real captures at about 240 px get 3000, `3dgs`'s time on fern (202 s
# against 198) (docs/benchmarks.md, "The grid recipe at 3dgs's time")
NERF_ITERS, NERF_MIN_ITERS, NERF_ITERS_PER_MPIXEL = 3000, 2000, 7500
# The GPU recipe of the fast field: 4x the rays, 5x the steps and a finer final lattice
# (1024^3 over the contracted cube, samples every 2 of its voxels: texels and samples twice
# as fine as the CPU recipe's, for 2-4x larger images). Reasoned from the CPU measurements
# (the field fits its images in about 3k CPU steps at 128 to 250 px); not yet timed on a GPU
# (docs/profiles.md). NERF_GPU holds what every method on this field shares; each method
# spreads NERF_GPU_RAYS over its own phases and batches.
NERF_GPU_RAYS = 4096
NERF_GPU = ["trainer.max_iters=15000", "trainer.iters_per_mpixel=0", "field.resolution_final=1024",
            "trainer.eval_every=2500", "trainer.checkpoint_every=2500"]

nerf = MethodSpec(
    name="nerf",
    description="fast grid field fitted to the (rainy) images; minutes on a CPU (no rain model)",
    config=PipelineConfig(
        method="nerf",
        dataparser=ComponentConfig("auto"),
        field=ComponentConfig("grid", {"lr_decay_steps": 0}),  # the rates halve over the run
        # random rays from all training views: more, cheaper steps on a CPU
        phases={"fit": PhaseConfig(patches=1024, patch_size=1)},
        losses=_photometric(),
        trainer=TrainerConfig(
            max_iters=NERF_ITERS,
            min_iters=NERF_MIN_ITERS,
            iters_per_mpixel=NERF_ITERS_PER_MPIXEL,
            eval_every=250,
            checkpoint_every=500,
        ),
    ),
    gpu=NERF_GPU + [f"phases.fit.patches={NERF_GPU_RAYS}"],
)

VANILLA_ITERS = 200_000  # nerf-pytorch's default run
VANILLA_GPU = ["trainer.max_iters=18000", "trainer.eval_every=3000", "trainer.checkpoint_every=3000"]  # the paper's

vanilla_nerf = MethodSpec(
    name="vanilla-nerf",
    description="the paper's NeRF: 8x256 MLP, 64+64 samples, 4096 random rays, nerf-pytorch schedule",
    config=PipelineConfig(
        method="vanilla-nerf",
        dataparser=ComponentConfig("auto"),
        field=ComponentConfig("nerf-mlp", {}),
        phases={"fit": PhaseConfig(patches=4096, patch_size=1)},  # nerf-pytorch: 4096 random rays
        losses=_photometric(),
        trainer=TrainerConfig(
            max_iters=VANILLA_ITERS,
            eval_every=5000,
            checkpoint_every=10_000,
        ),
    ),
    gpu=VANILLA_GPU,
)
