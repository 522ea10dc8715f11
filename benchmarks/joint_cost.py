"""What the joint phase costs: a plain step against a rain-method joint step, in one process.

    python benchmarks/joint_cost.py [--pairs 3dgs:rainyscape-3dgs,nerf:rainyscape-nerf]
                                    [--data DIR] [--repeats 10] [--warm 30] [--profile gpu]
                                    [key=value ...]

For each pair (plain method, rain method) both pipelines are built on the same scene (the
rainy images of --data; default the embedded demo scene), each trained --warm steps in its
own phase (both trainers are placed at the first step of the rain method's last phase, the
joint one, so that step-driven schedules such as the SH degree or the grid resolution put both
fields in the same state), then their steps are timed alternately, --repeats
times each, so both see the same load. Reported: median step time of each, the ratio,
and the rain method's step broken down by where the time goes:

- ``render``: the field's forward (``field.render``);
- ``head``: the rain head's forward for the step's window;
- ``losses``: the loss terms' forward (the phase's ``compute_losses``);
- ``backward``: the step's ``backward()`` (field, head and losses);
- ``optimizers``: every Adam step;
- ``latents``: the Langevin latent updates (each a head forward + the energy + its gradient);
- ``callbacks``: the field's callbacks (densification, grid growth, occupancy);
- ``other``: the rest (batch sampling, logging numbers).

Times are wall clock on CUDA (every timed section synchronised, so the breakdown adds up)
and this process's CPU time on a CPU (``time.process_time``: on a shared, loaded machine
wall time mostly measures the other jobs; with one thread CPU time is the step's cost).
Also reported: the aten operators each step dispatches, in all and per section (a GPU
launches at least one kernel per operator, so a joint step with many small operators is
launch-bound there however fast the device).
Extra key=value overrides go to both methods of a pair.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from collections import defaultdict
from contextlib import contextmanager
from pathlib import Path

import torch
from torch.utils._python_dispatch import TorchDispatchMode

sys.path.insert(0, str(Path(__file__).parent))
from fields import build  # noqa: E402

SECTIONS = ("render", "head", "losses", "backward", "optimizers", "latents", "callbacks", "other")


# Operators that hand a value to the host: on a GPU each waits for every kernel queued before it.
READS = {"_local_scalar_dense", "is_nonzero", "equal"}


class OpCounter(TorchDispatchMode):
    """Counts the aten operators dispatched, forward and backward. On a GPU each is at least
    one kernel launch and a trip through Python and the dispatcher, so a step's count is its
    launch-bound cost, whatever the device it is counted on. ``reads`` counts those that hand
    a value to the host (``float(t)``, ``t.item()``, ``if t:``); a lower bound: ``tolist()``
    and ``cpu()`` dispatch nothing on a CPU tensor, and a GPU waits for them too."""

    def __init__(self):
        super().__init__()
        self.count = 0
        self.reads = 0

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        self.count += 1
        self.reads += func.overloadpacket.__name__ in READS
        return func(*args, **(kwargs or {}))


class Timer:
    """Accumulates wall time (or any other ``clock``, such as an operator count) per section
    of one step (nested sections are not double counted: only the outermost open section is
    charged)."""

    def __init__(self, device: torch.device, clock_fn=None):
        self.sync = torch.cuda.synchronize if device.type == "cuda" and clock_fn is None else (lambda: None)
        self.clock = clock_fn or clock(device)
        self.totals: dict[str, float] = defaultdict(float)
        self.depth = 0

    @contextmanager
    def section(self, name: str):
        if self.depth:
            yield
            return
        self.depth += 1
        self.sync()
        t0 = self.clock()
        try:
            yield
        finally:
            self.sync()
            self.totals[name] += self.clock() - t0
            self.depth -= 1

    def wrap(self, obj, attr: str, name: str) -> None:
        original = getattr(obj, attr)

        def timed(*args, **kwargs):
            with self.section(name):
                return original(*args, **kwargs)

        setattr(obj, attr, timed)


def clock(device: torch.device):
    """Wall clock on CUDA, this process's CPU time on a CPU."""
    return time.perf_counter if device.type == "cuda" else time.process_time


def instrument(trainer, timer: Timer) -> None:
    """Route the trainer's work through ``timer`` (instance attributes only: the classes and
    other trainers are untouched, except ``compute_losses`` and ``Tensor.backward``, which
    are patched while a step of this trainer runs, see :func:`timed_step`)."""
    p = trainer.pipeline
    timer.wrap(p.field, "render", "render")
    for head in p.heads.values():
        timer.wrap(head, "forward", "head")
        if hasattr(head, "update_latents"):
            timer.wrap(head, "update_latents", "latents")
    for opt in trainer.optimizers.values():
        timer.wrap(opt, "step", "optimizers")
    for cb in trainer.callbacks:
        for hook in ("before_step", "after_backward", "after_step"):
            timer.wrap(cb, hook, "callbacks")


def timed_step(trainer, timer: Timer | None) -> float:
    """One training step; with ``timer``, its sections are charged to it."""
    import rainyscape.engine.trainer as trainer_module

    sync = torch.cuda.synchronize if trainer.device.type == "cuda" else (lambda: None)
    now = timer.clock if timer is not None else clock(trainer.device)
    if timer is None:
        sync()
        t0 = now()
        trainer.train_step()
        sync()
        return now() - t0
    losses, backward = trainer_module.compute_losses, torch.Tensor.backward

    def timed_losses(*args, **kwargs):
        with timer.section("losses"):
            return losses(*args, **kwargs)

    def timed_backward(self, *args, **kwargs):
        with timer.section("backward"):
            return backward(self, *args, **kwargs)

    trainer_module.compute_losses, torch.Tensor.backward = timed_losses, timed_backward
    try:
        before = sum(timer.totals.values())
        sync()
        t0 = now()
        trainer.train_step()
        sync()
        total = now() - t0
        timer.totals["other"] += total - (sum(timer.totals.values()) - before)
        return total
    finally:
        trainer_module.compute_losses, torch.Tensor.backward = losses, backward


def last_phase_start(trainer) -> int:
    phases = trainer.phases
    return phases.ends[-2] if len(phases.ends) > 1 else 0


def run_pair(plain: str, rain: str, args) -> dict:
    common = ([f"data={args.data}"] if args.data else []) + [
        f"profile={args.profile}", "trainer.progress=false", "trainer.eval_every=0",
        "trainer.checkpoint_every=0", *args.overrides]
    out = Path(args.out)
    _, a = build(plain, common, out / plain)
    _, b = build(rain, common, out / rain)
    # Both at the first joint step, so that schedules that follow the step (SH degree, grid
    # resolution, occupancy) put both fields in the same state.
    a.step = b.step = last_phase_start(b)
    phase = b.phases.at(b.step)[0]
    for _ in range(args.warm):
        a.train_step()
        b.train_step()
    timer = Timer(b.device)
    instrument(b, timer)
    times_a, times_b = [], []
    for _ in range(args.repeats):
        times_a.append(timed_step(a, None))
        times_b.append(timed_step(b, timer))
    ta, tb = statistics.median(times_a), statistics.median(times_b)
    total = sum(timer.totals.values())
    result = {
        "plain": plain, "rain": rain, "phase": phase, "device": str(b.device),
        "clock": "wall" if b.device.type == "cuda" else "process cpu",
        "threads": torch.get_num_threads(), "repeats": args.repeats, "warm": args.warm,
        "plain_step_ms": round(1e3 * ta, 2), "rain_step_ms": round(1e3 * tb, 2),
        "ratio": round(tb / ta, 2),
        "plain_field": a.pipeline.field.stats(), "rain_field": b.pipeline.field.stats(),
        "breakdown_ms": {k: round(1e3 * timer.totals.get(k, 0.0) / args.repeats, 2) for k in SECTIONS},
        "breakdown_share": {k: round(timer.totals.get(k, 0.0) / total, 3) for k in SECTIONS},
    }
    result.update(count_ops(a, b))
    print(json.dumps(result), flush=True)
    return result


def count_ops(a, b) -> dict:
    """Operators dispatched in one more step of each pipeline, and the rain step's per section
    (counted after the timing: the counting itself slows a step)."""
    counter = OpCounter()
    ops = Timer(b.device, clock_fn=lambda: counter.count)
    instrument(b, ops)
    with counter:
        timed_step(a, None)
        plain, plain_reads = counter.count, counter.reads
        timed_step(b, ops)
    return {"plain_step_ops": plain, "rain_step_ops": counter.count - plain,
            "plain_step_reads": plain_reads, "rain_step_reads": counter.reads - plain_reads,
            "ops_by_section": {k: int(ops.totals.get(k, 0)) for k in SECTIONS}}


def main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--pairs", default="3dgs:rainyscape-3dgs,nerf:rainyscape-nerf")
    ap.add_argument("--data", default="", help="scene folder (default: the embedded demo scene)")
    ap.add_argument("--repeats", type=int, default=10)
    ap.add_argument("--warm", type=int, default=30, help="steps each pipeline trains before timing")
    ap.add_argument("--profile", default="auto", choices=["auto", "cpu", "gpu"])
    ap.add_argument("--out", default="outputs/benchmarks/joint_cost")
    ap.add_argument("overrides", nargs="*", help="key=value overrides for both methods")
    args = ap.parse_args(argv)
    results = [run_pair(*pair.split(":"), args) for pair in args.pairs.split(",")]
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    with open(out / "joint_cost.jsonl", "a") as fh:
        for r in results:
            fh.write(json.dumps(r) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
