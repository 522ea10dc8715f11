"""Where rs-process-data writes, and what it may replace: it never deletes what it did not write.

The scene is built in a staging folder beside the output (``.<name>.partial-<random>``) and
moved into place only once it is complete: to a new output folder by one atomic rename, into
an existing one entry by entry, ``process_report.json`` last. Before anything is written:

- the output folder may neither contain the input nor lie inside it;
- without ``overwrite`` an existing output folder must be empty;
- with ``overwrite`` the entries the tool writes (:data:`OUTPUTS`) are replaced (all of
  them: the folder then holds one scene), and only those, and only when the
  ``process_report.json`` there lists every file in them as written by an earlier run;
  anything else in the folder is left as it is.

On any failure (bad frames, SfM, an interrupt) the staging folder is removed, with the parent
folders made for it, and the output folder is left exactly as it was.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
from pathlib import Path
from typing import Iterator

from rainyscape.errors import DataError
from rainyscape.formats.output import make_folders, move_all, new_staging, remove_made

REPORT = "process_report.json"
WORK_DIR = "colmap"
# Every entry the tool writes in a scene folder; the report goes last: it marks a whole scene.
OUTPUTS = ("images", "sparse", "transforms.json", "sparse_pc.ply", WORK_DIR, REPORT)
WRITTEN_KEY = "written"  # the report's list of every file of the scene, relative paths
# The entries that record how a scene was made (COLMAP's work files, the report's timings), not
# what it is: they differ in bytes between runs that give the same scene.
RECORDS = (WORK_DIR, REPORT)


def is_record(relative: Path) -> bool:
    """Whether ``relative`` (a path inside a scene folder) lies in one of :data:`RECORDS`."""
    return bool(relative.parts) and relative.parts[0] in RECORDS


def check_output(source: Path, scene_dir: Path, overwrite: bool) -> None:
    """DataError (one line, naming the folder) unless the scene may be written to ``scene_dir``."""
    src, out = source.resolve(), scene_dir.resolve()
    if src == out or src.is_relative_to(out):
        raise DataError(f"{scene_dir}: the output folder contains the input {source}; "
                        "choose an --output-dir outside it")
    if out.is_relative_to(src):
        raise DataError(f"{scene_dir}: the output folder is inside the input folder {source}; "
                        "choose an --output-dir outside it")
    if os.path.lexists(out) and not out.is_dir():
        raise DataError(f"{scene_dir}: the output path exists and is not a folder")
    if out.is_dir():
        replaceable(scene_dir, overwrite)


def replaceable(scene_dir: Path, overwrite: bool) -> list[str]:
    """The entries of :data:`OUTPUTS` present in ``scene_dir``, which the new scene replaces;
    DataError where the folder is not empty and ``overwrite`` is off, or where one of them
    holds a file that the earlier run's report does not list."""
    entries = sorted(p.name for p in scene_dir.iterdir())
    if entries and not overwrite:
        shown = ", ".join(entries[:5]) + (", ..." if len(entries) > 5 else "")
        raise DataError(f"{scene_dir}: the output folder is not empty ({shown}); pass --overwrite "
                        "to replace a scene rs-process-data wrote there (nothing else in the "
                        "folder is touched), or choose another --output-dir")
    present = [name for name in OUTPUTS if name in entries]
    written = written_by_earlier_run(scene_dir)
    for name in present:
        for rel in files_below(scene_dir, name):
            if rel not in written:
                raise DataError(f"{scene_dir / rel}: not written by rs-process-data ({REPORT} "
                                "does not list it), so --overwrite will not replace it; move it "
                                "away or choose another --output-dir")
    return present


def written_by_earlier_run(scene_dir: Path) -> set[str]:
    """The files an earlier run's report lists (empty without a readable report)."""
    try:
        report = json.loads((scene_dir / REPORT).read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError):
        return set()
    listed = report.get(WRITTEN_KEY) if isinstance(report, dict) else None
    return {p for p in listed if isinstance(p, str)} if isinstance(listed, list) else set()


def files_below(root: Path, name: str) -> list[str]:
    """Relative paths (``/``-separated) of the files and links at or below ``root / name``;
    links are not followed."""
    top = root / name
    if top.is_symlink() or not top.is_dir():
        return [name]
    found = []
    for folder, dirs, files in os.walk(top):
        rel = Path(folder).relative_to(root)
        found += [(rel / f).as_posix() for f in files]
        found += [(rel / d).as_posix() for d in dirs if (Path(folder) / d).is_symlink()]
    return sorted(found)


def scene_files(root: Path) -> list[str]:
    """Every file the tool wrote in a (staged) scene folder, the report included: what the
    report lists under :data:`WRITTEN_KEY`."""
    files = {f for name in OUTPUTS if os.path.lexists(root / name) for f in files_below(root, name)}
    return sorted(files | {REPORT})


@contextlib.contextmanager
def staged_scene(source: Path, scene_dir: Path, overwrite: bool) -> Iterator[Path]:
    """Check the output folder, then yield an empty staging folder to build the scene in.
    When the block ends without an error the scene is moved into ``scene_dir``; the staging
    folder (and any parent folder made for it) is removed in every case."""
    check_output(source, scene_dir, overwrite)
    out = scene_dir.resolve()
    made: list[Path] = []
    try:
        made = make_folders(out.parent)
        staging = new_staging(out)
    except OSError as exc:
        remove_made(made)
        raise DataError(f"{scene_dir}: cannot write beside the output folder "
                        f"({exc.strerror or exc})") from None
    try:
        yield staging
        _publish(staging, out, scene_dir, overwrite)
        made = []
    finally:
        shutil.rmtree(staging, ignore_errors=True)
        remove_made(made)


def _publish(staging: Path, out: Path, scene_dir: Path, overwrite: bool) -> None:
    if not os.path.lexists(out):
        with contextlib.suppress(OSError):  # it appeared meanwhile: go entry by entry
            os.rename(staging, out)
            return
    replaceable(out, overwrite)  # again: the folder may have changed while SfM ran
    old = staging / ".replaced"
    old.mkdir()
    moves: list[tuple[Path, Path]] = []
    for name in OUTPUTS:  # an earlier run's entry goes even where this run wrote none
        moves += [(src, dst) for src, dst in ((out / name, old / name), (staging / name, out / name))
                  if os.path.lexists(src)]
    move_all(moves, f"{scene_dir}: cannot move the new scene into place")
