"""rs-bench: the matrix, its resumable results file and the Table-I-style tables."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import pytest

from rainyscape.comparison.matrix import ABLATIONS, Cell, build_cells
from rainyscape.comparison.tables import markdown_report, markdown_table


def _result(psnr: float, post: bool = False, train_s: float = 10.0, mem: float = 500.0, scene: str = "") -> dict:
    summary = {"rainy_input_psnr": 20.0, "rainy_input_ssim": 0.7, "train_psnr": psnr, "train_ssim": 0.8,
               "heldout_psnr": psnr - 2, "heldout_ssim": 0.75}
    if post:
        summary.update({"train_fusion_psnr": psnr + 1, "train_fusion_ssim": 0.85, "train_fusion_coverage": 0.12,
                        "train_fusion_random_psnr": 20.5, "train_fusion_random_ssim": 0.71})
    return {"status": "finished", "summary": summary, "postprocess": ["fusion"] if post else [], "scene": scene,
            "train_s": train_s, "peak_rss_mib": mem, "lpips": {"available": False, "reason": "no weights"}}


ORACLE = {"yard": {"available": True, "train": {"psnr": 41.0, "ssim": 0.99}, "heldout": {"psnr": 40.0, "ssim": 0.98}},
          "street": {"available": True, "train": {"psnr": 43.0, "ssim": 0.97}, "heldout": {"psnr": 42.0, "ssim": 0.96}}}


def _rows(table: str) -> dict[str, str]:
    return {line.split(" | ")[0].strip("| "): line for line in table.splitlines()[2:]}


def test_table_one_layout():
    cells = build_cells(["nerf", "ours"], [("yard", "/y"), ("street", "/s")], [])
    results = {"cells": {"yard/nerf": _result(25.0), "street/nerf": _result(27.0, train_s=30),
                         "yard/ours": _result(28.0, post=True, mem=900, scene="yard"),
                         "street/ours": _result(30.0, post=True, scene="street")}, "oracle": ORACLE}
    table = markdown_table(cells, results, "train").splitlines()
    assert table[0].startswith("| Method | yard PSNR ↑ | yard SSIM ↑ | yard LPIPS ↓ | street PSNR ↑")
    assert "Average PSNR ↑" in table[0]
    assert table[0].endswith("Budget (steps × px/step) | Train time (s) | Peak memory (MiB) |")
    rows = _rows("\n".join(table))
    assert list(rows) == ["oracle 3D", "rainy input", "nerf", "ours", "ours + fusion", "↳ fused − input",
                          "↳ control: random mask, same coverage (12.0 %)"]
    assert rows["oracle 3D"].startswith("| oracle 3D | 41.00 | 0.990 | n/a | 43.00 | 0.970 | n/a | 42.00 | 0.980 |")
    assert rows["nerf"].startswith("| nerf | 25.00 | 0.800 | n/a | 27.00 | 0.800 | n/a | 26.00 | 0.800 | n/a | – | 20 | 500 |")
    assert "| 29.00 |" in rows["ours"] and "| 900 |" in rows["ours"]  # average, largest peak
    assert "| 30.00 |" in rows["ours + fusion"]  # (29 + 31) / 2
    # fused minus input: (29 - 20) and (31 - 20), average +10; SSIM 0.85 - 0.7
    assert rows["↳ fused − input"].startswith("| ↳ fused − input | +9.00 | +0.150 | n/a | +11.00 | +0.150 | n/a | +10.00 |")
    assert rows["↳ control: random mask, same coverage (12.0 %)"].split(" | ")[1:3] == ["20.50", "0.710"]
    held = markdown_table(cells, results, "heldout")
    assert "rainy input" not in held and "fused" not in held and "control" not in held
    assert _rows(held)["nerf"].startswith("| nerf | 23.00 |") and "| 24.00 |" in _rows(held)["nerf"]
    assert _rows(held)["oracle 3D"].startswith("| oracle 3D | 40.00 | 0.980 | n/a | 42.00 |")


def test_oracle_row_is_na_with_its_reason_on_scene_folders():
    cells = build_cells(["nerf"], [("mine", "/m"), ("yard", "/y")], [])
    results = {"cells": {"mine/nerf": _result(25.0), "yard/nerf": _result(26.0)},
               "oracle": {"mine": {"available": False, "reason": "not a simulated scene folder (no scene.json)"},
                          "yard": ORACLE["yard"]}}
    row = _rows(markdown_table(cells, results, "train"))["oracle 3D"]
    assert row.startswith("| oracle 3D | n/a | n/a | n/a | 41.00 | 0.990 | n/a | n/a |")  # no average
    report = markdown_report(cells, results)
    assert "n/a on mine (not a simulated scene folder (no scene.json))" in report


def test_unfinished_cells_leave_gaps_not_wrong_averages():
    cells = build_cells(["nerf"], [("yard", "/y"), ("street", "/s")], [])
    results = {"cells": {"yard/nerf": _result(25.0), "street/nerf": {"status": "failed", "error": "x"}}}
    (row,) = [l for l in markdown_table(cells, results, "train").splitlines() if l.startswith("| nerf")]
    assert "| 25.00 |" in row and row.count("n/a") >= 3 + 3  # street and the average are missing
    report = markdown_report(cells, results)
    assert "Failed cells: street/nerf" in report and "LPIPS: n/a (no weights)" in report
    assert "| oracle 3D | n/a |" in report and "n/a on yard, street (not computed)" in report


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


def test_fingerprint_is_the_config_the_cell_trains(monkeypatch):
    a = Cell("s/3dgs", "s", "/d", "3dgs", ["trainer.max_iters=10"])
    b = Cell("s/3dgs", "s", "/d", "3dgs", ["trainer.max_iters=20"])
    assert a.fingerprint() != b.fingerprint()  # another budget
    same = Cell("s/3dgs", "s", "/d", "3dgs", ["trainer.max_iters=10", "field.sh_degree=3"])  # the default
    assert same.fingerprint() == a.fingerprint()
    # a method whose default changed is another experiment: its earlier result is not reused
    from rainyscape.methods.gaussians import gaussians_3dgs

    before = a.fingerprint()
    monkeypatch.setattr(gaussians_3dgs.config.trainer, "seed", gaussians_3dgs.config.trainer.seed + 1)
    assert a.fingerprint() != before


@pytest.mark.slow
def test_cells_run_in_parallel_then_resume_as_done(tmp_path, tiny_scene_dir):
    """Two cells at once; unequal budgets run only with allow_unequal=true, and the tables then
    hold every row: oracle, the plain field on the clean views, input, methods, fused,
    fused − input and the control."""
    out = tmp_path / "results"
    args = ["rs-bench", "methods=nerf,rainyscape-nerf", f"scenes={tiny_scene_dir}", "iters=4", f"out={out}",
            "name=tiny", "device=cpu", "jobs=2", "threads=1", "trainer.eval_every=0",
            "rainyscape-nerf:phases.joint.patches=1", "rainyscape-nerf:phases.joint.patch_size=16",
            "rainyscape-nerf:phases.joint.rays=0"]  # 256 rays a joint step against nerf's 1024
    refused = subprocess.run(args, capture_output=True, text=True)
    assert refused.returncode == 2 and "allow_unequal=true" in refused.stderr and not out.exists()
    args.append("allow_unequal=true")
    first = subprocess.run(args, capture_output=True, text=True)
    assert first.returncode == 0, first.stdout + first.stderr
    assert "warning: unequal budgets (allow_unequal=true): field 'grid'" in first.stdout
    results = json.loads((out / "tiny.json").read_text())
    assert sorted(c["label"] for c in results["cells"].values()) == ["nerf", "nerf on clean views", "rainyscape-nerf"]
    cell = next(c for c in results["cells"].values() if c["label"] == "nerf")
    ceiling = next(c for c in results["cells"].values() if c["label"] == "nerf on clean views")
    assert "dataparser.images=images_wo_rain" in ceiling["overrides"] and ceiling["budget"] == cell["budget"]
    assert ceiling["summary"]["rainy_input_psnr"] > 60  # its "input" is the clean views themselves
    assert cell["status"] == "finished" and cell["iters"] == 4 and cell["how"] == "trained"
    assert cell["summary"]["train_psnr"] > 5 and cell["peak_rss_mib"] > 50 and cell["train_s"] > 0
    assert cell["cpu_s"] > 0 and cell["budget"]["steps"] == 4 and cell["budget"]["pixels_per_step"] == 1024
    assert cell["views"]["width"] == 48  # it trained on the scene it was given
    assert results["machine"]["cores"] >= 1 and results["command"].startswith("rs-bench methods=nerf")
    assert results["oracle"][tiny_scene_dir.name]["folder"] == str(tiny_scene_dir.resolve())
    ours = next(c for c in results["cells"].values() if c["method"] == "rainyscape-nerf")
    assert "train_rain-mask-fusion_coverage" in ours["summary"]
    table = (out / "tiny.md").read_text()
    train = table.split("## De-raining at the training views")[1].split("## Novel views")[0]
    labels = [line.split(" | ")[0].strip("| ") for line in train.splitlines() if line.startswith("| ")][1:]
    assert labels[:7] == ["oracle 3D", "nerf on clean views", "rainy input", "nerf", "rainyscape-nerf",
                          "rainyscape-nerf + rain-mask-fusion", "↳ fused − input"]
    assert labels[7].startswith("↳ control: random mask, same coverage")
    floor = next(line for line in train.splitlines() if line.startswith("| rainy input |"))
    assert f"| {cell['summary']['rainy_input_psnr']:.2f} |" in floor  # the rainy input, not the ceiling's
    assert "(≠ nerf: 4 × 1024)" in train and "**Unequal budgets within a field**" in train
    second = subprocess.run(args, capture_output=True, text=True)
    assert second.returncode == 0 and second.stdout.count("done earlier, skipped") == 3
    assert json.loads((out / "tiny.json").read_text())["cells"] == results["cells"]


def test_bad_arguments_fail_before_any_training(tmp_path, tiny_scene_dir):
    bad = subprocess.run(["rs-bench", "methods=nerf", f"scenes={tiny_scene_dir}", f"out={tmp_path}",
                          "field.no_such_option=1"], capture_output=True, text=True)
    assert bad.returncode == 2 and "no_such_option" in bad.stderr and "Traceback" not in bad.stderr
    assert not list(tmp_path.rglob("*.json"))
    typo = subprocess.run(["rs-bench", "method=nerf"], capture_output=True, text=True)
    assert typo.returncode == 2 and "Did you mean 'methods'" in typo.stderr


def test_the_ceiling_of_rain_variants_trains_once(tmp_path, tiny_scene_dir):
    """Two scenes with the same clean views and other rain (a capture's rain variants): the
    plain field's ceiling trains on the first and the second evaluates a copy of that run on
    its own scene, so its in-rain and dry columns split by its own rain."""
    import shutil

    from rainyscape.synth import generate

    other_rain = generate(tmp_path / "seed1", "demo", rows=3, cols=4, width=48, height=48, mode="static",
                          seed=1, size_scale=6.0, density=0.5)
    variant = tmp_path / "variant"
    shutil.copytree(tiny_scene_dir, variant)
    for folder in ("rain", "images_rain"):
        shutil.rmtree(variant / folder)
        shutil.copytree(other_rain / folder, variant / folder)
    out = tmp_path / "results"
    args = ["rs-bench", "methods=nerf", f"scenes={tiny_scene_dir},{variant}", "iters=4", f"out={out}",
            "name=v", "device=cpu", "jobs=2", "threads=1", "trainer.eval_every=0"]
    done = subprocess.run(args, capture_output=True, text=True)
    assert done.returncode == 0, done.stdout + done.stderr
    cells = json.loads((out / "v.json").read_text())["cells"]
    first, second = cells[f"{tiny_scene_dir.name}/nerf on clean views"], cells["variant/nerf on clean views"]
    assert first["how"] == "trained" and second["how"] == f"shared: {first['run_dir']}"
    assert "evaluating the run of" in done.stdout
    a, b = first["summary"], second["summary"]
    assert abs(a["train_psnr"] - b["train_psnr"]) < 1e-6 and abs(a["heldout_psnr"] - b["heldout_psnr"]) < 1e-6
    assert a["train_psnr_in_rain"] != b["train_psnr_in_rain"]  # scored against its own rain
    run = Path(second["run_dir"])
    assert run.is_relative_to(out / "runs" / "v") and f"data: {variant}" in (run / "config.yml").read_text()
    assert cells["variant/nerf"]["how"] == "trained"  # the rainy cells train on their own rain
