"""Distractor scenes: each view has its own transient objects, the clean views are the rain
presets' static scene, and the ground-truth layer holds exactly the pixels they change."""

from __future__ import annotations

import json

import numpy as np
import pytest

from rainyscape.errors import ConfigError
from rainyscape.synth import generate
from rainyscape.synth.presets import DISTRACTOR_PRESETS, PRESETS
from rainyscape.synth.transients import TransientConfig


def _png(path):
    from rainyscape.dataparsers.images import read_rgb, read_rgba

    return read_rgba(path) if path.parent.name == "rain" else read_rgb(path)


@pytest.fixture(scope="module")
def leaves(tmp_path_factory):
    return generate(tmp_path_factory.mktemp("transients") / "leaves", "yard-leaves", rows=1, cols=2,
                    width=40, height=40)


def test_distractor_presets_have_transients_and_no_rain():
    assert DISTRACTOR_PRESETS and all(PRESETS[p].transients and PRESETS[p].rain["density"] == 0
                                      for p in DISTRACTOR_PRESETS)
    with pytest.raises(ConfigError, match="unknown transient option 'ghosts'"):
        TransientConfig.of({"ghosts": 2})


def test_transients_change_only_their_pixels_and_differ_between_views(leaves, tmp_path):
    info = json.loads((leaves / "scene.json").read_text())
    assert info["transients"]["leaves"] == 40 and info["drops"] == 0
    masks = []
    for name in ("001", "002"):
        rainy = _png(leaves / "images_rain" / f"{name}.png").astype(int)
        clean = _png(leaves / "images_wo_rain" / f"{name}.png").astype(int)
        layer = _png(leaves / "rain" / f"{name}.png")
        alpha = layer[..., 3]
        assert set(np.unique(alpha)) <= {0, 255}  # opaque objects: all or nothing
        inside = alpha == 255
        assert 0.005 < inside.mean() < 0.6
        assert np.array_equal(rainy[~inside], clean[~inside])  # the rest is the clean view, exactly
        assert np.array_equal(layer[..., :3][inside], rainy[inside].astype(np.uint8))  # I = C where A = 1
        masks.append(inside)
    assert not np.array_equal(masks[0], masks[1])
    # the clean views are the static scene: those of the rain preset on the same scene
    rain = generate(tmp_path / "yard", "yard", rows=1, cols=2, width=40, height=40)
    for name in ("001", "002"):
        assert np.array_equal(_png(rain / "images_wo_rain" / f"{name}.png"),
                              _png(leaves / "images_wo_rain" / f"{name}.png"))


def test_a_render_like_another_reproduces_it_exactly():
    """Rendering a view with another render's edge samples (the transients' path) changes
    nothing where the scene is the same."""
    from rainyscape.synth.rig import make_rig
    from rainyscape.synth.raycast import SceneRenderer
    from rainyscape.synth.scenes import build_scene

    spec = build_scene("yard", 0)
    cams = make_rig(spec.rig, 1, 1, 24, 24, "sphere").cameras()
    renderer = SceneRenderer(spec)
    first = renderer.render(cams, 0)
    again = renderer.render(cams, 0, like=first)
    assert np.array_equal(first.rgb, again.rgb) and first.edge_samples == again.edge_samples
