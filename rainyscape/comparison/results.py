"""The results file ``OUT/NAME.json``: every cell's result, the command and the machine;
rewritten atomically after each cell."""

from __future__ import annotations

import json
import os
import platform
from pathlib import Path

from rainyscape.errors import ConfigError, DataError
from rainyscape.formats.atomic import write_text_atomic


def machine_description() -> dict:
    import torch

    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    gpu = torch.cuda.get_device_name(0) if torch.cuda.is_available() else None
    return {"cpu": cpu, "cores": os.cpu_count(), "gpu": gpu, "torch": torch.__version__,
            "python": platform.python_version(), "platform": platform.platform()}


def read_results(path: Path) -> dict:
    """A results file, or a DataError naming it and what is wrong."""
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise DataError(f"{path}: no such results file") from None
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        raise DataError(f"{path}: cannot read it as an rs-bench results file ({exc})") from None
    if not isinstance(data, dict) or not isinstance(data.get("cells"), dict):
        raise DataError(f"{path}: not an rs-bench results file (no 'cells')")
    return data


def load_results(path: Path) -> dict:
    """The benchmark's own results so far (none yet: no cells)."""
    if not path.is_file():
        return {"cells": {}}
    try:
        return read_results(path)
    except DataError as exc:
        raise ConfigError(f"{exc}; move it away to start afresh") from None


def save_results(path: Path, results: dict) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    write_text_atomic(path, json.dumps(results, indent=2))
