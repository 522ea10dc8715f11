"""rs-bench: the matrix, its resumable results file and the Table-I-style tables."""

from __future__ import annotations

import json
import subprocess

import pytest

from rainyscape.bench.matrix import ABLATIONS, Cell, build_cells
from rainyscape.bench.tables import markdown_report, markdown_table


def _result(psnr: float, post: bool = False, train_s: float = 10.0, mem: float = 500.0) -> dict:
    summary = {"rainy_input_psnr": 20.0, "rainy_input_ssim": 0.7, "train_psnr": psnr, "train_ssim": 0.8,
               "heldout_psnr": psnr - 2, "heldout_ssim": 0.75}
    if post:
        summary.update({"train_fusion_psnr": psnr + 1, "train_fusion_ssim": 0.85})
    return {"status": "finished", "summary": summary, "postprocess": ["fusion"] if post else [],
            "train_s": train_s, "peak_rss_mib": mem, "lpips": {"available": False, "reason": "no weights"}}


def test_table_one_layout():
    cells = build_cells(["nerf", "ours"], [("yard", "/y"), ("street", "/s")], [])
    results = {"cells": {"yard/nerf": _result(25.0), "street/nerf": _result(27.0, train_s=30),
                         "yard/ours": _result(28.0, post=True, mem=900), "street/ours": _result(30.0, post=True)}}
    table = markdown_table(cells, results, "train").splitlines()
    assert table[0].startswith("| Method | yard PSNR ↑ | yard SSIM ↑ | yard LPIPS ↓ | street PSNR ↑")
    assert "Average PSNR ↑" in table[0] and table[0].endswith("Train time (s) | Peak memory (MiB) |")
    rows = {line.split(" | ")[0].strip("| "): line for line in table[2:]}
    assert list(rows) == ["rainy input", "nerf", "ours", "ours + fusion"]
    assert rows["nerf"].startswith("| nerf | 25.00 | 0.800 | n/a | 27.00 | 0.800 | n/a | 26.00 | 0.800 | n/a | 20 | 500 |")
    assert "| 29.00 |" in rows["ours"] and "| 900 |" in rows["ours"]  # average, largest peak
    assert "| 30.00 |" in rows["ours + fusion"]  # (29 + 31) / 2
    held = markdown_table(cells, results, "heldout")
    assert "rainy input" not in held and "| 23.00 |" in held.splitlines()[2]  # nerf: (23 + 25) / 2


def test_unfinished_cells_leave_gaps_not_wrong_averages():
    cells = build_cells(["nerf"], [("yard", "/y"), ("street", "/s")], [])
    results = {"cells": {"yard/nerf": _result(25.0), "street/nerf": {"status": "failed", "error": "x"}}}
    (row,) = [l for l in markdown_table(cells, results, "train").splitlines() if l.startswith("| nerf")]
    assert "| 25.00 |" in row and row.count("n/a") >= 3 + 3  # street and the average are missing
    report = markdown_report(cells, results)
    assert "Failed cells: street/nerf" in report and "LPIPS: n/a (no weights)" in report


def test_ablation_cells_and_table():
    cells = build_cells(["nerf"], [("yard", "/y")], ["trainer.max_iters=10"], ("yard", "/y"), "rainyscape-nerf")
    ablation = [c for c in cells if c.key.startswith("ablation/")]
    assert [c.label for c in ablation] == list(ABLATIONS)
    assert ablation[0].overrides == ["trainer.max_iters=10", "losses.reconstruction=none"]
    assert len({c.fingerprint() for c in cells}) == len(cells)
    results = {"cells": {c.key: _result(20.0 + i) for i, c in enumerate(cells)}}
    report = markdown_report(cells, results)
    assert "## Loss ablation (rainyscape-nerf on yard; the paper's Table II)" in report
    assert "| w/o L_agr |" in report and "| full |" in report


def test_fingerprint_changes_with_the_budget():
    a = Cell("s/m", "s", "/d", "m", ["trainer.max_iters=10"])
    b = Cell("s/m", "s", "/d", "m", ["trainer.max_iters=20"])
    assert a.fingerprint() != b.fingerprint()


@pytest.mark.slow
def test_cells_run_in_parallel_then_resume_as_done(tmp_path, tiny_scene_dir):
    out = tmp_path / "results"
    args = ["rs-bench", "methods=nerf,robust-nerf", f"scenes={tiny_scene_dir}", "iters=4", f"out={out}",
            "name=tiny", "device=cpu", "jobs=2", "threads=1", "trainer.eval_every=0"]
    first = subprocess.run(args, capture_output=True, text=True)
    assert first.returncode == 0, first.stdout + first.stderr
    results = json.loads((out / "tiny.json").read_text())
    assert sorted(c["method"] for c in results["cells"].values()) == ["nerf", "robust-nerf"]
    cell = next(c for c in results["cells"].values() if c["method"] == "nerf")
    assert cell["status"] == "finished" and cell["iters"] == 4 and cell["how"] == "trained"
    assert cell["summary"]["train_psnr"] > 5 and cell["peak_rss_mib"] > 50 and cell["train_s"] > 0
    assert cell["views"]["width"] == 48  # it trained on the scene it was given
    assert results["machine"]["cores"] >= 1 and results["command"].startswith("rs-bench methods=nerf")
    table = (out / "tiny.md").read_text()
    assert "| rainy input |" in table and "| nerf |" in table and "| robust-nerf |" in table
    second = subprocess.run(args, capture_output=True, text=True)
    assert second.returncode == 0 and second.stdout.count("done earlier, skipped") == 2
    assert json.loads((out / "tiny.json").read_text())["cells"] == results["cells"]


def test_bad_arguments_fail_before_any_training(tmp_path, tiny_scene_dir):
    bad = subprocess.run(["rs-bench", "methods=nerf", f"scenes={tiny_scene_dir}", f"out={tmp_path}",
                          "field.no_such_option=1"], capture_output=True, text=True)
    assert bad.returncode == 2 and "no_such_option" in bad.stderr and "Traceback" not in bad.stderr
    assert not list(tmp_path.rglob("*.json"))
    typo = subprocess.run(["rs-bench", "method=nerf"], capture_output=True, text=True)
    assert typo.returncode == 2 and "Did you mean 'methods'" in typo.stderr
