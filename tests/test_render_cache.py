"""The render cache (engine/render_cache.py): holes filled from the nearest rendered pixels,
the newest render of a pixel kept, a whole view read back after a run of random rays, and a
phase that trains heads on whole cached views."""

from __future__ import annotations

import pytest
import torch

from rainyscape.cameras import Window
from rainyscape.components import RenderOutput
from rainyscape.engine.render_cache import RenderCache, box_sum, fill_holes


def _smooth(h: int = 24, w: int = 32) -> torch.Tensor:
    y, x = torch.meshgrid(torch.linspace(0, 1, h), torch.linspace(0, 1, w), indexing="ij")
    return torch.stack([x, y, 0.5 * (x + y)])[None]  # (1, 3, h, w)


def test_box_sum_is_the_square_windows_sum():
    x = torch.rand(2, 1, 9, 11, generator=torch.Generator().manual_seed(2))
    for size in (3, 5, 9):
        square = torch.nn.functional.conv2d(x, torch.ones(1, 1, size, size), padding=size // 2)
        assert torch.allclose(box_sum(x, size), square, atol=1e-5)


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
        "rainyscape-nerf", common + ["phases.joint.head_views=0", f"trainer.output_dir={tmp_path}/off"]))
    assert not any(k.startswith("cached_views.") for k in _joint_terms(off.run_dir))


def test_head_views_without_heads_is_a_config_error(tiny_scene_dir, tmp_path):
    from rainyscape import config
    from rainyscape.errors import ConfigError
    from rainyscape.workflow import train_and_evaluate

    cfg = config.method_config("nerf", [f"data={tiny_scene_dir}", "phases.fit.head_views=1",
                                        f"trainer.output_dir={tmp_path}", "trainer.max_iters=8", *SMALL[4:]])
    with pytest.raises(ConfigError, match="head_views"):
        train_and_evaluate(cfg)
