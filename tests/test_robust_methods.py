"""robust-nerf, robust-3dgs and desplat: each is its plain counterpart with only what its paper
changes (so it follows the counterpart's field), and each trains end to end on a tiny scene."""

from __future__ import annotations

import json

import pytest
import torch

from rainyscape import config
from rainyscape.comparison.budget import cell_budget
from rainyscape.engine.checkpoint import latest_checkpoint


def _rays(phase) -> int:
    return phase.patches * max(phase.patch_size, 1) ** 2


def test_robust_nerf_is_nerf_with_robustnerfs_loss_on_its_single_rays():
    base, robust = config.method_config("nerf"), config.method_config("robust-nerf")
    assert robust.field == base.field and robust.dataparser == base.dataparser
    assert robust.rain_head is None and robust.postprocess == {}
    assert list(robust.losses) == ["robust"] and robust.losses["robust"].name == "robust"
    fit, plain = robust.phases["fit"], base.phases["fit"]
    assert robust.trainer.max_iters == base.trainer.max_iters and list(robust.phases) == ["fit"]
    assert fit == plain and robust.losses["robust"].options.residual_map  # nerf's batch; the map decides
    assert cell_budget(robust, 64, 64, 16).same_as(cell_budget(base, 64, 64, 16))
    gpu, gpu_base = config.method_config("robust-nerf", ["profile=gpu"]), config.method_config("nerf", ["profile=gpu"])
    assert gpu.field == gpu_base.field and _rays(gpu.phases["fit"]) == _rays(gpu_base.phases["fit"])


def test_robust_3dgs_is_3dgs_with_robustfilter_and_its_schedule_changes():
    base, robust = config.method_config("3dgs"), config.method_config("robust-3dgs")
    assert robust.field.name == base.field.name and robust.rain_head is None
    assert list(robust.losses) == ["robust"] and robust.losses["robust"].name == "robust-filter"
    opts = robust.losses["robust"].options
    assert opts.percentile == 0.7 and opts.ssim_weight == 0.0 and opts.reset_group == "shN"
    f, b = robust.field.options, base.field.options
    assert f.reset_every > 30_000 and f.refine_start == 1000  # no opacity resets; densify from 1k of 30k
    for key in ("max_gaussians", "pixels_per_gaussian", "sh_degree", "strategy", "init", "lr_means"):
        assert getattr(f, key) == getattr(b, key)
    assert robust.phases == base.phases and robust.trainer.max_iters == base.trainer.max_iters


def test_desplat_is_3dgs_with_per_view_distractor_gaussians():
    base, d = config.method_config("3dgs"), config.method_config("desplat")
    assert d.field == base.field and d.phases["fit"].heads == ("rain_head",)
    assert d.rain_head.name == "distractor-gaussians" and d.losses["desplat"].name == "desplat"
    assert cell_budget(d, 64, 64, 16).same_as(cell_budget(base, 64, 64, 16))


def _train(method, tmp_path, scene, *extra):
    from rainyscape.workflow import train_and_evaluate

    cfg = config.method_config(method, [f"data={scene}", f"trainer.output_dir={tmp_path}", "trainer.device=cpu",
                                        "trainer.progress=false", "trainer.log_every=1", "trainer.eval_every=0",
                                        *extra])
    run = train_and_evaluate(cfg).run_dir
    records = [json.loads(line) for line in (run / "log.jsonl").read_text().splitlines()]
    return run, [r for r in records if "metrics" in r]


def test_robust_nerf_trains_and_checkpoints_its_threshold_and_residual_map(tmp_path, tiny_scene_dir):
    run, records = _train("robust-nerf", tmp_path, tiny_scene_dir, "trainer.max_iters=6")
    assert len(records) == 6 and records[0]["metrics"]["robust.threshold"] == 1.0
    assert all(0.0 < r["metrics"]["robust.inlier_fraction"] <= 1.0 for r in records)
    state = torch.load(latest_checkpoint(run / "checkpoints"), weights_only=True)
    # the last batch was judged by the quantile of the one before; the checkpoint holds the next
    assert records[-1]["metrics"]["robust.threshold"] < 1.0 and state["losses"]["robust"]["threshold"] > 0
    seen = state["losses"]["robust"]["map"]["seen"]  # the pixels the six steps' rays rendered
    assert int(seen.max()) == 5 and 0 < int((seen >= 0).sum()) <= 6 * _rays(config.method_config("nerf").phases["fit"])
    assert json.loads((run / "metrics.json").read_text())["summary"]["train_psnr"] > 5


def test_robust_3dgs_trains_and_resets_the_view_dependent_colour(tmp_path, tiny_scene_dir):
    # 8002 of 30k is step 2 of 8: the SH reset runs, its callback state is checkpointed
    run, records = _train("robust-3dgs", tmp_path, tiny_scene_dir, "trainer.max_iters=8",
                          "field.max_gaussians=2000")
    assert len(records) == 8 and records[0]["metrics"]["robust.blend"] == 1.0 > records[-1]["metrics"]["robust.blend"]
    state = torch.load(latest_checkpoint(run / "checkpoints"), weights_only=True)
    assert {"done": True} in state["callbacks"]
    assert float(state["models"]["field"]["params.shN"].max()) <= 0.001 + 1e-6
    assert json.loads((run / "metrics.json").read_text())["summary"]["train_psnr"] > 5


def test_desplat_trains_its_distractors_and_evaluates_the_static_scene(tmp_path, tiny_scene_dir):
    run, records = _train("desplat", tmp_path, tiny_scene_dir, "trainer.max_iters=6", "field.max_gaussians=2000",
                          "rain_head.gaussians_per_view=100", "rain_head.reference_pixels=0",
                          "rain_head.refine_every_views=1")
    assert len(records) == 6 and 0.0 < records[-1]["metrics"]["desplat.distractor_alpha"] < 1.0
    # the log carries the head's stats beside the field's: its Gaussians and their changes
    stats = records[-1]["stats"]
    views = stats["rain_head.num_gaussians"] / stats["rain_head.per_view"]
    changes = stats["rain_head.cloned"] + stats["rain_head.split"] - stats["rain_head.culled"]
    assert stats["rain_head.num_gaussians"] == 100 * views + changes and "field.num_gaussians" in stats
    summary = json.loads((run / "metrics.json").read_text())["summary"]
    assert summary["train_psnr"] > 5 and "train_rain_recovered" in summary  # the layer's share of the rain
    state = torch.load(latest_checkpoint(run / "checkpoints"), weights_only=True)
    assert any(k.startswith("sets.") for k in state["models"]["rain_head"])


@pytest.mark.parametrize("method", ["3dgs", "robust-3dgs", "desplat"])
def test_the_gaussian_methods_resume_exactly(tmp_path, tiny_scene_dir, tiny_scene, method):
    """Stopped at step 3 and resumed, a run ends where an uninterrupted one does (the C++
    rasteriser's multi-threaded gradient sums, the running
    histogram, the Bernoulli draws, the SH reset, the per-view sets and their densification)."""
    from rainyscape.engine.run import load_run
    from rainyscape.workflow import train_and_evaluate

    common = [f"data={tiny_scene_dir}", "trainer.device=cpu", "trainer.progress=false", "trainer.eval_every=0",
              "trainer.checkpoint_every=0", "trainer.final_eval_views=1", "field.max_gaussians=1000"]
    steps, stop = 6, 3
    if method == "desplat":  # a refinement of the distractors (after a pass over the views) on each side
        views = len(tiny_scene.train_indices)
        steps, stop = 2 * views + 1, views + 1
        common += ["rain_head.gaussians_per_view=50", "rain_head.reference_pixels=0", "rain_head.refine_every_views=1",
                   "rain_head.refine_stop=1"]
    common.append(f"trainer.max_iters={steps}")
    full = train_and_evaluate(config.method_config(method, common + [f"trainer.output_dir={tmp_path / 'a'}"]))
    first = train_and_evaluate(config.method_config(method, common + [f"trainer.output_dir={tmp_path / 'b'}",
                                                                       f"trainer.stop_at={stop}"]))
    resumed = config.load_yaml(first.run_dir / "config.yml")
    resumed.trainer.stop_at = 0
    train_and_evaluate(resumed, run_dir=first.run_dir)
    (a, _), (b, _) = load_run(full.run_dir, device="cpu"), load_run(first.run_dir, device="cpu")
    for key, model in a.models().items():
        theirs = b.models()[key].state_dict()
        for name, tensor in model.state_dict().items():
            assert torch.allclose(tensor, theirs[name], atol=1e-6, rtol=0), f"{key}.{name}"
    if method == "desplat":  # the distractors were refined before and after the split
        assert set(a.rain_head.counts().values()) != {50}
