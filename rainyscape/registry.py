"""Component registry: lazy discovery of plugins through Python entry points.

Listing reads entry-point metadata only; a component's module is imported the first
time it is used. A plugin that fails to import is reported once and skipped by
listings; asking for it by name raises a PluginError that carries the import error.

For development without packaging, ``RAINYSCAPE_PLUGINS`` registers components:
``RAINYSCAPE_PLUGINS="field:my-field=my_pkg.fields:MyField,loss:l2=my_pkg.l:L2"``.
"""

from __future__ import annotations

import difflib
import importlib
import os
import sys
from dataclasses import dataclass
from functools import lru_cache
from importlib import metadata

from rainyscape.errors import ConfigError, PluginError

KINDS: dict[str, str] = {
    "method": "rainyscape.methods",
    "dataparser": "rainyscape.dataparsers",
    "field": "rainyscape.fields",
    "rain_head": "rainyscape.rain_heads",
    "loss": "rainyscape.losses",
    "postprocess": "rainyscape.postprocess",
}
ENV_VAR = "RAINYSCAPE_PLUGINS"


@dataclass(frozen=True)
class Entry:
    kind: str
    name: str
    target: str  # "module:attribute"
    origin: str  # distribution name and version, or the env var


class UnknownComponent(PluginError, ConfigError):
    def __init__(self, kind: str, name: str, known: list[str]):
        close = difflib.get_close_matches(name, known, n=1)
        hint = f" Did you mean '{close[0]}'?" if close else ""
        listing = ", ".join(sorted(known)) or "(none installed)"
        super().__init__(f"unknown {kind} '{name}'.{hint} Known {kind}s: {listing}")


def _check_kind(kind: str) -> None:
    if kind not in KINDS:
        raise PluginError(f"unknown component kind '{kind}'; kinds are {', '.join(KINDS)}")


def _env_entries() -> list[Entry]:
    raw = os.environ.get(ENV_VAR, "").strip()
    out = []
    for item in filter(None, (part.strip() for part in raw.split(","))):
        try:
            kind_name, target = item.split("=", 1)
            kind, name = kind_name.split(":", 1)
        except ValueError:
            raise PluginError(
                f"{ENV_VAR}: cannot read '{item}'; expected kind:name=module:attribute"
            ) from None
        _check_kind(kind.strip())
        out.append(Entry(kind.strip(), name.strip(), target.strip(), ENV_VAR))
    return out


@lru_cache(maxsize=None)
def _entries_cached(kind: str, env_value: str) -> dict[str, Entry]:
    found: dict[str, Entry] = {}
    for ep in metadata.entry_points(group=KINDS[kind]):
        dist = getattr(ep, "dist", None)
        origin = f"{dist.metadata['Name']} {dist.version}" if dist is not None else "?"
        if ep.name in found and found[ep.name].target != ep.value:
            _report_once(
                f"{kind} '{ep.name}' is registered by both {found[ep.name].origin} and "
                f"{origin}; using {origin}"
            )
        found[ep.name] = Entry(kind, ep.name, ep.value, origin)
    for entry in _env_entries():
        if entry.kind == kind:
            found[entry.name] = entry  # explicit development registration wins
    return found


def entries(kind: str) -> dict[str, Entry]:
    """All registered components of a kind, by name. Imports nothing."""
    _check_kind(kind)
    return dict(_entries_cached(kind, os.environ.get(ENV_VAR, "")))


def names(kind: str) -> list[str]:
    return sorted(entries(kind))


_reported: set[str] = set()


def _report_once(message: str) -> None:
    if message not in _reported:
        _reported.add(message)
        print(f"rainyscape: warning: {message}", file=sys.stderr)


_loaded: dict[tuple[str, str], object] = {}


def _import_target(entry: Entry) -> object:
    module_name, _, attr = entry.target.partition(":")
    try:
        obj = importlib.import_module(module_name)
        for part in filter(None, attr.split(".")):
            obj = getattr(obj, part)
    except Exception as exc:  # any failure inside a plugin must not take the others down
        raise PluginError(
            f"{entry.kind} '{entry.name}' from {entry.origin} failed to load "
            f"({entry.target}): {type(exc).__name__}: {exc}"
        ) from exc
    return obj


def load(kind: str, name: str) -> object:
    """The component object registered as ``name`` (imported on first use)."""
    known = entries(kind)
    if name not in known:
        raise UnknownComponent(kind, name, list(known))
    key = (kind, name)
    if key not in _loaded:
        _loaded[key] = _import_target(known[name])
    return _loaded[key]


def load_all(kind: str) -> list[tuple[Entry, object]]:
    """Load every component of a kind; broken plugins are reported once and skipped."""
    out = []
    for name, entry in sorted(entries(kind).items()):
        try:
            out.append((entry, load(kind, name)))
        except PluginError as exc:
            _report_once(f"skipping broken plugin: {exc}")
    return out


def describe(obj: object) -> str:
    """One-line description of a component: its ``description`` or docstring's first line."""
    text = getattr(obj, "description", None) or (getattr(obj, "__doc__", None) or "")
    return text.strip().splitlines()[0] if text and text.strip() else ""


def clear_cache() -> None:
    """Forget discovered and loaded components (after installing a plugin at run time)."""
    _entries_cached.cache_clear()
    _loaded.clear()
    importlib.invalidate_caches()
