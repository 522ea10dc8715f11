"""rs-train: train a method on a scene (or the embedded demo scene).

Usage:
  rs-train method=NAME [data=PATH] [dataparser=NAME] [key=value ...]
  rs-train resume=RUN_DIR [trainer.KEY=value ...]
  rs-train --list                 methods and components, with their origin
  rs-train method=NAME --help     the method's full config tree with defaults

Keys are dotted paths into the config: field.KEY, rain_head.KEY, phases.PHASE.KEY,
losses.TERM.KEY (weight, phases, detach or the term's options), postprocess.NAME.KEY,
trainer.KEY. Swap a component with field=NAME (likewise dataparser=, rain_head=,
rain_head=none). profile=auto|cpu|gpu picks the method's recipe: auto (the default) runs
the paper-scale gpu recipe on a CUDA device and the minutes-on-a-laptop cpu recipe
elsewhere; config.yml records which one ran.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass

from rainyscape.cli import run_cli
from rainyscape.cli.args import Command, opt, parse, print_help


@dataclass
class TrainArgs:
    method: str = opt("", "the method to train (rs-train --list)")
    resume: str = opt("", "a run folder to continue (only trainer.* overrides)")


# Every other key=value is a config override, validated by the method's config.
COMMAND = Command("rs-train", __doc__, TrainArgs, actions=("--list",), overrides="any")


def print_listing() -> None:
    from rainyscape import registry

    rows = []
    for kind in registry.KINDS:
        for entry, obj in registry.load_all(kind):
            rows.append((kind, entry.name, entry.origin, registry.describe(obj)))
    widths = [max(len(r[i]) for r in rows) for i in range(3)] if rows else [0, 0, 0]
    for kind, name, origin, desc in rows:
        print(f"{kind:<{widths[0]}}  {name:<{widths[1]}}  {origin:<{widths[2]}}  {desc}")


def main(argv: list[str]) -> int:
    from rainyscape.errors import ConfigError

    args = parse(argv, COMMAND)
    method, rest = args.options.method, args.overrides
    if "--list" in args.actions:
        print_listing()
        return 0
    if args.help:
        if not method:
            return print_help(COMMAND)
        from rainyscape import config

        spec = config.method_spec(method)
        asked = next((a.split("=", 1)[1] for a in reversed(rest) if a.startswith("profile=")), "cpu")
        cfg = config.method_config(method, [*rest, f"profile={'cpu' if asked == 'auto' else asked}"])
        print(f"{spec.name}: {spec.description}\n")
        print(f"config, {cfg.profile} recipe (override with key=value; profile=auto, the default, "
              "runs the gpu recipe on a CUDA device and the cpu recipe elsewhere):")
        print(config.describe_tree(cfg))
        print("\ngpu recipe (profile=gpu): the cpu recipe with")
        print("\n".join(f"  {o}" for o in spec.gpu) or "  (no changes)")
        return 0
    if args.options.resume:
        return _resume(args.options.resume, rest)
    if not method:
        raise ConfigError("which method? e.g. rs-train method=rainyscape-nerf (rs-train --list shows all)")
    from rainyscape import config

    cfg = config.method_config(method, rest)  # validates everything before any work
    return _run(cfg, run_dir=None)


def _resume(run_dir: str, overrides: list[str]) -> int:
    from pathlib import Path

    from rainyscape import config
    from rainyscape.errors import ConfigError

    path = Path(run_dir)
    if not (path / "config.yml").is_file():
        raise ConfigError(f"{path}: not a run folder (no config.yml)")
    bad = [o for o in overrides if not o.startswith("trainer.")]
    if bad:
        raise ConfigError(f"resume accepts only trainer.* overrides, got '{bad[0]}'")
    cfg = config.load_yaml(path / "config.yml")
    cfg = config.apply_overrides(cfg, config.parse_overrides(overrides))
    return _run(cfg, run_dir=path)


def _run(cfg, run_dir) -> int:
    from rainyscape.workflow import train_and_evaluate

    result = train_and_evaluate(cfg, run_dir)
    print(f"run folder: {result.run_dir}")
    if result.metrics:
        for key, value in result.metrics.get("summary", {}).items():
            print(f"  {key}: {value:.3f}" if isinstance(value, float) else f"  {key}: {value}")
    return 0


def entry() -> None:
    sys.exit(run_cli(main))


if __name__ == "__main__":
    entry()
