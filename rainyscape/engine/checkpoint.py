"""Checkpoint files: atomic writes, keep the latest N, find the newest that reads.

A checkpoint is written to ``step-N.pt.tmp``, flushed to disk and renamed to ``step-N.pt``:
a kill at any moment leaves either the previous set of checkpoints or the new one, never a
truncated ``.pt`` (a leftover ``.tmp`` is removed by the next run in the folder). Loading uses
``torch.load(weights_only=True)``, which never runs code from the file.
"""

from __future__ import annotations

import os
import re
import sys
from pathlib import Path

import torch

from rainyscape.errors import RainyScapeError

_NAME = re.compile(r"step-(\d+)\.pt$")
REQUIRED = ("step", "models", "optimizers", "rng")


def checkpoint_path(folder: Path, step: int) -> Path:
    return Path(folder) / f"step-{step:07d}.pt"


def list_checkpoints(folder: Path) -> list[Path]:
    folder = Path(folder)
    if not folder.is_dir():
        return []
    found = [(int(m.group(1)), p) for p in folder.iterdir() if (m := _NAME.match(p.name))]
    return [p for _, p in sorted(found)]


def remove_partial_writes(folder: Path) -> list[Path]:
    """Delete ``step-N.pt.tmp`` files a killed write left behind (only the lock holder may)."""
    folder = Path(folder)
    if not folder.is_dir():
        return []
    found = [p for p in folder.glob("step-*.pt.tmp") if p.is_file()]
    for p in found:
        p.unlink(missing_ok=True)
    return found


def save_checkpoint(folder: Path, step: int, state: dict, keep: int) -> Path:
    """Write ``state`` to a temporary file then rename it in place, so a crash never leaves
    a truncated checkpoint; afterwards delete all but the newest ``keep``."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    final = checkpoint_path(folder, step)
    tmp = final.with_suffix(".pt.tmp")
    try:
        torch.save(state, tmp)
        with open(tmp, "rb") as fh:
            os.fsync(fh.fileno())
        os.replace(tmp, final)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    try:  # the rename itself survives a power cut once the folder is flushed too
        fd = os.open(folder, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
    except OSError:
        pass
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
        if "weights_only" in str(exc) or "Unsupported global" in str(exc):
            reason = "it holds Python objects other than tensors and plain values; refused unread"
        raise RainyScapeError(f"{path}: not a readable RainyScape checkpoint ({reason[:300]})") from None
    if not isinstance(state, dict) or not set(REQUIRED) <= set(state):
        missing = [k for k in REQUIRED if not isinstance(state, dict) or k not in state]
        raise RainyScapeError(f"{path}: not a RainyScape checkpoint (no '{missing[0]}' entry)")
    if not isinstance(state["models"], dict) or not isinstance(state["optimizers"], dict):
        raise RainyScapeError(f"{path}: not a RainyScape checkpoint (models / optimizers are not mappings)")
    return state


def load_newest_valid(folder: Path, device, set_aside: bool = False) -> tuple[Path, dict] | None:
    """The newest checkpoint of ``folder`` that reads, with its state (None when there is none).

    Unreadable newer ones are reported on stderr and skipped; with ``set_aside`` (the run's
    lock holder, about to write new checkpoints) they are renamed ``step-N.pt.corrupt``: kept
    for inspection, never picked again. When none reads, the newest one's error is raised
    and nothing is renamed."""
    found = list_checkpoints(folder)
    bad: list[tuple[Path, RainyScapeError]] = []
    for path in reversed(found):
        try:
            state = load_checkpoint(path, device)
        except RainyScapeError as exc:
            bad.append((path, exc))
            continue
        for broken, exc in bad:
            note = ""
            if set_aside:
                aside = broken.with_name(broken.name + ".corrupt")
                os.replace(broken, aside)
                note = f" (renamed to {aside.name})"
            print(f"rainyscape: warning: {exc}{note}; using {path.name}", file=sys.stderr)
        return path, state
    if bad:
        raise bad[0][1]
    return None


def latest_checkpoint(folder: Path) -> Path | None:
    found = list_checkpoints(folder)
    return found[-1] if found else None
