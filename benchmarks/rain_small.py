"""One rain-method run on the small rainy scene of tests/test_rain_end_to_end.py, one summary row.

    python benchmarks/rain_small.py METHOD TAG [key=value ...] [--out DIR] [--iters N]

The scene (the demo street at 64 x 64 px, 2 x 4 views, medium static rain, seed 0) is
simulated once into DIR/scene; the run trains ``METHOD`` with the overrides for N steps
(300) from the simulator's depth points, evaluates every view, and appends one JSON row
(render, held-out, rain correlation and recovery, fused output, its random-mask control and
coverage, streak-angle error) to DIR/rows.jsonl. docs/rain.md, "Issue 28", used it with
``trainer.seed=0`` and ``trainer.seed=1`` and one torch thread.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from rainyscape.comparison.plan import fixed_length
from rainyscape.config import method_config
from rainyscape.synth import generate
from rainyscape.workflow import train_and_evaluate

KEYS = ("train_psnr", "heldout_psnr", "rain_correlation", "train_rain_recovered", "train_rain-mask-fusion_psnr",
        "train_rain-mask-fusion_random_psnr", "train_rain-mask-fusion_coverage", "rain_angle_error_deg")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("method")
    parser.add_argument("tag")
    parser.add_argument("overrides", nargs="*")
    parser.add_argument("--out", default="outputs/benchmarks/rain_small")
    parser.add_argument("--iters", type=int, default=300)
    args = parser.parse_args()
    root = Path(args.out)
    scene = root / "scene"
    if not scene.exists():
        generate(scene, "demo", rows=2, cols=4, width=64, height=64, mode="static", seed=0)
    cfg = method_config(args.method, [f"data={scene}", "dataparser.points_from_depth=true",
                                      *fixed_length(args.iters), f"trainer.output_dir={root / args.tag}",
                                      "trainer.device=cpu", "trainer.progress=false", "trainer.eval_every=0",
                                      "trainer.checkpoint_every=0", *args.overrides])
    summary = json.loads((train_and_evaluate(cfg).run_dir / "metrics.json").read_text())["summary"]
    row = {"tag": args.tag, "method": args.method, "overrides": args.overrides, "iters": args.iters,
           **{k: summary.get(k) for k in KEYS}}
    print(json.dumps(row))
    with open(root / "rows.jsonl", "a") as fh:
        fh.write(json.dumps(row) + "\n")


if __name__ == "__main__":
    main()
