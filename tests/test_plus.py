"""``rainyscape-plus`` and ``rainyscape-plus-nerf``: each is its paper method with the same
parts beyond the paper (rainyscape/methods/plus.py), and the grid one trains end to end with
the neighbours' evidence acting."""

from __future__ import annotations

import dataclasses
import json

import pytest

from rainyscape.config import PhaseConfig, method_config
from rainyscape.methods.rainyscape_nerf import joint_batch
from test_render_cache import MIXED_JOINT, SMALL


@pytest.mark.parametrize("plus, paper, own, changed", [
    ("rainyscape-plus", "rainyscape-3dgs", {"multiview-rain", "floater-opacity"}, set()),
    # the warm-up with the pixels brighter than the render weighing half
    ("rainyscape-plus-nerf", "rainyscape-nerf", set(), {"photometric"})])
def test_a_plus_method_is_its_paper_method_with_the_shared_parts(plus, paper, own, changed):
    plus_cfg, paper_cfg = method_config(plus, []), method_config(paper, [])
    assert set(plus_cfg.losses) - set(paper_cfg.losses) == own
    assert plus_cfg.losses["tv"].options.cap == 0.1 and paper_cfg.losses["tv"].options.cap == 0.0
    # the rain's direction looked for near each view's down; the paper's AGR looks everywhere
    assert plus_cfg.losses["agr"].options.max_tilt == 60.0 and paper_cfg.losses["agr"].options.max_tilt == 90.0
    for key in changed:
        assert plus_cfg.losses[key].options.brighter == 0.5 and paper_cfg.losses[key].options.brighter == 1.0
    for key in paper_cfg.losses:
        if key not in {"tv", "agr"} | changed:
            assert plus_cfg.losses[key] == paper_cfg.losses[key], key
    assert (plus_cfg.field, plus_cfg.trainer) == (paper_cfg.field, paper_cfg.trainer)
    assert plus_cfg.phases["warmup"] == paper_cfg.phases["warmup"]
    # the grid's joint step: fewer patches and more single rays, the same rays a step
    joint, paper_joint = plus_cfg.phases["joint"], paper_cfg.phases["joint"]
    if plus == "rainyscape-plus-nerf":
        # the AGR steered by one fall fitted over whole views, where the head sees rain
        agr, paper_agr = plus_cfg.losses["agr"].options, paper_cfg.losses["agr"].options
        assert (agr.estimator, agr.directions, agr.where_rain) == ("structure", "world", 0.02)
        assert (paper_agr.estimator, paper_agr.directions, paper_agr.where_rain) == ("gradient", "batch", 0.0)
        assert (joint.patches, joint.patch_size, joint.rays) == (4, 4, 960)
        assert (paper_joint.patches, paper_joint.patch_size, paper_joint.rays) == (16, 4, 768)
        joint = dataclasses.replace(joint, patches=16, rays=768)
    assert joint == paper_joint
    # its CPU head: the latent at full resolution with four channels, the field fitted without
    # R less what runs across the streaks (found near the view's down), raised up to twice where
    # the residual stands out across them, kept only where the residual has the rain's colour;
    # the GPU recipe keeps the paper's latent
    head, paper_head = vars(plus_cfg.rain_head.options), vars(paper_cfg.rain_head.options)
    assert {k: v for k, v in head.items() if paper_head[k] != v} == \
        {"upscale": 1, "latent_channels": 4, "field_across": 2, "field_gain": 2.0, "max_tilt": 60.0,
         "field_colour": 0.1}
    gpu = [method_config(m, ["profile=gpu", "trainer.device=cpu"]) for m in (plus, paper)]
    assert [(c.rain_head.options.upscale, c.rain_head.options.latent_channels) for c in gpu] == [(2, 1), (2, 1)]
    assert gpu[0].phases == gpu[1].phases and gpu[0].trainer == gpu[1].trainer


def test_the_gaussians_plus_has_the_neighbours_say_how_much_rain():
    mv = method_config("rainyscape-plus", []).losses["multiview-rain"]
    # the reconstruction term's weight, where the head sees rain
    assert mv.name == "mv-rain" and mv.weight == 500.0 and mv.options.where_rain == 0.02
    fl = method_config("rainyscape-plus", []).losses["floater-opacity"]
    assert fl.weight == 5.0 and fl.phases == ("joint",)


def test_rainyscape_plus_nerf_trains_end_to_end_with_the_evidence_on_every_kind_of_batch(tiny_scene_dir, tmp_path):
    """End to end on the tiny scene with the recipe's mixed joint batch (patches, single
    rays, a cached whole view), with the rain evidence added as an option, as it was measured:
    the run finishes and evaluates, and the evidence term is finite in every joint step, on
    the patches and on the cached view."""
    from rainyscape.workflow import train_and_evaluate

    run = train_and_evaluate(method_config("rainyscape-plus-nerf", [f"data={tiny_scene_dir}", *SMALL, *MIXED_JOINT,
                                                                    "losses.mv-rain.weight=500",
                                                                    f"trainer.output_dir={tmp_path}"]))
    assert "train_psnr" in json.loads((run.run_dir / "metrics.json").read_text())["summary"]
    records = [json.loads(line) for line in (run.run_dir / "log.jsonl").read_text().splitlines()]
    joint = [r["terms"] for r in records if r.get("phase") == "joint" and "terms" in r]
    assert len(joint) == 4
    for terms in joint:
        assert {"mv-rain", "cached_views.mv-rain", "tv", "agr"} <= set(terms)
        assert all(0 <= terms[k] < float("inf") for k in ("mv-rain", "cached_views.mv-rain"))


def test_a_joint_batch_keeps_the_warm_ups_rays_in_square_patches():
    warmup = PhaseConfig(patches=1024, patch_size=1)
    assert joint_batch(warmup, 4, 960) == {"patches": 4, "patch_size": 4, "rays": 960}
    assert joint_batch(warmup, 1, 0) == {"patches": 1, "patch_size": 32, "rays": 0}
    with pytest.raises(ValueError, match="no square patch"):
        joint_batch(warmup, 4, 900)  # 124 rays leave 31 a patch
