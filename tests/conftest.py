"""Shared fixtures: a tiny simulated rainy scene (Maya layout) and its parsed SceneData.

``tiny_scene_dir``: 3 x 4 = 12 views at 48 x 48 px of the demo street in static rain, with
clean images, depth and the ground-truth rain layer (generated once per test session, ~2 s).
Fewer, larger drops than the demo's (rainy vs clean about 28 dB at 48 px).
``tiny_scene``: that folder read by the maya-csv parser (every 8th view held out, world
normalised), with the point cloud the field's unit tests start from: back-projected from the
simulator's depth by the explicit ``points_from_depth=true`` (off by default: training never
sees ground truth unasked; at 48 px triangulation finds too few points to test with).
"""

from __future__ import annotations

import pytest


@pytest.fixture(scope="session")
def tiny_scene_dir(tmp_path_factory):
    from rainyscape.synth import generate

    return generate(tmp_path_factory.mktemp("tiny_scene") / "scene", "demo", rows=3, cols=4,
                    width=48, height=48, mode="static", seed=0, size_scale=6.0, density=0.5)


@pytest.fixture(scope="session")
def tiny_scene(tiny_scene_dir):
    from rainyscape.dataparsers.maya_csv import MayaCsvConfig, MayaCsvParser

    return MayaCsvParser(MayaCsvConfig(points_from_depth=True)).parse(tiny_scene_dir)
