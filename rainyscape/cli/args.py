"""The argument layer of every ``rs-*`` command.

A command line is positional arguments, ``key=value`` options and flags, in any order:

- ``key=value`` sets a field of the command's options dataclass; the value is typed through
  :func:`rainyscape.config.coerce` (``rows=two`` -> "rows: cannot read 'two' as int").
- A bool option is also a flag: ``--name`` sets it true, ``--no-name`` false (``-`` and
  ``_`` are the same in flag names: ``--no-video`` is ``video=false``).
- Commands with ``dashed=True`` (rs-process-data, typed after nerfstudio's ns-process-data)
  also read ``--key VALUE`` and ``--key=VALUE``; a fixed-length tuple takes that many values
  (``--crop 0.1 0 0 0``).
- ``--help`` / ``-h`` and the command's own actions (``--list``, ...) are recorded, not acted on.
- ``overrides="dotted"`` passes keys with a dot through untouched (config overrides, in order);
  ``overrides="any"`` passes every key that is not an option (rs-train: the config validates).

Anything else is a :class:`ConfigError` naming the valid keys or flags and the closest match.
``--help`` prints :func:`help_text`: the command's module docstring, then every option with
its default (and its flag), generated from the options dataclass. An option's help line is its
field's ``metadata["help"]`` (:func:`opt` writes it).

This module imports nothing heavy: ``rs-train --help`` must not import torch.
"""

from __future__ import annotations

import difflib
import typing
from dataclasses import MISSING, dataclass, field, fields
from pathlib import Path
from typing import Any

from rainyscape.config.schema import DEVICES, MAX_STEPS, SEED_MAX  # noqa: F401 (for the commands' options)
from rainyscape.errors import ConfigError

HELP_FLAGS = ("--help", "-h")
# What to lower when a command that renders a trained run (rs-eval, rs-render, rs-export) runs
# out of memory: it renders with the run's own chunk
READ_OOM_HINT = "free memory (close other programs), or pass device=cpu when the GPU ran out"
HELP_COLUMN = 32  # where --help starts an option's help text (at most)


def opt(default: Any, help: str = "", lo: float | None = None, hi: float | None = None,
        above: float | None = None, choices: tuple[str, ...] | None = None) -> Any:
    """A dataclass field with a default, the line ``--help`` shows for it and the range its
    value must lie in (``lo`` .. ``hi``, greater than ``above``) or the ``choices`` it must be
    one of (``NAME:N`` stands for NAME:0, NAME:1, ...). Both are checked as the command line
    is read, before any work."""
    return field(default=default, metadata={"help": help, "min": lo, "max": hi, "above": above,
                                            "choices": tuple(choices) if choices else None})


@dataclass(frozen=True)
class Command:
    """What a command accepts."""

    name: str  # "rs-eval"
    doc: str  # the command module's docstring: Usage and what it does
    options: type | None = None  # its options dataclass (filled into Args.options)
    more: tuple[tuple[str, type], ...] = ()  # further option groups (title, dataclass), in Args.values
    actions: tuple[str, ...] = ()  # flags asking for an action besides --help: ("--list",)
    overrides: str = ""  # "" | "dotted" | "any": which unknown keys pass through (see module doc)
    dashed: bool = False  # also --key VALUE and --key=VALUE
    positional: str = ""  # what positional arguments are (for errors); "": none accepted
    oom_hint: str = ""  # what to lower when the command runs out of memory ("": training's knobs)


@dataclass
class Args:
    """What a command line said."""

    options: Any  # the options dataclass, defaults filled in
    values: dict[str, Any] = field(default_factory=dict)  # every option given, typed (all groups)
    given: dict[str, str] = field(default_factory=dict)  # option -> as typed: "--num-frames 1", "num_frames=1"
    positional: list[str] = field(default_factory=list)
    actions: set[str] = field(default_factory=set)  # --help / -h and the command's actions given
    overrides: list[str] = field(default_factory=list)  # key=value passed through, in order
    ranges: dict[str, Any] = field(default_factory=dict, repr=False)  # option -> its field's metadata

    @property
    def help(self) -> bool:
        return bool(self.actions & set(HELP_FLAGS))


# ------------------------------------------------------------------------------ parsing


def _groups(command: Command) -> list[tuple[str, type]]:
    main = [("Options", command.options)] if command.options is not None else []
    return main + list(command.more)


def _option_types(command: Command) -> dict[str, Any]:
    """Every option's annotated type, by key, over all groups."""
    out: dict[str, Any] = {}
    for _, cls in _groups(command):
        hints = typing.get_type_hints(cls)
        out.update({f.name: hints[f.name] for f in fields(cls)})
    return out


def _option_metadata(command: Command) -> dict[str, Any]:
    """Every option's field metadata (help, range), by key, over all groups."""
    return {f.name: f.metadata for _, cls in _groups(command) for f in fields(cls)}


def _suggest(name: str, valid: list[str]) -> str:
    close = difflib.get_close_matches(name, valid, n=1)
    return f" Did you mean '{close[0]}'?" if close else ""


def _tuple_length(tp: Any) -> int:
    """How many values ``--key`` takes: the length of a fixed-length tuple, else 1."""
    args = typing.get_args(tp)
    if typing.get_origin(tp) is tuple and args and Ellipsis not in args:
        return len(args)
    return 1


def _flag_names(command: Command, types: dict[str, Any]) -> list[str]:
    """Every flag the command understands (for errors and suggestions)."""
    names = [*HELP_FLAGS, *command.actions]
    for key, tp in types.items():
        if tp is bool:
            names += [f"--{key.replace('_', '-')}", f"--no-{key.replace('_', '-')}"]
        elif command.dashed:
            names.append(f"--{key.replace('_', '-')}")
    return names


def _set(args: Args, key: str, text: str, spelled: str, tp: Any, typed: str) -> None:
    """Record option ``key`` (written ``spelled``; the whole argument as ``typed``)."""
    from rainyscape.config import coerce  # here, not at the top: `--help` never needs it
    from rainyscape.config.schema import check_range

    value = coerce(text, tp, spelled)
    check_range(value, args.ranges.get(key, {}), spelled)
    n = _tuple_length(tp)
    if n > 1 and len(value) != n:
        raise ConfigError(f"{spelled}: expected {n} values, got {len(value)} ('{text}')")
    args.values[key] = value
    args.given[key] = typed


def parse(argv: list[str], command: Command) -> Args:
    """Read ``argv`` for ``command`` (see the module docstring); raises ConfigError."""
    types = _option_types(command)
    args = Args(options=None, ranges=_option_metadata(command))
    i = 0
    while i < len(argv):
        arg = argv[i]
        i += 1
        if arg.startswith("-") and len(arg) > 1:
            if arg in HELP_FLAGS or arg in command.actions:
                args.actions.add(arg)
                continue
            name, eq, text = arg.lstrip("-").partition("=")
            key = name.replace("-", "_")
            if not eq and types.get(key) is bool:
                _set(args, key, "true", arg, bool, arg)
            elif not eq and key.startswith("no_") and types.get(key[3:]) is bool:
                _set(args, key[3:], "false", arg, bool, arg)
            elif key in types and command.dashed:
                if eq:
                    typed = arg
                else:
                    n = _tuple_length(types[key])
                    if i + n > len(argv):
                        raise ConfigError(f"{command.name}: {arg} expects {n} value{'s' * (n > 1)}")
                    typed = " ".join(argv[i - 1:i + n])
                    text, i = ",".join(argv[i:i + n]), i + n
                _set(args, key, text, f"--{name}", types[key], typed)
            elif key in types:
                raise ConfigError(f"{command.name}: {arg} takes a value: write {key}=VALUE")
            else:
                valid = _flag_names(command, types)
                raise ConfigError(f"{command.name}: unknown option {arg}.{_suggest(arg, valid)} "
                                  f"Options: {', '.join(valid)}")
        elif "=" in arg:
            key, text = arg.split("=", 1)
            if key in types:
                _set(args, key, text, key, types[key], arg)
            elif command.overrides == "any" or (command.overrides == "dotted" and "." in key):
                args.overrides.append(arg)
            else:
                valid = list(types)
                raise ConfigError(f"{command.name}: unknown key '{key}'.{_suggest(key, valid)} "
                                  f"Valid keys: {', '.join(valid) or '(none)'}")
        elif command.positional:
            args.positional.append(arg)
        else:
            raise ConfigError(f"{command.name}: unexpected argument '{arg}'; options are key=value "
                              f"(see {command.name} --help)")
    if command.options is not None:
        own = {f.name for f in fields(command.options)}
        args.options = command.options(**{k: v for k, v in args.values.items() if k in own})
    return args


def run_dir(args: Args, command: Command) -> Path:
    """The one RUN_DIR argument, checked to be a run folder."""
    if len(args.positional) != 1:
        raise ConfigError(f"{command.name}: expected one RUN_DIR (a folder made by rs-train), "
                          f"got {len(args.positional)} positional arguments; see {command.name} --help")
    from rainyscape.engine.run_folder import RunFolder  # light: no torch

    return RunFolder.check(Path(args.positional[0]).expanduser()).path


# --------------------------------------------------------------------------------- help


def _default_text(f) -> str:
    value = f.default if f.default_factory is MISSING else f.default_factory()
    if value is None:
        return "none"
    if isinstance(value, bool):
        return str(value).lower()
    if isinstance(value, (tuple, list)):
        return ",".join(map(str, value))
    return f"{value:g}" if isinstance(value, float) else str(value)


def _option_lines(cls: type, dashed: bool) -> list[tuple[str, str]]:
    hints = typing.get_type_hints(cls)
    out = []
    for f in fields(cls):
        flag = f.name.replace("_", "-")
        left = f"{f.name}={_default_text(f)}"
        if hints[f.name] is bool:
            left += f"  (--no-{flag})" if f.default is True else f"  (--{flag})"
        elif dashed:
            left = f"--{flag}, {left}"
        text = f.metadata.get("help", "")
        span = _range_text(f.metadata)
        out.append((left, f"{text} ({span})" if span and text else text or span))
    return out


def _range_text(metadata: Any) -> str:
    lo, hi, above = metadata.get("min"), metadata.get("max"), metadata.get("above")
    if metadata.get("choices"):
        from rainyscape.config.schema import choices_text

        return "one of " + choices_text(metadata["choices"])
    if lo is None and hi is None and above is None:
        return ""
    from rainyscape.config.schema import range_text  # config imports nothing heavy

    return range_text(lo, hi, above)


def help_text(command: Command) -> str:
    """The module docstring, then each option group with defaults (``key=default  help``)."""
    parts = [command.doc.strip()]
    for title, cls in _groups(command):
        lines = _option_lines(cls, command.dashed)
        width = min(max(len(left) for left, _ in lines), HELP_COLUMN)
        parts.append(f"\n{title} (key=value; defaults shown):")
        for left, text in lines:  # a long left side puts its help on the next line
            gap = "\n" + " " * (width + 4) if len(left) > width and text else "  "
            parts.append(f"  {left:<{width}}{gap}{text}".rstrip())
    return "\n".join(parts)


def print_help(command: Command) -> int:
    """Print :func:`help_text`; returns the exit code (0)."""
    print(help_text(command))
    return 0
