"""Where a command may write, and how it writes a folder so that a failure leaves nothing
half done (docs/reliability.md, "What each command may write").

The rule every ``rs-*`` command follows:

- it writes only into what it created, or what it owns by a marker file (a run folder's
  ``config.yml``, an rs-bench results file, ...); anything else is refused, naming the file,
  unless ``force=true``;
- ``force=true`` replaces the whole output (every entry the command writes), never a part;
- a failed command leaves the user's folders as they were: the output is built in a
  temporary sibling (``.NAME.partial-<random hex>``) and moved into place only when complete.

:func:`check_can_create` and :func:`check_writable` are the early checks (before any work);
:func:`staged_folder` is the build-aside-then-publish writer; :func:`os_error` turns an
``OSError`` into the one line a user sees.
"""

from __future__ import annotations

import contextlib
import errno
import os
import secrets
import shutil
from pathlib import Path
from typing import Iterable, Iterator

from rainyscape.errors import DataError

STAGING_MARK = ".partial-"  # staging folders: .NAME.partial-<8 random hex digits> beside the output


def os_error(path: Path | str, exc: OSError, doing: str = "") -> DataError:
    """One line for an ``OSError`` met at ``path`` (the file it names, when it names one)."""
    where = exc.filename if isinstance(exc.filename, str) and exc.filename else str(path)
    reason = exc.strerror or str(exc) or type(exc).__name__
    return DataError(f"{where}: {doing + ': ' if doing else ''}{reason.lower()}")


def _nearest_existing(path: Path) -> Path:
    while not os.path.lexists(path) and path != path.parent:
        path = path.parent
    return path


def check_can_create(path: Path | str, key: str = "") -> None:
    """DataError (naming ``path`` and ``key``, the option that named it) unless ``path`` is a
    folder this process may write in, or one it can create: every existing part of it must be a
    folder, and the deepest existing one writable."""
    path = Path(path).expanduser()
    label = f"{key}={path}" if key else str(path)
    base = _nearest_existing(path.absolute())
    if not base.is_dir():
        raise DataError(f"{label}: {base} is a file, not a folder")
    if not os.access(base, os.W_OK | os.X_OK):
        what = "read-only file system" if _read_only_fs(base) else "permission denied"
        raise DataError(f"{label}: cannot write in {base} ({what})")


def check_writable(folder: Path | str, what: str = "") -> None:
    """DataError unless the existing ``folder`` may be written in (``what``: what the command
    would write there, for the message)."""
    folder = Path(folder)
    if not os.access(folder, os.W_OK | os.X_OK):
        why = "read-only file system" if _read_only_fs(folder) else "permission denied"
        raise DataError(f"{folder}: cannot write here ({why})" + (f"; {what}" if what else ""))


def _read_only_fs(path: Path) -> bool:
    try:
        return bool(os.statvfs(path).f_flag & os.ST_RDONLY)
    except OSError:
        return False


def make_folders(folder: Path) -> list[Path]:
    """Make ``folder`` and its missing parents; return those made, outermost first (for
    :func:`remove_made`)."""
    folder = Path(folder)
    missing = []
    while not os.path.lexists(folder) and folder != folder.parent:
        missing.append(folder)
        folder = folder.parent
    made: list[Path] = []
    try:
        for path in reversed(missing):
            path.mkdir()
            made.append(path)
    except FileExistsError:  # another process made it meanwhile: fine if it is a folder
        if not path.is_dir():
            remove_made(made)
            raise
    except OSError:
        remove_made(made)
        raise
    return made


def remove_made(folders: Iterable[Path]) -> None:
    """Remove folders :func:`make_folders` made (innermost first) while they are empty."""
    for folder in reversed(list(folders)):
        with contextlib.suppress(OSError):
            folder.rmdir()


def entries_of(folder: Path) -> list[str]:
    """The names in ``folder`` (sorted), [] when it does not exist."""
    try:
        return sorted(p.name for p in Path(folder).iterdir())
    except (FileNotFoundError, NotADirectoryError):
        return []


def check_output_folder(out: Path, force: bool, writes: str, option: str = "out") -> None:
    """DataError unless the command may write its output folder ``out``: absent, empty, or
    (``force``) anything that is a folder. ``writes`` says what the command puts there, for
    the refusal ("a simulated scene: images_rain/, ...")."""
    if os.path.lexists(out) and not out.is_dir():
        raise DataError(f"{out}: exists and is not a folder; choose another {option}=")
    names = entries_of(out)
    if names and not force:
        shown = ", ".join(names[:5]) + (", ..." if len(names) > 5 else "")
        raise DataError(f"{out}: folder exists and is not empty ({shown}); choose another {option}= or "
                        f"pass force=true to replace {writes} there (nothing else in it is touched)")
    check_can_create(out, option)


@contextlib.contextmanager
def staged_folder(out: Path | str, replaces: Iterable[str], force: bool, writes: str,
                  option: str = "out", last: str = "") -> Iterator[Path]:
    """Check ``out`` (:func:`check_output_folder`), then yield an empty staging folder beside it
    to build the output in. When the block ends without an error the output is published:
    a new ``out`` by one rename; into an existing folder entry by entry, each of ``replaces``
    (the entries the command owns there: all of them go, even those this run did not write)
    and each entry the staging folder holds replacing the old one as a whole, ``last`` (the
    file that marks a complete output, e.g. a scene's ``scene.json``) last. On any error the
    staging folder and the parents made for it are removed and ``out`` is as it was."""
    out = Path(out).expanduser()
    check_output_folder(out, force, writes, option)
    out = out.absolute()
    try:
        made = make_folders(out.parent)
        staging = new_staging(out)
    except OSError as exc:
        raise os_error(out.parent, exc, "cannot write beside the output folder") from None
    try:
        yield staging
        _publish(staging, out, set(replaces), force, writes, option, last)
        made = []
    except OSError as exc:
        raise os_error(out, exc) from None
    finally:
        shutil.rmtree(staging, ignore_errors=True)
        remove_made(made)


def new_staging(out: Path) -> Path:
    """An empty, new staging folder beside ``out`` (``.NAME.partial-<8 random hex digits>``)."""
    while True:
        path = out.parent / f".{out.name}{STAGING_MARK}{secrets.token_hex(4)}"
        try:
            path.mkdir()
            return path
        except FileExistsError:
            continue


def move_entry(src: Path, dst: Path) -> None:
    """Rename ``src`` to ``dst``, copying when they are on different file systems."""
    try:
        os.rename(src, dst)
    except OSError as exc:
        if exc.errno != errno.EXDEV:
            raise
        shutil.move(str(src), str(dst))  # another file system


def move_all(moves: Iterable[tuple[Path, Path]], failure: str) -> None:
    """Make each ``(src, dst)`` move in order, or none: on a failure the moves made are undone
    and a ``DataError`` starting with ``failure`` is raised."""
    done: list[tuple[Path, Path]] = []
    try:
        for src, dst in moves:
            move_entry(src, dst)
            done.append((src, dst))
    except OSError as exc:
        for src, dst in reversed(done):  # put everything back
            with contextlib.suppress(OSError):
                move_entry(dst, src)
        raise DataError(f"{failure} ({exc.strerror or exc}); the folder is as it was") from None


def _publish(staging: Path, out: Path, replaces: set[str], force: bool, writes: str, option: str,
             last: str) -> None:
    if not os.path.lexists(out):
        try:
            os.rename(staging, out)
            return
        except OSError:  # it appeared meanwhile: go entry by entry, after checking it again
            pass
    check_output_folder(out, force, writes, option)
    names = entries_of(staging)
    old = staging / ".replaced"
    old.mkdir()
    # the old output goes first, its marker first; the new one comes in, its marker last
    moves = [(out / name, old / name) for name in sorted(replaces | set(names), key=lambda n: (n != last, n))
             if os.path.lexists(out / name)]
    moves += [(staging / name, out / name) for name in sorted(names, key=lambda n: (n == last, n))]
    move_all(moves, f"{out}: cannot move the new output into place")
