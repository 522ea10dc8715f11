"""Run folders: ``outputs/<scene>/<method>/<timestamp>/``, never reused; :class:`RunFolder`
owns a run folder's layout and answers every question about it, so no other module spells
its file names.

Layout: config.yml (plain YAML; its presence makes a folder a run folder), status.json
(running / stopped / finished / failed / interrupted; a running one names its pid and host),
run.lock (held by the process training there), checkpoints/ (``step-N.pt``), log.jsonl
(training curves); evaluation adds metrics.json, renders/ and report.html.

Light on purpose (no torch at import): ``cli/args.py`` asks it while reading a command line;
what needs torch (checkpoints, typed configs) is imported where it is used."""

from __future__ import annotations

import json
import os
import re
import shutil
import socket
import time
import traceback
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

from rainyscape.engine.lock import RunLock, is_locked
from rainyscape.errors import ConfigError, DataError, RainyScapeError
from rainyscape.formats.atomic import write_text_atomic
from rainyscape.formats.output import check_can_create, make_folders, os_error, remove_made

# The exceptions a checkpoint that does not match the pipeline raises while it is restored
# (a missing or extra tensor, a different shape, another optimiser layout).
MISFIT = (KeyError, IndexError, TypeError, ValueError, RuntimeError)


def _slug(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9._-]+", "-", text).strip("-") or "scene"


def reached_end(step: int, max_iters: int) -> bool:
    """Whether a run at ``step`` has trained all of its ``max_iters`` steps."""
    return step >= max_iters


@contextmanager
def fitting_the_run(checkpoint: Path) -> Iterator[None]:
    """Restoring ``checkpoint`` into a pipeline: a mismatch becomes one line naming the file
    (RainyScapeError), whichever part of the state did not fit."""
    try:
        yield
    except MISFIT as exc:
        reason = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise RainyScapeError(f"{checkpoint}: does not fit this run's config ({type(exc).__name__}: "
                              f"{reason[:300]})") from None


class RunFolder:
    """A run folder: where each of its files lives, and the questions asked of it (is it a
    run, its typed config, its status with the dead-owner correction, its lock, which
    checkpoint to restore, finished or resumable)."""

    CONFIG = "config.yml"
    STATUS = "status.json"
    LOCK = "run.lock"
    CHECKPOINTS = "checkpoints"
    LOG = "log.jsonl"
    METRICS = "metrics.json"
    RENDERS = "renders"
    REPORT = "report.html"

    def __init__(self, path: str | Path):
        self.path = Path(path)

    def __repr__(self) -> str:
        return f"RunFolder({str(self.path)!r})"

    def __str__(self) -> str:
        return str(self.path)

    # ------------------------------------------------------------------ layout

    @property
    def config_file(self) -> Path:
        return self.path / self.CONFIG

    @property
    def status_file(self) -> Path:
        return self.path / self.STATUS

    @property
    def checkpoints(self) -> Path:
        return self.path / self.CHECKPOINTS

    @property
    def log_file(self) -> Path:
        return self.path / self.LOG

    @property
    def metrics_file(self) -> Path:
        return self.path / self.METRICS

    @property
    def renders(self) -> Path:
        return self.path / self.RENDERS

    @property
    def strips(self) -> Path:
        """The comparison strips evaluation saves for the report."""
        return self.renders / "strips"

    @property
    def report_file(self) -> Path:
        return self.path / self.REPORT

    # -------------------------------------------------------------- is it a run

    @classmethod
    def is_run(cls, path: str | Path) -> bool:
        return (Path(path) / cls.CONFIG).is_file()

    @classmethod
    def check(cls, path: str | Path) -> "RunFolder":
        """The run folder at ``path``, else ConfigError naming it."""
        if not cls.is_run(path):
            raise ConfigError(f"{path}: not a run folder (no {cls.CONFIG}); pass the folder rs-train printed")
        return cls(path)

    @classmethod
    def under(cls, output_dir: str | Path) -> list["RunFolder"]:
        """The run folders rs-train made under ``output_dir`` (``<scene>/<method>/<timestamp>``),
        oldest first."""
        return [cls(p.parent) for p in sorted(Path(output_dir).glob(f"*/*/*/{cls.CONFIG}"))]

    # ------------------------------------------------------------------ config

    def config(self):
        """The run's typed config (ConfigError naming config.yml when it does not load)."""
        from rainyscape.config import load_yaml

        return load_yaml(self.config_file)

    def config_text(self) -> str:
        return self.config_file.read_text()

    def save_config(self, cfg) -> None:
        from rainyscape.config import save_yaml

        save_yaml(cfg, self.config_file)

    # ------------------------------------------------------------------ status

    def set_status(self, state: str, **extra) -> None:
        """status.json, atomically; a "running" status names this process (pid, host)."""
        data = {"state": state, "time": time.strftime("%Y-%m-%d %H:%M:%S"), **extra}
        if state == "running":
            data.update(pid=os.getpid(), host=socket.gethostname())
        write_text_atomic(self.status_file, json.dumps(data, indent=2))

    def status(self) -> dict:
        """status.json ({} when absent or unreadable). A "running" status whose process is gone
        (nobody holds the folder's lock: killed, crashed, power cut) is corrected to
        "interrupted" on disk and in the answer."""
        try:
            status = json.loads(self.status_file.read_text())
        except (OSError, ValueError):
            return {}
        if not isinstance(status, dict):
            return {}
        if status.get("state") == "running" and not self.is_locked():
            owner = f"pid {status.get('pid', '?')}" + (f" on {status['host']}" if status.get("host") else "")
            status = {**status, "state": "interrupted",
                      "note": f"the training process ({owner}) ended without recording its end "
                              "(killed or crashed); resume with rs-train resume=RUN_DIR"}
            try:
                write_text_atomic(self.status_file, json.dumps(status, indent=2))
            except OSError:
                pass
        return status

    @contextmanager
    def recording_failures(self) -> Iterator[None]:
        """Whatever escapes the block is written to status.json (interrupted or failed)."""
        try:
            yield
        except KeyboardInterrupt:
            self.set_status("interrupted")
            raise
        except BaseException as exc:
            self.set_status("failed", error=f"{type(exc).__name__}: {exc}", traceback=traceback.format_exc())
            raise

    def finished(self, max_iters: int | None = None) -> bool:
        """Whether the run is done: it trained all its steps (``max_iters``, default its
        config's), recorded that, and its evaluation is written."""
        status = self.status()
        if status.get("state") != "finished" or not self.metrics_file.is_file():
            return False
        if max_iters is None:
            max_iters = self.config().trainer.max_iters
        return reached_end(int(status.get("step", 0)), max_iters)

    def resumable(self, max_iters: int | None = None) -> bool:
        """Whether training can continue here: it has a checkpoint and is not finished."""
        return self.has_checkpoint() and not self.finished(max_iters)

    # -------------------------------------------------------------------- lock

    def lock(self, command: str = "rs-train") -> RunLock:
        """The folder's exclusive lock (acquire it, or use it as a context manager)."""
        return RunLock(self.path, command, name=self.LOCK)

    def is_locked(self) -> bool:
        """Whether some process (this one included) holds the folder's lock."""
        return is_locked(self.path / self.LOCK)

    # ------------------------------------------------------------- checkpoints

    def checkpoint_files(self) -> list[Path]:
        """The checkpoints, oldest first."""
        from rainyscape.engine.checkpoint import list_checkpoints

        return list_checkpoints(self.checkpoints)

    def has_checkpoint(self) -> bool:
        return bool(self.checkpoint_files())

    def newest_checkpoint(self) -> Path | None:
        found = self.checkpoint_files()
        return found[-1] if found else None

    def save_checkpoint(self, step: int, state: dict, keep: int) -> Path:
        from rainyscape.engine.checkpoint import save_checkpoint

        return save_checkpoint(self.checkpoints, step, state, keep)

    def remove_partial_writes(self) -> list[Path]:
        """Delete checkpoint writes a kill left half done (only the lock holder may)."""
        from rainyscape.engine.checkpoint import remove_partial_writes

        return remove_partial_writes(self.checkpoints)

    def checkpoint_to_restore(self, device, step: int | None = None, set_aside: bool = False) -> tuple[Path, dict]:
        """The checkpoint to restore and its state: the one of ``step``, else the newest that
        reads (``set_aside``: the lock holder renames unreadable newer ones ``*.corrupt``).
        RainyScapeError naming the folder when there is none."""
        from rainyscape.engine.checkpoint import checkpoint_path, load_checkpoint, load_newest_valid

        if step is not None:
            path = checkpoint_path(self.checkpoints, step)
            if not path.is_file():
                have = ", ".join(str(int(p.stem.split("-")[1])) for p in self.checkpoint_files())
                raise RainyScapeError(f"{self.path}: no checkpoint of step {step} (have: {have or 'none'})")
            return path, load_checkpoint(path, device)
        found = load_newest_valid(self.checkpoints, device, set_aside=set_aside)
        if found is None:
            raise RainyScapeError(f"{self.path}: no checkpoint found (the run was stopped before its "
                                  f"first one; resume it with rs-train resume={self.path})")
        return found

    def restore(self, pipeline, step: int | None = None) -> int:
        """Load the models of ``pipeline`` from the checkpoint of ``step`` (default: the newest
        that reads), in evaluation mode; returns the checkpoint's step."""
        from rainyscape.engine.snapshot import restore_models

        path, state = self.checkpoint_to_restore(pipeline.device, step)
        with fitting_the_run(path):
            restore_models(state, pipeline.models())
        for model in pipeline.models().values():
            model.eval()
        return int(state["step"])

    # --------------------------------------------------------------------- log

    def append_log(self, record: dict) -> None:
        with open(self.log_file, "a") as fh:
            fh.write(json.dumps(record) + "\n")

    def log_records(self) -> list[dict]:
        """Every record of log.jsonl that reads (a run killed mid-write leaves a truncated
        last line, skipped)."""
        if not self.log_file.is_file():
            return []
        records = []
        for line in self.log_file.read_text().splitlines():
            try:
                rec = json.loads(line)
            except json.JSONDecodeError:
                continue
            if isinstance(rec, dict):
                records.append(rec)
        return records

    def cut_log(self, step: int) -> None:
        """Drop log records past ``step`` (a killed run logged steps its last checkpoint does
        not hold; they are trained again) and any torn last line."""
        if not self.log_file.is_file():
            return
        kept, changed = [], False
        for line in self.log_file.read_text().splitlines():
            try:
                keep = int(json.loads(line).get("step", 0)) <= step
            except (ValueError, TypeError, AttributeError):
                keep = False
            if keep:
                kept.append(line)
            changed |= not keep
        if changed:
            write_text_atomic(self.log_file, "".join(f"{line}\n" for line in kept))

    # ----------------------------------------------------------------- metrics

    def metrics(self) -> dict:
        """metrics.json ({} when absent or unreadable)."""
        try:
            data = json.loads(self.metrics_file.read_text())
        except (OSError, ValueError):
            return {}
        return data if isinstance(data, dict) else {}

    def save_metrics(self, metrics: dict) -> Path:
        return write_text_atomic(self.metrics_file, json.dumps(metrics, indent=2))


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
