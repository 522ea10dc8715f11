"""What ``rs-bench`` writes in its results folder ``OUT``, what it owns there, and the lock.

One benchmark (``name=NAME``) writes, and owns by their marker:

- ``OUT/NAME.json``: the results (marker: a JSON object holding ``"cells"``, as rs-bench
  writes it);
- ``OUT/NAME.md``: the tables (marker: its first line, ``# Benchmark NAME``);
- ``OUT/runs/NAME/``: one folder per cell (marker: each holds the ``cell.json`` rs-bench
  writes there);
- ``OUT/scenes/``: the simulated scenes, shared by the benchmarks of ``OUT`` (marker: each
  scene's ``scene.json``);
- ``OUT/.NAME.lock``: locked (``fcntl.flock``) while the benchmark runs, so that a second
  rs-bench with the same ``out=`` and ``name=`` is refused instead of training the same cells.

Rerunning the same command resumes: its own files are read back and updated. Anything of
another origin in their place is refused, naming it, unless ``force=true``, which starts the
benchmark afresh (its results, tables and cell folders all go). Nothing else in ``OUT`` is
touched. The checks run before anything is simulated, trained or written.
"""

from __future__ import annotations

import re
import shutil
from dataclasses import dataclass
from pathlib import Path

from rainyscape.comparison.results import read_results
from rainyscape.errors import ConfigError, DataError
from rainyscape.formats.output import check_can_create

CELL_SPEC = "cell.json"  # the marker of a cell folder
NAME_PATTERN = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]*")


@dataclass(frozen=True)
class BenchOutput:
    out: Path
    name: str

    @property
    def results(self) -> Path:
        return self.out / f"{self.name}.json"

    @property
    def tables(self) -> Path:
        return self.out / f"{self.name}.md"

    @property
    def runs(self) -> Path:
        return self.out / "runs" / self.name

    @property
    def scenes(self) -> Path:
        return self.out / "scenes"

    @property
    def lock_name(self) -> str:
        return f".{self.name}.lock"


def check_name(name: str) -> str:
    """``name`` when it is a plain file name (it names NAME.json, NAME.md and runs/NAME)."""
    if not NAME_PATTERN.fullmatch(name) or name.endswith(".json") or name.endswith(".md"):
        raise ConfigError(f"name={name}: a results name is letters, digits, '.', '_' and '-' (not a path, "
                          "no .json / .md ending: rs-bench adds them)")
    return name


def is_results_file(path: Path) -> bool:
    try:
        read_results(path)
    except DataError:
        return False
    return True


def is_tables_file(path: Path, name: str) -> bool:
    try:
        with open(path, encoding="utf-8") as fh:
            return fh.readline().rstrip("\n") == f"# Benchmark {name}"
    except (OSError, UnicodeDecodeError):
        return False


def foreign(target: BenchOutput, scene_folders: list[Path] = ()) -> list[tuple[Path, str]]:
    """The entries the benchmark would write over that rs-bench did not write, each with why."""
    found = []
    if target.results.exists() and not is_results_file(target.results):
        found.append((target.results, "not an rs-bench results file"))
    if target.tables.exists() and not is_tables_file(target.tables, target.name):
        found.append((target.tables, f"its first line is not '# Benchmark {target.name}'"))
    for folder in (target.out / "runs", target.runs, target.scenes):
        if folder.exists() and not folder.is_dir():
            found.append((folder, "a file where rs-bench keeps a folder"))
    if target.runs.is_dir():
        for entry in sorted(target.runs.iterdir()):
            if not (entry / CELL_SPEC).is_file():
                found.append((entry, f"not a cell folder of rs-bench (no {CELL_SPEC})"))
    for folder in scene_folders:
        if folder.exists() and not (folder / "scene.json").is_file():
            found.append((folder, "not a scene rs-bench simulated (no scene.json)"))
    return found


def check_output(target: BenchOutput, force: bool, scene_folders: list[Path] = ()) -> None:
    """Before any work: DataError naming the first entry in the way (unless ``force``), or the
    folder rs-bench may not write or create."""
    if target.out.exists() and not target.out.is_dir():
        raise DataError(f"out={target.out}: exists and is not a folder")
    check_can_create(target.out, "out")
    if force:
        return
    for path, why in foreign(target, scene_folders)[:1]:
        raise DataError(f"{path}: {why}; rs-bench would write over it. Choose another name= or out=, or pass "
                        f"force=true to start benchmark '{target.name}' afresh (replacing {target.results.name}, "
                        f"{target.tables.name} and runs/{target.name}/)")


def start_afresh(target: BenchOutput, scene_folders: list[Path] = ()) -> None:
    """force=true: remove the benchmark's whole output (and whatever stands in its place)."""
    for path in (target.results, target.tables, target.runs, *scene_folders):
        if path.is_dir() and not path.is_symlink():
            if path in scene_folders and (path / "scene.json").is_file():
                continue  # a complete cached scene is kept: it is the same scene
            shutil.rmtree(path)
        elif path.exists() or path.is_symlink():
            path.unlink()
    for folder in (target.out / "runs", target.scenes):
        if folder.exists() and not folder.is_dir():
            folder.unlink()
