"""``key=value`` overrides of a typed config, method lookup, and the ``--help`` tree.

Keys: ``data``, ``dataparser[.KEY]``, ``field[.KEY]``, ``rain_head[.KEY]`` (``=none`` drops
it), ``phases.PHASE.KEY``, ``losses.TERM.{weight,phases,detach,name,KEY}`` (``=none`` drops a
term; a new TERM adds that loss, or the loss ``losses.TERM.name`` names),
``postprocess.NAME[.KEY]`` (``=on|none``), ``trainer.KEY``.
"""

from __future__ import annotations

import copy
import dataclasses
import sys
from dataclasses import fields
from typing import Any

from rainyscape import registry
from rainyscape.config.schema import (ComponentConfig, LossConfig, MethodSpec, PipelineConfig,
                                      coerce_field, default_phases, is_materialized, materialize,
                                      materialize_component, set_option, unknown_key_message)
from rainyscape.errors import ConfigError

_LOSS_GENERIC = {f.name for f in fields(LossConfig)} - {"options", "name"}
TOP_KEYS = ["data", "profile", "dataparser", "field", "rain_head", "phases", "losses", "postprocess", "trainer"]


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


def apply_overrides(cfg: PipelineConfig, overrides: list[tuple[str, str]]) -> PipelineConfig:
    """``key=value`` pairs applied to a typed config; returns a new, validated config."""
    if not is_materialized(cfg):
        raise TypeError("apply_overrides needs a typed config (from method_config or load_yaml)")
    cfg = copy.deepcopy(cfg)
    # Component swaps first so that their options can be set in the same command.
    for key, value in sorted(overrides, key=lambda kv: kv[0].count(".")):
        parts = key.split(".")
        head = parts[0]
        if head in ("method", "profile"):
            raise ConfigError(f"{head}= picks the method's recipe; it cannot be changed inside a config")
        if head == "data" and len(parts) == 1:
            cfg.data = value
        elif head in ("dataparser", "field", "rain_head") and len(parts) == 1:
            _swap_component(cfg, head, value)
        elif head in ("dataparser", "field", "rain_head"):
            comp = getattr(cfg, head)
            if comp is None:
                raise ConfigError(f"{key}: this method has no {head}; set {head}=NAME first")
            if head == "dataparser" and len(parts) == 2 and parts[1] not in {f.name for f in fields(comp.options)}:
                _resolve_for_option(cfg, key)
                comp = cfg.dataparser
            set_option(comp.options, parts[1:], value, head)
        elif head == "trainer":
            set_option(cfg.trainer, parts[1:], value, "trainer")
        elif head == "phases":
            _override_phase(cfg, parts, value, key)
        elif head == "losses":
            _override_loss(cfg, parts, value, key)
        elif head == "postprocess":
            _override_postprocess(cfg, parts, value, key)
        else:
            raise ConfigError(unknown_key_message(key, head, TOP_KEYS))
    return materialize(cfg)


def resolve_dataparser(cfg: PipelineConfig) -> PipelineConfig | None:
    """``cfg`` with a resolving dataparser (``auto``) replaced by the one it picks for the
    scene folder ``data=`` (its options carried over); None when it does not resolve or no
    folder is set. Raises the parser's DataError for a folder it cannot read."""
    cls = registry.load("dataparser", cfg.dataparser.name)
    if not cfg.data or not callable(getattr(cls, "resolve", None)):
        return None
    name = cls.resolve(cfg.data)
    if name == cfg.dataparser.name:
        return None
    out = copy.deepcopy(cfg)
    target = materialize_component("dataparser", ComponentConfig(name, {}), "dataparser")
    shared = {f.name for f in fields(target.options)} & {f.name for f in fields(cfg.dataparser.options)}
    for k in shared:
        setattr(target.options, k, getattr(cfg.dataparser.options, k))
    out.dataparser = target
    return out


def _resolve_for_option(cfg: PipelineConfig, key: str) -> None:
    """``dataparser.KEY`` unknown to the current (resolving) dataparser: resolve it from the
    scene folder so that the detected format's options are accepted."""
    cls = registry.load("dataparser", cfg.dataparser.name)
    if not callable(getattr(cls, "resolve", None)):
        return  # set_option names the valid keys
    if not cfg.data:
        valid = ", ".join(f.name for f in fields(cfg.dataparser.options))
        raise ConfigError(f"{key}: dataparser={cfg.dataparser.name} knows only its common options "
                          f"({valid}) until it sees the scene: give data=SCENE_FOLDER, or name the "
                          "format with dataparser=NAME (rs-train --list)")
    resolved = resolve_dataparser(cfg)
    if resolved is not None:
        print(f"dataparser={cfg.dataparser.name}: {cfg.data} is {resolved.dataparser.name}; "
              f"using its options", file=sys.stderr)
        cfg.dataparser = resolved.dataparser


def _swap_component(cfg: PipelineConfig, head: str, value: str) -> None:
    if head == "rain_head" and value.lower() in ("none", ""):
        cfg.rain_head = None
        for phase in cfg.phases.values():  # nothing left to predict the rain layer
            phase.heads = tuple(h for h in phase.heads if h != "rain_head")
        return
    setattr(cfg, head, materialize_component(head, ComponentConfig(value, {}), head))


def _override_phase(cfg: PipelineConfig, parts: list[str], value: str, key: str) -> None:
    if len(parts) != 3:
        raise ConfigError(f"{key}: expected phases.PHASE.OPTION=value")
    if parts[1] not in cfg.phases:
        raise ConfigError(unknown_key_message(key, parts[1], list(cfg.phases)))
    set_option(cfg.phases[parts[1]], parts[2:], value, f"phases.{parts[1]}")


def _override_loss(cfg: PipelineConfig, parts: list[str], value: str, key: str) -> None:
    if len(parts) == 2 and value.lower() == "none":
        cfg.losses.pop(parts[1], None)  # losses.tv=none drops a term
        return
    if len(parts) != 3:
        raise ConfigError(f"{key}: expected losses.TERM.OPTION=value (or losses.TERM=none)")
    term, opt = parts[1], parts[2]
    if term not in cfg.losses:
        # A new term: the loss named by losses.TERM.name=LOSS, or else TERM itself (its
        # default phases apply).
        name = value if opt == "name" else term
        comp = materialize_component("loss", ComponentConfig(name, {}), f"losses.{term}")
        cfg.losses[term] = LossConfig(name, weight=1.0, phases=default_phases(name, list(cfg.phases)),
                                      options=comp.options)
    loss = cfg.losses[term]
    if opt == "name":
        comp = materialize_component("loss", ComponentConfig(value, {}), f"losses.{term}")
        cfg.losses[term] = dataclasses.replace(loss, name=value, options=comp.options)
    elif opt in _LOSS_GENERIC:
        setattr(loss, opt, coerce_field(LossConfig, opt, value, key))
    else:
        try:
            set_option(loss.options, [opt], value, f"losses.{term}")
        except ConfigError as exc:
            if "unknown key" not in str(exc):
                raise
            valid = sorted(_LOSS_GENERIC | {"name"} | {f.name for f in fields(loss.options)})
            raise ConfigError(unknown_key_message(key, opt, valid)) from None


def _override_postprocess(cfg: PipelineConfig, parts: list[str], value: str, key: str) -> None:
    if len(parts) == 2 and value.lower() == "none":
        cfg.postprocess.pop(parts[1], None)
        return
    if len(parts) == 2 and value.lower() in ("on", "true"):
        cfg.postprocess[parts[1]] = materialize_component("postprocess", ComponentConfig(parts[1], {}), key)
        return
    if len(parts) != 3:
        raise ConfigError(f"{key}: expected postprocess.NAME.OPTION=value, postprocess.NAME=on|none")
    name = parts[1]
    if name not in cfg.postprocess:
        cfg.postprocess[name] = materialize_component("postprocess", ComponentConfig(name, {}), key)
    set_option(cfg.postprocess[name].options, [parts[2]], value, f"postprocess.{name}")


# ------------------------------------------------------------------------ methods


def method_spec(name: str) -> MethodSpec:
    spec = registry.load("method", name)
    if not isinstance(spec, MethodSpec):
        raise ConfigError(f"method '{name}' is registered but is not a MethodSpec")
    return spec


def method_config(name: str, overrides: list[str] | None = None) -> PipelineConfig:
    """The method's typed config, in the recipe ``profile=`` picks (auto: gpu when the run's
    device is CUDA), with the other ``key=value`` overrides applied and validated."""
    spec = method_spec(name)
    pairs = parse_overrides(overrides or [])
    profile = next((v for k, v in reversed(pairs) if k == "profile"), "auto")
    pairs = [(k, v) for k, v in pairs if k != "profile"]
    cfg = materialize(copy.deepcopy(spec.config))
    if profile == "auto":
        device = next((v for k, v in reversed(pairs) if k == "trainer.device"), cfg.trainer.device)
        profile = "gpu" if uses_cuda(device) else "cpu"
    cfg = dataclasses.replace(cfg, profile=profile)
    if profile == "gpu":
        cfg = apply_overrides(cfg, parse_overrides(spec.gpu))
    return apply_overrides(cfg, pairs)


def uses_cuda(device: str) -> bool:
    """Whether a run on ``device`` (auto | cpu | cuda[:N]) trains on a CUDA GPU."""
    if device == "auto":
        import torch  # only here: choosing the recipe for auto needs to look

        return torch.cuda.is_available()
    return device.startswith("cuda")


def describe_tree(cfg: PipelineConfig) -> str:
    """The whole config as dotted ``key = value`` lines, for ``--help``."""
    from rainyscape.config.yaml_io import to_dict

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
