"""``config.yml``: a typed config as plain data (names, numbers, strings) and back."""

from __future__ import annotations

from dataclasses import fields, is_dataclass
from pathlib import Path
from typing import Any

from rainyscape import __version__
from rainyscape.config.schema import (RETIRED_KEYS, ComponentConfig, LossConfig, PhaseConfig,
                                      PipelineConfig, TrainerConfig, build_dataclass, is_materialized,
                                      materialize)
from rainyscape.errors import ConfigError
from rainyscape.formats.atomic import write_text_atomic

_LOSS_GENERIC = ("weight", "phases", "detach")


def _plain(obj: Any) -> Any:
    if is_dataclass(obj):
        return {f.name: _plain(getattr(obj, f.name)) for f in fields(obj)}
    if isinstance(obj, (list, tuple)):
        return [_plain(v) for v in obj]
    if isinstance(obj, dict):
        return {str(k): _plain(v) for k, v in obj.items()}
    return obj


def to_dict(cfg: PipelineConfig) -> dict:
    """Plain data (names, numbers, strings, lists) describing a typed config."""
    if not is_materialized(cfg):
        raise TypeError("to_dict needs a typed config (from method_config or load_yaml)")

    def comp(c: ComponentConfig | None) -> dict | None:
        return None if c is None else {"name": c.name, **_plain(c.options)}

    return {
        "rainyscape_version": __version__,
        "method": cfg.method,
        "profile": cfg.profile,
        "data": cfg.data,
        "dataparser": comp(cfg.dataparser),
        "field": comp(cfg.field),
        "rain_head": comp(cfg.rain_head),
        "phases": _plain(cfg.phases),
        "losses": {
            k: {"name": l.name, "weight": l.weight, "phases": list(l.phases), "detach": l.detach,
                **_plain(l.options)}
            for k, l in cfg.losses.items()
        },
        "postprocess": {k: comp(p) for k, p in cfg.postprocess.items()},
        "trainer": _plain(cfg.trainer),
    }


def from_dict(data: dict) -> PipelineConfig:
    """Inverse of :func:`to_dict`: a typed config (every key validated through the registry)."""
    data = dict(data)
    data.pop("rainyscape_version", None)

    def comp(d: dict | None) -> ComponentConfig | None:
        if d is None:
            return None
        d = dict(d)
        return ComponentConfig(d.pop("name"), d)

    losses = {}
    for key, raw in (data.get("losses") or {}).items():
        raw = dict(raw)
        generic = {k: raw.pop(k) for k in list(raw) if k in _LOSS_GENERIC}
        losses[key] = LossConfig(name=raw.pop("name", key), weight=generic.get("weight", 1.0),
                                 phases=tuple(generic.get("phases", ())),
                                 detach=generic.get("detach", ""), options=raw)
    try:
        phases = data["phases"]
        if not isinstance(phases, dict):
            raise ConfigError("phases: expected a mapping of phase names to options")
        cfg = PipelineConfig(
            method=data["method"],
            profile=data.get("profile", "cpu"),
            data=data.get("data", ""),
            dataparser=comp(data["dataparser"]),
            field=comp(data["field"]),
            phases={name: build_dataclass(PhaseConfig, opts or {}, f"phases.{name}")
                    for name, opts in phases.items()},
            rain_head=comp(data.get("rain_head")),
            losses=losses,
            postprocess={k: comp(v) for k, v in (data.get("postprocess") or {}).items()},
            trainer=build_dataclass(TrainerConfig, _current(data.get("trainer"), "trainer"), "trainer"),
        )
    except KeyError as exc:
        raise ConfigError(f"config is missing the key {exc}") from None
    return materialize(cfg)


def _current(section: dict | None, where: str) -> dict:
    """A saved section without its retired keys (an older run's config.yml still loads)."""
    if section is not None and not isinstance(section, dict):
        raise ConfigError(f"{where}: expected a mapping of options")
    return {k: v for k, v in (section or {}).items() if f"{where}.{k}" not in RETIRED_KEYS}


def save_yaml(cfg: PipelineConfig, path: Path) -> None:
    """Write ``config.yml`` atomically (a temporary file renamed in place)."""
    import yaml

    write_text_atomic(Path(path), yaml.safe_dump(to_dict(cfg), sort_keys=False))


def load_yaml(path: Path) -> PipelineConfig:
    import yaml

    path = Path(path)
    try:
        data = yaml.safe_load(path.read_text())
    except FileNotFoundError:
        raise ConfigError(f"{path}: no such config file") from None
    except yaml.YAMLError as exc:
        raise ConfigError(f"{path}: not valid YAML ({exc})") from None
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: expected a mapping at the top level")
    try:
        return from_dict(data)
    except ConfigError as exc:
        raise ConfigError(f"{path}: {exc}") from None
