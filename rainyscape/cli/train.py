"""rs-train: train a method on a scene (or the embedded demo scene).

Usage:
  rs-train method=NAME [data=PATH] [dataparser=NAME] [key=value ...]
  rs-train resume=RUN_DIR [trainer.KEY=value ...] [data=MOVED_SCENE] [force=true]
  rs-train --list                 methods and components, with their origin
  rs-train method=NAME --help     the method's full config tree with defaults

Keys are dotted paths into the config: field.KEY, rain_head.KEY, phases.PHASE.KEY,
losses.TERM.KEY (weight, phases, detach or the term's options), postprocess.NAME.KEY,
trainer.KEY. Swap a component with field=NAME (likewise dataparser=, rain_head=,
rain_head=none). profile=auto|cpu|gpu picks the method's recipe: auto (the default) runs
the paper-scale gpu recipe on a CUDA device and the minutes-on-a-laptop cpu recipe
elsewhere; config.yml records which one ran. With dataparser=auto (the default) and data=,
the detected format's options are accepted too (dataparser.clean=..., shown by --help).

A run folder is locked while it trains: a second rs-train resume= of it is refused, naming
the process that holds it. A killed run resumes from its newest readable checkpoint
(written every trainer.checkpoint_every steps and at least every
trainer.checkpoint_minutes). Resuming a finished run is refused unless force=true (it would
evaluate again and replace metrics.json and report.html; rs-eval does that).
"""

from __future__ import annotations

import sys
from dataclasses import dataclass

from rainyscape.cli import run_cli
from rainyscape.cli.args import Command, opt, parse, print_help


@dataclass
class TrainArgs:
    method: str = opt("", "the method to train (rs-train --list)")
    resume: str = opt("", "a run folder to continue (only trainer.* and data= overrides; not "
                          "trainer.output_dir or trainer.seed)")
    force: bool = opt(False, "resume: evaluate a finished run again (replaces its metrics and report)")


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
        cfg = _with_detected_format(cfg)
        print(f"config, {cfg.profile} recipe (override with key=value; profile=auto, the default, "
              "runs the gpu recipe on a CUDA device and the cpu recipe elsewhere):")
        print(config.describe_tree(cfg))
        print(f"\nrun length: {config.describe_run_length(cfg.trainer)}")
        print("\ngpu recipe (profile=gpu): the cpu recipe with")
        print("\n".join(f"  {o}" for o in spec.gpu) or "  (no changes)")
        return 0
    from rainyscape.engine.signals import stop_on_sigterm

    stop_on_sigterm()
    if args.options.resume:
        return _resume(args.options.resume, rest, args.options.force, method)
    if not method:
        raise ConfigError("which method? e.g. rs-train method=rainyscape-nerf (rs-train --list shows all)")
    if args.options.force:
        raise ConfigError("force=true: only for resume= (a new run never writes over anything: it makes "
                          "a new folder under trainer.output_dir)")
    from rainyscape import config

    cfg = config.method_config(method, rest)  # validates everything before any work
    return _run(cfg, run_dir=None)


def _with_detected_format(cfg):
    """For --help: with data= and dataparser=auto, the detected format's options."""
    from rainyscape.config.overrides import resolve_dataparser
    from rainyscape.errors import RainyScapeError

    try:
        resolved = resolve_dataparser(cfg)
    except RainyScapeError as exc:
        print(f"(dataparser={cfg.dataparser.name}: {exc})\n")
        return cfg
    if resolved is None:
        if cfg.dataparser.name == "auto":
            print("(dataparser=auto: give data=SCENE to see the options of the format it detects)\n")
        return cfg
    print(f"dataparser={cfg.dataparser.name}: {cfg.data} is {resolved.dataparser.name}; its options "
          f"are shown and accepted (dataparser.KEY=value)\n")
    return resolved


# Trainer keys a resume cannot change: the folder is the run's, and its random state comes
# back from the checkpoint (a new seed would be recorded and not used).
FIXED_ON_RESUME = {"trainer.output_dir": "the run stays in its folder", "trainer.seed": "its random state "
                   "is restored from the checkpoint"}


def _resume(run_dir: str, overrides: list[str], force: bool = False, method: str = "") -> int:
    from pathlib import Path

    from rainyscape import config
    from rainyscape.engine.run_folder import RunFolder
    from rainyscape.errors import ConfigError

    folder = RunFolder.check(Path(run_dir).expanduser())
    path = folder.path
    bad = [o for o in overrides if not o.startswith("trainer.") and not o.startswith("data=")]
    if bad:
        raise ConfigError(f"resume accepts only trainer.* and data= overrides, got '{bad[0]}'")
    fixed = [o for o in overrides if o.split("=", 1)[0] in FIXED_ON_RESUME]
    if fixed:
        key = fixed[0].split("=", 1)[0]
        raise ConfigError(f"{key}: cannot change on resume ({FIXED_ON_RESUME[key]}); start a new run "
                          f"with method=... instead")
    cfg = folder.config()
    if method and method != cfg.method:
        raise ConfigError(f"method={method}: {path} is a run of {cfg.method}; a resume continues it "
                          f"(drop method=, or start a new run without resume=)")
    cfg = config.apply_overrides(cfg, config.parse_overrides(overrides))
    if folder.finished(cfg.trainer.max_iters):
        if not force:
            raise ConfigError(
                f"{path}: finished (step {folder.status().get('step')} of {cfg.trainer.max_iters}); resuming would "
                f"only evaluate it again and replace metrics.json and report.html. rs-eval {path} "
                f"does that; raise trainer.max_iters to train longer, or pass force=true")
        print(f"{path}: finished; evaluating it again (force=true)", file=sys.stderr)
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
