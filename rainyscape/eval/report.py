"""``report.html`` of a run: one self-contained page (every image inlined as base64 PNG, no
scripts, no external links) with the training curves (loss terms; PSNR vs clean and vs rainy
over steps: the paper's Fig. 2 and 6), the comparison strips, the metric table and the config.
"""

from __future__ import annotations

import base64
import html
import io
from pathlib import Path

from rainyscape.engine.run_folder import RunFolder
from rainyscape.errors import RainyScapeError
from rainyscape.eval.metric_keys import (ANGLE_ERROR, CORRELATION, IMAGE_MEASURES, LPIPS, RAIN_ANGLE, RAIN_KEPT,
                                         RAIN_RECOVERED, RESIDUAL_ANGLE, SPLITS, TRUE_ANGLE, Metric, post,
                                         quick_key, rain_stat, rainy_input, render)
from rainyscape.formats.atomic import write_text_atomic

POINTS_RECORD = "scene_points"  # log.jsonl: the sparse points the field started from (step 0)
MAX_STRIPS = 6  # comparison strips shown (rs-render writes one per view under renders/strips)
CSS = """
body{font-family:system-ui,sans-serif;margin:24px auto;max-width:1200px;color:#222;padding:0 16px}
h1{font-size:1.5em}h2{font-size:1.2em;margin-top:1.6em;border-bottom:1px solid #ddd}
table{border-collapse:collapse;margin:8px 0}td,th{border:1px solid #ccc;padding:3px 8px;text-align:right}
th{background:#f3f3f3}td:first-child,th:first-child{text-align:left}
img{max-width:100%;image-rendering:pixelated;display:block;margin:6px 0}
pre{background:#f7f7f7;padding:8px;overflow:auto;font-size:12px}.note{color:#666;font-size:.9em}
"""


# ----------------------------------------------------------------------------- reading


def read_log(run_dir: Path) -> tuple[list[dict], list[dict]]:
    """Training records and evaluation records of a run's log."""
    train, evals = [], []
    for rec in RunFolder(run_dir).log_records():
        if POINTS_RECORD not in rec:
            (evals if "eval" in rec else train).append(rec)
    return train, evals


def read_points_record(run_dir: Path) -> dict | None:
    """The log's record of the sparse points the field started from (None: not logged)."""
    found = [rec[POINTS_RECORD] for rec in RunFolder(run_dir).log_records()
             if isinstance(rec.get(POINTS_RECORD), dict)]
    return found[-1] if found else None


def points_line(record: dict) -> str:
    """The points record in words: count, source, and the triangulation's figures."""
    text = f"{record.get('points', 0)}, {record.get('source', 'unknown source')}"
    tri = record.get("triangulation")
    if tri:
        text += f"; {tri.get('views')} training views"
        if tri.get("points"):
            text += (f", mean track {tri['mean_track_length']:.1f} views, mean reprojection error "
                     f"{tri['mean_reprojection_error']:.2f} px")
        text += ", from the cache" if tri.get("cached") else f", {tri.get('seconds', 0):.1f} s"
    return text + f" (field.init={record.get('field_init')})"


# ------------------------------------------------------------------------------- plots


def _figure(width: float = 6.4, height: float = 3.4):
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width, height), dpi=100, layout="constrained")
    return fig, fig.add_subplot(1, 1, 1)


def _png_data_uri(png: bytes) -> str:
    return "data:image/png;base64," + base64.b64encode(png).decode("ascii")


def _fig_uri(fig) -> str:
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    return _png_data_uri(buf.getvalue())


def loss_plot(train: list[dict]) -> str | None:
    """Total loss and each loss term over steps (log scale when all are positive)."""
    if not train:
        return None
    fig, ax = _figure()
    steps = [r["step"] for r in train]
    ax.plot(steps, [r["loss"] for r in train], label="total", color="black", lw=1.5)
    for key in sorted({k for r in train for k in r.get("terms", {})}):
        pts = [(r["step"], r["terms"][key]) for r in train if key in r.get("terms", {})]
        ax.plot(*zip(*pts), label=key, lw=1)
    values = [r["loss"] for r in train] + [v for r in train for v in r.get("terms", {}).values()]
    if values and min(values) > 0:
        ax.set_yscale("log")
    _mark_phases(ax, train)
    ax.set_xlabel("step"), ax.set_ylabel("loss"), ax.legend(fontsize=8), ax.grid(alpha=0.3)
    return _fig_uri(fig)


def psnr_plot(train: list[dict], evals: list[dict]) -> str | None:
    """PSNR over steps: renders vs clean and vs rainy images (Fig. 2 / 6 of the paper)."""
    series: dict[str, list[tuple[int, float]]] = {}
    for rec in evals:
        for key, value in rec["eval"].items():
            series.setdefault(key, []).append((rec["step"], value))
    if not series and not train:
        return None
    fig, ax = _figure()
    views = {"train": "training views", "heldout": "held-out views"}
    names = {quick_key(split, against): (f"{views[split]} vs {against}", "-" if against == "clean" else "--")
             for split in SPLITS for against in ("clean", "rainy")}
    for key, pts in sorted(series.items()):
        label, style = names.get(key, (key, "-"))
        ax.plot(*zip(*pts), style, marker="o", ms=3, label=label)
    batch = [(r["step"], r["psnr_input"]) for r in train if "psnr_input" in r]
    if batch:
        ax.plot(*zip(*batch), color="grey", alpha=0.5, lw=0.8, label="batch: B (+R) vs rainy")
    _mark_phases(ax, train)
    ax.set_xlabel("step"), ax.set_ylabel("PSNR (dB)"), ax.legend(fontsize=8), ax.grid(alpha=0.3)
    return _fig_uri(fig)


def term_metrics_plot(train: list[dict]) -> str | None:
    """What loss terms report about themselves (e.g. AGR's estimated angle, robust inliers).

    Per-view keys (``name/view3``) share one panel per name, drawn as points."""
    groups: dict[str, list[tuple[int, float]]] = {}
    per_view: set[str] = set()
    for r in train:
        for key, value in r.get("metrics", {}).items():
            if isinstance(value, (int, float)):
                name = key.split("/", 1)[0]
                per_view.update([name] if "/" in key else [])
                groups.setdefault(name, []).append((r["step"], float(value)))
    if not groups:
        return None
    from matplotlib.figure import Figure

    fig = Figure(figsize=(6.4, 1.9 * len(groups)), dpi=100, layout="constrained")
    axes = fig.subplots(len(groups), 1, sharex=True, squeeze=False)[:, 0]
    for ax, (name, pts) in zip(axes, sorted(groups.items())):
        if name in per_view:
            ax.plot(*zip(*pts), ".", ms=2)
        else:
            ax.plot(*zip(*pts), lw=1)
        ax.set_ylabel(name, fontsize=8), ax.grid(alpha=0.3)
    axes[-1].set_xlabel("step")
    return _fig_uri(fig)


def _mark_phases(ax, train: list[dict]) -> None:
    joint = [r["step"] for r in train if r.get("phase") == "joint"]
    if joint and any(r.get("phase") == "warmup" for r in train):
        ax.axvline(min(joint), color="grey", ls=":", lw=1)
        ax.text(min(joint), ax.get_ylim()[1], " joint phase", fontsize=7, va="top", color="grey")


# ------------------------------------------------------------------------------ tables


def _fmt(value, digits: int = 3) -> str:
    if value is None:
        return "–"
    if isinstance(value, float):
        return f"{value:.{digits}f}"
    return html.escape(str(value))


def metric_rows(summary: dict, postprocess: list[str]) -> list[tuple[str, list[Metric]]]:
    """(label, its image metrics) rows of the evaluation protocol, in reading order; rows
    without a value left out."""
    rows = [("rainy input (floor)", [rainy_input(m) for m in IMAGE_MEASURES]),
            ("render, training views", [render(m, "train") for m in IMAGE_MEASURES])]
    rows += [(f"render + {p}, training views", [post(m, p) for m in IMAGE_MEASURES]) for p in postprocess]
    rows.append(("render, held-out views", [render(m, "heldout") for m in IMAGE_MEASURES]))
    return [(label, metrics) for label, metrics in rows if any(m.of(summary) is not None for m in metrics)]


def metric_table(metrics: dict) -> str:
    summary = metrics.get("summary", {})
    rows = metric_rows(summary, metrics.get("postprocess", []))
    if not rows:
        return "<p>No metrics against clean images (the scene has none).</p>" + evaluated_note(metrics)
    head = "<tr><th></th>" + "".join(f"<th>{m.title} {m.arrow}</th>" for m in IMAGE_MEASURES) + "</tr>"
    def cell(m: Metric) -> str:  # LPIPS may be unavailable here (the note says why)
        return m.measure.format(m.of(summary), missing="n/a" if m.measure is LPIPS else "–")

    body = "".join(f"<tr><td>{html.escape(label)}</td>" + "".join(f"<td>{cell(m)}</td>" for m in ms) + "</tr>"
                   for label, ms in rows)
    note = ""
    lp = metrics.get("lpips", {})
    if lp and not lp.get("available", False):
        note = f"<p class='note'>LPIPS unavailable: {html.escape(lp.get('reason', ''))}.</p>"
    note += evaluated_note(metrics)
    return f"<table>{head}{body}</table>{note}"


def evaluated_note(metrics: dict) -> str:
    """How many views the metrics were measured on, and which."""
    done = metrics.get("evaluated", {})
    if not done:
        return ""
    views = metrics.get("views", {})
    total = views.get("train", 0) + views.get("heldout", 0)
    names = ", ".join(html.escape(str(v)) for v in done.get("views", []))
    if done.get("all", True):
        return f"<p class='note'>Measured on every view ({total}).</p>"
    return (f"<p class='note'>Measured on {len(done.get('views', []))} of {total} views: {names} "
            f"({done.get('train', 0)} training, {done.get('heldout', 0)} held-out; the fixed subset "
            "of the evaluation at the end of rs-train, trainer.final_eval_views). rs-eval RUN_DIR "
            "measures every view.</p>")


RAIN_ROWS = (rain_stat(RAIN_ANGLE), rain_stat(RESIDUAL_ANGLE), rain_stat(TRUE_ANGLE), rain_stat(ANGLE_ERROR),
             rain_stat(CORRELATION), render(RAIN_RECOVERED, "train"), render(RAIN_KEPT, "train"))


def rain_table(summary: dict) -> str:
    rows = [(m.measure.title, m.of(summary)) for m in RAIN_ROWS if m.key in summary]
    if not rows:
        return ""
    body = "".join(f"<tr><td>{html.escape(l)}</td><td>{_fmt(v)}</td></tr>" for l, v in rows)
    note = ("<p class='note'>–: the predicted rain has no streaks to measure.</p>"
            if any(v is None for _, v in rows) else "")
    return f"<h2>Rain</h2><table>{body}</table>{note}"


def per_view_table(rows: list[dict]) -> str:
    """The per-view values, one table per split (their keys differ: each names its split)."""
    if not rows:
        return ""
    tables = []
    for split in SPLITS:
        mine = [r for r in rows if r.get("split") == split]
        if not mine:
            continue
        keys = [k for k in dict.fromkeys(k for r in mine for k in r) if k not in ("view", "split")]
        head = "<tr><th>view</th>" + "".join(f"<th>{html.escape(k)}</th>" for k in keys) + "</tr>"
        body = "".join(f"<tr><td>{html.escape(r['view'])}</td>"
                       + "".join(f"<td>{_fmt(r.get(k))}</td>" for k in keys) + "</tr>" for r in mine)
        tables.append(f"<p class='note'>{split} views</p><table>{head}{body}</table>")
    return (f"<details><summary>Per-view values ({len(rows)} views)</summary>"
            f"{''.join(tables)}</details>")


# ------------------------------------------------------------------------------ images


def _image_uri(path: Path) -> str:
    return _png_data_uri(path.read_bytes())


def image_section(title: str, paths: list[Path], caption: str = "") -> str:
    if not paths:
        return ""
    imgs = "".join(f"<p class='note'>{html.escape(p.stem)}</p><img alt='{html.escape(p.stem)}' "
                   f"src='{_image_uri(p)}'>" for p in paths)
    cap = f"<p class='note'>{html.escape(caption)}</p>" if caption else ""
    return f"<h2>{html.escape(title)}</h2>{cap}{imgs}"


# ------------------------------------------------------------------------------- page


def _max_iters(folder: RunFolder) -> str:
    try:
        return str(folder.config().trainer.max_iters)
    except RainyScapeError:  # a config that no longer loads (a plugin gone): the page still shows
        return "?"


def build_report(run_dir: Path) -> str:
    folder = RunFolder.check(run_dir)
    run_dir = folder.path
    metrics = folder.metrics()
    status = folder.status()  # a dead owner's "running" reads as interrupted
    train, evals = read_log(run_dir)
    title = f"{metrics.get('method', run_dir.parent.name)} on {metrics.get('scene', run_dir.parent.parent.name)}"
    step = train[-1]["step"] if train else status.get("step", 0)
    state = status.get("state", "")
    # While the run itself writes this page its status still says "running": show only states
    # that tell the reader something (failed, interrupted, stopped early).
    note = f" · {state}" if state in ("failed", "interrupted", "stopped") else ""
    parts = [f"<h1>RainyScape run: {html.escape(title)}</h1>",
             f"<p class='note'>{html.escape(str(run_dir.resolve()))} · step {step} of "
             f"{_max_iters(folder)}{html.escape(note)} · {html.escape(str(status.get('time', '')))}</p>"]
    points = read_points_record(run_dir)
    if points is not None:
        parts.append(f"<p class='note'>Initial sparse points: {html.escape(points_line(points))}</p>")
    parts.append("<h2>Metrics</h2>" + (metric_table(metrics) if metrics else
                                       f"<p>No {RunFolder.METRICS} yet (run rs-eval RUN_DIR).</p>"))
    parts.append(rain_table(metrics.get("summary", {})))
    plots = [("Loss terms", loss_plot(train)),
             ("PSNR during training (paper Fig. 2 and 6)", psnr_plot(train, evals)),
             ("Loss-term diagnostics", term_metrics_plot(train))]
    for name, uri in plots:
        if uri:
            parts.append(f"<h2>{name}</h2><img alt='{html.escape(name)}' src='{uri}'>")
    strips = sorted(folder.strips.glob("*.png"))[:MAX_STRIPS]
    parts.append(image_section("Comparison strips", strips,
                               "rainy input | render | (post-processed) | ground truth | predicted rain | true rain"))
    parts.append(image_section("Embedding study (paper Fig. 8)",
                               sorted(folder.renders.glob("embedding_study*.png")),
                               "predicted rain with N(0, 0.5) noise added to the scene state s, "
                               "the view vector v and the camera vector p"))
    parts.append(per_view_table(metrics.get("per_view", [])))
    config_text = folder.config_text()
    parts.append(f"<h2>Configuration</h2><pre>{html.escape(config_text)}</pre>")
    body = "\n".join(p for p in parts if p)
    return (f"<!DOCTYPE html>\n<html lang='en'><head><meta charset='utf-8'>"
            f"<title>{html.escape(title)}</title><style>{CSS}</style></head>\n<body>\n{body}\n</body></html>\n")


def write_report(run_dir: Path) -> Path:
    return write_text_atomic(RunFolder(run_dir).report_file, build_report(run_dir))
