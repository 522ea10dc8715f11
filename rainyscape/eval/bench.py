"""``rs-bench``: a matrix of methods x scenes at one budget, resumable, and its tables.

Every cell trains in its own subprocess (so its peak memory is its own) under
``OUT/runs/NAME/<scene>__<method>/``; the results file ``OUT/NAME.json`` is rewritten after
each cell, and a rerun of the same command skips finished cells and resumes interrupted
ones from their last checkpoint. ``OUT/NAME.md`` holds the tables: the paper's Table I
layout (per scene PSNR / SSIM / LPIPS, then the average) for de-raining at the training
views and for held-out views, with training time and peak memory, and the loss ablation
(the paper's Table II) when asked.
"""

from __future__ import annotations

import hashlib
import json
import os
import platform
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor, as_completed
from dataclasses import dataclass, field
from pathlib import Path

from rainyscape.errors import ConfigError

METRICS = ("psnr", "ssim", "lpips")
# The paper's loss ablation (Table II): variant label -> overrides of the ablated method.
ABLATIONS: dict[str, list[str]] = {
    "w/o L_rec": ["losses.reconstruction=none"],
    "w/o L_tv": ["losses.tv=none"],
    "w/o L_agr": ["losses.agr=none"],
    "30 bins": ["losses.agr.bins=30"],
    "90 bins": ["losses.agr.bins=90"],
    "full": [],
}


@dataclass
class Cell:
    """One training run of the matrix."""

    key: str  # "<scene>/<method>" or "ablation/<scene>/<variant>"
    scene: str  # the scene's label in the tables
    data: str  # scene folder ("" = the embedded demo)
    method: str
    overrides: list[str] = field(default_factory=list)
    label: str = ""  # row label (the method, or the ablation variant)

    def fingerprint(self) -> str:
        """What makes two cells the same experiment (a changed budget reruns the cell)."""
        text = json.dumps([self.data, self.method, sorted(self.overrides)])
        return hashlib.sha1(text.encode()).hexdigest()[:12]

    @property
    def folder_name(self) -> str:
        return self.key.replace("/", "__").replace(" ", "_")


# ------------------------------------------------------------------------------ scenes


def resolve_scene(spec: str, cache: Path, width: int = 0, rows: int = 0, cols: int = 0) -> tuple[str, str]:
    """(label, folder) of a scene given as ``demo``, a simulator preset or a folder path.

    ``demo`` without size options is the embedded demo scene; presets are simulated once
    into ``cache`` (a folder per preset, size and simulator version)."""
    path = Path(spec).expanduser()
    if path.is_dir():
        return path.name, str(path.resolve())
    from rainyscape.synth.presets import PRESETS

    if spec not in PRESETS:
        raise ConfigError(f"scene '{spec}' is neither a folder nor a simulator preset "
                          f"({', '.join(PRESETS)})")
    if spec == "demo" and not (width or rows or cols):
        from rainyscape.synth.demo import ensure_demo_scene

        return "demo", str(ensure_demo_scene())
    from rainyscape.synth import SIM_VERSION, generate

    size = f"-{width or 'd'}x{rows or 'd'}x{cols or 'd'}" if (width or rows or cols) else ""
    folder = cache / f"{spec}{size}-v{SIM_VERSION}"
    if not (folder / "scene.json").is_file():
        print(f"simulating scene '{spec}' into {folder} ...", flush=True)
        tmp = folder.with_name(folder.name + ".partial")
        if tmp.exists():
            import shutil

            shutil.rmtree(tmp)
        generate(tmp, spec, rows=rows or None, cols=cols or None, width=width or None, force=True)
        tmp.rename(folder)
    return spec, str(folder)


# ------------------------------------------------------------------------------ matrix


def build_cells(methods: list[str], scenes: list[tuple[str, str]], overrides: list[str],
                ablation: tuple[str, str] | None = None, ablation_method: str = "rainyscape-nerf") -> list[Cell]:
    cells = [Cell(f"{label}/{m}", label, data, m, list(overrides), m) for label, data in scenes for m in methods]
    if ablation is not None:
        label, data = ablation
        cells += [Cell(f"ablation/{label}/{variant}", label, data, ablation_method,
                       list(overrides) + extra, variant) for variant, extra in ABLATIONS.items()]
    return cells


def validate_cells(cells: list[Cell]) -> None:
    """Every cell's config must build before anything trains (typos fail at once)."""
    from rainyscape.config import method_config

    for cell in cells:
        try:
            method_config(cell.method, [f"data={cell.data}", *cell.overrides])
        except ConfigError as exc:
            raise ConfigError(f"{cell.key.strip('/')}: {exc}") from None


# -------------------------------------------------------------------- running a cell


def find_run(output_dir: Path) -> Path | None:
    """The newest run folder under a cell's output folder."""
    runs = sorted(p.parent for p in output_dir.glob("*/*/*/config.yml"))
    return runs[-1] if runs else None


def peak_memory_mib() -> dict:
    import resource

    import torch

    out = {"peak_rss_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0}
    if torch.cuda.is_available():
        out["peak_cuda_mib"] = torch.cuda.max_memory_allocated() / 2**20
    return out


def training_seconds(run_dir: Path) -> float | None:
    """Training time from the log (the trainer stamps seconds since its start; a resumed run
    adds its segments)."""
    from rainyscape.eval.report import read_log

    train, _ = read_log(run_dir / "log.jsonl")
    total, last = 0.0, 0.0
    for rec in train:
        t = float(rec.get("time", 0.0))
        if t < last:  # a resume restarted the clock
            total += last
        last = t
    return total + last if train else None


def run_cell_here(spec: dict) -> dict:
    """Train (or resume, or just read back) one cell in this process; returns its result."""
    from rainyscape.config import method_config
    from rainyscape.workflow import train_and_evaluate

    output_dir = Path(spec["output_dir"])
    cfg = method_config(spec["method"], spec["overrides"] + [f"trainer.output_dir={output_dir}"])
    existing = find_run(output_dir)
    started = time.perf_counter()
    status = {}
    if existing is not None:
        status = json.loads((existing / "status.json").read_text()) if (existing / "status.json").is_file() else {}
    if existing is not None and status.get("state") == "finished" and (existing / "metrics.json").is_file():
        run_dir, resumed = existing, "read back"
    else:
        from rainyscape.engine.checkpoint import latest_checkpoint

        resume = existing if existing is not None and latest_checkpoint(existing / "checkpoints") else None
        run_dir = train_and_evaluate(cfg, resume).run_dir
        resumed = "resumed" if resume is not None else "trained"
    metrics = json.loads((run_dir / "metrics.json").read_text())
    return {"status": "finished", "how": resumed, "run_dir": str(run_dir),
            "wall_s": time.perf_counter() - started, "train_s": training_seconds(run_dir),
            "iters": cfg.trainer.max_iters, "summary": metrics.get("summary", {}),
            "postprocess": metrics.get("postprocess", []), "lpips": metrics.get("lpips", {}),
            "views": metrics.get("views", {}), **peak_memory_mib()}


def run_cell_subprocess(cell: Cell, output_dir: Path, device: str, threads: int = 0) -> dict:
    """Run a cell in a fresh interpreter (``threads`` > 0: that many torch / OpenMP
    threads); its console output goes to ``bench.log``."""
    output_dir.mkdir(parents=True, exist_ok=True)
    spec = {"method": cell.method, "overrides": [f"data={cell.data}", *cell.overrides,
                                                 f"trainer.device={device}", "trainer.progress=false"],
            "output_dir": str(output_dir)}
    spec_path, result_path = output_dir / "cell.json", output_dir / "result.json"
    spec_path.write_text(json.dumps(spec, indent=2))
    result_path.unlink(missing_ok=True)
    env = dict(os.environ, OMP_NUM_THREADS=str(threads)) if threads > 0 else None
    with open(output_dir / "bench.log", "a") as log:
        done = subprocess.run([sys.executable, "-m", "rainyscape.eval.bench", str(spec_path), str(result_path)],
                              stdout=log, stderr=subprocess.STDOUT, env=env)
    if done.returncode == 0 and result_path.is_file():
        return json.loads(result_path.read_text())
    tail = (output_dir / "bench.log").read_text().strip().splitlines()[-5:]
    return {"status": "failed", "error": " | ".join(tail) or f"exit code {done.returncode}"}


# ---------------------------------------------------------------------------- results


def machine_description() -> dict:
    import torch

    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    gpu = torch.cuda.get_device_name(0) if torch.cuda.is_available() else None
    return {"cpu": cpu, "cores": os.cpu_count(), "gpu": gpu, "torch": torch.__version__,
            "python": platform.python_version(), "platform": platform.platform()}


def load_results(path: Path) -> dict:
    if not path.is_file():
        return {"cells": {}}
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError:
        raise ConfigError(f"{path}: results file is not valid JSON; move it away to start afresh") from None


def save_results(path: Path, results: dict) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(results, indent=2))
    tmp.replace(path)


# ----------------------------------------------------------------------------- tables


def _fmt(value: float | None, metric: str) -> str:
    if value is None:
        return "n/a"
    return f"{value:.2f}" if metric == "psnr" else f"{value:.3f}"


def _mean(values: list) -> float | None:
    values = [v for v in values if v is not None]
    return sum(values) / len(values) if values else None


def table_rows(cells: list[Cell], results: dict, prefix: str) -> list[tuple[str, dict, list[dict]]]:
    """(row label, {scene: {metric: value}}, cell results) for one evaluation split.

    ``prefix`` "train" gives the paper's numbers: a rainy-input row, each method, and each
    method's post-processed variant; "heldout" gives novel views."""
    scenes = list(dict.fromkeys(c.scene for c in cells))
    done = {c.key: results["cells"][c.key] for c in cells
            if results["cells"].get(c.key, {}).get("status") == "finished"}
    rows: list[tuple[str, dict, list[dict]]] = []
    if prefix == "train":
        floor = {}
        for s in scenes:
            found = [r for c in cells if c.scene == s and (r := done.get(c.key))
                     and "rainy_input_psnr" in r["summary"]]
            if found:
                floor[s] = {m: found[0]["summary"].get(f"rainy_input_{m}") for m in METRICS}
        if floor:
            rows.append(("rainy input", floor, []))
    for label in dict.fromkeys(c.label for c in cells):
        mine = [c for c in cells if c.label == label and c.key in done]
        if not mine:
            continue
        variants = [("", f"{prefix}_")]
        if prefix == "train":
            posts = dict.fromkeys(p for c in mine for p in done[c.key].get("postprocess", []))
            variants += [(f" + {p}", f"train_{p}_") for p in posts]
        for suffix, key in variants:
            per_scene = {c.scene: {m: done[c.key]["summary"].get(key + m) for m in METRICS} for c in mine}
            rows.append((label + suffix, per_scene, [done[c.key] for c in mine]))
    return rows


def markdown_table(cells: list[Cell], results: dict, prefix: str) -> str:
    scenes = list(dict.fromkeys(c.scene for c in cells))
    cols = scenes + (["Average"] if len(scenes) > 1 else [])
    head = ["Method"] + [f"{s} {m.upper()} {'↓' if m == 'lpips' else '↑'}" for s in cols for m in METRICS]
    head += ["Train time (s)", "Peak memory (MiB)"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for label, per_scene, runs in table_rows(cells, results, prefix):
        values = []
        for s in scenes:
            values += [_fmt(per_scene.get(s, {}).get(m), m) for m in METRICS]
        if len(scenes) > 1:
            complete = all(s in per_scene for s in scenes)
            values += [_fmt(_mean([per_scene[s].get(m) for s in scenes]) if complete else None, m)
                       for m in METRICS]
        t = _mean([r.get("train_s") for r in runs])
        mem = max([r.get("peak_cuda_mib") or r.get("peak_rss_mib") or 0 for r in runs], default=0)
        values += [f"{t:.0f}" if t is not None else "–", f"{mem:.0f}" if runs else "–"]
        lines.append("| " + " | ".join([label] + values) + " |")
    return "\n".join(lines)


def markdown_report(cells: list[Cell], results: dict) -> str:
    main = [c for c in cells if not c.key.startswith("ablation/")]
    ablation = [c for c in cells if c.key.startswith("ablation/")]
    m = results.get("machine", {})
    machine = f"{m.get('cpu', '?')}, {m.get('cores', '?')} cores" + (f", GPU {m['gpu']}" if m.get("gpu") else "")
    parts = [f"# Benchmark {results.get('name', '')}", "",
             f"Command: `{results.get('command', '')}`  ",
             f"Machine: {machine}; torch {m.get('torch', '?')}  ",
             f"Updated: {results.get('updated', '')}", ""]
    if main:
        parts += ["## De-raining at the training views (the paper's Table I protocol)", "",
                  markdown_table(main, results, "train"), "",
                  "## Novel views (held-out views)", "", markdown_table(main, results, "heldout"), ""]
    if ablation:
        parts += [f"## Loss ablation ({ablation[0].method} on {ablation[0].scene}; the paper's Table II)", "",
                  markdown_table(ablation, results, "train"), ""]
    lp = next((r.get("lpips") for r in results["cells"].values() if r.get("lpips")), None)
    if lp and not lp.get("available", False):
        parts += [f"LPIPS: n/a ({lp.get('reason', 'unavailable')}).", ""]
    failed = [k for k, r in results["cells"].items() if r.get("status") == "failed"]
    if failed:
        parts += [f"Failed cells: {', '.join(failed)} (see their bench.log).", ""]
    parts += ["Train time: mean over scenes of the training wall time (evaluation excluded); "
              "peak memory: the largest peak over scenes (resident memory on CPU, "
              "allocated CUDA memory on a GPU).", ""]
    return "\n".join(parts)


# ------------------------------------------------------------------------------- main


@dataclass
class BenchOptions:
    methods: str = "nerf,robust-nerf,rainyscape-nerf,3dgs,robust-3dgs,rainyscape-3dgs"
    scenes: str = "demo"
    iters: int = 0  # trainer.max_iters of every cell (0: each method's own)
    out: str = "benchmarks/results"
    name: str = ""  # results file name (default: today's date)
    device: str = "auto"
    ablation: str = ""  # a scene for the loss ablation table ("" : none)
    ablation_method: str = "rainyscape-nerf"
    scene_width: int = 0  # simulated scenes: image width (0: the preset's)
    scene_rows: int = 0  # simulated scenes: camera rows x cols (0: the preset's)
    scene_cols: int = 0
    jobs: int = 1  # cells trained at the same time
    threads: int = 0  # torch threads per cell (0: torch's default, or cores / jobs when jobs > 1)


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


def _cell_main(spec_path: str, result_path: str) -> int:
    """Subprocess entry: ``python -m rainyscape.eval.bench CELL.json RESULT.json``."""
    from rainyscape.errors import RainyScapeError

    spec = json.loads(Path(spec_path).read_text())
    try:
        result = run_cell_here(spec)
    except RainyScapeError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    Path(result_path).write_text(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(_cell_main(*sys.argv[1:3]))
