"""robust-nerf / robust-3dgs: derived from their counterparts, and they train with a checkpointed threshold."""

from __future__ import annotations

import json

import pytest
import torch

from rainyscape import config
from rainyscape.engine.checkpoint import latest_checkpoint


def _rays(phase) -> int:
    return phase.patches * max(phase.patch_size, 1) ** 2


def test_robust_nerf_is_nerf_with_the_trimmed_loss():
    base, robust = config.method_config("nerf"), config.method_config("robust-nerf")
    assert robust.field == base.field and robust.dataparser == base.dataparser
    assert robust.rain_head is None and robust.postprocess == {}
    assert list(robust.losses) == ["robust"] and robust.losses["robust"].options.residual == "l2"
    t, b = robust.phases["fit"], base.phases["fit"]
    assert robust.trainer.max_iters == base.trainer.max_iters and list(robust.phases) == ["fit"]
    assert t.patch_size >= 16 and _rays(t) == _rays(b)  # patches, same rays per step


def test_robust_3dgs_is_3dgs_with_the_trimmed_l1_dssim_loss():
    base, robust = config.method_config("3dgs"), config.method_config("robust-3dgs")
    assert robust.field == base.field and robust.rain_head is None
    opts = robust.losses["robust"].options
    assert opts.residual == "l1" and 0 < opts.ssim_weight < 1
    assert robust.trainer.max_iters == base.trainer.max_iters and list(robust.phases) == ["fit"]
    size = robust.phases["fit"].patch_size
    assert size == 0 or size >= 16


def test_robust_nerf_trains_and_checkpoints_its_threshold(tmp_path, tiny_scene_dir):
    from rainyscape.workflow import train_and_evaluate

    cfg = config.method_config("robust-nerf", [f"data={tiny_scene_dir}", "trainer.max_iters=6",
                                               f"trainer.output_dir={tmp_path}", "trainer.device=cpu",
                                               "trainer.progress=false", "trainer.log_every=1",
                                               "trainer.eval_every=0"])
    run = train_and_evaluate(cfg).run_dir
    records = [json.loads(line) for line in (run / "log.jsonl").read_text().splitlines()]
    fractions = [r["metrics"]["robust.inlier_fraction"] for r in records if "metrics" in r]
    assert len(fractions) == 6 and all(0.5 < f <= 1.0 for f in fractions)
    state = torch.load(latest_checkpoint(run / "checkpoints"), weights_only=False)
    recent = state["losses"]["robust"]["recent"]
    assert len(recent) == 6  # one quantile per batch, saved with the run
    # the last batch was judged by the mean quantile of the five batches before it
    assert records[-1]["metrics"]["robust.threshold"] == pytest.approx(sum(recent[:5]) / 5, rel=1e-6)
    assert json.loads((run / "metrics.json").read_text())["summary"]["train_psnr"] > 5
