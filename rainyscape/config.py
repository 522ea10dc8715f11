"""Pipeline configuration: dataclasses, ``key=value`` overrides, plain-YAML save/load.

A method is a :class:`MethodSpec` whose :class:`PipelineConfig` names its components.
Component options start as plain dicts (so method modules stay import-light) and are
turned into the component's own ``Config`` dataclass by :func:`materialize`, which
validates every key. Nothing here imports torch.
"""

from __future__ import annotations

import copy
import dataclasses
import difflib
import types
import typing
from dataclasses import dataclass, field, fields, is_dataclass
from pathlib import Path
from typing import Any

from rainyscape import __version__, registry
from rainyscape.errors import ConfigError

PHASES = ("warmup", "joint")


@dataclass
class TrainerConfig:
    """Optimisation schedule and run bookkeeping (the engine's options)."""

    max_iters: int = 2000
    warmup_fraction: float = 0.5  # paper: first half of the run fits the field alone
    stop_at: int = 0  # stop after this step (0: max_iters); resume continues the same schedule
    warmup_patches: int = 16  # warm-up batch: this many patches from random views ...
    warmup_patch_size: int = 16  # ... of this size (0: whole images)
    joint_patches: int = 1  # joint batch: this many patches ...
    joint_patch_size: int = 64  # ... of this size (paper: one 64 x 64 patch, 4096 rays)
    latent_steps: int = 5  # latent updates after each joint network update
    latent_patch_size: int = 0  # latent updates on a random crop of the step's window (0: all of it)
    langevin_noise_steps: int = 2  # the first k of them add Langevin noise
    langevin_step: float = 0.03  # d in x <- x - d^2/2 (grad E + x / prior_var) + d * noise
    langevin_prior_var: float = 50.0
    seed: int = 0
    device: str = "auto"  # auto | cpu | cuda | cuda:N
    log_every: int = 25
    eval_every: int = 500  # periodic evaluation on a few views (0: off)
    eval_views: int = 2
    checkpoint_every: int = 1000
    keep_checkpoints: int = 2
    output_dir: str = "outputs"
    progress: bool = True


@dataclass
class ComponentConfig:
    name: str
    options: Any = field(default_factory=dict)  # dict before materialize, dataclass after


@dataclass
class LossConfig:
    name: str  # the registered loss component
    weight: float = 1.0
    phases: tuple[str, ...] = ("joint",)
    detach: str = ""  # "" | "rendered" | "rain": stop gradients into that input
    options: Any = field(default_factory=dict)


@dataclass
class PipelineConfig:
    method: str
    dataparser: ComponentConfig
    field: ComponentConfig
    rain_head: ComponentConfig | None = None
    losses: dict[str, LossConfig] = field(default_factory=dict)
    postprocess: dict[str, ComponentConfig] = field(default_factory=dict)
    trainer: TrainerConfig = field(default_factory=TrainerConfig)
    data: str = ""  # scene folder; empty runs the embedded demo scene


@dataclass
class MethodSpec:
    name: str
    description: str
    config: PipelineConfig


# --------------------------------------------------------------------------- types


def _config_class(kind: str, name: str) -> type:
    """The ``Config`` dataclass of a registered component (an empty one if it has none)."""
    comp = registry.load(kind, name)
    cfg = getattr(comp, "Config", None)
    if cfg is None:
        return _Empty
    if not is_dataclass(cfg):
        raise ConfigError(f"{kind} '{name}': its Config is not a dataclass")
    return cfg


@dataclass
class _Empty:
    pass


def _strip_optional(tp: Any) -> tuple[Any, bool]:
    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        if len(args) == 1 and len(typing.get_args(tp)) == 2:
            return args[0], True
    return tp, False


def coerce(text: Any, tp: Any, key: str) -> Any:
    """Convert a command-line string (or a YAML value) to the annotated type."""
    inner, optional = _strip_optional(tp)
    if optional and (text is None or (isinstance(text, str) and text.lower() in ("none", "null", ""))):
        return None
    origin = typing.get_origin(inner)
    try:
        if inner is bool:
            if isinstance(text, bool):
                return text
            low = str(text).lower()
            if low in ("true", "1", "yes", "on"):
                return True
            if low in ("false", "0", "no", "off"):
                return False
            raise ValueError
        if inner is int:
            if isinstance(text, bool):
                raise ValueError
            if isinstance(text, float) and not text.is_integer():
                raise ValueError
            return int(text) if not isinstance(text, str) else int(text.replace("_", ""))
        if inner is float:
            if isinstance(text, bool):
                raise ValueError
            return float(text)
        if inner is str:
            return str(text)
        if origin is typing.Literal:
            choices = typing.get_args(inner)
            for c in choices:
                if str(c) == str(text):
                    return c
            raise ConfigError(f"{key}: '{text}' is not one of {', '.join(map(str, choices))}")
        if origin in (tuple, list):
            args = typing.get_args(inner)
            item_tp = args[0] if args else str
            if isinstance(text, str):
                parts = [p.strip() for p in text.strip("()[] ").split(",") if p.strip()]
            else:
                parts = list(text)
            values = [coerce(p, item_tp, key) for p in parts]
            return tuple(values) if origin is tuple else values
        if origin is dict or inner is dict:
            if isinstance(text, dict):
                return dict(text)
            raise ValueError
    except ConfigError:
        raise
    except (TypeError, ValueError):
        raise ConfigError(f"{key}: cannot read '{text}' as {_type_name(tp)}") from None
    return text


def _type_name(tp: Any) -> str:
    inner, optional = _strip_optional(tp)
    name = getattr(inner, "__name__", None) or str(inner).replace("typing.", "")
    return f"{name} or none" if optional else name


def _hints(cls: type) -> dict[str, Any]:
    return typing.get_type_hints(cls)


def _build_dataclass(cls: type, values: dict, where: str) -> Any:
    hints = _hints(cls)
    valid = [f.name for f in fields(cls)]
    kwargs = {}
    for key, value in values.items():
        if key not in valid:
            raise ConfigError(_unknown_key_message(f"{where}.{key}", key, valid))
        kwargs[key] = coerce(value, hints[key], f"{where}.{key}")
    return cls(**kwargs)


def _unknown_key_message(full_key: str, key: str, valid: list[str]) -> str:
    close = difflib.get_close_matches(key, valid, n=1)
    hint = f" Did you mean '{close[0]}'?" if close else ""
    return f"unknown key '{full_key}'.{hint} Valid keys here: {', '.join(valid) or '(none)'}"


# --------------------------------------------------------------------- materialize


def _materialize_component(kind: str, comp: ComponentConfig, where: str) -> ComponentConfig:
    cls = _config_class(kind, comp.name)
    opts = comp.options
    if is_dataclass(opts) and isinstance(opts, cls):
        return ComponentConfig(comp.name, copy.deepcopy(opts))
    values = dataclasses.asdict(opts) if is_dataclass(opts) else dict(opts or {})
    return ComponentConfig(comp.name, _build_dataclass(cls, values, where))


def materialize(cfg: PipelineConfig) -> PipelineConfig:
    """A copy of ``cfg`` with every component's options as its typed Config dataclass."""
    out = copy.deepcopy(cfg)
    out.dataparser = _materialize_component("dataparser", cfg.dataparser, "dataparser")
    out.field = _materialize_component("field", cfg.field, "field")
    if cfg.rain_head is not None:
        out.rain_head = _materialize_component("rain_head", cfg.rain_head, "rain_head")
    out.losses = {}
    for key, loss in cfg.losses.items():
        comp = _materialize_component("loss", ComponentConfig(loss.name, loss.options), f"losses.{key}")
        bad = [p for p in loss.phases if p not in PHASES]
        if bad:
            raise ConfigError(f"losses.{key}.phases: unknown phase {bad[0]!r}; phases are {PHASES}")
        if loss.detach not in ("", "rendered", "rain"):
            raise ConfigError(f"losses.{key}.detach: '{loss.detach}' is not one of '', rendered, rain")
        out.losses[key] = dataclasses.replace(loss, options=comp.options, phases=tuple(loss.phases))
    out.postprocess = {
        key: _materialize_component("postprocess", pp, f"postprocess.{key}")
        for key, pp in cfg.postprocess.items()
    }
    return out


# ------------------------------------------------------------------------ overrides

_LOSS_GENERIC = {f.name for f in fields(LossConfig)} - {"options", "name"}


def parse_overrides(args: list[str]) -> list[tuple[str, str]]:
    out = []
    for arg in args:
        if "=" not in arg:
            raise ConfigError(f"cannot read argument '{arg}': expected key=value")
        key, value = arg.split("=", 1)
        if not key:
            raise ConfigError(f"cannot read argument '{arg}': empty key")
        out.append((key.strip(), value))
    return out


def _default_phases(name: str) -> tuple[str, ...]:
    return tuple(getattr(registry.load("loss", name), "phases", ("joint",)))


def apply_overrides(cfg: PipelineConfig, overrides: list[tuple[str, str]]) -> PipelineConfig:
    """Apply ``key=value`` pairs to a (materialized) config; returns a new, validated config."""
    cfg = materialize(cfg)
    # Component swaps first so that their options can be set in the same command.
    ordered = sorted(overrides, key=lambda kv: kv[0].count("."))
    for key, value in ordered:
        parts = key.split(".")
        head = parts[0]
        if head in ("method",):
            raise ConfigError("method= picks the method; it cannot be overridden inside a config")
        if head == "data" and len(parts) == 1:
            cfg.data = value
        elif head in ("dataparser", "field", "rain_head") and len(parts) == 1:
            if head == "rain_head" and value.lower() in ("none", ""):
                cfg.rain_head = None
            else:
                kind = head
                comp = _materialize_component(kind, ComponentConfig(value, {}), head)
                setattr(cfg, head, comp)
        elif head in ("dataparser", "field", "rain_head"):
            comp = getattr(cfg, head)
            if comp is None:
                raise ConfigError(f"{key}: this method has no {head}; set {head}=NAME first")
            _set_option(comp.options, parts[1:], value, head)
        elif head == "trainer":
            _set_option(cfg.trainer, parts[1:], value, "trainer")
        elif head == "losses":
            _override_loss(cfg, parts, value, key)
        elif head == "postprocess":
            _override_postprocess(cfg, parts, value, key)
        else:
            valid = ["data", "dataparser", "field", "rain_head", "losses", "postprocess", "trainer"]
            raise ConfigError(_unknown_key_message(key, head, valid))
    return materialize(cfg)


def _set_option(obj: Any, path: list[str], value: str, where: str) -> None:
    if len(path) != 1:
        raise ConfigError(f"{where}.{'.'.join(path)}: options are one level deep under {where}")
    name = path[0]
    valid = [f.name for f in fields(obj)]
    if name not in valid:
        raise ConfigError(_unknown_key_message(f"{where}.{name}", name, valid))
    setattr(obj, name, coerce(value, _hints(type(obj))[name], f"{where}.{name}"))


def _override_loss(cfg: PipelineConfig, parts: list[str], value: str, key: str) -> None:
    if len(parts) == 2 and value.lower() == "none":
        cfg.losses.pop(parts[1], None)  # losses.tv=none drops a term
        return
    if len(parts) != 3:
        raise ConfigError(f"{key}: expected losses.TERM.OPTION=value (or losses.TERM=none)")
    term, opt = parts[1], parts[2]
    if term not in cfg.losses:
        # A new term: TERM must be a registered loss (its default phases apply).
        comp = _materialize_component("loss", ComponentConfig(term, {}), f"losses.{term}")
        cfg.losses[term] = LossConfig(term, weight=1.0, phases=_default_phases(term), options=comp.options)
    loss = cfg.losses[term]
    if opt == "name":
        comp = _materialize_component("loss", ComponentConfig(value, {}), f"losses.{term}")
        cfg.losses[term] = dataclasses.replace(loss, name=value, options=comp.options)
    elif opt in _LOSS_GENERIC:
        setattr(loss, opt, coerce(value, _hints(LossConfig)[opt], key))
    else:
        try:
            _set_option(loss.options, [opt], value, f"losses.{term}")
        except ConfigError:
            valid = sorted(_LOSS_GENERIC | {"name"} | {f.name for f in fields(loss.options)})
            raise ConfigError(_unknown_key_message(key, opt, valid)) from None


def _override_postprocess(cfg: PipelineConfig, parts: list[str], value: str, key: str) -> None:
    if len(parts) == 2 and value.lower() == "none":
        cfg.postprocess.pop(parts[1], None)
        return
    if len(parts) == 2 and value.lower() in ("on", "true"):
        comp = _materialize_component("postprocess", ComponentConfig(parts[1], {}), key)
        cfg.postprocess[parts[1]] = comp
        return
    if len(parts) != 3:
        raise ConfigError(f"{key}: expected postprocess.NAME.OPTION=value, postprocess.NAME=on|none")
    name = parts[1]
    if name not in cfg.postprocess:
        cfg.postprocess[name] = _materialize_component("postprocess", ComponentConfig(name, {}), key)
    _set_option(cfg.postprocess[name].options, [parts[2]], value, f"postprocess.{name}")


# --------------------------------------------------------------------- plain data


def _plain(obj: Any) -> Any:
    if is_dataclass(obj):
        return {f.name: _plain(getattr(obj, f.name)) for f in fields(obj)}
    if isinstance(obj, (list, tuple)):
        return [_plain(v) for v in obj]
    if isinstance(obj, dict):
        return {str(k): _plain(v) for k, v in obj.items()}
    return obj


def to_dict(cfg: PipelineConfig) -> dict:
    """Plain data (names, numbers, strings, lists) describing the config."""
    cfg = materialize(cfg)

    def comp(c: ComponentConfig | None) -> dict | None:
        return None if c is None else {"name": c.name, **_plain(c.options)}

    return {
        "rainyscape_version": __version__,
        "method": cfg.method,
        "data": cfg.data,
        "dataparser": comp(cfg.dataparser),
        "field": comp(cfg.field),
        "rain_head": comp(cfg.rain_head),
        "losses": {
            k: {"name": l.name, "weight": l.weight, "phases": list(l.phases), "detach": l.detach,
                **_plain(l.options)}
            for k, l in cfg.losses.items()
        },
        "postprocess": {k: comp(p) for k, p in cfg.postprocess.items()},
        "trainer": _plain(cfg.trainer),
    }


def from_dict(data: dict) -> PipelineConfig:
    """Inverse of :func:`to_dict` (validates every key through the registry)."""
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
        name = raw.pop("name", key)
        losses[key] = LossConfig(
            name=name,
            weight=float(generic.get("weight", 1.0)),
            phases=tuple(generic.get("phases", ("joint",))),
            detach=generic.get("detach", ""),
            options=raw,
        )
    try:
        trainer = _build_dataclass(TrainerConfig, data.get("trainer") or {}, "trainer")
        cfg = PipelineConfig(
            method=data["method"],
            data=data.get("data", ""),
            dataparser=comp(data["dataparser"]),
            field=comp(data["field"]),
            rain_head=comp(data.get("rain_head")),
            losses=losses,
            postprocess={k: comp(v) for k, v in (data.get("postprocess") or {}).items()},
            trainer=trainer,
        )
    except KeyError as exc:
        raise ConfigError(f"config is missing the key {exc}") from None
    return materialize(cfg)


def save_yaml(cfg: PipelineConfig, path: Path) -> None:
    import yaml

    Path(path).write_text(yaml.safe_dump(to_dict(cfg), sort_keys=False))


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
    return from_dict(data)


# ------------------------------------------------------------------------ methods


def method_spec(name: str) -> MethodSpec:
    spec = registry.load("method", name)
    if not isinstance(spec, MethodSpec):
        raise ConfigError(f"method '{name}' is registered but is not a MethodSpec")
    return spec


def method_config(name: str, overrides: list[str] | None = None) -> PipelineConfig:
    """The method's config with ``key=value`` overrides applied and validated."""
    cfg = copy.deepcopy(method_spec(name).config)
    return apply_overrides(cfg, parse_overrides(overrides or []))


def describe_tree(cfg: PipelineConfig) -> str:
    """The whole config as dotted ``key = value`` lines, for ``--help``."""
    lines = []

    def walk(prefix: str, value: Any) -> None:
        if isinstance(value, dict):
            for k, v in value.items():
                walk(f"{prefix}.{k}" if prefix else k, v)
        else:
            lines.append(f"  {prefix} = {value}")

    d = to_dict(cfg)
    d.pop("rainyscape_version")
    walk("", d)
    return "\n".join(lines)
