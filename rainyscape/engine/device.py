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
