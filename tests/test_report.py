"""report.html: self-contained, shows curves / strips / metrics / config, opens in Chromium."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
from html.parser import HTMLParser
from pathlib import Path

import pytest

from rainyscape.eval.protocol import evaluate_pipeline, write_metrics
from rainyscape.eval.report import build_report, read_log
from _eval_fixtures import make_pipeline


class _Refs(HTMLParser):
    def __init__(self):
        super().__init__()
        self.refs: list[str] = []
        self.tags: list[str] = []

    def handle_starttag(self, tag, attrs):
        self.tags.append(tag)
        self.refs += [v for k, v in attrs if k in ("src", "href") and v is not None]


def html_references(text: str) -> tuple[list[str], list[str]]:
    parser = _Refs()
    parser.feed(text)
    return parser.refs, parser.tags


def make_run(folder: Path) -> Path:
    """A run folder as rs-train leaves it: config, a log with warm-up and joint records, metrics."""
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "config.yml").write_text("method: fake\ntrainer:\n  max_iters: 60\n")
    (folder / "status.json").write_text(json.dumps({"state": "finished", "step": 60}))
    lines = []
    for step in range(1, 61):
        phase = "warmup" if step <= 30 else "joint"
        terms = {"photometric": 1.0 / step} if phase == "warmup" else {"likelihood": 0.5 / step, "agr": 0.1}
        lines.append({"step": step, "phase": phase, "loss": sum(terms.values()), "terms": terms,
                      "psnr_input": 15 + step / 10, "metrics": {"agr.angle_deg": 80.0} if phase == "joint" else {}})
        if step % 20 == 0:
            lines.append({"step": step, "phase": phase, "eval": {"train_psnr_clean": 18 + step / 20,
                                                                 "train_psnr_rainy": 19 + step / 10}})
    text = "\n".join(json.dumps(r) for r in lines) + '\n{"step": 61, "pha'  # a truncated last line
    (folder / "log.jsonl").write_text(text)
    write_metrics(folder, evaluate_pipeline(make_pipeline(), folder))
    return folder


@pytest.fixture(scope="module")
def fake_run(tmp_path_factory) -> Path:
    return make_run(tmp_path_factory.mktemp("report") / "run")


def test_log_reader_skips_a_truncated_line(fake_run):
    train, evals = read_log(fake_run)
    assert len(train) == 60 and len(evals) == 3


def test_report_is_self_contained_and_complete(fake_run):
    run = fake_run
    text = (run / "report.html").read_text()
    refs, tags = html_references(text)
    assert "script" not in tags and "link" not in tags
    for ref in refs:  # every reference is inlined data or an existing file
        assert ref.startswith("data:image/png;base64,") or (run / ref).exists(), ref
    assert sum(r.startswith("data:image/png") for r in refs) == 3 + 3  # 3 plots + 3 strips
    for needle in ("Loss terms", "PSNR during training", "Comparison strips", "rainy input (floor)",
                   "render + keep, training views", "render, held-out views", "predicted rain streak angle",
                   "Configuration", "max_iters: 60", "LPIPS"):
        assert needle in text, needle
    assert build_report(run) == text  # deterministic: rebuilding gives the same page


def test_report_of_a_run_without_metrics(tmp_path):
    run = tmp_path / "bare"
    run.mkdir()
    (run / "config.yml").write_text("method: fake\n")
    text = build_report(run)
    assert "No metrics.json yet" in text


def chromium_probe(report: Path) -> tuple[int, int]:
    """Open ``report`` in headless Chromium; (images on the page, images that failed to decode).

    Fails the test on a non-zero exit or any console message besides the probe's own; skips
    it where Debian's chromium is not installed."""
    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    if chromium is None:
        pytest.skip("Debian's chromium is not installed here (apt-get install -y chromium)")
    # A probe appended to a copy counts images that failed to decode once the page has loaded.
    probe = report.with_name("probe.html")
    probe.write_text(report.read_text() + (
        "<script>window.addEventListener('load', () => console.log('probe images=' + document.images.length"
        " + ' broken=' + [...document.images].filter(i => !i.complete || i.naturalWidth === 0).length))"
        "</script>"))
    done = subprocess.run([chromium, "--headless", "--no-sandbox", "--disable-gpu", "--enable-logging=stderr",
                           "--v=0", "--virtual-time-budget=5000", "--dump-dom", probe.as_uri()],
                          capture_output=True, text=True, timeout=120)
    probe.unlink()
    assert done.returncode == 0, done.stderr[-2000:]
    assert "RainyScape run" in done.stdout
    console = [line for line in done.stderr.splitlines() if ":CONSOLE" in line]
    assert len(console) == 1, console
    found = re.search(r'"probe images=(\d+) broken=(\d+)"', console[0])
    assert found, console
    return int(found.group(1)), int(found.group(2))


def test_report_opens_in_headless_chromium(fake_run):
    assert chromium_probe(fake_run / "report.html") == (6, 0)


def test_rain_table_says_where_the_true_rain_went():
    from rainyscape.eval.report import rain_table

    html_ = rain_table({"rain_correlation": 0.5, "train_rain_recovered": 0.49, "train_rain_kept": 0.15})
    assert "share of the true rain the predicted rain holds</td><td>0.49" in html_
    assert "share of the true rain the render still shows</td><td>0.15" in html_
