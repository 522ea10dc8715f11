"""Checkpoint files: atomic writes, keep the latest N, find the newest."""

from __future__ import annotations

import os
import re
from pathlib import Path

import torch

from rainyscape.errors import RainyScapeError

_NAME = re.compile(r"step-(\d+)\.pt$")


def checkpoint_path(folder: Path, step: int) -> Path:
    return Path(folder) / f"step-{step:07d}.pt"


def list_checkpoints(folder: Path) -> list[Path]:
    folder = Path(folder)
    if not folder.is_dir():
        return []
    found = [(int(m.group(1)), p) for p in folder.iterdir() if (m := _NAME.match(p.name))]
    return [p for _, p in sorted(found)]


def save_checkpoint(folder: Path, step: int, state: dict, keep: int) -> Path:
    """Write ``state`` to a temporary file then rename it in place, so a crash never leaves
    a truncated checkpoint; afterwards delete all but the newest ``keep``."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    final = checkpoint_path(folder, step)
    tmp = final.with_suffix(".pt.tmp")
    torch.save(state, tmp)
    with open(tmp, "rb") as fh:
        os.fsync(fh.fileno())
    os.replace(tmp, final)
    if keep > 0:
        for old in list_checkpoints(folder)[:-keep]:
            old.unlink(missing_ok=True)
    return final


def load_checkpoint(path: Path, device) -> dict:
    """A checkpoint's tensors and plain values; never runs code from the file (weights_only)."""
    try:
        state = torch.load(path, map_location=device, weights_only=True)
    except Exception as exc:
        reason = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise RainyScapeError(f"{path}: not a readable RainyScape checkpoint ({reason})") from None
    if not isinstance(state, dict) or not {"step", "models", "optimizers", "rng"} <= set(state):
        raise RainyScapeError(f"{path}: not a RainyScape checkpoint (missing its step, models, "
                              "optimizers or RNG state)")
    return state


def latest_checkpoint(folder: Path) -> Path | None:
    found = list_checkpoints(folder)
    return found[-1] if found else None
