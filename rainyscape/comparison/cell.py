"""One cell of a benchmark: trained (or resumed, or read back) in a fresh interpreter, so its
peak memory is its own.

The parent writes ``cell.json`` (method, overrides, output folder) and runs
``python -m rainyscape.comparison.cell CELL.json RESULT.json``; the child trains and writes
``result.json``. Console output of the child goes to ``bench.log`` in the cell's folder.
"""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

from rainyscape.comparison.matrix import Cell
from rainyscape.engine.run_folder import RunFolder
from rainyscape.errors import RainyScapeError


def find_run(output_dir: Path) -> RunFolder | None:
    """The newest run folder under a cell's output folder."""
    runs = RunFolder.under(output_dir)
    return runs[-1] if runs else None


def peak_memory_mib() -> dict:
    import resource

    import torch

    usage = resource.getrusage(resource.RUSAGE_SELF)
    # CPU time (user + system) of the cell: on a shared machine, what its wall time would be alone
    out = {"peak_rss_mib": usage.ru_maxrss / 1024.0, "cpu_s": usage.ru_utime + usage.ru_stime}
    if torch.cuda.is_available():
        out["peak_cuda_mib"] = torch.cuda.max_memory_allocated() / 2**20
    return out


def training_seconds(folder: RunFolder) -> float | None:
    """Training time from the log (the trainer stamps its step records with seconds since its
    start; a resumed run adds its segments)."""
    times = [float(rec["time"]) for rec in folder.log_records() if "time" in rec]
    total, last = 0.0, 0.0
    for t in times:
        if t < last:  # a resume restarted the clock
            total += last
        last = t
    return total + last if times else None


def run_cell_here(spec: dict) -> dict:
    """Train (or resume, or just read back) one cell in this process; returns its result."""
    from rainyscape.config import method_config
    from rainyscape.workflow import train_and_evaluate

    output_dir = Path(spec["output_dir"])
    cfg = method_config(spec["method"], spec["overrides"] + [f"trainer.output_dir={output_dir}"])
    existing = find_run(output_dir)
    started = time.perf_counter()
    if existing is None and spec.get("share_from"):
        folder, resumed = share_run(Path(spec["share_from"]), output_dir, cfg), f"shared: {spec['share_from']}"
    elif existing is not None and existing.finished(cfg.trainer.max_iters):
        folder, resumed = existing, "read back"
    else:
        resume = existing.path if existing is not None and existing.resumable(cfg.trainer.max_iters) else None
        folder = RunFolder(train_and_evaluate(cfg, resume).run_dir)
        resumed = "resumed" if resume is not None else "trained"
    metrics = folder.metrics()
    return {"status": "finished", "how": resumed, "run_dir": str(folder.path),
            "wall_s": time.perf_counter() - started, "train_s": training_seconds(folder),
            "iters": cfg.trainer.max_iters, "summary": metrics.get("summary", {}),
            "postprocess": metrics.get("postprocess", []), "lpips": metrics.get("lpips", {}),
            "views": metrics.get("views", {}), **peak_memory_mib()}


def share_run(source: Path, output_dir: Path, cfg) -> RunFolder:
    """A copy of the finished run ``source`` (another cell's, whose training was this cell's:
    comparison/sharing.py) under ``output_dir``, naming this cell's scene and evaluated on it.
    Built in a hidden folder and moved into place once evaluated."""
    from rainyscape.eval.protocol import evaluate_pipeline, write_metrics
    from rainyscape.workflow import load_trained

    rel = source.relative_to(source.parents[2])  # <scene>/<method>/<timestamp>
    partial = output_dir / ".shared-partial"
    shutil.rmtree(partial, ignore_errors=True)
    shutil.copytree(source, partial / rel, ignore=shutil.ignore_patterns(RunFolder.LOCK))
    copy = RunFolder(partial / rel)
    copy.save_config(dataclasses.replace(copy.config(), data=cfg.data))
    pipeline, step = load_trained(copy.path, cfg.trainer.device)
    print(f"the run of {source} trained this cell's ceiling; evaluating it on {cfg.data}", flush=True)
    metrics = evaluate_pipeline(pipeline, copy.path)
    metrics["step"] = step
    write_metrics(copy.path, metrics)
    (partial / rel.parts[0]).rename(output_dir / rel.parts[0])
    partial.rmdir()
    return RunFolder(output_dir / rel)


_RUNNING: set[subprocess.Popen] = set()  # the cells' processes now running


def stop_running_cells() -> None:
    """Ask every running cell to stop (SIGTERM: its run saves a checkpoint, so the next
    rs-bench resumes it)."""
    for child in list(_RUNNING):
        if child.poll() is None:
            child.terminate()


def run_cell_subprocess(cell: Cell, output_dir: Path, device: str, threads: int = 0,
                        share_from: str | None = None) -> dict:
    """Run a cell in a fresh interpreter (``threads`` > 0: that many torch / OpenMP
    threads); its console output goes to ``bench.log``. ``share_from``: a finished run whose
    training is this cell's, copied and evaluated here instead of training."""
    output_dir.mkdir(parents=True, exist_ok=True)
    spec = {"method": cell.method, "overrides": [f"data={cell.data}", *cell.overrides,
                                                 f"trainer.device={device}", "trainer.progress=false"],
            "output_dir": str(output_dir), "share_from": share_from}
    spec_path, result_path = output_dir / "cell.json", output_dir / "result.json"
    spec_path.write_text(json.dumps(spec, indent=2))
    result_path.unlink(missing_ok=True)
    env = dict(os.environ, OMP_NUM_THREADS=str(threads)) if threads > 0 else None
    with open(output_dir / "bench.log", "a") as log:
        child = subprocess.Popen([sys.executable, "-m", "rainyscape.comparison.cell", str(spec_path),
                                  str(result_path)], stdout=log, stderr=subprocess.STDOUT, env=env)
        _RUNNING.add(child)
        try:
            code = child.wait()
        finally:
            _RUNNING.discard(child)
    if code == 0 and result_path.is_file():
        return json.loads(result_path.read_text())
    tail = (output_dir / "bench.log").read_text().strip().splitlines()[-5:]
    return {"status": "failed", "error": " | ".join(tail) or f"exit code {code}"}


def main(spec_path: str, result_path: str) -> int:
    """Subprocess entry: ``python -m rainyscape.comparison.cell CELL.json RESULT.json``."""
    from rainyscape.engine.signals import stop_on_sigterm

    stop_on_sigterm()
    spec = json.loads(Path(spec_path).read_text())
    try:
        result = run_cell_here(spec)
    except RainyScapeError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted (rs-bench was stopped); rerun it to resume this cell", file=sys.stderr)
        return 130
    Path(result_path).write_text(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main(*sys.argv[1:3]))
