"""The oracle 3D row: the clean scene re-rendered, scored against the stored clean images on
the training and held-out views as the methods' dataparser splits them."""

from __future__ import annotations

import sys
import types

import numpy as np
import pytest
from PIL import Image

from rainyscape.comparison.oracle import ORACLE_SAMPLES, cached_oracle, scene_oracle
from rainyscape.config import method_config


def _cfg():
    return method_config("nerf", [])


def test_folders_the_simulator_did_not_make_have_no_oracle(tmp_path):
    entry = scene_oracle(str(tmp_path), _cfg())
    assert entry["available"] is False and "not a simulated scene folder" in entry["reason"]
    assert cached_oracle(entry, str(tmp_path))  # n/a for as long as the reason holds
    (tmp_path / "scene.json").write_text("{}")
    assert not cached_oracle(entry, str(tmp_path))


def test_oracle_scores_the_rerender_against_the_stored_clean_views(tiny_scene_dir, tiny_scene, monkeypatch):
    """With a stand-in re-render (the stored clean view plus a known error) the oracle's numbers
    are known: it reads the right view for every image and splits like the dataparser."""
    calls = []

    def rerender_clean(scene_dir, view_index, samples=2):
        calls.append((view_index, samples))
        img = np.asarray(Image.open(tiny_scene_dir / "images_wo_rain" / f"{view_index + 1:03d}.png"), dtype=np.float64)
        return np.clip(img[..., :3] / 255.0 + 0.01, 0, 1)  # 40 dB where nothing clips

    monkeypatch.setitem(sys.modules, "rainyscape.synth.oracle", types.SimpleNamespace(rerender_clean=rerender_clean))
    entry = scene_oracle(str(tiny_scene_dir), _cfg())
    split = {"train": len(tiny_scene.train_indices), "heldout": len(tiny_scene.eval_indices)}
    assert entry["available"] and entry["views"] == split and split["heldout"] >= 1  # the methods' split
    assert sorted(v for v, _ in calls) == list(range(12)) and {s for _, s in calls} == {ORACLE_SAMPLES}
    for split in ("train", "heldout"):
        assert entry[split]["psnr"] == pytest.approx(40.0, abs=0.5) and entry[split]["ssim"] > 0.99
    assert cached_oracle(entry, str(tiny_scene_dir)) and not cached_oracle(entry, "/elsewhere")


def test_oracle_of_a_real_generated_scene(tiny_scene_dir):
    entry = scene_oracle(str(tiny_scene_dir), _cfg())
    assert entry["available"], entry.get("reason")
    # an independent sample set of the same clean scene: far above any method, below identity
    for split in ("train", "heldout"):
        assert 30 < entry[split]["psnr"] < 70 and entry[split]["ssim"] > 0.95
