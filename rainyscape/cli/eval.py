"""rs-eval: evaluate a trained run with the evaluation protocol (docs/evaluation.md).

Usage:
  rs-eval RUN_DIR [device=auto|cpu|cuda] [step=N] [data=MOVED_SCENE] [postprocess.NAME=on|none ...]

Computes PSNR / SSIM (and LPIPS when its weights are on this machine) of the rainy inputs,
the renders at training views (with and without post-processing) and at held-out views
against the clean images, the predicted rain angle and, on simulated scenes, the
correlation of the predicted with the true rain layer, on every view (a progress bar
with its ETA shows on a terminal). Writes RUN_DIR/metrics.json,
comparison strips under RUN_DIR/renders/strips and RUN_DIR/report.html.

``postprocess.NAME=on|none`` and ``postprocess.NAME.KEY=VALUE`` evaluate the run with other
post-processes than it trained with (they change no trained state): for example
``postprocess.streak-fusion=on`` fuses a plain field's renders. metrics.json lists the
post-processes it evaluated.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass

from rainyscape.cli import run_cli
from rainyscape.cli.args import DEVICES, MAX_STEPS, READ_OOM_HINT, Command, opt, parse, print_help, run_dir


@dataclass
class EvalOptions:
    device: str = opt("auto", "the device to evaluate on", choices=DEVICES)
    data: str = opt("", "the scene folder, if it moved since training (config.yml names the old one)")
    step: int | None = opt(None, "the checkpoint's step (default: the latest)", lo=0, hi=MAX_STEPS)


COMMAND = Command("rs-eval", __doc__, EvalOptions, positional="RUN_DIR", oom_hint=READ_OOM_HINT,
                  overrides="dotted")


def print_summary(summary: dict) -> None:
    for key, value in summary.items():
        print(f"  {key}: {value:.4f}" if isinstance(value, float) else f"  {key}: {value}")


def main(argv: list[str]) -> int:
    args = parse(argv, COMMAND)
    if args.help:
        return print_help(COMMAND)
    folder, opts = run_dir(args, COMMAND), args.options
    from rainyscape.workflow import load_trained
    from rainyscape.engine.run_folder import RunFolder
    from rainyscape.eval.protocol import evaluate_pipeline, write_metrics
    from rainyscape.formats.output import check_writable

    check_writable(folder, "rs-eval writes metrics.json, report.html and renders/strips there")

    pipeline, step = load_trained(folder, opts.device, opts.step, data=opts.data,
                                  postprocess=args.overrides)
    print(f"evaluating every view ({pipeline.scene.num_images}) of {folder} at step {step}",
          file=sys.stderr)
    metrics = evaluate_pipeline(pipeline, folder)
    metrics["step"] = step
    write_metrics(folder, metrics)
    print(f"{folder} (step {step}):")
    print_summary(metrics["summary"])
    if not metrics["lpips"]["available"]:
        print(f"  lpips: unavailable ({metrics['lpips']['reason']})")
    written = RunFolder(folder)
    print(f"wrote {written.metrics_file} and {written.report_file}")
    return 0


def entry() -> None:
    sys.exit(run_cli(main))


if __name__ == "__main__":
    entry()
