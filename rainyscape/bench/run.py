"""A whole benchmark: validate every cell, resolve the scenes, run the cells not done yet
(``jobs`` at a time, each in its own process) and rewrite the results file and the tables
after each one."""

from __future__ import annotations

import os
import time
from concurrent.futures import ThreadPoolExecutor, as_completed
from pathlib import Path

from rainyscape.bench.cell import run_cell_subprocess
from rainyscape.bench.matrix import Cell, build_cells, validate_cells
from rainyscape.bench.options import BenchOptions
from rainyscape.bench.results import load_results, machine_description, save_results
from rainyscape.bench.scenes import resolve_scene
from rainyscape.bench.tables import markdown_report
from rainyscape.errors import ConfigError


def run_bench(opts: BenchOptions, overrides: list[str], command: str) -> tuple[Path, Path, int]:
    """Run (or resume) the matrix; returns (results json, markdown, number of failed cells)."""
    out = Path(opts.out)
    name = opts.name or time.strftime("%Y-%m-%d")
    methods = [m.strip() for m in opts.methods.split(",") if m.strip()]
    if not methods:
        raise ConfigError("rs-bench: methods= lists no method")
    if opts.iters < 0:
        raise ConfigError(f"rs-bench: iters must be >= 0, got {opts.iters}")
    if opts.jobs < 1 or opts.threads < 0:
        raise ConfigError(f"rs-bench: jobs must be >= 1 and threads >= 0, got {opts.jobs} and {opts.threads}")
    threads = opts.threads or (max(1, (os.cpu_count() or 1) // opts.jobs) if opts.jobs > 1 else 0)
    budget = [f"trainer.max_iters={opts.iters}"] if opts.iters else []
    # Every method and override must be valid before any scene is simulated or cell trained.
    validate_cells(build_cells(methods, [("", "")], budget + overrides,
                               ("", "") if opts.ablation else None, opts.ablation_method))
    cache = out / "scenes"
    size = (opts.scene_width, opts.scene_rows, opts.scene_cols)
    scene_specs = [s.strip() for s in opts.scenes.split(",") if s.strip()]
    scenes = [resolve_scene(s, cache, *size) for s in scene_specs]
    ablation = resolve_scene(opts.ablation, cache, *size) if opts.ablation else None
    cells = build_cells(methods, scenes, budget + overrides, ablation, opts.ablation_method)
    json_path, md_path = out / f"{name}.json", out / f"{name}.md"
    results = load_results(json_path)
    results.update({"name": name, "command": command, "machine": machine_description()})
    todo = []
    for n, cell in enumerate(cells, 1):
        prev = results["cells"].get(cell.key, {})
        if prev.get("status") == "finished" and prev.get("fingerprint") == cell.fingerprint():
            print(f"[{n}/{len(cells)}] {cell.key}: done earlier, skipped", flush=True)
        else:
            todo.append((n, cell))

    def run(n: int, cell: Cell) -> dict:
        folder = out / "runs" / name / f"{cell.folder_name}-{cell.fingerprint()}"
        print(f"[{n}/{len(cells)}] {cell.key}: running (log: {folder / 'bench.log'})", flush=True)
        return run_cell_subprocess(cell, folder, opts.device, threads)

    failed = 0
    # Cells run in their own processes; threads here only wait on them, and results are
    # recorded from this thread as each finishes, so the results file has one writer.
    with ThreadPoolExecutor(max_workers=opts.jobs) as pool:
        running = {pool.submit(run, n, cell): (n, cell) for n, cell in todo}
        for future in as_completed(running):
            n, cell = running[future]
            result = future.result()
            result.update({"fingerprint": cell.fingerprint(), "method": cell.method, "scene": cell.scene,
                           "label": cell.label, "overrides": cell.overrides})
            results["cells"][cell.key] = result
            results["updated"] = time.strftime("%Y-%m-%d %H:%M:%S")
            save_results(json_path, results)
            md_path.write_text(markdown_report(cells, results))
            if result["status"] == "finished":
                s = result["summary"]
                print(f"[{n}/{len(cells)}] {cell.key}: PSNR {s.get('train_psnr', float('nan')):.2f} dB, "
                      f"SSIM {s.get('train_ssim', float('nan')):.3f} ({result['how']}, {result['wall_s']:.0f} s)",
                      flush=True)
            else:
                failed += 1
                print(f"[{n}/{len(cells)}] {cell.key}: FAILED: {result['error']}", flush=True)
    results["updated"] = time.strftime("%Y-%m-%d %H:%M:%S")
    save_results(json_path, results)
    md_path.write_text(markdown_report(cells, results))
    return json_path, md_path, failed
