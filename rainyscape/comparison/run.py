"""A whole benchmark: validate every cell and check its budget, resolve the scenes and their
oracle, run the cells not done yet (``jobs`` at a time, each in its own process) and rewrite
the results file and the tables after each one."""

from __future__ import annotations

import multiprocessing
import os
import time
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, ThreadPoolExecutor, as_completed, wait
from pathlib import Path

from rainyscape.comparison.cell import run_cell_subprocess, stop_running_cells
from rainyscape.comparison.matrix import Cell, cell_config
from rainyscape.comparison.options import BenchOptions
from rainyscape.comparison.oracle import cached_oracle, na_entry, scene_oracle, unavailable
from rainyscape.comparison.output import BenchOutput, check_name, check_output, start_afresh
from rainyscape.comparison.plan import plan_bench
from rainyscape.comparison.results import load_results, machine_description, save_results
from rainyscape.comparison.scenes import cache_folder, resolve_scene
from rainyscape.comparison.sharing import shared_runs
from rainyscape.comparison.tables import markdown_report
from rainyscape.engine.lock import RunLock
from rainyscape.eval.metric_keys import PSNR, SSIM, render
from rainyscape.formats.atomic import write_text_atomic
from rainyscape.formats.output import make_folders, os_error, remove_made


def _oracle_job(folder: str, cell: Cell) -> dict:
    return scene_oracle(folder, cell_config(cell))


def update_oracles(cells: list[Cell], results: dict, jobs: int, save) -> None:
    """The oracle 3D entry of every scene of ``cells`` in ``results["oracle"]``: kept when it
    was computed for the folder as it is, else computed (``jobs`` scenes at a time, each in
    its own process) and saved as each one finishes."""
    oracle = results.setdefault("oracle", {})
    todo = {}
    for label, folder in dict.fromkeys((c.scene, c.data) for c in cells):
        if cached_oracle(oracle.get(label), folder):
            continue
        reason = unavailable(folder)
        if reason is not None:
            oracle[label] = na_entry(folder, reason)
        else:
            todo[label] = (folder, next(c for c in cells if c.scene == label))
    save()
    if todo:
        print(f"oracle 3D: re-rendering the clean views of {', '.join(todo)} ...", flush=True)
        ctx = multiprocessing.get_context("spawn")
        with ProcessPoolExecutor(max_workers=max(1, min(jobs, len(todo))), mp_context=ctx) as pool:
            running = {pool.submit(_oracle_job, folder, cell): label for label, (folder, cell) in todo.items()}
            for future in as_completed(running):
                oracle[running[future]] = future.result()
                save()
    for label in dict.fromkeys(c.scene for c in cells):
        entry = oracle[label]
        if entry.get("available"):
            print(f"oracle 3D on {label}: training views {PSNR.text(entry['train'][PSNR.name])}"
                  + (f", held-out {PSNR.text(entry['heldout'][PSNR.name])}" if "heldout" in entry else ""),
                  flush=True)
        else:
            print(f"oracle 3D on {label}: n/a ({entry.get('reason')})", flush=True)


def run_bench(opts: BenchOptions, overrides: list[str], command: str) -> tuple[Path, Path, int]:
    """Run (or resume) the matrix; returns (results json, markdown, number of failed cells).

    Before anything is simulated, trained or written (:func:`plan_bench`): every option is
    checked, every cell's config is built, and its budget computed and checked (methods of one
    field family on one scene must train the same steps on the same mean pixels per step,
    unless ``allow_unequal``); then what the benchmark would write over in ``out=`` must be
    its own (:mod:`rainyscape.comparison.output`), and the benchmark's lock free."""
    plan = plan_bench(opts, overrides)
    target = BenchOutput(Path(opts.out).expanduser(), check_name(opts.name or time.strftime("%Y-%m-%d")))
    cache = target.scenes
    simulated = [f for f in (cache_folder(p, cache) for p in plan.plans.values()) if f is not None]
    check_output(target, opts.force, simulated)
    try:
        made = make_folders(target.out)
    except OSError as exc:
        raise os_error(target.out, exc, "cannot create the results folder (out=)") from None
    lock = RunLock(target.out, "rs-bench", name=target.lock_name, label=f"benchmark {target.results}")
    with lock:
        try:
            if opts.force:
                start_afresh(target, simulated)
            return _run_locked(opts, plan, target, command)
        except BaseException:
            if not target.results.exists():  # nothing written: leave out= as it was
                lock.path.unlink(missing_ok=True)
                remove_made(made)
            raise


def _run_locked(opts: BenchOptions, plan, target: BenchOutput, command: str) -> tuple[Path, Path, int]:
    name = target.name
    threads = opts.threads or (max(1, (os.cpu_count() or 1) // opts.jobs) if opts.jobs > 1 else 0)
    for m in plan.mismatches:
        print(f"warning: unequal budgets (allow_unequal=true): {m.describe()}", flush=True)
    cells = plan.cells({label: resolve_scene(p, target.scenes)[1] for label, p in plan.plans.items()})
    budgets = plan.budgets
    json_path, md_path = target.results, target.tables
    results = load_results(json_path)
    results.update({"name": name, "command": command, "machine": machine_description(),
                    "scene_set": plan.scene_set, "allow_unequal": opts.allow_unequal,
                    "budgets": {k: b.to_dict() for k, b in budgets.items()},
                    "budget_mismatches": [m.describe() for m in plan.mismatches]})
    update_oracles(cells, results, opts.jobs, lambda: save_results(json_path, results))
    prints = {c.key: c.fingerprint() for c in cells}  # each builds the cell's whole config
    todo = []
    for n, cell in enumerate(cells, 1):
        prev = results["cells"].get(cell.key, {})
        if prev.get("status") == "finished" and prev.get("fingerprint") == prints[cell.key]:
            print(f"[{n}/{len(cells)}] {cell.key}: done earlier, skipped", flush=True)
        else:
            todo.append((n, cell))

    sources = shared_runs(cells)  # a ceiling -> the earlier ceiling that trains the same run

    def finished_run(key: str) -> str | None:
        done = results["cells"].get(key, {})
        ok = done.get("status") == "finished" and done.get("fingerprint") == prints[key]
        return done["run_dir"] if ok and Path(done.get("run_dir", "")).is_dir() else None

    def run(n: int, cell: Cell, share_from: str | None = None) -> dict:
        folder = target.runs / f"{cell.folder_name}-{prints[cell.key]}"
        doing = f"evaluating the run of {sources[cell.key]} (the same training)" if share_from else "running"
        print(f"[{n}/{len(cells)}] {cell.key}: {doing} (log: {folder / 'bench.log'})", flush=True)
        return run_cell_subprocess(cell, folder, opts.device, threads, share_from)

    failed = 0

    def record(n: int, cell: Cell, result: dict) -> None:
        nonlocal failed
        result.update({"fingerprint": prints[cell.key], "method": cell.method, "scene": cell.scene,
                       "label": cell.label, "overrides": cell.overrides, "budget": budgets[cell.key].to_dict()})
        results["cells"][cell.key] = result
        results["updated"] = time.strftime("%Y-%m-%d %H:%M:%S")
        save_results(json_path, results)
        write_text_atomic(md_path, markdown_report(cells, results))
        if result["status"] == "finished":
            s = result["summary"]
            print(f"[{n}/{len(cells)}] {cell.key}: PSNR {PSNR.text(render(PSNR).of(s))}, "
                  f"SSIM {SSIM.format(render(SSIM).of(s))} ({result['how']}, {result['wall_s']:.0f} s)", flush=True)
        else:
            failed += 1
            print(f"[{n}/{len(cells)}] {cell.key}: FAILED: {result['error']}", flush=True)

    # Cells run in their own processes; threads here only wait on them, and results are
    # recorded from this thread as each finishes, so the results file has one writer.
    with ThreadPoolExecutor(max_workers=opts.jobs) as pool:
        running, waiting = {}, {}  # future -> (n, cell); a source's key -> the cells sharing its run
        for n, cell in todo:
            source = sources.get(cell.key)
            shared = finished_run(source) if source else None
            if source and shared is None:
                waiting.setdefault(source, []).append((n, cell))
            else:
                running[pool.submit(run, n, cell, shared)] = (n, cell)
        try:
            pending = set(running)
            while pending:
                done, pending = wait(pending, return_when=FIRST_COMPLETED)
                for future in done:
                    n, cell = running[future]
                    record(n, cell, future.result())
                    for m, sharer in waiting.pop(cell.key, []):  # a failed source: they train
                        started = pool.submit(run, m, sharer, finished_run(cell.key))
                        running[started] = (m, sharer)
                        pending.add(started)
        except BaseException:  # stopped (Ctrl-C, SIGTERM): start no more cells, stop those running
            for future in running:
                future.cancel()
            stop_running_cells()
            raise
    results["updated"] = time.strftime("%Y-%m-%d %H:%M:%S")
    save_results(json_path, results)
    write_text_atomic(md_path, markdown_report(cells, results))
    return json_path, md_path, failed

