"""Run folders: outputs/<scene>/<method>/<timestamp>/, never reused; and the one answer to
"is this a run folder" (its ``config.yml``, written by rs-train, is the folder's marker).

Light on purpose (no torch): ``cli/args.py`` asks it while reading a command line."""

from __future__ import annotations

import re
import shutil
import time
from pathlib import Path

from rainyscape.errors import ConfigError, DataError
from rainyscape.formats.output import check_can_create, make_folders, os_error, remove_made

CONFIG_FILE = "config.yml"  # the run's config; its presence makes a folder a run folder
CHECKPOINTS = "checkpoints"


def _slug(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9._-]+", "-", text).strip("-") or "scene"


def is_run_folder(path: str | Path) -> bool:
    return (Path(path) / CONFIG_FILE).is_file()


def check_run_folder(path: str | Path) -> Path:
    """``path`` when it is a run folder, else ConfigError naming it."""
    path = Path(path)
    if not is_run_folder(path):
        raise ConfigError(f"{path}: not a run folder (no {CONFIG_FILE}); pass the folder rs-train printed")
    return path


def check_output_dir(output_dir: str | Path) -> None:
    """Before any work: ``trainer.output_dir`` must be a folder rs-train can write in or create
    (DataError naming the key and the file in the way or the folder it may not write)."""
    check_can_create(Path(output_dir).expanduser(), "trainer.output_dir")


class NewRunDir:
    """A fresh run folder and the parent folders made for it, so that a run that fails before
    it holds anything worth keeping can leave ``trainer.output_dir`` as it was."""

    def __init__(self, path: Path, made: list[Path]):
        self.path, self.made = path, made

    def remove(self) -> None:
        """Delete the run folder (and the parents made for it, while empty)."""
        shutil.rmtree(self.path, ignore_errors=True)
        remove_made(self.made)


def new_run_dir(output_dir: str | Path, scene: str, method: str) -> NewRunDir:
    """Create a fresh run folder; a second run in the same second gets a suffix."""
    base = Path(output_dir).expanduser() / _slug(scene) / _slug(method)
    try:
        made = make_folders(base)
    except OSError as exc:
        raise os_error(base, exc, "cannot create the run folder (trainer.output_dir)") from None
    stamp = time.strftime("%Y-%m-%d_%H%M%S")
    for i in range(1000):
        candidate = base / (stamp if i == 0 else f"{stamp}-{i}")
        try:
            candidate.mkdir()  # atomic: fails if another run took the name
            return NewRunDir(candidate, made)
        except FileExistsError:
            continue
        except OSError as exc:
            remove_made(made)
            raise os_error(candidate, exc, "cannot create the run folder (trainer.output_dir)") from None
    remove_made(made)
    raise DataError(f"{base}: could not create a new run folder (1000 names of this second taken)")
