"""Scene sets (``rs-bench scenes=cpu|paper``) resolve to their documented sizes, budgets and
presets; explicit options override them; presets, folders and the demo still work."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from rainyscape.comparison.matrix import has_clean_views
from rainyscape.comparison.options import BenchOptions
from rainyscape.comparison.plan import plan_bench
from rainyscape.comparison.scenes import cache_folder, resolve_scene
from rainyscape.comparison.sets import SCENE_SETS, scene_set
from rainyscape.errors import ConfigError
from rainyscape.synth.presets import PRESETS

SIX = "nerf,robust-nerf,3dgs,robust-3dgs"  # equal budgets today within each field


def _plan(**kw):
    overrides = kw.pop("overrides", [])
    return plan_bench(BenchOptions(**{"methods": SIX, **kw}), overrides)


def _iters(plan) -> dict[str, int]:
    return {k.split("/")[1]: b.steps for k, b in plan.budgets.items() if k.startswith(plan.scenes[0].label + "/")}


def test_documented_sets():
    cpu, paper = SCENE_SETS["cpu"], SCENE_SETS["paper"]
    assert (cpu.width, cpu.height) == (128, 128) and len(cpu.presets) == 5
    assert (paper.width, paper.height, paper.rows, paper.cols) == (512, 512, 5, 10)
    assert paper.iters == {"grid": 18000, "gaussians": 30000}  # the paper's NeRF and 3DGS step counts
    for s in (cpu, paper):
        assert set(s.presets) <= set(PRESETS) and len(set(s.presets)) == len(s.presets)
        assert set(s.iters) == {"grid", "gaussians"}


def test_cpu_set_resolves_to_its_sizes_and_budgets():
    cpu = SCENE_SETS["cpu"]
    plan = _plan(scenes="cpu")
    assert plan.scene_set == "cpu" and [p.label for p in plan.scenes] == list(cpu.presets)
    assert all((p.width, p.height, p.rows, p.cols) == (128, 128, cpu.rows, cpu.cols) for p in plan.scenes)
    assert all(not p.embedded and not p.folder for p in plan.scenes)  # simulated at the set's size
    steps = _iters(plan)
    assert steps["nerf"] == steps["robust-nerf"] == cpu.iters["grid"]
    assert steps["3dgs"] == steps["robust-3dgs"] == cpu.iters["gaussians"]
    b = plan.budgets[f"{cpu.presets[0]}/3dgs"]
    assert b.pixels_per_step == 128 * 128  # a whole view of the set's size


def test_distractors_set_plans_the_transient_presets_for_the_peers_at_equal_budgets():
    d = SCENE_SETS["distractors"]
    assert set(d.presets) <= set(PRESETS) and all(PRESETS[p].transients for p in d.presets)
    plan = _plan(scenes="distractors", methods="nerf,robust-nerf,3dgs,robust-3dgs,desplat")
    assert plan.scene_set == "distractors" and [p.label for p in plan.scenes] == list(d.presets)
    assert all((p.width, p.height, p.rows, p.cols) == (128, 128, 3, 6) for p in plan.scenes)
    assert plan.mismatches == []  # each peer at its plain field's budget
    steps = _iters(plan)
    assert steps["robust-nerf"] == steps["nerf"] and steps["robust-3dgs"] == steps["desplat"] == steps["3dgs"]
    assert "3dgs on clean views" in steps  # the ceiling: the field on the views without transients


def test_every_cell_trains_the_recipe_its_budget_was_checked_for():
    assert _plan(scenes="demo", device="cpu").overrides[0] == "profile=cpu"
    assert _plan(scenes="demo", device="cpu", profile="gpu").overrides[0] == "profile=gpu"
    with pytest.raises(ConfigError, match="profile=tpu: not one of auto | cpu | gpu"):
        _plan(scenes="demo", profile="tpu")


def test_a_table_evaluates_every_view():
    overrides = _plan(scenes="demo", device="cpu").overrides
    assert "trainer.final_eval_views=0" in overrides


def test_paper_set_and_explicit_overrides():
    plan = _plan(scenes="paper")
    assert all((p.width, p.height, p.rows, p.cols) == (512, 512, 5, 10) for p in plan.scenes)
    assert _iters(plan) == {"nerf": 18000, "robust-nerf": 18000, "3dgs": 30000, "robust-3dgs": 30000,
                            "nerf on clean views": 18000, "3dgs on clean views": 30000}
    mine = _plan(scenes="cpu", scene_width=64, scene_rows=2, iters=7)
    assert all((p.width, p.height, p.rows, p.cols) == (64, 64, 2, SCENE_SETS["cpu"].cols) for p in mine.scenes)
    assert set(_iters(mine).values()) == {7}
    dotted = _plan(scenes="cpu", overrides=["trainer.max_iters=9"])  # a dotted key wins over the set
    assert set(_iters(dotted).values()) == {9}


def test_presets_folders_and_demo_still_work(tiny_scene_dir):
    demo = _plan(scenes="demo")
    assert demo.scene_set is None and demo.scenes[0].embedded
    assert demo.budgets["demo/3dgs"].pixels_per_step == PRESETS["demo"].width * PRESETS["demo"].height
    from rainyscape.config import method_config

    assert _iters(demo)["nerf"] == method_config("nerf", []).trainer.max_iters  # the method's own budget
    yard = _plan(scenes="yard", scene_width=96)
    assert (yard.scenes[0].width, yard.scenes[0].height) == (96, 96) and not yard.scenes[0].embedded
    folder = _plan(scenes=str(tiny_scene_dir))
    assert folder.scenes[0].folder == str(tiny_scene_dir.resolve())
    assert folder.budgets[f"{tiny_scene_dir.name}/3dgs"].pixels_per_step == 48 * 48  # from its scene.json
    half = _plan(scenes=str(tiny_scene_dir), overrides=["dataparser.downscale=2"])
    assert half.budgets[f"{tiny_scene_dir.name}/3dgs"].pixels_per_step == 24 * 24


def test_bad_scene_specs():
    assert scene_set("yard,street") is None
    with pytest.raises(ConfigError, match="cannot be combined"):
        scene_set("cpu,yard")
    with pytest.raises(ConfigError, match="neither a scene set"):
        _plan(scenes="no-such-scene")


def test_ceiling_rows_train_listed_plain_fields_on_the_clean_views(tiny_scene_dir, tmp_path):
    cells = _plan(scenes=str(tiny_scene_dir)).cells()
    ceilings = [c for c in cells if c.clean]
    assert [c.method for c in ceilings] == ["nerf", "3dgs"] and cells[:2] == ceilings  # the rows come first
    nerf = next(c for c in cells if c.label == "nerf")
    assert ceilings[0].overrides[:len(nerf.overrides)] == nerf.overrides  # the method's budget and recipe
    assert "dataparser.images=images_wo_rain" in ceilings[0].overrides
    assert not [c for c in _plan(scenes=str(tiny_scene_dir), ceiling="none").cells() if c.clean]
    assert [c.method for c in _plan(scenes="yard", ceiling="3dgs").cells() if c.clean] == ["3dgs"]
    with pytest.raises(ConfigError, match="rainyscape-3dgs not in methods"):
        _plan(scenes="yard", ceiling="rainyscape-3dgs")
    (tmp_path / "cameras.csv").write_text("")  # a folder without clean views gets no ceiling row
    assert has_clean_views(str(tiny_scene_dir)) and has_clean_views("") and not has_clean_views(str(tmp_path))


def test_dynamic_rain_plans_its_own_labelled_and_cached_scenes(tmp_path):
    static, dynamic = _plan(scenes="cpu"), _plan(scenes="cpu", scene_rain="dynamic")
    assert [p.label for p in dynamic.scenes] == [f"{p.label}-dynamic" for p in static.scenes]
    assert all(p.mode == "dynamic" and p.preset for p in dynamic.scenes)
    folders = {cache_folder(p, tmp_path) for p in static.scenes + dynamic.scenes}
    assert len(folders) == 10  # static and dynamic scenes never share a cache folder
    with pytest.raises(ConfigError, match="scene_rain=dynamic .*simulates none"):
        _plan(scenes=str(tmp_path), scene_rain="dynamic")
    # simulated with rain that moves: the scene says so, and its views' rain differs in time
    tiny = _plan(scenes="yard", scene_rain="dynamic", scene_width=32, scene_rows=1, scene_cols=3).scenes[0]
    label, folder = resolve_scene(tiny, tmp_path)
    assert label == "yard-dynamic" and json.loads((Path(folder) / "scene.json").read_text())["mode"] == "dynamic"
