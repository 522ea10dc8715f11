"""Console entry points (rs-*). Each keeps its imports light until it has work to do."""

from __future__ import annotations

import errno
import os
import sys
from typing import Callable

# What to lower when training runs out of memory; a command with other knobs says its own
# (its Command's ``oom_hint``).
OOM_HINT = ("lower the batch (phases.NAME.patches, phases.NAME.patch_size), the field's chunk "
            "(field.chunk) or the image size (dataparser.downscale=2)")
# OSErrors about the user's files and disks, not bugs: one line naming the file, exit code 2
FILE_SYSTEM_ERRORS = {errno.EACCES, errno.EPERM, errno.EROFS, errno.ENOSPC, errno.EDQUOT,
                      errno.ENOTDIR, errno.EISDIR, errno.ENAMETOOLONG, errno.EFBIG}


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip()
    return text.splitlines()[0][:300] if text else type(exc).__name__


def _is_out_of_memory(exc: BaseException) -> bool:
    return isinstance(exc, MemoryError) or type(exc).__name__ == "OutOfMemoryError" or (
        isinstance(exc, RuntimeError) and "DefaultCPUAllocator: can't allocate memory" in str(exc))


def _oom_hint(main: Callable) -> str:
    """The hint of the command whose ``main`` runs (its module's COMMAND), else training's."""
    command = getattr(sys.modules.get(getattr(main, "__module__", ""), None), "COMMAND", None)
    return getattr(command, "oom_hint", "") or OOM_HINT


def run_cli(main: Callable[[list[str]], int], argv: list[str] | None = None) -> int:
    """Run a CLI body; user errors become one clear line on stderr and exit code 2.

    Running out of memory is one line too (exit code 2, with what the command can lower), and
    so is a file-system error about a file (permission denied, read-only, disk full, a file
    where a folder belongs: :data:`FILE_SYSTEM_ERRORS`). Anything else is a bug: one line
    naming it and a file holding the traceback (exit code 1); ``RAINYSCAPE_DEBUG=1`` lets the
    traceback through instead."""
    from rainyscape.errors import RainyScapeError

    try:
        return main(sys.argv[1:] if argv is None else argv) or 0
    except RainyScapeError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return exc.exit_code
    except KeyboardInterrupt:
        return 130
    except BrokenPipeError:  # e.g. `rs-eval --help | head`: the reader left; exit quietly
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 1
    except Exception as exc:
        if os.environ.get("RAINYSCAPE_DEBUG"):
            raise
        if _is_out_of_memory(exc):
            print(f"error: out of memory ({_first_line(exc)}); {_oom_hint(main)}", file=sys.stderr)
            return 2
        if isinstance(exc, OSError) and exc.errno in FILE_SYSTEM_ERRORS:
            where = exc.filename if exc.filename else "a file"
            print(f"error: {where}: {(exc.strerror or str(exc)).lower()}", file=sys.stderr)
            return 2
        where = _save_traceback()
        print(f"error: unexpected {type(exc).__name__}: {_first_line(exc)} (a bug in rainyscape or "
              f"a plugin; traceback in {where}, or rerun with RAINYSCAPE_DEBUG=1)", file=sys.stderr)
        return 1


def _save_traceback() -> str:
    import tempfile
    import traceback

    try:
        fd, path = tempfile.mkstemp(prefix="rainyscape-traceback-", suffix=".txt")
        with os.fdopen(fd, "w") as fh:
            fh.write(traceback.format_exc())
        return path
    except OSError:
        return "(could not be saved)"
