"""A whole benchmark: validate every cell and check its budget, resolve the scenes and their
oracle, run the cells not done yet (``jobs`` at a time, each in its own process) and rewrite
the results file and the tables after each one."""

from __future__ import annotations

import os
import time
from concurrent.futures import ThreadPoolExecutor, as_completed
from pathlib import Path

from rainyscape.bench.budget import Budget, cell_budget, check_budgets
from rainyscape.bench.cell import run_cell_subprocess
from rainyscape.bench.matrix import Cell, build_cells, cell_config, validate_cells
from rainyscape.bench.options import BenchOptions
from rainyscape.bench.oracle import cached_oracle, scene_oracle
from rainyscape.bench.results import load_results, machine_description, save_results
from rainyscape.bench.scenes import ScenePlan, plan_scene, planned_image_size, resolve_scene
from rainyscape.bench.sets import scene_set
from rainyscape.bench.tables import markdown_report
from rainyscape.errors import ConfigError


def family_iters(methods: list[str], overrides: list[str], iters: dict[str, int]) -> dict[str, list[str]]:
    """Per method, the ``trainer.max_iters`` override a scene set gives its field family."""
    out = {}
    for m in methods:
        family = cell_config(Cell(m, "", "", m, list(overrides))).field.name
        if family in iters:
            out[m] = [f"trainer.max_iters={iters[family]}"]
    return out


def image_size(plan: ScenePlan, cfg) -> tuple[int, int]:
    """(width, height) of a scene's images as the cells' dataparser delivers them (after its
    downscale); a folder without ``scene.json`` is parsed to find out."""
    size = planned_image_size(plan)
    if size is None:
        from rainyscape.engine.pipeline import load_scene

        scene = load_scene(cfg, Path(plan.folder))
        return scene.width, scene.height
    factor = max(1, int(getattr(cfg.dataparser.options, "downscale", 1) or 1))
    return size[0] // factor, size[1] // factor


def plan_budgets(cells: list[Cell], plans: dict[str, ScenePlan]) -> dict[str, Budget]:
    """Every cell's training budget from its typed config, before anything is simulated or trained."""
    sizes: dict[str, tuple[int, int]] = {}
    budgets = {}
    for cell in cells:
        cfg = cell_config(cell)
        if cell.scene not in sizes:
            sizes[cell.scene] = image_size(plans[cell.scene], cfg)
        budgets[cell.key] = cell_budget(cfg, *sizes[cell.scene])
    return budgets


def run_bench(opts: BenchOptions, overrides: list[str], command: str) -> tuple[Path, Path, int]:
    """Run (or resume) the matrix; returns (results json, markdown, number of failed cells).

    Before anything is simulated or trained: every cell's config is built, and its budget
    computed and checked (methods of one field family on one scene must train the same steps
    on the same mean pixels per step, unless ``allow_unequal``)."""
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
    sset = scene_set(opts.scenes)
    budget = [f"trainer.max_iters={opts.iters}"] if opts.iters else []
    # Every method and override must be valid before any scene is simulated or cell trained.
    validate_cells(build_cells(methods, [("", "")], budget + overrides,
                               ("", "") if opts.ablation else None, opts.ablation_method))
    every = list(dict.fromkeys(methods + ([opts.ablation_method] if opts.ablation else [])))
    per_method = family_iters(every, budget + overrides, sset.iters) if sset and not opts.iters else {}
    size = dict(width=opts.scene_width or (sset.width if sset else 0),
                height=opts.scene_height or (sset.height if sset and not opts.scene_width else 0),
                rows=opts.scene_rows or (sset.rows if sset else 0), cols=opts.scene_cols or (sset.cols if sset else 0))
    specs = list(sset.presets) if sset else [s.strip() for s in opts.scenes.split(",") if s.strip()]
    main_plans = list({p.label: p for p in (plan_scene(s, **size) for s in specs)}.values())
    ablation_plan = plan_scene(opts.ablation, **size) if opts.ablation else None
    plans = {p.label: p for p in main_plans}
    if ablation_plan is not None:
        plans.setdefault(ablation_plan.label, ablation_plan)

    def matrix(folders: dict[str, str]) -> list[Cell]:
        return build_cells(methods, [(p.label, folders[p.label]) for p in main_plans], budget + overrides,
                           (ablation_plan.label, folders[ablation_plan.label]) if ablation_plan else None,
                           opts.ablation_method, per_method)

    # Budgets are checked before any scene is simulated or cell trained.
    budgets = plan_budgets(matrix({label: p.folder for label, p in plans.items()}), plans)
    mismatches = check_budgets([(key, key.split("/")[0], b) for key, b in budgets.items()
                                if not key.startswith("ablation/")], opts.allow_unequal)
    for m in mismatches:
        print(f"warning: unequal budgets (allow_unequal=true): {m.describe()}", flush=True)
    cache = out / "scenes"
    cells = matrix({label: resolve_scene(plan, cache)[1] for label, plan in plans.items()})
    json_path, md_path = out / f"{name}.json", out / f"{name}.md"
    results = load_results(json_path)
    results.update({"name": name, "command": command, "machine": machine_description(),
                    "scene_set": sset.name if sset else None, "allow_unequal": opts.allow_unequal,
                    "budgets": {k: b.to_dict() for k, b in budgets.items()},
                    "budget_mismatches": [m.describe() for m in mismatches]})
    oracle = results.setdefault("oracle", {})
    for label, folder in dict.fromkeys((c.scene, c.data) for c in cells):
        if not cached_oracle(oracle.get(label), folder):
            print(f"oracle 3D: re-rendering the clean views of '{label}' ...", flush=True)
            oracle[label] = scene_oracle(folder, cell_config(next(c for c in cells if c.scene == label)))
            save_results(json_path, results)
        entry = oracle[label]
        if entry.get("available"):
            print(f"oracle 3D on {label}: training views {entry['train']['psnr']:.2f} dB"
                  + (f", held-out {entry['heldout']['psnr']:.2f} dB" if "heldout" in entry else ""), flush=True)
        else:
            print(f"oracle 3D on {label}: n/a ({entry.get('reason')})", flush=True)
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
                           "label": cell.label, "overrides": cell.overrides,
                           "budget": budgets[cell.key].to_dict()})
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
