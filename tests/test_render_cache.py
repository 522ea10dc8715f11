"""The render cache (engine/render_cache.py): holes filled from the nearest rendered pixels,
the newest render of a pixel kept, a whole view read back after a run of random rays, and a
phase that trains heads on whole cached views, and the layer cache against whose whole-view
predictions a phase's single rays fit the field."""

from __future__ import annotations

import pytest
import torch

from rainyscape.cameras import Window
from rainyscape.components import RenderOutput
from rainyscape.engine.render_cache import LayerCache, RenderCache, fill_holes
from rainyscape.imaging.filters import box_sum


def _smooth(h: int = 24, w: int = 32) -> torch.Tensor:
    y, x = torch.meshgrid(torch.linspace(0, 1, h), torch.linspace(0, 1, w), indexing="ij")
    return torch.stack([x, y, 0.5 * (x + y)])[None]  # (1, 3, h, w)


def test_box_sum_is_the_square_windows_sum():
    x = torch.rand(2, 1, 9, 11, generator=torch.Generator().manual_seed(2))
    for size in (3, 5, 9):
        square = torch.nn.functional.conv2d(x, torch.ones(1, 1, size, size), padding=size // 2)
        assert torch.allclose(box_sum(x, size), square, atol=1e-5)
    # padded with a value, and an even size reaching one pixel further up and left
    padded = torch.nn.functional.pad(x, (2, 1, 2, 1), value=1.0)
    assert torch.allclose(box_sum(x, 4, value=1.0), torch.nn.functional.conv2d(padded, torch.ones(1, 1, 4, 4)),
                          atol=1e-5)


def test_fill_holes_keeps_known_pixels_and_fills_from_neighbours():
    image = _smooth()
    known = torch.rand(1, 1, 24, 32, generator=torch.Generator().manual_seed(0)) < 0.4
    filled = fill_holes(torch.where(known, image, torch.zeros_like(image)), known)
    assert torch.equal(filled[known.expand_as(image)], image[known.expand_as(image)])
    # a smooth image is recovered to within a couple of pixels' change of it
    assert (filled - image).abs().max() < 3 / 24
    # one known pixel fills the whole image with its value; no known pixel leaves it as it is
    one = torch.zeros(1, 1, 24, 32, dtype=torch.bool)
    one[0, 0, 5, 7] = True
    assert torch.allclose(fill_holes(image, one), image[:, :, 5, 7][..., None, None].expand_as(image))
    none = torch.zeros_like(one)
    assert torch.equal(fill_holes(image, none), image)


def test_the_cache_keeps_the_newest_render_of_each_pixel_and_fills_the_rest():
    cache = RenderCache(views=3, height=24, width=32)
    image = _smooth()
    view = torch.tensor([1])
    gen = torch.Generator().manual_seed(1)
    for _ in range(400):  # single random rays, as a NeRF batch
        x, y = torch.randint(32, (1,), generator=gen), torch.randint(24, (1,), generator=gen)
        window = Window(x, y, 1, 1)
        cache.write(view, window, RenderOutput(rgb=window.crop(image), depth=torch.full((1, 1, 1, 1), 2.0)))
    coverage = cache.known.float().mean((1, 2, 3))
    assert 0.3 < coverage[1] < 0.6 and coverage[0] == 0
    whole = Window(torch.zeros(1, dtype=torch.long), torch.zeros(1, dtype=torch.long), 32, 24)
    read = cache.read(view, whole)
    assert read.rgb.shape == (1, 3, 24, 32) and read.depth.shape == (1, 1, 24, 32)
    assert (read.rgb - image).abs().max() < 3 / 24 and torch.allclose(read.depth, torch.tensor(2.0))
    # a newer render of a window replaces the old one there
    patch = Window(torch.tensor([4]), torch.tensor([2]), 8, 8)
    cache.write(view, patch, RenderOutput(rgb=torch.full((1, 3, 8, 8), 0.25)))
    assert torch.allclose(patch.crop(cache.read(view, whole).rgb), torch.tensor(0.25))
    # a pixel drawn twice in one batch keeps the later render, whatever the thread timing
    twice = Window(torch.tensor([3, 3]), torch.tensor([7, 7]), 1, 1)
    cache.write(torch.tensor([2, 2]), twice, RenderOutput(rgb=torch.tensor([0.1, 0.9]).view(2, 1, 1, 1).expand(2, 3, 1, 1)))
    assert torch.allclose(cache.rgb[2, 7, 3].float(), torch.tensor(0.9), atol=1e-3)
    restored = RenderCache(views=3, height=24, width=32)
    restored.load_state_dict(cache.state_dict())
    assert torch.equal(restored.read(view, whole).rgb, cache.read(view, whole).rgb)


def test_the_layer_cache_predicts_a_view_whole_once_and_reads_any_window_of_it():
    calls = []

    def predict(views, window):  # a view's layer: its index plus a ramp across the image
        calls.append((views.tolist(), window.width, window.height))
        ramp = torch.arange(8.0) / 8
        return (views.float().view(-1, 1, 1, 1) + ramp).expand(-1, 3, 6, -1)

    cache = LayerCache(views=3, height=6, width=8)
    rays = Window(torch.tensor([5, 1, 7]), torch.tensor([0, 3, 5]), 1, 1)
    got = cache.read(torch.tensor([2, 2, 0]), rays, predict)
    assert calls == [([0, 2], 8, 6)]  # the missing views, each once, whole
    assert got.shape == (3, 3, 1, 1)
    assert torch.allclose(got[:, 0, 0, 0], torch.tensor([2 + 5 / 8, 2 + 1 / 8, 7 / 8]), atol=1e-2)
    patch = Window(torch.tensor([2]), torch.tensor([1]), 4, 3)
    assert torch.allclose(cache.read(torch.tensor([0]), patch, predict)[0, 1, 2], torch.arange(2.0, 6) / 8)
    assert len(calls) == 1  # known views are read, not predicted again
    cache.write(torch.tensor([2]), torch.full((1, 3, 6, 8), 0.5))  # a newer prediction replaces it
    assert torch.allclose(cache.read(torch.tensor([2]), rays[0], predict), torch.tensor(0.5))
    restored = LayerCache(views=3, height=6, width=8)
    restored.load_state_dict(cache.state_dict())
    assert torch.equal(restored.read(torch.tensor([0, 2]), patch, predict), cache.read(torch.tensor([0, 2]), patch, predict))
    assert len(calls) == 1
    # a layer of any channel count (an occluding head's colour and alpha)
    four = LayerCache(views=2, height=6, width=8)
    assert four.read(torch.tensor([1]), rays[:1], lambda v, w: torch.ones(len(v), 4, 6, 8)).shape == (1, 4, 1, 1)


SMALL = ["trainer.max_iters=8", "phases.warmup.end=0.5", "phases.warmup.patches=64",
         "phases.joint.patch_size=8", "field.resolution_final=32", "trainer.device=cpu",
         "trainer.progress=false", "trainer.eval_every=0", "trainer.checkpoint_every=0", "trainer.log_every=1"]


def _joint_terms(run_dir) -> dict:
    import json

    records = [json.loads(line) for line in (run_dir / "log.jsonl").read_text().splitlines()]
    return [r["terms"] for r in records if r.get("phase") == "joint" and "terms" in r][-1]


def test_a_phase_with_head_views_trains_the_head_on_whole_cached_views(tiny_scene_dir, tmp_path):
    from rainyscape import config
    from rainyscape.workflow import train_and_evaluate

    common = [f"data={tiny_scene_dir}", *SMALL]
    on = train_and_evaluate(config.method_config("rainyscape-nerf", common + [f"trainer.output_dir={tmp_path}/on"]))
    terms = _joint_terms(on.run_dir)
    assert {"cached_views.reconstruction", "cached_views.likelihood"} <= set(terms)
    off = train_and_evaluate(config.method_config(
        "rainyscape-nerf", common + ["phases.joint.head_views=0", "phases.joint.rays=0",
                                     f"trainer.output_dir={tmp_path}/off"]))
    assert not any(k.startswith("cached_views.") for k in _joint_terms(off.run_dir))


def test_head_views_without_heads_or_a_refresh_without_head_views_is_a_config_error(tiny_scene_dir, tmp_path):
    from rainyscape import config
    from rainyscape.errors import ConfigError
    from rainyscape.workflow import train_and_evaluate

    cfg = config.method_config("nerf", [f"data={tiny_scene_dir}", "phases.fit.head_views=1",
                                        f"trainer.output_dir={tmp_path}", "trainer.max_iters=8", *SMALL[4:]])
    with pytest.raises(ConfigError, match="head_views"):
        train_and_evaluate(cfg)
    cfg = config.method_config("nerf", [f"data={tiny_scene_dir}", "phases.fit.refresh_every=5",
                                        f"trainer.output_dir={tmp_path}", "trainer.max_iters=8", *SMALL[4:]])
    with pytest.raises(ConfigError, match="refresh_every=5.*head_views"):
        train_and_evaluate(cfg)


# the recipe's mixed joint batch, small: patches for every term, single rays for the per-pixel ones
MIXED_JOINT = ["phases.joint.patches=4", "phases.joint.patch_size=4", "phases.joint.rays=64"]


def test_a_joint_step_with_rays_gives_them_the_per_pixel_terms_only(tiny_scene_dir, tmp_path):
    from rainyscape import config
    from rainyscape.workflow import train_and_evaluate

    cfg = config.method_config("rainyscape-nerf", [f"data={tiny_scene_dir}", *SMALL, *MIXED_JOINT,
                                                   f"trainer.output_dir={tmp_path}"])
    terms = _joint_terms(train_and_evaluate(cfg).run_dir)
    assert {"likelihood", "reconstruction", "tv", "agr"} <= set(terms)  # the patches
    assert {k for k in terms if k.startswith("rays.")} == {"rays.likelihood", "rays.reconstruction"}
    assert {"cached_views.reconstruction", "cached_views.agr"} <= set(terms)


def test_rays_fit_the_field_to_the_input_less_the_cached_rain_and_leave_the_head_alone(tiny_scene, tmp_path):
    from rainyscape import config
    from rainyscape.engine.pipeline import build_pipeline
    from rainyscape.engine.trainer import Trainer

    cfg = config.method_config("rainyscape-nerf", [*SMALL, *MIXED_JOINT, "phases.warmup.end=0.0"])
    pipeline = build_pipeline(cfg, tiny_scene, torch.device("cpu"))
    trainer = Trainer(pipeline, tmp_path)
    name, phase = trainer.phases.at(0)
    views = torch.arange(tiny_scene.num_images)
    losses = {}
    for rain in (0.0, 0.3):
        trainer.generator.manual_seed(5)  # the same rays
        trainer.layer_caches["rain"].write(views, torch.full((len(views), 3, tiny_scene.height, tiny_scene.width), rain))
        pipeline.field.zero_grad(set_to_none=True)
        total, values = trainer._ray_losses(name, phase, [pipeline.rain_head], pipeline.loss_terms(name))
        total.backward()
        assert set(values) == {"likelihood", "reconstruction"}
        assert all(p.grad is None for p in pipeline.rain_head.parameters())
        assert any(p.grad is not None and bool(p.grad.abs().sum() > 0) for p in pipeline.field.parameters())
        losses[rain] = values["reconstruction"]
    assert losses[0.0] != pytest.approx(losses[0.3])  # the cached rain is what the rays are fitted against


def test_rays_with_heads_need_whole_views(tiny_scene_dir, tmp_path):
    from rainyscape import config
    from rainyscape.errors import ConfigError
    from rainyscape.workflow import train_and_evaluate

    cfg = config.method_config("rainyscape-nerf", [f"data={tiny_scene_dir}", *SMALL, *MIXED_JOINT,
                                                   "phases.joint.head_views=0", f"trainer.output_dir={tmp_path}"])
    with pytest.raises(ConfigError, match="head_views"):
        train_and_evaluate(cfg)


def test_a_refresh_renders_one_training_view_whole_into_the_cache_in_turn(tiny_scene, tmp_path):
    from rainyscape import config
    from rainyscape.engine.pipeline import build_pipeline
    from rainyscape.engine.trainer import Trainer
    from rainyscape.eval.views import render_view

    cfg = config.method_config("rainyscape-nerf", [*SMALL, *MIXED_JOINT, "phases.warmup.end=0.0",
                                                   "phases.joint.refresh_every=2"])
    pipeline = build_pipeline(cfg, tiny_scene, torch.device("cpu"))
    trainer = Trainer(pipeline, tmp_path)
    cache, pool = trainer.render_cache, trainer.train_pool
    assert not bool(cache.known.any())
    trainer._refresh_cache(len(pool) + 1)  # turns go round the training views
    view = int(pool[1])
    assert bool(cache.known[view].all()) and int(cache.known.sum()) == cache.known[view].numel()
    assert pipeline.field.training  # the field trains on after the refresh
    fresh = render_view(pipeline, view).rgb
    assert torch.allclose(cache.rgb[view].permute(2, 0, 1).float(), fresh[0], atol=2e-3)  # half precision
    # in the joint phase, step 0 refreshes the first training view whole
    trainer2 = Trainer(build_pipeline(cfg, tiny_scene, torch.device("cpu")), tmp_path / "steps")
    trainer2.train_step()
    assert bool(trainer2.render_cache.known[int(pool[0])].all())
