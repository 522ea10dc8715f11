"""rs-eval: evaluate a trained run with the evaluation protocol (docs/evaluation.md).

Usage:
  rs-eval RUN_DIR [device=auto|cpu|cuda] [step=N]

Computes PSNR / SSIM (and LPIPS when its weights are on this machine) of the rainy inputs,
the renders at training views (with and without post-processing) and at held-out views
against the clean images, the predicted rain angle and, on simulated scenes, the
correlation of the predicted with the true rain layer. Writes RUN_DIR/metrics.json,
comparison strips under RUN_DIR/renders/strips and RUN_DIR/report.html.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass

from rainyscape.cli import run_cli


@dataclass
class EvalOptions:
    device: str = "auto"
    step: int | None = None  # a checkpoint's step (default: the latest)


def print_summary(summary: dict) -> None:
    for key, value in summary.items():
        print(f"  {key}: {value:.4f}" if isinstance(value, float) else f"  {key}: {value}")


def main(argv: list[str]) -> int:
    from rainyscape.eval.cli_args import parse_args, run_dir_arg

    parsed, opts = parse_args(argv, EvalOptions, set(), "rs-eval")
    if "--help" in parsed.flags or "-h" in parsed.flags:
        print(__doc__.strip())
        return 0
    run_dir = run_dir_arg(parsed, "rs-eval")
    from rainyscape.engine.run import load_run
    from rainyscape.eval.evaluate import evaluate_pipeline, write_metrics

    pipeline, step = load_run(run_dir, opts.device, opts.step)
    metrics = evaluate_pipeline(pipeline, run_dir)
    metrics["step"] = step
    write_metrics(run_dir, metrics)
    print(f"{run_dir} (step {step}):")
    print_summary(metrics["summary"])
    if not metrics["lpips"]["available"]:
        print(f"  lpips: unavailable ({metrics['lpips']['reason']})")
    print(f"wrote {run_dir / 'metrics.json'} and {run_dir / 'report.html'}")
    return 0


def entry() -> None:
    sys.exit(run_cli(main))


if __name__ == "__main__":
    entry()
