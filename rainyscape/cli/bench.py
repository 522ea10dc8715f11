"""rs-bench: train a matrix of methods x scenes at equal budgets and tabulate the results.

Usage:
  rs-bench [methods=M1,M2,...] [scenes=SET|S1,S2,...] [iters=N] [out=DIR] [name=NAME] [key=value ...]
           [KEY.PATH=value ...] [METHOD:KEY.PATH=value ...]

Scenes: a scene set (cpu: five presets at 128 px, the six-method table in an hour on 2 cores
with jobs=2 threads=1; paper: 512 px, 5 x 10 views, the paper's step counts, for a GPU), or
simulator presets (simulated once into OUT/scenes) and scene folders; demo alone is the
embedded demo. A set fixes size, views and steps per field; scene_width= ... iters= override.
A scene folder is read by its own format's parser (dataparser=NAME names one for every folder)
and takes that parser's options: dataparser.clean=FOLDER scores against its clean photos.
Before anything trains, every cell's budget (steps, mean pixels per step) is computed and
methods training the same field must match (exit 2 naming them, unless allow_unequal=true).
Dotted keys (trainer.eval_every=0, ...) go to every cell; METHOD:KEY.PATH=value to that
method's cells only. Each cell trains in its own process;
OUT/NAME.json is updated after every cell and rerunning the same command skips finished cells
and resumes interrupted ones. jobs=N trains N cells at once, each with threads= torch threads
(default: cores / N). OUT/NAME.md holds the Table-I-style tables: the oracle 3D row (the clean
scene re-rendered), the rainy input, each method, each fused row with its gain over the input
and its random-mask control, and a budget column (docs/evaluation.md, "How to read the
tables"); with ablation=SCENE, the loss ablation of ablation_method (the paper's Table II).

In OUT, a benchmark writes only its own NAME.json, NAME.md, runs/NAME/ and scenes/ (each
recognised by what rs-bench writes in it); a file of other origin in their place is refused,
naming it, before anything runs, unless force=true, which starts benchmark NAME afresh. A
second rs-bench of the same OUT and NAME while one runs is refused (the benchmark is locked).
"""

from __future__ import annotations

import sys

from rainyscape.comparison.options import BenchOptions
from rainyscape.cli import run_cli
from rainyscape.cli.args import Command, parse, print_help

COMMAND = Command("rs-bench", __doc__, BenchOptions, overrides="dotted",
                  oom_hint="train fewer cells at once (jobs=) or smaller scenes (scene_width=)")


def main(argv: list[str]) -> int:
    args = parse(argv, COMMAND)
    if args.help:
        return print_help(COMMAND)
    from rainyscape.comparison.run import run_bench
    from rainyscape.engine.signals import stop_on_sigterm

    stop_on_sigterm()
    command = " ".join(["rs-bench", *argv])
    json_path, md_path, failed = run_bench(args.options, args.overrides, command)
    print(md_path.read_text())
    print(f"results: {json_path}\ntables: {md_path}")
    return 1 if failed else 0


def entry() -> None:
    sys.exit(run_cli(main))


if __name__ == "__main__":
    entry()
