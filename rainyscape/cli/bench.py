"""rs-bench: train a matrix of methods x scenes at one budget and tabulate the results.

Usage:
  rs-bench [methods=M1,M2,...] [scenes=S1,S2,...] [iters=N] [out=benchmarks/results]
           [name=DATE] [device=auto] [ablation=SCENE] [ablation_method=rainyscape-nerf]
           [scene_width=W] [scene_rows=R] [scene_cols=C] [jobs=1] [threads=0]
           [KEY.PATH=value ...]

Scenes are simulator presets (demo, yard, street, bridge, plaza; simulated once into
OUT/scenes) or scene folders. iters sets trainer.max_iters of every cell (0: each method's
own); dotted keys (trainer.eval_every=0, ...) are passed to every cell. Each cell trains in
its own process; OUT/NAME.json is updated after every cell and rerunning the same command
skips finished cells and resumes interrupted ones. jobs=N trains N cells at once, each
with threads= torch threads (default: cores / N). OUT/NAME.md holds the Table-I-style
tables (per scene PSNR / SSIM / LPIPS, then the average; training time and peak memory)
and, with ablation=SCENE, the loss ablation of ablation_method (the paper's Table II).
"""

from __future__ import annotations

import sys

from rainyscape.cli import run_cli


def main(argv: list[str]) -> int:
    from rainyscape.bench.options import BenchOptions
    from rainyscape.bench.run import run_bench
    from rainyscape.eval.cli_args import parse_args
    from rainyscape.errors import ConfigError

    overrides = [a for a in argv if "=" in a and "." in a.split("=", 1)[0]]
    rest = [a for a in argv if a not in overrides]
    parsed, opts = parse_args(rest, BenchOptions, set(), "rs-bench")
    if "--help" in parsed.flags or "-h" in parsed.flags:
        print(__doc__.strip())
        return 0
    if parsed.positional:
        raise ConfigError(f"rs-bench: unexpected argument '{parsed.positional[0]}' (options are key=value)")
    command = " ".join(["rs-bench", *argv])
    json_path, md_path, failed = run_bench(opts, overrides, command)
    print(md_path.read_text())
    print(f"results: {json_path}\ntables: {md_path}")
    return 1 if failed else 0


def entry() -> None:
    sys.exit(run_cli(main))


if __name__ == "__main__":
    entry()
