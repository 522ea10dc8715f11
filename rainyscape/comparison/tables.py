"""The Markdown tables of a benchmark: the paper's Table I layout (per scene PSNR / SSIM /
LPIPS, then the average, with each method's budget, training time and peak memory) for the
training and the held-out views, and the loss ablation (Table II).

Every table starts with the ``oracle 3D`` row (the clean scene re-rendered: the ceiling of
any method), the ``METHOD on clean views`` rows (a plain field trained on the clean views at
the same budget: the ceiling of the rain methods on that field) and, on training views, the
``rainy input`` row (the floor). Each fused row (``method + <pp>``) is
followed by ``↳ fused − input`` (its gain over the rainy input) and ``↳ control`` (the same
fusion with a random mask of the same coverage): a fused gain belongs to the rain model only
as far as the fused row is above its control.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from rainyscape.comparison.budget import Budget
from rainyscape.comparison.matrix import CEILING, Cell
from rainyscape.comparison.oracle import ORACLE_SAMPLES
from rainyscape.eval.metric_keys import (ANGLE_ERROR, CORRELATION, COVERAGE, IMAGE_MEASURES, PSNR, PSNR_DRY,
                                         PSNR_IN_RAIN, Measure, control, post, rain_stat, rainy_input,
                                         render)
from rainyscape.eval.summary import mean_of

ORACLE = "oracle 3D"
INPUT = "rainy input"
GAIN = "↳ fused − input"
CONTROL = "↳ control: random mask, same coverage"


@dataclass
class Row:
    label: str
    per_scene: dict[str, dict[Measure, float | None]]  # scene -> measure -> value
    runs: list[dict] = field(default_factory=list)  # the cells' results (time, memory)
    kind: str = "method"  # oracle | ceiling | input | method | fused | gain | control
    method: str = ""  # the row label of the method it belongs to (budget column)


def _markdown(head: list[str], rows: list[list[str]]) -> str:
    """A markdown table: the header, its rule, then the rows."""
    rule = "|" + "---|" * len(head)
    return "\n".join(["| " + " | ".join(head) + " |", rule] + ["| " + " | ".join(r) + " |" for r in rows])


def _done(cells: list[Cell], results: dict) -> dict[str, dict]:
    return {c.key: results["cells"][c.key] for c in cells
            if results["cells"].get(c.key, {}).get("status") == "finished"}


def input_summaries(cells: list[Cell], done: dict[str, dict]) -> dict[str, dict]:
    """Per scene, the summary of the first finished cell trained on the rainy views: it holds
    the rainy input's metrics (a ceiling cell's "input" is the clean views)."""
    out: dict[str, dict] = {}
    for c in cells:
        if not c.clean and c.key in done and any(rainy_input(m).key in done[c.key]["summary"]
                                                 for m in (*IMAGE_MEASURES, PSNR_IN_RAIN)):
            out.setdefault(c.scene, done[c.key]["summary"])
    return out


def table_rows(cells: list[Cell], results: dict, split: str) -> list[Row]:
    """The rows of one evaluation split: "train" gives the paper's numbers (oracle, rainy
    input, each method, each fused variant with its gain over the input and its random-mask
    control); "heldout" gives novel views (oracle and methods)."""
    scenes = list(dict.fromkeys(c.scene for c in cells))
    done = _done(cells, results)
    oracle = results.get("oracle", {})
    rows = [Row(ORACLE, {s: {m: oracle[s][split].get(m.name) for m in IMAGE_MEASURES} for s in scenes
                         if oracle.get(s, {}).get("available") and split in oracle[s]}, kind="oracle")]
    if split == "train":
        floor = {s: {m: rainy_input(m).of(summary) for m in IMAGE_MEASURES}
                 for s, summary in input_summaries(cells, done).items()}
        rows.append(Row(INPUT, floor, kind="input"))
    for label in dict.fromkeys(c.label for c in cells):
        mine = [c for c in cells if c.label == label and c.key in done]
        if not mine:
            continue
        runs = [done[c.key] for c in mine]
        rows.append(Row(label, {c.scene: {m: render(m, split).of(done[c.key]["summary"]) for m in IMAGE_MEASURES}
                                for c in mine}, runs, "ceiling" if mine[0].clean else "method", label))
        if split != "train" or mine[0].clean:
            continue
        for p in dict.fromkeys(p for r in runs for p in r.get("postprocess", [])):
            def values(metric, minus=None) -> dict:
                """Per scene and measure: ``metric(measure)``, less ``minus(measure)`` when given."""
                out = {}
                for c in mine:
                    s = done[c.key]["summary"]
                    out[c.scene] = {}
                    for m in IMAGE_MEASURES:
                        v, base = metric(m).of(s), (minus(m).of(s) if minus else 0.0)
                        out[c.scene][m] = v - base if v is not None and base is not None else None
                return out

            rows.append(Row(f"{label} + {p}", values(lambda m: post(m, p)), runs, "fused", label))
            rows.append(Row(GAIN, values(lambda m: post(m, p), rainy_input), [], "gain", label))
            coverage = mean_of([post(COVERAGE, p).of(r["summary"]) for r in runs])
            label_ = CONTROL + (f" ({100 * coverage:.1f} %)" if coverage is not None else "")
            rows.append(Row(label_, values(lambda m: control(m, p)), [], "control", label))
    first = {"oracle": 0, "ceiling": 1}  # the two ceilings, then the floor and the methods
    return sorted(rows, key=lambda r: first.get(r.kind, 2))


def _budget(key: str, results: dict) -> Budget | None:
    d = results["cells"].get(key, {}).get("budget") or results.get("budgets", {}).get(key)
    return Budget.from_dict(d) if d else None


def budget_column(cells: list[Cell], results: dict) -> dict[str, str]:
    """Row label -> the budget column's text: ``steps × mean pixels per step`` (several values
    when scenes differ), and where a method's budget differs from the first method of its
    field family on some scene (allowed only with allow_unequal=true), that difference."""
    # the methods first, so that a difference is named against a method, not its ceiling
    labels = list(dict.fromkeys(c.label for c in sorted(cells, key=lambda c: c.clean)))
    by = {(c.label, c.scene): _budget(c.key, results) for c in cells}
    text = {}
    for label in labels:
        mine = [(s, b) for (lab, s), b in by.items() if lab == label and b is not None]
        if not mine:
            continue
        shorts = list(dict.fromkeys(b.short() for _, b in mine))
        out = " / ".join(shorts)
        for s, b in mine:
            ref = next(((lab, r) for lab in labels if (r := by.get((lab, s))) is not None
                        and r.family == b.family), None)
            if ref is not None and ref[0] != label and not b.same_as(ref[1]):
                out += f" (≠ {ref[0]}: {ref[1].short()})"
                break
        text[label] = out
    return text


def markdown_table(cells: list[Cell], results: dict, split: str) -> str:
    scenes = list(dict.fromkeys(c.scene for c in cells))
    cols = scenes + (["Average"] if len(scenes) > 1 else [])
    head = ["Method"] + [f"{s} {m.title} {m.arrow}" for s in cols for m in IMAGE_MEASURES]
    head += ["Budget (steps × px/step)", "Train time (s)", "Peak memory (MiB)"]
    lines = []
    budgets = budget_column(cells, results)
    for row in table_rows(cells, results, split):
        signed = row.kind == "gain"
        values = []
        for s in scenes:
            values += [m.format(row.per_scene.get(s, {}).get(m), signed) for m in IMAGE_MEASURES]
        if len(scenes) > 1:
            complete = all(s in row.per_scene for s in scenes)
            values += [m.format(mean_of([row.per_scene[s].get(m) for s in scenes]) if complete else None, signed)
                       for m in IMAGE_MEASURES]
        if row.kind in ("method", "fused", "ceiling"):
            t = mean_of([r.get("train_s") for r in row.runs])
            mem = max([r.get("peak_cuda_mib") or r.get("peak_rss_mib") or 0 for r in row.runs], default=0)
            values += [budgets.get(row.method, "–"), f"{t:.0f}" if t is not None else "–",
                       f"{mem:.0f}" if row.runs else "–"]
        else:
            values += ["–", "–", "–"]
        lines.append([row.label] + values)
    return _markdown(head, lines)


def oracle_notes(cells: list[Cell], results: dict) -> list[str]:
    scenes = list(dict.fromkeys(c.scene for c in cells))
    oracle = results.get("oracle", {})
    why: dict[str, list[str]] = {}  # reason -> scenes, so one reason is said once
    for s in scenes:
        if not oracle.get(s, {}).get("available"):
            why.setdefault(oracle.get(s, {}).get("reason", "not computed"), []).append(s)
    missing = [f"{', '.join(names)} ({reason})" for reason, names in why.items()]
    text = (f"`{ORACLE}`: the clean scene itself re-rendered ({ORACLE_SAMPLES} x {ORACLE_SAMPLES} base samples "
            "per pixel, an independent sample set) against the stored clean images: what a perfect 3D "
            "reconstruction scores, the ceiling of each column.")
    if missing:
        text += " n/a on " + "; on ".join(missing) + "."
    notes = [text]
    ceilings = list(dict.fromkeys(c.label for c in cells if c.clean))
    if ceilings:
        notes.append(f"`{'`, `'.join(ceilings)}`: the method trained on the scene's clean views at the same budget: "
                     "what its field reaches here without rain, so the most a rain method on that field can "
                     "reach. A rain method's gain over the plain field is bounded by the gap between the two, up to "
                     "run-to-run noise.")
    return notes


def fusion_notes(cells: list[Cell], results: dict) -> list[str]:
    rows = [r for r in table_rows(cells, results, "train") if r.kind == "fused"]
    if not rows:
        return []
    parts = []
    for row in rows:
        p = row.label.split(" + ", 1)[1]
        cov = ", ".join(f"{r.get('scene', '?')} {100 * c:.1f} %" for r in row.runs
                        if (c := post(COVERAGE, p).of(r["summary"])) is not None)
        if cov:
            parts.append(f"{row.label}: {cov}")
    text = (f"`{GAIN}`: the fused row minus the rainy input (PSNR in dB, SSIM). `{CONTROL}`: the same fusion "
            "with a mask of random pixels covering the same fraction of each view as the predicted rain "
            "mask (seeded); the fused gain is the rain model's only as far as the fused row is above its "
            "control, the rest comes from copying the input.")
    if parts:
        text += " Mask coverage per scene: " + "; ".join(parts) + "."
    return [text]


def budget_notes(cells: list[Cell], results: dict) -> list[str]:
    fams: dict[str, list[str]] = {}
    for c in cells:
        b = _budget(c.key, results)
        if b is not None and c.label not in fams.setdefault(b.family, []):
            fams[b.family].append(c.label)
    if not fams:
        return []
    text = ("Budget: training steps × mean pixels (rays) per step, each phase weighted by its steps "
            "(a whole view counts width × height). Methods that train the same field ("
            + "; ".join(f"{f}: {', '.join(labels)}" for f, labels in fams.items())
            + ") get the same budget (rs-bench refuses otherwise)")
    text += "; different fields may differ (a Gaussian step renders whole views, a NeRF step a batch of rays)." \
        if len(fams) > 1 else "."
    notes = [text]
    if results.get("budget_mismatches"):
        notes.append("**Unequal budgets within a field** (allow_unequal=true), so these rows do not compare "
                     "like for like: " + "; ".join(results["budget_mismatches"]) + ".")
    return notes


def _corr_angle(corr: float, error: float) -> str:
    return f"{CORRELATION.format(corr)} / {ANGLE_ERROR.format(error)}°"


def rain_table(cells: list[Cell], results: dict) -> str:
    """Per rain method and scene: the predicted rain's correlation with the true rain layer
    and its streak angle's error (degrees), and their means; "" when no cell has them."""
    done = _done(cells, results)
    scenes = list(dict.fromkeys(c.scene for c in cells))
    corr, error = rain_stat(CORRELATION), rain_stat(ANGLE_ERROR)
    methods = [m for m in dict.fromkeys(c.method for c in cells)
               if any(corr.key in done.get(f"{sc}/{m}", {}).get("summary", {}) for sc in scenes)]
    if not methods:
        return ""
    head = ["Method"] + [f"{sc} corr {CORRELATION.arrow} / angle err {ANGLE_ERROR.arrow}" for sc in scenes] + ["Average"]
    lines = []
    for m in methods:
        pairs = [(corr.of(s), error.of(s)) for s in (done.get(f"{sc}/{m}", {}).get("summary", {}) for sc in scenes)]
        cols = ["n/a" if r is None or a is None else _corr_angle(r, a) for r, a in pairs]
        known = [(r, a) for r, a in pairs if r is not None and a is not None]
        mean = (_corr_angle(sum(r for r, _ in known) / len(known), sum(a for _, a in known) / len(known))
                if known else "n/a")
        lines.append([m] + cols + [mean])
    return _markdown(head, lines)


def region_table(cells: list[Cell], results: dict) -> str:
    """Per method and scene, training views: the render's PSNR on the pixels the true rain
    covers / on the others (the rainy input's row: on the rain pixels only, it is exact
    elsewhere), and their means; "" when no cell has them."""
    done = _done(cells, results)
    scenes = list(dict.fromkeys(c.scene for c in cells))
    summary = {(c.label, c.scene): done[c.key]["summary"] for c in cells if c.key in done}
    rainy = input_summaries(cells, done)
    wet, dry = render(PSNR_IN_RAIN), render(PSNR_DRY)
    rows = [(INPUT, {sc: (rainy_input(PSNR_IN_RAIN).of(rainy.get(sc, {})), None) for sc in scenes})]
    rows += [(label, {sc: (wet.of(summary.get((label, sc), {})), dry.of(summary.get((label, sc), {})))
                      for sc in scenes})
             for label in dict.fromkeys(c.label for c in cells)]
    lines = []
    for label, values in rows:
        if all(wet is None for wet, _ in values.values()):
            continue
        wets, drys = zip(*values.values())
        cols = [_region(wet, dry) for wet, dry in zip(wets, drys)]
        lines.append([label] + cols + [_region(_mean_of_all(wets), _mean_of_all(drys))])
    if len(lines) < 2:
        return ""
    return _markdown(["Method"] + [f"{sc} in rain / dry" for sc in scenes] + ["Average"], lines)


def _mean_of_all(values) -> float | None:
    """The mean, or None when a value is missing."""
    return None if any(v is None for v in values) else sum(values) / len(values)


def _region(wet: float | None, dry: float | None) -> str:
    if wet is None:
        return "n/a"
    return PSNR_IN_RAIN.format(wet) + ("" if dry is None else " / " + PSNR_DRY.format(dry))


def _gain(gain: float, gap: float) -> str:
    return f"{PSNR.format(gain, signed=True)} / {PSNR.format(gap)}"


def gap_table(cells: list[Cell], results: dict, split: str) -> str:
    """Per method, per scene: its gain over the plain field it trains (PSNR, dB) out of the
    gap between that field on the rainy and on the clean views (the ceiling row), and the
    mean of both; "" without ceiling rows."""
    done = _done(cells, results)
    scenes = list(dict.fromkeys(c.scene for c in cells))
    family = {c.label: b.family for c in cells if (b := _budget(c.key, results)) is not None}
    plain = {family[c.label]: c.method for c in cells if c.clean and c.label in family}
    psnr = {(c.label, c.scene): render(PSNR, split).of(done[c.key]["summary"]) for c in cells if c.key in done}
    rows = []
    for label in dict.fromkeys(c.label for c in cells if not c.clean):
        base = plain.get(family.get(label))
        if base is None or base == label:
            continue
        pairs = []
        for sc in scenes:
            m, b, top = psnr.get((label, sc)), psnr.get((base, sc)), psnr.get((f"{base}{CEILING}", sc))
            pairs.append(None if None in (m, b, top) else (m - b, top - b))
        known = [x for x in pairs if x is not None]
        cols = ["n/a" if x is None else _gain(*x) for x in pairs]
        mean = (_gain(sum(g for g, _ in known) / len(known), sum(t for _, t in known) / len(known))
                if len(known) == len(pairs) else "n/a")
        rows.append([f"{label} (over {base})"] + cols + [mean])
    if not rows:
        return ""
    return _markdown(["Method"] + [f"{sc} gain / gap" for sc in scenes] + ["Average"], rows)


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
                  markdown_table(main, results, "train"), ""]
        for note in oracle_notes(main, results) + fusion_notes(main, results) + budget_notes(main, results):
            parts += [note, ""]
        gaps = [(views, gap_table(main, results, split)) for views, split in
                (("training views", "train"), ("held-out views", "heldout"))]
        if gaps[0][1]:
            parts += ["## Gain over the plain field, out of the gap rain leaves (raw renders)", ""]
            for views, table in gaps:
                parts += [f"{views.capitalize()}:", "", table, ""]
            parts += ["Each cell: the method's PSNR minus its plain field's (`nerf` or `3dgs` trained on the "
                      "rainy views) / the same field on the clean views minus on the rainy views: the most a "
                      "rain method on that field can gain at this budget.", ""]
        regions = region_table(main, results)
        if regions:
            parts += ["## Where the renders err: pixels in rain and dry pixels (training views, PSNR)", "",
                      regions, "",
                      "Each cell: the raw render's PSNR against the clean view on the pixels the true rain "
                      "covers (any channel above 0.02) / on the other pixels. Rain left in the render "
                      "lowers the first; a rain method that degrades the rest of the scene lowers the second.", ""]
        parts += ["## Novel views (held-out views)", "", markdown_table(main, results, "heldout"), ""]
        rain = rain_table(main, results)
        if rain:
            parts += ["## The predicted rain layer (training views)", "", rain, "",
                      "Correlation of the predicted rain with the true rain layer, and the error of its "
                      "streak angle against the true rain's (degrees).", ""]
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
    return "\n".join([p for i, p in enumerate(parts) if p or (i and parts[i - 1])])
