"""What the field is fitted without (``ImageHead.for_field``): terms that see a layer detached
read the head's part for the field, terms that train the head read the whole layer, and a
ray field's single rays fit against the cached part."""

from __future__ import annotations

import torch

from rainyscape.components import LossContext, RenderOutput
from rainyscape.config import LossConfig
from rainyscape.engine.loss_sum import compute_losses
from rainyscape.losses.rain_losses import Reconstruction
from test_render_cache import MIXED_JOINT, SMALL


def test_a_term_that_sees_the_layer_detached_reads_the_fields_part():
    g = torch.Generator().manual_seed(0)
    rendered = torch.rand(1, 3, 8, 8, generator=g).requires_grad_(True)
    target = torch.rand(1, 3, 8, 8, generator=g)
    rain = torch.rand(1, 3, 8, 8, generator=g).mul(0.2).requires_grad_(True)
    part = torch.zeros(1, 3, 8, 8)
    ctx = LossContext(rendered, target, {"rain": rain}, RenderOutput(rgb=rendered), torch.tensor([0]),
                      step=0, phase="joint", field_layers={"rain": part})
    field_term = {"field": (LossConfig("reconstruction", detach="rain"), Reconstruction())}
    head_term = {"head": (LossConfig("reconstruction"), Reconstruction())}
    _, values = compute_losses(field_term, ctx)
    with torch.no_grad():
        field_value, head_value = (target - rendered).pow(2).mean(), (target - rendered - rain).pow(2).mean()
    assert float(values["field"]) == float(field_value)  # I - B - 0
    _, values = compute_losses(head_term, ctx)
    assert float(values["head"]) == float(head_value)  # I - B - R
    total, _ = compute_losses({**field_term, **head_term}, ctx)
    total.backward()
    assert rain.grad is not None and bool(rain.grad.abs().sum() > 0)  # the head still learns R


def test_the_rays_fit_against_the_heads_part_for_the_field(tiny_scene, tmp_path, monkeypatch):
    from rainyscape import config
    from rainyscape.engine.pipeline import build_pipeline
    from rainyscape.engine.trainer import Trainer

    cfg = config.method_config("rainyscape-nerf", [*SMALL, *MIXED_JOINT, "phases.warmup.end=0.0"])
    pipeline = build_pipeline(cfg, tiny_scene, torch.device("cpu"))
    trainer = Trainer(pipeline, tmp_path)
    name, phase = trainer.phases.at(0)
    head = pipeline.rain_head
    cached = {}
    for narrowed in (False, True):
        if narrowed:
            monkeypatch.setattr(head, "for_field", lambda layer, residual, view_ids, background: 0.5 * layer)
        trainer.generator.manual_seed(5)  # the same view
        trainer._cached_view_losses(name, phase, [head], pipeline.loss_terms(name))
        cached[narrowed] = trainer.layer_caches["rain"].values.float().clone()
    assert bool(cached[False].abs().sum() > 0)
    assert torch.allclose(cached[True], 0.5 * cached[False], atol=1e-3)
