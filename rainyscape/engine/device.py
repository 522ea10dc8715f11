"""Which device a run trains on: ``trainer.device`` (auto | cpu | cuda | cuda:N) checked
against what this machine has."""

from __future__ import annotations

import torch

from rainyscape.errors import ConfigError


def resolve_device(name: str) -> torch.device:
    """The torch device ``name`` asks for (auto: CUDA when present, else the CPU); ConfigError
    naming ``trainer.device`` when it is not one or this machine lacks it."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        dev = torch.device(name)
    except RuntimeError:
        raise ConfigError(f"trainer.device={name}: not a device (auto, cpu, cuda or cuda:N)") from None
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise ConfigError(f"trainer.device={name}, but CUDA is not available here")
    if dev.type not in ("cpu", "cuda"):
        raise ConfigError(f"trainer.device={name}: only cpu and cuda are supported")
    return dev


def flush_denormals(device: torch.device) -> bool:
    """Make CPU arithmetic treat numbers below float32's normal range (1.2e-38) as zero
    (``torch.set_flush_denormal``, kept after the run); whether the CPU allows it.

    Why: Adam's moments of grid texels that rays stopped reaching decay by 0.9 and 0.999 a
    step into that range, where every operation on them takes the slow path. On the 512^3
    grid field the optimiser step then took 60 % of a step and the step twice as long
    (docs/benchmarks.md, "Denormal numbers in the optimiser"). The grid field's figures did
    not move; the Gaussians' round differently from there on (noise-level changes)."""
    if device.type != "cpu":
        return False
    return bool(torch.set_flush_denormal(True))
