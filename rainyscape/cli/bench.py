"""rs-bench: train a matrix of methods x scenes at one budget and tabulate the results.

Usage:
  rs-bench [methods=M1,M2,...] [scenes=S1,S2,...] [iters=N] [out=DIR] [name=NAME] [key=value ...]
           [KEY.PATH=value ...]

Scenes are simulator presets (demo, yard, street, bridge, plaza; simulated once into
OUT/scenes) or scene folders. Dotted keys (trainer.eval_every=0, ...) are passed to every
cell. Each cell trains in its own process; OUT/NAME.json is updated after every cell and
rerunning the same command skips finished cells and resumes interrupted ones. jobs=N trains
N cells at once, each with threads= torch threads (default: cores / N). OUT/NAME.md holds the
Table-I-style tables (per scene PSNR / SSIM / LPIPS, then the average; training time and peak
memory) and, with ablation=SCENE, the loss ablation of ablation_method (the paper's Table II).
"""

from __future__ import annotations

import sys

from rainyscape.bench.options import BenchOptions
from rainyscape.cli import run_cli
from rainyscape.cli.args import Command, parse, print_help

COMMAND = Command("rs-bench", __doc__, BenchOptions, overrides="dotted")


def main(argv: list[str]) -> int:
    args = parse(argv, COMMAND)
    if args.help:
        return print_help(COMMAND)
    from rainyscape.bench.run import run_bench

    command = " ".join(["rs-bench", *argv])
    json_path, md_path, failed = run_bench(args.options, args.overrides, command)
    print(md_path.read_text())
    print(f"results: {json_path}\ntables: {md_path}")
    return 1 if failed else 0


def entry() -> None:
    sys.exit(run_cli(main))


if __name__ == "__main__":
    entry()
