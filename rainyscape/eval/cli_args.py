"""Argument parsing shared by rs-eval, rs-render, rs-export and rs-bench:
``[RUN_DIR] [key=value ...] [--flag ...]`` with typed, validated options."""

from __future__ import annotations

import difflib
import typing
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

from rainyscape.config import coerce
from rainyscape.errors import ConfigError


@dataclass
class ParsedArgs:
    positional: list[str] = field(default_factory=list)
    options: dict[str, Any] = field(default_factory=dict)
    flags: set[str] = field(default_factory=set)


def parse_args(argv: list[str], options: type, flags: set[str], command: str) -> tuple[ParsedArgs, Any]:
    """Split ``argv`` and fill the ``options`` dataclass from ``key=value`` pairs.

    Unknown keys and flags raise :class:`ConfigError` naming the valid ones."""
    parsed = ParsedArgs()
    valid = [f.name for f in fields(options)]
    hints = typing.get_type_hints(options)
    values = {}
    for arg in argv:
        if arg.startswith("-"):
            if arg not in flags | {"--help", "-h"}:
                known = ", ".join(sorted(flags)) or "(none)"
                raise ConfigError(f"{command}: unknown option {arg}; options: {known}, --help")
            parsed.flags.add(arg)
        elif "=" in arg:
            key, value = arg.split("=", 1)
            if key not in valid:
                close = difflib.get_close_matches(key, valid, n=1)
                hint = f" Did you mean '{close[0]}'?" if close else ""
                raise ConfigError(f"{command}: unknown key '{key}'.{hint} Valid keys: {', '.join(valid)}")
            values[key] = coerce(value, hints[key], key)
        else:
            parsed.positional.append(arg)
    return parsed, options(**values)


def run_dir_arg(parsed: ParsedArgs, command: str) -> Path:
    """The one RUN_DIR argument, checked to be a run folder."""
    if len(parsed.positional) != 1:
        raise ConfigError(f"{command}: expected one RUN_DIR (a folder made by rs-train), "
                          f"got {len(parsed.positional)} positional arguments; see {command} --help")
    path = Path(parsed.positional[0]).expanduser()
    if not (path / "config.yml").is_file():
        raise ConfigError(f"{path}: not a run folder (no config.yml); pass the folder rs-train printed")
    return path
