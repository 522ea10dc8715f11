"""Equal budgets: every cell's steps and pixels per step from its real typed config, and the
refusal of a table whose methods of one field differ."""

from __future__ import annotations

import subprocess

import pytest

from rainyscape.comparison.budget import Budget, budget_mismatches, cell_budget, check_budgets
from rainyscape.comparison.matrix import build_cells
from rainyscape.comparison.sets import SCENE_SETS
from rainyscape.comparison.tables import budget_column, markdown_report
from rainyscape.config import method_config
from rainyscape.errors import ConfigError


PAPER_PATCH = ("phases.warmup.end=0.5", "phases.joint.patches=1", "phases.joint.patch_size=64",
               "phases.joint.rays=0")  # the paper: half the run warm-up, then one 64 x 64 patch


def _budget(method: str, *overrides: str, size: int = 128) -> Budget:
    return cell_budget(method_config(method, ["trainer.max_iters=100", *overrides]), size, size, 16)


def test_budgets_of_the_real_methods():
    nerf = _budget("nerf")
    assert (nerf.family, nerf.steps, nerf.pixels_per_step) == ("grid", 100, 1024)
    robust = _budget("robust-nerf")  # nerf's single rays
    assert robust.family == "grid" and robust.same_as(nerf)
    ours = _budget("rainyscape-nerf")  # warm-up: nerf's rays; joint: 16 patches of 4 x 4 and 768 rays, as many
    assert [(p.name, p.steps, p.pixels) for p in ours.phases] == [("warmup", 35, 1024), ("joint", 65, 1024)]
    assert ours.same_as(nerf)
    paper = _budget("rainyscape-nerf", *PAPER_PATCH)  # the paper's 64 x 64 joint patch on nerf's warm-up
    assert paper.pixels_per_step == 2560 and not paper.same_as(nerf)
    assert paper.describe() == "100 steps × 2560 px/step (warmup 50 × 1024, joint 50 × 4096)"
    gs = _budget("3dgs")  # whole views: width x height
    assert (gs.family, gs.pixels_per_step) == ("gaussians", 128 * 128)
    assert _budget("rainyscape-3dgs").same_as(gs) and _budget("robust-3dgs").same_as(gs)
    assert _budget("rainyscape-plus").same_as(gs)
    assert _budget("3dgs", size=64).pixels_per_step == 64 * 64
    # a run stopped early counts the steps it runs, in the phases it runs them
    stopped = _budget("rainyscape-nerf", "trainer.stop_at=40")
    assert stopped.steps == 40 and stopped.pixels_per_step == 1024
    assert Budget.from_dict(ours.to_dict()) == ours


def _table(*methods: str) -> list[tuple[str, str, Budget]]:
    """Cells on yard; rainyscape-nerf with the paper's joint patch (more rays than nerf's)."""
    return [(f"yard/{m}", "yard", _budget(m, *(PAPER_PATCH if m == "rainyscape-nerf" else ()))) for m in methods]


def test_unequal_budgets_within_a_field_are_refused():
    with pytest.raises(ConfigError) as err:
        check_budgets(_table("nerf", "rainyscape-nerf"))
    msg = str(err.value)
    assert "field 'grid' on scene yard: nerf: 100 steps × 1024 px/step; " \
           "rainyscape-nerf: 100 steps × 2560 px/step (warmup 50 × 1024, joint 50 × 4096)" in msg
    assert "allow_unequal=true" in msg
    # different steps are unequal too
    steps = [("yard/nerf", "yard", _budget("nerf")), ("yard/robust-nerf", "yard", _budget("robust-nerf", "trainer.max_iters=200"))]
    assert len(budget_mismatches(steps)) == 1
    # allowed: the mismatch is returned, not raised
    (m,) = check_budgets(_table("nerf", "rainyscape-nerf"), allow_unequal=True)
    assert m.family == "grid" and m.scenes == ("yard",)
    # the same difference on several scenes is one line naming them
    two = _table("nerf", "rainyscape-nerf") + [(k.replace("yard", "plaza"), "plaza", b) for k, _, b in _table("nerf", "rainyscape-nerf")]
    (m,) = budget_mismatches(two)
    assert m.scenes == ("yard", "plaza") and m.describe().startswith("field 'grid' on scenes yard, plaza: nerf: ")


def test_equal_budgets_and_different_fields_pass():
    assert check_budgets(_table("nerf", "robust-nerf", "3dgs", "robust-3dgs", "rainyscape-3dgs")) == []
    # the same method on scenes of different sizes is not a mismatch (scenes are checked apart)
    assert check_budgets([("a/3dgs", "a", _budget("3dgs", size=64)), ("b/3dgs", "b", _budget("3dgs"))]) == []


def test_budget_column_prints_the_difference():
    cells = build_cells(["nerf", "rainyscape-nerf", "3dgs"], [("yard", "/y")], [])
    budgets = {key: b.to_dict() for key, _, b in _table("nerf", "rainyscape-nerf", "3dgs")}
    results = {"cells": {}, "budgets": budgets}
    col = budget_column(cells, results)
    assert col == {"nerf": "100 × 1024", "rainyscape-nerf": "100 × 2560 (≠ nerf: 100 × 1024)", "3dgs": "100 × 16384"}
    results["cells"] = {k: {"status": "finished", "summary": {"train_psnr": 20.0}, "budget": b, "scene": "yard"}
                        for k, b in budgets.items()}
    results["budget_mismatches"] = ["field 'grid' on scene yard: ..."]
    report = markdown_report(cells, results)
    assert "| 100 × 2560 (≠ nerf: 100 × 1024) |" in report
    assert "grid: nerf, rainyscape-nerf; gaussians: 3dgs" in report and "different fields may differ" in report
    assert "**Unequal budgets within a field** (allow_unequal=true)" in report


def test_rs_bench_refuses_unequal_budgets_before_anything_runs(tmp_path):
    done = subprocess.run(["rs-bench", "scenes=cpu", "methods=nerf,rainyscape-nerf", "iters=5",
                           *(f"rainyscape-nerf:{o}" for o in PAPER_PATCH),
                           f"out={tmp_path}"],
                          capture_output=True, text=True)
    assert done.returncode == 2 and "Traceback" not in done.stderr, done.stderr
    scenes = ", ".join(SCENE_SETS["cpu"].presets)
    assert f"field 'grid' on scenes {scenes}: nerf: 5 steps × 1024 px/step; " \
           "rainyscape-nerf: 5 steps × 2867 px/step (warmup 2 × 1024, joint 3 × 4096)" in done.stderr
    assert "allow_unequal=true" in done.stderr
    assert not list(tmp_path.iterdir())  # nothing simulated, trained or written


def test_rain_table_lists_rain_methods_with_their_means():
    from rainyscape.comparison.tables import rain_table

    cells = build_cells(["3dgs", "rainyscape-3dgs"], [("yard", "/y"), ("plaza", "/p")], [])
    summaries = {"yard/3dgs": {"train_psnr": 20.0},
                 "plaza/3dgs": {"train_psnr": 20.0},
                 "yard/rainyscape-3dgs": {"rain_correlation": 0.5, "rain_angle_error_deg": 10.0},
                 "plaza/rainyscape-3dgs": {"rain_correlation": 0.7, "rain_angle_error_deg": 4.0}}
    results = {"cells": {k: {"status": "finished", "summary": s} for k, s in summaries.items()}}
    table = rain_table(cells, results).splitlines()
    assert len(table) == 3 and "3dgs |" not in table[2].replace("rainyscape-3dgs |", "")
    assert table[2] == "| rainyscape-3dgs | 0.50 / 10.0° | 0.70 / 4.0° | 0.60 / 7.0° |"
    assert rain_table(cells[:1], results) == ""


def test_gap_table_puts_each_gain_next_to_the_gap_its_field_leaves():
    from rainyscape.comparison.tables import gap_table, markdown_report

    cells = build_cells(["3dgs", "rainyscape-3dgs"], [("yard", "/y"), ("plaza", "/p")], [], ceiling=["3dgs"])
    psnr = {"yard/3dgs on clean views": 31.0, "plaza/3dgs on clean views": 33.0, "yard/3dgs": 30.0,
            "plaza/3dgs": 25.0, "yard/rainyscape-3dgs": 29.5, "plaza/rainyscape-3dgs": 28.0}
    gauss = Budget("gaussians", 10, 100.0, ()).to_dict()
    results = {"cells": {k: {"status": "finished", "summary": {"train_psnr": v}, "budget": gauss}
                         for k, v in psnr.items()}}
    table = gap_table(cells, results, "train").splitlines()
    assert table[2] == "| rainyscape-3dgs (over 3dgs) | -0.50 / 1.00 | +3.00 / 8.00 | +1.25 / 4.50 |"
    assert len(table) == 3  # the plain field is not compared with itself
    assert "Gain over the plain field" in markdown_report(cells, results)
    assert gap_table([c for c in cells if not c.clean], results, "train") == ""  # no ceiling, no table


@pytest.mark.parametrize("profile", ["cpu", "gpu"])
def test_every_recipe_builds_and_a_field_family_shares_one_budget(profile):
    """Both recipes of every method of this package materialise, and methods training one field
    get one budget (within the paper-faithful pairs, robust baselines and both plus methods)."""
    from rainyscape import registry

    ours = [n for n, e in registry.entries("method").items() if e.target.startswith("rainyscape.methods")]
    budgets = {m: cell_budget(method_config(m, [f"profile={profile}"]), 512, 512, 44) for m in ours}
    groups = {"grid": ("nerf", "robust-nerf", "rainyscape-nerf", "rainyscape-plus-nerf"),
              "nerf-mlp": ("vanilla-nerf", "rainyscape-vanilla-nerf"),
              "gaussians": ("3dgs", "robust-3dgs", "desplat", "rainyscape-3dgs", "rainyscape-plus")}
    assert sorted(ours) == sorted(m for g in groups.values() for m in g)
    for family, methods in groups.items():
        first = budgets[methods[0]]
        assert first.family == family
        assert all(budgets[m].same_as(first) for m in methods), {m: budgets[m].describe() for m in methods}


def test_region_table_splits_each_render_into_rain_and_dry_pixels():
    from rainyscape.comparison.tables import region_table

    cells = build_cells(["3dgs", "rainyscape-3dgs"], [("yard", "/y"), ("plaza", "/p")], [], ceiling=["3dgs"])
    # the ceiling trains on the clean views: its "input" is exact (PSNR capped at 120 dB)
    s = {"yard/3dgs on clean views": {"rainy_input_psnr_in_rain": 120.0, "train_psnr_in_rain": 31.0,
                                      "train_psnr_dry": 32.0},
         "yard/3dgs": {"rainy_input_psnr_in_rain": 13.0, "train_psnr_in_rain": 20.0, "train_psnr_dry": 30.0},
         "plaza/3dgs": {"rainy_input_psnr_in_rain": 11.0, "train_psnr_in_rain": 18.0, "train_psnr_dry": 28.0},
         "yard/rainyscape-3dgs": {"train_psnr_in_rain": 22.0, "train_psnr_dry": 29.0},
         "plaza/rainyscape-3dgs": {"train_psnr_in_rain": 23.0}}
    results = {"cells": {k: {"status": "finished", "summary": v} for k, v in s.items()}}
    table = region_table(cells, results).splitlines()
    assert table[0] == "| Method | yard in rain / dry | plaza in rain / dry | Average |"
    assert table[2] == "| rainy input | 13.00 | 11.00 | 12.00 |"
    assert table[3] == "| 3dgs on clean views | 31.00 / 32.00 | n/a | n/a |"
    assert table[4] == "| 3dgs | 20.00 / 30.00 | 18.00 / 28.00 | 19.00 / 29.00 |"
    assert table[5] == "| rainyscape-3dgs | 22.00 / 29.00 | 23.00 | 22.50 |"  # a dry value missing
    assert region_table(cells, {"cells": {k: {"status": "finished", "summary": {"train_psnr": 1.0}}
                                          for k in s}}) == ""
