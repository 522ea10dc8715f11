"""The whole training state as one checkpointable dict, and back.

Models (the field and the heads, latents included), every optimiser, stateful loss terms,
callback state and all random-number-generator states, so that a resumed run continues
exactly. Everything is tensors and plain Python values: checkpoints load with
``torch.load(weights_only=True)``, which never runs code from the file.
"""

from __future__ import annotations

import random
from dataclasses import dataclass, field

import numpy as np
import torch
from torch import nn

from rainyscape.components import Callback, Loss
from rainyscape.engine.render_cache import LayerCache, RenderCache


@dataclass
class TrainingParts:
    """What a snapshot covers (the trainer's live objects)."""

    models: dict[str, nn.Module]  # "field" and each head, by pipeline key
    optimizers: dict[str, torch.optim.Optimizer]
    losses: dict[str, Loss]
    callbacks: list[Callback]
    generator: torch.Generator  # the batch sampler's
    render_cache: RenderCache | None = None  # the field's last renders, where a phase uses them
    layer_caches: dict[str, LayerCache] = field(default_factory=dict)  # the heads' last whole views, by layer


def rng_state() -> dict:
    """torch, CUDA, numpy and Python RNG states as tensors and plain values."""
    _, keys, pos, has_gauss, cached = np.random.get_state()
    version, internal, gauss_next = random.getstate()
    return {
        "torch": torch.get_rng_state(),
        "cuda": torch.cuda.get_rng_state_all() if torch.cuda.is_available() else None,
        "numpy": {"keys": torch.from_numpy(np.asarray(keys, np.int64)), "pos": int(pos),
                  "has_gauss": int(has_gauss), "cached": float(cached)},
        "python": {"version": int(version), "internal": list(internal), "gauss_next": gauss_next},
    }


def set_rng_state(state: dict) -> None:
    torch.set_rng_state(state["torch"].cpu())
    if state.get("cuda") is not None and torch.cuda.is_available():
        torch.cuda.set_rng_state_all([s.cpu() for s in state["cuda"]])
    n = state["numpy"]
    np.random.set_state(("MT19937", n["keys"].numpy().astype(np.uint32), n["pos"], n["has_gauss"],
                         n["cached"]))
    p = state["python"]
    random.setstate((p["version"], tuple(p["internal"]), p["gauss_next"]))


def capture(step: int, parts: TrainingParts) -> dict:
    return {
        "step": step,
        "models": {k: m.state_dict() for k, m in parts.models.items()},
        "optimizers": {k: o.state_dict() for k, o in parts.optimizers.items()},
        "losses": {k: t.state_dict() for k, t in parts.losses.items()},
        "callbacks": [cb.state_dict() for cb in parts.callbacks],
        "rng": {"sampler": parts.generator.get_state(), **rng_state()},
        "render_cache": parts.render_cache.state_dict() if parts.render_cache is not None else None,
        "layer_caches": {k: c.state_dict() for k, c in parts.layer_caches.items()},
    }


def restore_models(state: dict, models: dict[str, nn.Module]) -> None:
    """Load the models' weights (first, so that fields can resize their parameters)."""
    for key, model in models.items():
        if state["models"].get(key) is not None:
            model.load_state_dict(state["models"][key])


def restore_rest(state: dict, parts: TrainingParts) -> None:
    """Optimisers (built for the restored models), loss terms, callbacks and RNG states."""
    for k, opt in parts.optimizers.items():
        if k in state["optimizers"]:
            opt.load_state_dict(state["optimizers"][k])
    for k, term in parts.losses.items():
        if k in state.get("losses", {}):
            term.load_state_dict(state["losses"][k])
    for cb, cb_state in zip(parts.callbacks, state.get("callbacks", [])):
        cb.load_state_dict(cb_state)
    if parts.render_cache is not None and state.get("render_cache") is not None:
        parts.render_cache.load_state_dict(state["render_cache"])
    for k, cache in parts.layer_caches.items():
        if k in state.get("layer_caches", {}):
            cache.load_state_dict(state["layer_caches"][k])
    parts.generator.set_state(state["rng"]["sampler"].cpu())
    set_rng_state(state["rng"])
