"""An exclusive lock on a folder: one process works in it at a time.

A run folder's lock file (``RunFolder.lock``) is locked with ``fcntl.flock`` for as long as a
training process works in the folder (training, then its evaluation); rs-bench locks one
benchmark of its results folder the same way. The kernel releases the lock when the process
ends, however it ends (kill -9 included), so a lock is never stale. The holder writes its
pid, host, command and start time into the file; a second process that finds the folder
locked reads them for its error message.

Where ``fcntl`` does not exist (Windows) runs are not locked.
"""

from __future__ import annotations

import json
import os
import socket
import sys
import time
from pathlib import Path

from rainyscape.errors import RainyScapeError, RunBusyError

try:
    import fcntl
except ImportError:  # pragma: no cover - not on Linux / macOS
    fcntl = None



def holder_info(path: Path) -> dict:
    """What the lock file ``path`` says about its holder (empty when unreadable)."""
    try:
        data = json.loads(Path(path).read_text() or "{}")
    except (OSError, ValueError):
        return {}
    return data if isinstance(data, dict) else {}


def describe_holder(info: dict) -> str:
    if not info:
        return "another process"
    where = f"pid {info.get('pid', '?')}"
    if info.get("host") and info["host"] != socket.gethostname():
        where += f" on host {info['host']}"
    what = info.get("command") or "a process"
    since = f", since {info['started']}" if info.get("started") else ""
    return f"{what} ({where}{since})"


class RunLock:
    """``with RunLock(folder, "rs-train", name):`` holds the lock file ``folder/name``
    (RunBusyError if taken). ``label``: what the refusal names (default: the folder)."""

    def __init__(self, folder: Path, command: str, name: str, label: str = ""):
        self.folder = Path(folder)
        self.name = name
        self.path = self.folder / name
        self.label = label or str(self.folder)
        self.command = command or Path(sys.argv[0]).name or "python"
        self.fd: int | None = None

    def acquire(self) -> "RunLock":
        if fcntl is None or self.fd is not None:
            return self
        try:
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
        except OSError as exc:
            raise RainyScapeError(f"{self.path}: cannot open the lock file "
                                  f"({(exc.strerror or str(exc)).lower()})") from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            os.close(fd)
            info = holder_info(self.path)
            raise RunBusyError(
                f"{self.label}: in use by {describe_holder(info)}; wait until it ends"
                + (f" or stop it (kill {info['pid']})" if info.get("pid") and
                   info.get("host", socket.gethostname()) == socket.gethostname() else "")) from None
        info = {"pid": os.getpid(), "host": socket.gethostname(), "command": self.command,
                "started": time.strftime("%Y-%m-%d %H:%M:%S")}
        os.ftruncate(fd, 0)
        os.pwrite(fd, (json.dumps(info) + "\n").encode(), 0)
        self.fd = fd
        return self

    def release(self) -> None:
        if self.fd is None:
            return
        fd, self.fd = self.fd, None
        try:
            os.ftruncate(fd, 0)
            fcntl.flock(fd, fcntl.LOCK_UN)
        finally:
            os.close(fd)

    def __enter__(self) -> "RunLock":
        return self.acquire()

    def __exit__(self, *exc) -> None:
        self.release()


def is_locked(path: Path) -> bool:
    """Whether some process (this one included) holds the lock file ``path``."""
    path = Path(path)
    if fcntl is None or not path.is_file():
        return False
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return False
    try:
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
    except OSError:
        return True
    finally:
        os.close(fd)  # closing releases a lock we took
    return False
