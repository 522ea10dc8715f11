"""The Markdown tables of a benchmark: the paper's Table I layout (per scene PSNR / SSIM /
LPIPS, then the average, with training time and peak memory) for the training and the
held-out views, and the loss ablation (Table II)."""

from __future__ import annotations

from rainyscape.bench.matrix import Cell
from rainyscape.eval.summary import mean_of

METRICS = ("psnr", "ssim", "lpips")


def _fmt(value: float | None, metric: str) -> str:
    if value is None:
        return "n/a"
    return f"{value:.2f}" if metric == "psnr" else f"{value:.3f}"


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
            values += [_fmt(mean_of([per_scene[s].get(m) for s in scenes]) if complete else None, m)
                       for m in METRICS]
        t = mean_of([r.get("train_s") for r in runs])
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
