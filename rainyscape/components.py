"""The small interfaces components implement and the dataclasses they exchange.

A component class is registered under an entry point and is built as
``cls(config, scene)`` where ``config`` is an instance of its nested ``Config`` dataclass
and ``scene`` the :class:`~rainyscape.scene.SceneData` (losses and post-processes get
``cls(config)``). Its ``description`` (or docstring's first line) shows in ``rs-train --list``.

Images exchanged between components are float tensors (B, 3, h, w) in [0, 1] (rain
maps are >= 0), on the training device.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

import torch
from torch import Tensor, nn

from rainyscape.cameras import Cameras, Window
from rainyscape.scene import SceneData


@dataclass
class ParamGroup:
    """Parameters sharing one Adam optimiser and learning-rate schedule.

    lr(step) = lr * lr_decay ** (step / lr_decay_steps) (no decay when lr_decay_steps is 0);
    in the joint phase ``lr_joint`` (when set) replaces it, as the paper does for NeRF.
    """

    name: str
    params: list[nn.Parameter]
    lr: float
    lr_decay: float = 1.0
    lr_decay_steps: int = 0
    lr_joint: float | None = None
    betas: tuple[float, float] = (0.9, 0.999)
    eps: float = 1e-8


@dataclass
class RenderOutput:
    rgb: Tensor  # (B, 3, h, w) in [0, 1]
    depth: Tensor | None = None  # (B, 1, h, w) z-depth
    acc: Tensor | None = None  # (B, 1, h, w) accumulated opacity
    extras: dict[str, Any] = field(default_factory=dict)  # field-specific (coarse rgb, 2D means...)


@dataclass
class TrainState:
    """What callbacks see: where training is and the optimisers (by param-group name)."""

    step: int
    max_iters: int
    warmup_iters: int
    phase: str  # "warmup" | "joint"
    optimizers: dict[str, torch.optim.Optimizer]
    device: torch.device


class Callback:
    """Hooks the trainer calls at fixed places; override the ones you need."""

    def on_phase_start(self, state: TrainState) -> None: ...

    def before_step(self, state: TrainState) -> None: ...

    def after_backward(self, state: TrainState, output: RenderOutput) -> None: ...

    def after_step(self, state: TrainState) -> None: ...

    def after_training(self, state: TrainState) -> None: ...

    def state_dict(self) -> dict:
        return {}

    def load_state_dict(self, state: dict) -> None: ...


class Field(nn.Module):
    """A radiance field: renders windows of cameras. Knows nothing of rain."""

    description = ""

    def render(self, cameras: Cameras, window: Window) -> RenderOutput:
        """Render ``window`` of each camera (B cameras, B window offsets).

        Must bound memory for large windows (chunking) and honour ``self.training``.
        """
        raise NotImplementedError  # abstract: every field implements it

    def param_groups(self) -> list[ParamGroup]:
        raise NotImplementedError  # abstract

    def callbacks(self) -> list[Callback]:
        return []

    def extra_losses(self, output: RenderOutput, target: Tensor) -> dict[str, Tensor]:
        """Field-internal losses given what ``output.rgb`` should match (e.g. a coarse network)."""
        return {}


class RainHead(nn.Module):
    """Predicts a rain layer R >= 0 for (view, window) from learnable latents."""

    description = ""

    def forward(self, view_ids: Tensor, window: Window) -> Tensor:  # (B, 3, h, w)
        raise NotImplementedError  # abstract

    def param_groups(self) -> list[ParamGroup]:
        raise NotImplementedError  # abstract

    def latents(self) -> list[nn.Parameter]:
        """Latent variables updated by Langevin steps (not by the network optimiser)."""
        return []


@dataclass
class LossContext:
    """Everything a loss term may look at for one batch."""

    rendered: Tensor  # B: the field's render (B, 3, h, w)
    target: Tensor  # I: the rainy input (B, 3, h, w)
    rain: Tensor | None  # R: predicted rain (B, 3, h, w), None in warm-up
    output: RenderOutput
    view_ids: Tensor
    step: int
    phase: str


class Loss:
    """A loss term: ``__call__(ctx) -> scalar``. ``phases`` are its default phases.

    ``metrics`` may be filled during a call (floats) and is logged by the trainer.
    Stateful terms implement ``state_dict`` / ``load_state_dict`` for checkpoints.
    """

    phases: tuple[str, ...] = ("joint",)
    description = ""

    def __init__(self, config: Any = None):
        self.config = config
        self.metrics: dict[str, float] = {}

    def __call__(self, ctx: LossContext) -> Tensor:
        raise NotImplementedError  # abstract

    def state_dict(self) -> dict:
        return {}

    def load_state_dict(self, state: dict) -> None: ...


class PostProcess:
    """``__call__(rendered, rain, rainy) -> image`` on one training view (3, H, W)."""

    description = ""

    def __init__(self, config: Any = None):
        self.config = config

    def __call__(self, rendered: Tensor, rain: Tensor, rainy: Tensor) -> Tensor:
        raise NotImplementedError  # abstract


class DataParser:
    """Reads a scene folder: ``cls(config).parse(path) -> SceneData``.

    Errors about the input raise :class:`rainyscape.errors.DataError` naming the file.
    """

    description = ""

    def __init__(self, config: Any = None):
        self.config = config

    def parse(self, path: Path) -> SceneData:
        raise NotImplementedError  # abstract


# ------------------------------------------------------------------ declared capabilities
# Optional abilities a component states by implementing them; callers check with
# isinstance(obj, Protocol) instead of probing attribute names.


@runtime_checkable
class DensityField(Protocol):
    """A field with a volume density (for meshing)."""

    def density(self, points: Tensor) -> Tensor:
        """Volume density (P,) at world points (P, 3) of the normalised scene."""


@runtime_checkable
class PlyExportable(Protocol):
    """A field that writes itself as a standard 3DGS ``.ply``."""

    def export_ply(self, path: Path) -> None: ...


@runtime_checkable
class HasEmbeddings(Protocol):
    """A rain head whose prediction is steered by a scene state, per-view states and per-view
    camera vectors (the paper's s, v_i and p_i; the embedding study perturbs them)."""

    scene_state: Tensor  # (D,)
    view_states: Tensor  # (N, D)
    camera_vectors: Tensor  # (N, P)
