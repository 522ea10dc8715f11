"""Where a late step of a ray field's training goes: render, backward and optimiser, and the
step time against the rays a step.

    OMP_NUM_THREADS=1 python benchmarks/grid_step_split.py --data SCENE [--at STEP] [--steps 40] \
        [--rays 512,1024,2048] [key=value ...]

Trains ``--method`` (default ``nerf``) on the clean views of SCENE (as ``fields_curve.py``)
to step ``--at`` (by default 0.82 of the run: past the last growth, on the final lattice), then times ``--steps`` steps
split into their parts, and the same number of the trainer's whole steps at each ray count
of ``--rays``.
Wall times in ms, medians for the whole steps. No profiler: torch's profiler charged a
fresh gradient's page faults to ``fill_`` at several times their cost in a whole run
(docs/benchmarks.md, "The grid field on an AMD EPYC").
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from fields import build, timed_steps  # noqa: E402  (benchmarks/fields.py)
from fields_curve import scene_overrides  # noqa: E402


def split_step(trainer, rays: int) -> dict[str, float]:
    """One step of ``rays`` random rays against the photometric loss, timed in parts (s)."""
    t = [time.perf_counter()]
    view_ids, window, target = trainer._sample(rays, 1)
    out = trainer._render(view_ids, window)
    t.append(time.perf_counter())
    loss = (out.rgb - target).square().mean()
    for opt in trainer.optimizers.values():
        opt.zero_grad(set_to_none=True)
    loss.backward()
    t.append(time.perf_counter())
    for opt in trainer.optimizers.values():
        opt.step()
    t.append(time.perf_counter())
    return {"render": t[1] - t[0], "backward": t[2] - t[1], "optimiser": t[3] - t[2]}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", required=True)
    p.add_argument("--method", default="nerf")
    p.add_argument("--at", type=int, default=0, help="step to time from (0: 0.82 of the run)")
    p.add_argument("--steps", type=int, default=40)
    p.add_argument("--rays", default="512,1024,2048")
    p.add_argument("--out", default="/tmp/grid_step_split")
    p.add_argument("overrides", nargs="*")
    args = p.parse_args(argv)
    overrides = scene_overrides(args.data) + ["trainer.progress=false", "trainer.eval_every=0",
                                              "trainer.checkpoint_every=0", *args.overrides]
    cfg, trainer = build(args.method, overrides, Path(args.out))
    args.at = args.at or int(0.82 * cfg.trainer.max_iters)
    while trainer.step < args.at:
        trainer.train_step()
    phase = trainer.phases.at(trainer.step)[0]
    rays = trainer.batch_sizes[phase]
    parts = [split_step(trainer, rays) for _ in range(args.steps)]
    result = {"data": args.data, "at": args.at, "threads": torch.get_num_threads(), "rays": rays,
              "split_ms": {k: round(1000 * statistics.median(p_[k] for p_ in parts), 1) for k in parts[0]},
              "stats": trainer.pipeline.field.stats(), "step_ms_by_rays": {}}
    for count in (int(r) for r in args.rays.split(",")):
        trainer.batch_sizes[phase] = count  # the trainer's own steps, callbacks included
        result["step_ms_by_rays"][count] = round(1000 * statistics.median(timed_steps(trainer, args.steps)), 1)
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
