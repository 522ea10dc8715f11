"""The config dataclasses, value coercion and range checks, and :func:`materialize`.

A method's recipe names its components with options as plain dicts; :func:`materialize`
turns each into the component's own ``Config`` dataclass (validating every key, type and
range) and checks the phases and loss terms against each other. It is the only gate from
plain data to typed configs: :func:`rainyscape.config.method_config` and
:func:`rainyscape.config.load_yaml` call it, and everything after them sees typed options.
"""

from __future__ import annotations

import copy
import dataclasses
import difflib
import math
import types
import typing
from dataclasses import dataclass, field, fields, is_dataclass
from typing import Any

from rainyscape import registry
from rainyscape.errors import ConfigError

DETACHABLE = ("", "rendered", "rain")  # what a loss term may stop gradients into
PROFILES = ("cpu", "gpu")  # a method's recipe for a laptop CPU, and its paper-scale one


def bounded(default: Any, lo: float | None = None, hi: float | None = None, *,
            above: float | None = None, **kwargs) -> Any:
    """A dataclass field whose value must lie in [lo, hi], and be greater than ``above`` when
    given (checked by :func:`coerce_field`; for tuples, every item)."""
    return field(default=default, metadata={"min": lo, "max": hi, "above": above}, **kwargs)


def number_text(x: float) -> str:
    """A bound or a value as a message shows it: integers in full (4294967295), floats short."""
    return str(x) if isinstance(x, int) and not isinstance(x, bool) else f"{x:g}"


def range_text(lo: float | None, hi: float | None, above: float | None = None) -> str:
    """How a range reads in messages and ``--help``: "at least 1", "between 0 and 1", ..."""
    parts = []
    if above is not None:
        parts.append(f"greater than {number_text(above)}")
    if lo is not None and hi is not None:
        parts.append(f"between {number_text(lo)} and {number_text(hi)}")
    elif lo is not None:
        parts.append(f"at least {number_text(lo)}")
    elif hi is not None:
        parts.append(f"at most {number_text(hi)}")
    return " and ".join(parts)


def choice(default: str, choices: tuple[str, ...], **kwargs) -> Any:
    """A dataclass field whose value must be one of ``choices`` (checked with the ranges; a
    choice ``NAME:N`` stands for NAME:0, NAME:1, ...: ``cuda:N``)."""
    return field(default=default, metadata={"choices": tuple(choices)}, **kwargs)


def matches_choice(value: str, choices: tuple[str, ...]) -> bool:
    for c in choices:
        if c.endswith(":N"):
            head, _, tail = str(value).partition(":")
            if head == c[:-2] and tail.isdigit():
                return True
        elif str(value) == c:
            return True
    return False


def choices_text(choices: tuple[str, ...]) -> str:
    """How choices read in messages and ``--help``: "auto | cpu | cuda" ('' for the empty one)."""
    return " | ".join(c or "''" for c in choices)


def check_choice(value: Any, choices: tuple[str, ...] | None, key: str) -> None:
    """ConfigError naming ``key`` and the choices unless ``value`` is one of them."""
    if choices and value is not None and not matches_choice(value, choices):
        raise ConfigError(f"{key}={value}: not one of {choices_text(choices)}")


# Devices a run may name: auto (CUDA when present, else the CPU), cpu, cuda, cuda:N
DEVICES = ("auto", "cpu", "cuda", "cuda:N")
SEED_MAX = 2**32 - 1  # numpy's seeds are 32-bit
MAX_STEPS = 100_000_000  # step counts: far beyond any run, short of an overflow
MAX_VIEWS = 100_000  # view counts


def check_range(value: Any, metadata: Any, key: str) -> None:
    """ConfigError when a number (or any number in a tuple / list) is outside the range that
    ``metadata`` (a field's: ``min``, ``max``, ``above``) states, or a value is not one of its
    ``choices``."""
    check_choice(value, metadata.get("choices"), key)
    lo, hi, above = metadata.get("min"), metadata.get("max"), metadata.get("above")
    if lo is None and hi is None and above is None:
        return
    for item in (value if isinstance(value, (tuple, list)) else [value]):
        if not isinstance(item, (int, float)) or isinstance(item, bool):
            continue
        if ((lo is not None and item < lo) or (hi is not None and item > hi)
                or (above is not None and item <= above)):
            raise ConfigError(f"{key}: must be {range_text(lo, hi, above)}, got {number_text(item)}")


@dataclass
class TrainerConfig:
    """The run's length and bookkeeping (the engine's options)."""

    max_iters: int = bounded(2000, 1, MAX_STEPS)  # the run's length (the most steps, with a rule below)
    # > 0: the run is this many steps per training view, within min_iters .. max_iters, so a
    # capture of more views trains longer (resolved once the scene is read; config.yml records it)
    iters_per_view: int = bounded(0, 0, MAX_STEPS)
    # > 0 (and iters_per_view 0): this many steps per million training pixels, within
    # min_iters .. max_iters: a ray field's steps see a fixed number of rays, so a capture of
    # more or larger views needs more of them
    iters_per_mpixel: int = bounded(0, 0, MAX_STEPS)
    min_iters: int = bounded(0, 0, MAX_STEPS)
    stop_at: int = bounded(0, 0, MAX_STEPS)  # stop after this step (0: max_iters); resume continues the same schedule
    seed: int = bounded(0, 0, SEED_MAX)
    device: str = choice("auto", DEVICES)  # auto | cpu | cuda | cuda:N
    log_every: int = bounded(25, 1, MAX_STEPS)
    eval_every: int = bounded(500, 0, MAX_STEPS)  # periodic evaluation on a few views (0: off)
    eval_views: int = bounded(2, 0, MAX_VIEWS)
    checkpoint_every: int = bounded(1000, 0, MAX_STEPS)  # steps between checkpoints (0: only at the end) ...
    checkpoint_minutes: float = bounded(5.0, 0.0, 24 * 60.0)  # ... and at least this often in minutes (0: off)
    keep_checkpoints: int = bounded(2, 0, 1_000_000)  # newest checkpoints kept (0: all)
    output_dir: str = "outputs"
    progress: bool = True
    # The evaluation at the end of rs-train (rs-eval runs the whole protocol on every view):
    # a fixed subset of this many views, spread over both splits (0: all); never bounded by time,
    # so that two evaluations of the same weights give the same metrics
    final_eval_views: int = bounded(8, 0, MAX_VIEWS)


# Keys a saved config.yml may hold that the code no longer has, with why: read and dropped
# (they change nothing a run did), refused on the command line with the reason.
RETIRED_KEYS = {
    "trainer.final_eval_share": "the end-of-run evaluation is bounded by views only "
                                "(trainer.final_eval_views), never by time",
}


def run_length(trainer: TrainerConfig, train_views: int, train_pixels: int = 0) -> int:
    """The steps a run of ``trainer`` trains on a scene of ``train_views`` training views
    holding ``train_pixels`` pixels in all."""
    if trainer.iters_per_view > 0:
        steps = trainer.iters_per_view * train_views
    elif trainer.iters_per_mpixel > 0:
        steps = round(trainer.iters_per_mpixel * train_pixels / 1e6)
    else:
        return trainer.max_iters
    return max(min(steps, trainer.max_iters), min(trainer.min_iters, trainer.max_iters))


@dataclass
class PhaseConfig:
    """One phase of a method's schedule: how long it runs, what a step sees, what acts in it.

    Phases run in the order the method lists them; each ends at ``end`` (a fraction of
    ``trainer.max_iters``) and the last at the end of the run. Loss terms name the phases
    they act in (``LossConfig.phases``).
    """

    end: float = bounded(1.0, 0.0, 1.0)  # this phase runs until step round(end * max_iters)
    patches: int = bounded(1, 1, 65536)  # a batch: this many windows from random training views ...
    patch_size: int = bounded(64, 0, 8192)  # ... of this size in pixels (0: whole images)
    heads: tuple[str, ...] = ()  # pipeline heads predicting image layers here (e.g. rain_head)
    field_lr_scale: float = bounded(1.0, 0.0, 1000.0)  # the field's scheduled lr times this ...
    field_lr: float | None = bounded(None, 0.0, 10.0)  # ... or this fixed lr (the paper's NeRF: 1e-6)
    # each model's gradient norm clipped to this before its step (0: no clipping; the authors'
    # code clips at 1 in its 3DGS joint phase)
    grad_clip: float = bounded(0.0, 0.0, 1e6)
    # beyond the paper: each step the heads also learn on this many whole training views
    # against the field's cached render of them (engine/render_cache.py); for ray fields,
    # whose batches show a head each pixel about once a run (0: off)
    head_views: int = bounded(0, 0, 64)
    # ray fields: a step also fits this many single random rays to the input less the heads'
    # last whole-view layers (the per-pixel terms only; needs head_views); its loss is the
    # pixel-weighted mean over the windows and the rays
    rays: int = bounded(0, 0, 1 << 20)
    # with head_views: every this many steps one whole training view (each in turn) is
    # rendered without gradients into the render cache, so that the heads learn against a
    # recent background (0: the cache holds only the batches' renders, hundreds of steps old)
    refresh_every: int = bounded(0, 0, 1 << 20)


@dataclass
class ComponentConfig:
    name: str
    options: Any = field(default_factory=dict)  # a recipe's dict; the component's Config once materialised


@dataclass
class LossConfig:
    name: str  # the registered loss component
    weight: float = bounded(1.0, 0.0, 1e6)
    phases: tuple[str, ...] = ()  # the phases it acts in (empty: the loss class's default phases)
    detach: str = ""  # "" | "rendered" | "rain": stop gradients into that input
    options: Any = field(default_factory=dict)


@dataclass
class PipelineConfig:
    method: str
    dataparser: ComponentConfig
    field: ComponentConfig
    phases: dict[str, PhaseConfig] = field(default_factory=lambda: {"fit": PhaseConfig()})
    rain_head: ComponentConfig | None = None
    losses: dict[str, LossConfig] = field(default_factory=dict)
    postprocess: dict[str, ComponentConfig] = field(default_factory=dict)
    trainer: TrainerConfig = field(default_factory=TrainerConfig)
    data: str = ""  # scene folder; empty runs the embedded demo scene
    profile: str = "cpu"  # which recipe of the method this is (cpu | gpu)

    def heads(self) -> dict[str, ComponentConfig]:
        """The image-layer heads of the pipeline, by config key."""
        return {} if self.rain_head is None else {"rain_head": self.rain_head}


@dataclass
class MethodSpec:
    """A method: its CPU recipe (minutes on a laptop) and the overrides that turn it into its
    GPU recipe (the paper's scale). Recipes hold component options as plain dicts."""

    name: str
    description: str
    config: PipelineConfig  # the CPU recipe
    gpu: list[str] = field(default_factory=list)  # key=value overrides: the GPU recipe


# --------------------------------------------------------------------------- types


@dataclass
class _Empty:
    pass


def config_class(kind: str, name: str) -> type:
    """The ``Config`` dataclass of a registered component (an empty one if it has none)."""
    comp = registry.load(kind, name)
    cfg = getattr(comp, "Config", None)
    if cfg is None:
        return _Empty
    if not is_dataclass(cfg):
        raise ConfigError(f"{kind} '{name}': its Config is not a dataclass")
    return cfg


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
            value = float(text)
            if not math.isfinite(value):
                raise ConfigError(f"{key}: {text} is not a finite number")
            return value
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


def coerce_field(cls: type, name: str, value: Any, key: str) -> Any:
    """``value`` coerced to field ``name`` of dataclass ``cls`` and checked against its range."""
    f = next(f for f in fields(cls) if f.name == name)
    out = coerce(value, typing.get_type_hints(cls)[name], key)
    check_range(out, f.metadata, key)
    return out


def _type_name(tp: Any) -> str:
    inner, optional = _strip_optional(tp)
    name = getattr(inner, "__name__", None) or str(inner).replace("typing.", "")
    return f"{name} or none" if optional else name


def build_dataclass(cls: type, values: dict, where: str) -> Any:
    """``cls(**values)`` with every key known, every value coerced and range-checked."""
    valid = [f.name for f in fields(cls)]
    kwargs = {}
    for key, value in values.items():
        if key not in valid:
            raise ConfigError(unknown_key_message(f"{where}.{key}", key, valid))
        kwargs[key] = coerce_field(cls, key, value, f"{where}.{key}")
    out = cls(**kwargs)
    for f in fields(cls):  # defaults pass the range check too (a component's bad default is a bug)
        if f.name not in kwargs and f.metadata:
            coerce_field(cls, f.name, getattr(out, f.name), f"{where}.{f.name}")
    return out


def set_option(obj: Any, path: list[str], value: Any, where: str) -> None:
    """Set ``obj.<path[0]>`` (a dataclass field) from text, typed and range-checked."""
    if len(path) != 1:
        raise ConfigError(f"{where}.{'.'.join(path)}: options are one level deep under {where}")
    name = path[0]
    valid = [f.name for f in fields(obj)]
    if f"{where}.{name}" in RETIRED_KEYS:
        raise ConfigError(f"{where}.{name}: no longer an option: {RETIRED_KEYS[f'{where}.{name}']}")
    if name not in valid:
        raise ConfigError(unknown_key_message(f"{where}.{name}", name, valid))
    setattr(obj, name, coerce_field(type(obj), name, value, f"{where}.{name}"))


def unknown_key_message(full_key: str, key: str, valid: list[str]) -> str:
    close = difflib.get_close_matches(key, valid, n=1)
    hint = f" Did you mean '{close[0]}'?" if close else ""
    return f"unknown key '{full_key}'.{hint} Valid keys here: {', '.join(valid) or '(none)'}"


# --------------------------------------------------------------------- materialize


def materialize_component(kind: str, comp: ComponentConfig, where: str) -> ComponentConfig:
    """The component with its options as its typed ``Config`` (a copy; validated)."""
    cls = config_class(kind, comp.name)
    opts = comp.options
    values = dataclasses.asdict(opts) if is_dataclass(opts) else dict(opts or {})
    return ComponentConfig(comp.name, build_dataclass(cls, values, where))


def default_phases(name: str, method_phases: list[str]) -> tuple[str, ...]:
    """The phases a loss term added without ``phases`` acts in: the loss class's own
    (those of them the method has), else every phase of the method."""
    own = [p for p in getattr(registry.load("loss", name), "phases", ()) if p in method_phases]
    return tuple(own or method_phases)


def materialize(cfg: PipelineConfig) -> PipelineConfig:
    """A copy of ``cfg`` with typed component options, checked phases and loss terms."""
    out = copy.deepcopy(cfg)
    if cfg.profile not in PROFILES:
        raise ConfigError(f"profile: '{cfg.profile}' is not one of auto, {', '.join(PROFILES)}")
    if not cfg.phases:
        raise ConfigError("the method declares no phases")
    out.phases = {name: build_dataclass(PhaseConfig, _fields_of(p), f"phases.{name}")
                  for name, p in cfg.phases.items()}
    _check_phases(out)
    out.trainer = build_dataclass(TrainerConfig, _fields_of(cfg.trainer), "trainer")
    out.dataparser = materialize_component("dataparser", cfg.dataparser, "dataparser")
    out.field = materialize_component("field", cfg.field, "field")
    if cfg.rain_head is not None:
        out.rain_head = materialize_component("rain_head", cfg.rain_head, "rain_head")
    names = list(out.phases)
    out.losses = {}
    for key, loss in cfg.losses.items():
        comp = materialize_component("loss", ComponentConfig(loss.name, loss.options), f"losses.{key}")
        phases = tuple(loss.phases) or default_phases(loss.name, names)
        bad = [p for p in phases if p not in names]
        if bad:
            raise ConfigError(f"losses.{key}.phases: unknown phase {bad[0]!r}; this method's phases "
                              f"are {', '.join(names)}")
        if loss.detach not in DETACHABLE:
            raise ConfigError(f"losses.{key}.detach: '{loss.detach}' is not one of "
                              f"'', {', '.join(DETACHABLE[1:])}")
        out.losses[key] = dataclasses.replace(loss, options=comp.options, phases=phases,
                                              weight=float(loss.weight))
    out.postprocess = {key: materialize_component("postprocess", pp, f"postprocess.{key}")
                       for key, pp in cfg.postprocess.items()}
    return out


def _fields_of(obj: Any) -> dict:
    return {f.name: getattr(obj, f.name) for f in fields(obj)} if is_dataclass(obj) else dict(obj)


def _check_phases(cfg: PipelineConfig) -> None:
    heads = cfg.heads()
    ends = [p.end for p in cfg.phases.values()]
    if any(b < a for a, b in zip(ends, ends[1:])):
        raise ConfigError(f"phases end in order: got ends {ends} for {', '.join(cfg.phases)}")
    for name, phase in cfg.phases.items():
        for head in phase.heads:
            if head not in heads:
                have = ", ".join(heads) or "none (set rain_head=NAME)"
                raise ConfigError(f"phases.{name}.heads: '{head}' is not a head of this pipeline; "
                                  f"its heads: {have}")


def describe_run_length(trainer: TrainerConfig) -> str:
    """The rule :func:`run_length` applies, in words (for ``--help``)."""
    bounds = f"at least {min(trainer.min_iters, trainer.max_iters)} and at most {trainer.max_iters}"
    if trainer.iters_per_view > 0:
        return (f"{trainer.iters_per_view} steps per training view, {bounds} (trainer.iters_per_view, "
                "trainer.min_iters, trainer.max_iters; trainer.iters_per_view=0 makes it trainer.max_iters)")
    if trainer.iters_per_mpixel > 0:
        return (f"{trainer.iters_per_mpixel} steps per million training pixels, {bounds} "
                "(trainer.iters_per_mpixel, trainer.min_iters, trainer.max_iters; "
                "trainer.iters_per_mpixel=0 makes it trainer.max_iters)")
    return f"{trainer.max_iters} steps (trainer.max_iters)"


def with_run_length(cfg: PipelineConfig, train_views: int, train_pixels: int = 0) -> PipelineConfig:
    """``cfg`` with ``trainer.max_iters`` resolved by :func:`run_length` for a scene of
    ``train_views`` training views of ``train_pixels`` pixels in all (the same config when no
    rule applies)."""
    length = run_length(cfg.trainer, train_views, train_pixels)
    if length == cfg.trainer.max_iters:
        return cfg
    return dataclasses.replace(cfg, trainer=dataclasses.replace(cfg.trainer, max_iters=length))


def is_materialized(cfg: PipelineConfig) -> bool:
    return is_dataclass(cfg.field.options) and is_dataclass(cfg.dataparser.options)


def require_typed(cfg: PipelineConfig, what: str) -> None:
    """TypeError unless ``cfg`` is typed (a programming error: configs come from method_config
    or load_yaml)."""
    if not is_materialized(cfg):
        raise TypeError(f"{what} needs a typed config (from method_config or load_yaml)")
