"""Compare settings of the fast field: a short fit of ``nerf`` with config overrides.

    python benchmarks/field_settings.py ITERS TAG [key=value ...]

Fits ``nerf`` for ITERS steps on the rainy 64 px bench demo scene (simulated by the rs-bench command of docs/benchmarks.md into
benchmarks/results/scenes/demo-64x3x6-v3; data=DIR for another scene) and
prints the training time and PSNR of six training and the held-out views against the clean
and the rainy images. One process per setting; compare settings run under the same load.
"""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))
from fields import build, timed_steps  # noqa: E402

from rainyscape.comparison.plan import fixed_length  # noqa: E402
from rainyscape.eval.views import quick_eval  # noqa: E402

DEFAULT_DATA = Path(__file__).parent / "results" / "scenes" / "demo-64x3x6-v3"


def main(argv: list[str]) -> int:
    if len(argv) < 2:
        print(__doc__.strip(), file=sys.stderr)
        return 2
    iters, tag, overrides = int(argv[0]), argv[1], argv[2:]
    data = [] if any(o.startswith("data=") for o in overrides) else [f"data={DEFAULT_DATA}"]
    _, trainer = build("nerf", data + [*fixed_length(iters),
                                       "trainer.progress=false", "trainer.eval_every=0",
                                       "trainer.checkpoint_every=0", "trainer.eval_views=6", *overrides],
                       Path("outputs/benchmarks/field_settings") / tag)
    seconds = sum(timed_steps(trainer, iters))
    scores = {k: round(v, 2) for k, v in quick_eval(trainer.pipeline, trainer.cfg.eval_views).items()}
    print(tag, " ".join(overrides), f"{seconds:.0f}s", scores, flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
