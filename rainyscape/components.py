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
from typing import Any, Callable, Protocol, runtime_checkable

import torch
from torch import Tensor, nn

from rainyscape.cameras import Cameras, Window
from rainyscape.scene import SceneData


@dataclass
class ParamGroup:
    """Parameters sharing one Adam optimiser and one learning-rate schedule.

    lr(step) = lr * lr_decay ** (step / span), span = ``lr_decay_steps`` or, when that is 0,
    the whole run (so ``lr_decay`` is then the final lr over the initial one, as 3DGS's
    position lr). After ``anneal_at`` of the run the lr is further multiplied by
    ``anneal_to ** progress`` (progress 0 to 1 over the rest of the run): a late anneal that
    lets the last steps settle without slowing the run's middle. A phase may scale or fix the
    field's lr (``PhaseConfig``).
    """

    name: str
    params: list[nn.Parameter]
    lr: float
    lr_decay: float = 1.0
    lr_decay_steps: int = 0
    betas: tuple[float, float] = (0.9, 0.999)
    eps: float = 1e-8
    anneal_at: float = 1.0
    anneal_to: float = 1.0

    def lr_at(self, step: int, total_steps: int) -> float:
        lr = self.lr
        if self.lr_decay != 1.0:
            lr *= self.lr_decay ** (step / (self.lr_decay_steps or total_steps))
        start = self.anneal_at * total_steps
        if self.anneal_to != 1.0 and step > start:
            lr *= self.anneal_to ** ((step - start) / max(total_steps - start, 1))
        return lr


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
    phase: str  # the method's name for the current phase
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
    # Per-pixel quantities the field can add to its training renders' extras when a loss
    # term asks (they cost time, so they are computed only then), and those asked for.
    provides: tuple[str, ...] = ()
    requested: frozenset[str] = frozenset()

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

    def request(self, names: set[str]) -> None:
        """Add ``names`` (from :attr:`provides`) to every training render's extras."""
        self.requested = frozenset(names)

    def stats(self) -> dict[str, float]:
        """Numbers describing the field's current state (its size, resolution, cumulative counts
        of structural changes) that the trainer logs with each record as ``stats.field.KEY``."""
        return {}


class ImageHead(nn.Module):
    """Predicts an image layer for (view, window): the observed image is the field's render
    with the layers of the heads active in the phase laid over it (:meth:`composite`; an
    additive layer by default). ``layer`` names it for the losses (``LossContext.layers``)."""

    description = ""
    layer = ""

    def forward(self, view_ids: Tensor, window: Window) -> Tensor:  # (B, C, h, w), C = 3 if additive
        raise NotImplementedError  # abstract

    def param_groups(self) -> list[ParamGroup]:
        raise NotImplementedError  # abstract

    def composite(self, below: Tensor, layer: Tensor) -> Tensor:
        """The image (B, 3, h, w) that ``layer`` (this head's prediction) makes of ``below``
        (the render, with the layers of earlier heads): ``below + layer`` for an additive
        layer; a head predicting an occluding (colour, alpha) layer lays it over instead."""
        return below + layer

    def for_field(self, layer: Tensor, residual: Tensor, view_ids: Tensor,
                  background: Tensor | None = None) -> Tensor:
        """What of ``layer`` (B, C, h, w) the field is fitted without: what the terms that
        see the layer detached and a ray field's single rays read (``residual``: the input
        less the field's render there, ``background``; ``view_ids`` (B,): whose views). The
        whole layer unless the head reshapes it (the rain head narrows it to its streaks,
        raises it where the residual shows more rain than it holds, and keeps it where the
        residual has the rain's colour)."""
        return layer

    def callbacks(self) -> list[Callback]:
        """Hooks the trainer calls for this head (e.g. changing its parameter set)."""
        return []

    def stats(self) -> dict[str, float]:
        """Numbers describing the head's current state (as :meth:`Field.stats`), logged as
        ``stats.KEY.NAME`` with KEY the head's config key (e.g. ``rain_head``)."""
        return {}


Energy = Callable[[Window, Tensor], Tensor]


@runtime_checkable
class LatentModel(Protocol):
    """A head with latent variables that it updates itself after each network update."""

    def update_latents(self, view_ids: Tensor, window: Window, energy: Energy,
                       generator: torch.Generator) -> None:
        """Update the latents with the networks frozen. ``energy(sub_window, prediction)`` is
        the phase's loss for a prediction of ``sub_window`` (a window inside ``window``, with
        the same offsets convention), everything else held at this step's values."""


class RainHead(ImageHead):
    """Predicts a rain layer R >= 0 for (view, window) from learnable latents."""

    layer = "rain"

    def latents(self) -> list[nn.Parameter]:
        """Latent variables updated by :meth:`update_latents` (not by the network optimiser)."""
        return []


@dataclass
class LossContext:
    """Everything a loss term may look at for one batch."""

    rendered: Tensor  # B: the field's render (B, 3, h, w)
    target: Tensor  # I: the observed (rainy) input (B, 3, h, w)
    layers: dict[str, Tensor]  # image layers predicted by the phase's heads, by name
    output: RenderOutput | None
    view_ids: Tensor
    step: int
    phase: str
    window: Window | None = None  # which pixels of the views the batch holds
    # False while a head's latent update evaluates the loss as its energy (on a crop): terms
    # then leave what they record (metrics, estimated angles) to the network update's call
    record: bool = True
    # Each layer as the field is fitted without it (the head's ``for_field``): what a term
    # that sees a layer detached reads; absent: the layer itself
    field_layers: dict[str, Tensor] = field(default_factory=dict)
    # What terms derive from the batch alone (the input, the detached render and depth), not
    # from any layer: a latent update evaluates its energy several times on one context, and
    # these stay the same (copies made with ``replace`` share it; a new window needs a new one)
    memo: dict = field(default_factory=dict, repr=False, compare=False)

    def memoized(self, key, compute):
        """``compute()``, once per context and key (see ``memo``)."""
        if key not in self.memo:
            self.memo[key] = compute()
        return self.memo[key]

    @property
    def rain(self) -> Tensor | None:
        """R: the predicted rain (B, 3, h, w), None where no rain head runs."""
        return self.layers.get("rain")


class Loss:
    """A loss term: ``__call__(ctx) -> scalar``. ``phases`` are its default phases (used
    where the method has them), ``needs`` the image layers it cannot do without, ``spatial``
    whether it compares neighbouring pixels (a phase's single rays, ``PhaseConfig.rays``, do
    not feed it).

    ``metrics`` may be filled during a call (floats) and is logged by the trainer.
    Stateful terms implement ``state_dict`` / ``load_state_dict`` for checkpoints.
    """

    phases: tuple[str, ...] = ()
    needs: tuple[str, ...] = ()
    render_extras: tuple[str, ...] = ()  # per-pixel quantities it reads from the field's render (Field.provides)
    spatial = False
    description = ""

    def __init__(self, config: Any = None):
        self.config = config
        self.metrics: dict[str, float] = {}

    def __call__(self, ctx: LossContext) -> Tensor:
        raise NotImplementedError  # abstract

    def setup(self, scene: SceneData, device: torch.device) -> None:
        """Called once the pipeline is built; terms that look at other views keep what they need."""

    def callbacks(self) -> list[Callback]:
        """Hooks the trainer calls for this term: changes to the parameters it trains that its
        method schedules with it (SpotLessSplats' reset of the view-dependent colour)."""
        return []

    def state_dict(self) -> dict:
        return {}

    def load_state_dict(self, state: dict) -> None: ...


class PostProcess:
    """``__call__(rendered, rain, rainy) -> image`` on one training view (3, H, W); ``rain``
    is the rain head's predicted rain, None in a pipeline without one (``needs_rain``: the
    post-process cannot work then, and the pipeline refuses to build).

    A fusion that keeps rendered pixels under a mask and input pixels elsewhere also states
    :class:`MaskFusion` (its coverage and its random-mask control)."""

    description = ""
    needs_rain = False

    def __init__(self, config: Any = None):
        self.config = config

    def __call__(self, rendered: Tensor, rain: Tensor | None, rainy: Tensor) -> Tensor:
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


@dataclass
class FusionControl:
    """What a mask fusion reports of one training view."""

    coverage: float  # share of the view's pixels the fusion takes from the render
    control: Tensor  # (3, H, W): the same fusion under a random mask of that coverage


@runtime_checkable
class MaskFusion(Protocol):
    """A post-process that keeps rendered pixels under a mask and input pixels elsewhere.
    Evaluation asks it for its coverage and a control, the same fusion under a mask of random
    pixels with the same coverage: a fused gain the control also shows comes from copying the
    input, not from finding the rain."""

    def control(self, rendered: Tensor, rain: Tensor | None, rainy: Tensor, seed: int) -> FusionControl:
        """Coverage of this view's mask and the control (its random mask placed with ``seed``:
        the same seed gives the same mask anywhere)."""


@runtime_checkable
class MeasuresRainAngles(Protocol):
    """A component that estimates the rain's streak directions while training (the AGR loss);
    evaluation measures the angles of the predicted, residual and true rain with its settings,
    so they are measured as training measured them."""

    def angle_settings(self) -> dict[str, Any]:
        """Keyword arguments of :func:`rainyscape.imaging.angles.estimate_rain_angles`
        (``bins``, ``threshold``, ``smoothing``, ``kernel``, ``k``: directions per image,
        ``max_tilt``: the most the streaks lean from the world's down in the view, ``estimator``:
        how the orientation histogram counts)."""


@runtime_checkable
class HasEmbeddings(Protocol):
    """A rain head whose prediction is steered by a scene state, per-view states and per-view
    camera vectors (the paper's s, v_i and p_i; the embedding study perturbs them)."""

    scene_state: Tensor  # (D,)
    view_states: Tensor  # (N, D)
    camera_vectors: Tensor  # (N, P)
