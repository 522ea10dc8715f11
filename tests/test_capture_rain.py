"""Rain added to a capture in its own cameras (synth/capture_rain.py) and the real-capture
benchmark scenes made from it (comparison/captures.py)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from rainyscape.comparison.captures import Capture, benchmark_downscale, parse_capture, rainy_scene
from rainyscape.comparison.matrix import clean_overrides, has_clean_views
from rainyscape.dataparsers.transforms_json import TransformsJsonConfig, TransformsJsonParser
from rainyscape.errors import ConfigError
from rainyscape.imaging.angles import angle_difference_deg, estimate_rain_angles, streak_angle
from rainyscape.cameras import world_up
from rainyscape.synth.capture_rain import CaptureRain, add_rain, rain_frame

REPO = Path(__file__).resolve().parents[1]
FERN = next((p for p in (REPO.parent / "shared/data/real/fern", Path("/work/shared/data/real/fern"))
             if (p / "poses_bounds.npy").is_file()), None)


def _clean_capture(tiny_scene):
    """The tiny simulated scene's clean views as a capture without rain."""
    from dataclasses import replace

    return replace(tiny_scene, images=tiny_scene.clean_images, clean_images=None, rain_layers=None,
                   depths=None, points=None, point_colors=None)


def test_rain_frame_puts_up_against_the_cameras_down_axis():
    c2w = np.tile(np.eye(4), (3, 1, 1))
    c2w[:, :3, :3] = np.array([[1, 0, 0], [0, 0, 1], [0, -1, 0]])  # camera y (down) = world -z
    assert np.allclose(world_up(c2w), [0, 0, 1])
    rot = rain_frame(c2w)
    assert np.allclose(rot @ rot.T, np.eye(3), atol=1e-9) and np.allclose(rot @ [0, 0, 1], [0, 1, 0])


def test_added_rain_is_an_ordinary_scene_with_its_true_rain(tiny_scene, tmp_path):
    capture = _clean_capture(tiny_scene)
    out = add_rain(capture, tmp_path / "rainy", CaptureRain(level="heavy", mode="static"))
    info = json.loads((out / "scene.json").read_text())
    scene = TransformsJsonParser(TransformsJsonConfig()).parse(out)
    # the photos are the clean views, the rain is on top of them
    assert torch.equal(scene.clean_images, capture.images)
    assert scene.eval_indices == capture.eval_indices  # the capture's split is kept
    rainy, clean = scene.images.float() / 255, scene.clean_images.float() / 255
    assert (rainy - clean).abs().mean() > 0.01
    # the true rain layer is what the rainy view adds to the clean one (to 8-bit rounding)
    assert (rainy - clean - scene.rain_layers).abs().max() < 3 / 255
    # calibrated to the heavy label (21 dB), measured on every view
    assert abs(info["metrics"]["psnr_rainy_vs_clean"] - 21.0) < 1.5
    assert scene.metadata["rain_directions"] == 1


def test_static_rain_is_one_instant_and_dynamic_rain_moves(tiny_scene, tmp_path):
    capture = _clean_capture(tiny_scene)
    a = add_rain(capture, tmp_path / "a", CaptureRain(level="medium", mode="static", seed=3))
    b = add_rain(capture, tmp_path / "b", CaptureRain(level="medium", mode="static", seed=3))
    c = add_rain(capture, tmp_path / "c", CaptureRain(level="medium", mode="dynamic", seed=3))
    files = sorted((a / "rain").iterdir())
    same = [np.array_equal(_png(f), _png(b / "rain" / f.name)) for f in files]
    moved = [not np.array_equal(_png(f), _png(c / "rain" / f.name)) for f in files[1:]]
    assert all(same) and all(moved)  # deterministic; the first view is the same instant


def _png(path):
    import cv2

    return cv2.imread(str(path), cv2.IMREAD_UNCHANGED)


def test_rain_falls_down_the_photos_of_upright_cameras(tiny_scene, tmp_path):
    out = add_rain(_clean_capture(tiny_scene), tmp_path / "r", CaptureRain(level="heavy"))
    scene = TransformsJsonParser(TransformsJsonConfig()).parse(out)
    # the streaks' direction in the image: within 25 degrees of vertical (the heavy preset's
    # wind is 6 degrees; perspective tilts streaks away from the image centre)
    theta, valid = estimate_rain_angles(scene.rain_layers.permute(0, 3, 1, 2).abs())
    degrees = torch.rad2deg(streak_angle(theta[valid])).tolist()
    assert len(degrees) >= len(theta) // 2
    assert np.median([angle_difference_deg(d, 90.0) for d in degrees]) < 25


def test_bad_rain_options_are_refused(tiny_scene, tmp_path):
    for bad in (CaptureRain(level="drizzle"), CaptureRain(mode="sometimes"), CaptureRain(surface_m=0.5)):
        with pytest.raises(ConfigError):
            add_rain(_clean_capture(tiny_scene), tmp_path / "x", bad)


def test_the_clean_views_of_a_rainy_capture_train_the_ceiling(tiny_scene, tmp_path):
    out = add_rain(_clean_capture(tiny_scene), tmp_path / "r", CaptureRain(level="light"))
    assert has_clean_views(str(out))
    overrides = clean_overrides(str(out))
    assert overrides[0] == "dataparser=transforms-json"
    opts = {k.split(".", 1)[1]: v for k, v in (o.split("=", 1) for o in overrides[1:])}
    scene = TransformsJsonParser(TransformsJsonConfig(**opts)).parse(out)
    assert torch.equal(scene.images, scene.clean_images)  # trains on the photos, scored on them
    assert scene.eval_indices == TransformsJsonParser(TransformsJsonConfig()).parse(out).eval_indices


@pytest.mark.skipif(FERN is None, reason="the real captures (../shared/data/real) are not here")
def test_a_real_capture_becomes_a_cached_rainy_benchmark_scene(tmp_path):
    capture = Capture("fern", FERN, posed=True)
    assert benchmark_downscale(FERN) == 16  # images_8 (504 px) halved: 252 px, the CPU size
    label, folder = rainy_scene(capture, "medium", "dynamic", tmp_path)
    assert label == "fern-medium-dynamic"
    info = json.loads((folder / "scene.json").read_text())
    assert (info["width"], info["height"]) == (252, 189) and abs(info["calibrated_db"] - 26) < 1
    stamp = (folder / "scene.json").stat().st_mtime_ns
    assert rainy_scene(capture, "medium", "dynamic", tmp_path) == (label, folder)
    assert (folder / "scene.json").stat().st_mtime_ns == stamp  # made once
    scene = TransformsJsonParser(TransformsJsonConfig()).parse(folder)
    photos = parse_capture(FERN, 16)
    assert torch.equal(scene.clean_images, photos.images) and scene.points is None


def test_real_set_needs_a_captures_folder(tmp_path, monkeypatch):
    from rainyscape.comparison.captures import captures_root

    monkeypatch.delenv("RAINYSCAPE_CAPTURES", raising=False)
    with pytest.raises(ConfigError, match="captures=.*no such folder"):
        captures_root(str(tmp_path / "absent"))
    monkeypatch.setenv("RAINYSCAPE_CAPTURES", str(tmp_path))
    assert captures_root("") == tmp_path.resolve()


@pytest.mark.skipif(FERN is None, reason="the real captures (../shared/data/real) are not here")
def test_rs_bench_real_set_plans_every_strength_of_every_capture(tmp_path):
    from rainyscape.comparison.options import BenchOptions
    from rainyscape.comparison.plan import plan_bench

    (tmp_path / "caps").mkdir()
    (tmp_path / "caps" / "fern").symlink_to(FERN)
    plan = plan_bench(BenchOptions(methods="3dgs", scenes="real", captures=str(tmp_path / "caps"),
                                   out=str(tmp_path / "out")), [])
    assert [p.label for p in plan.scenes] == ["fern-light-static", "fern-medium-dynamic", "fern-heavy-static"]
    cells = plan.cells()
    ceiling = [c for c in cells if c.clean]
    assert len(ceiling) == 3 and "dataparser=transforms-json" in ceiling[0].overrides
    assert {b.pixels_per_step for b in plan.budgets.values()} == {252 * 189}
    assert {b.steps for b in plan.budgets.values()} == {18 * 100}  # the 3DGS recipe: 100 a training view


def test_a_capture_cache_follows_the_photos_content_not_their_times(tmp_path):
    import os
    import shutil

    from rainyscape.comparison.captures import _source_stamp

    photos = tmp_path / "a" / "images"
    photos.mkdir(parents=True)
    for i in range(3):
        (photos / f"{i}.jpg").write_bytes(bytes([i]) * 100)
    copy = tmp_path / "b"
    shutil.copytree(tmp_path / "a", copy)  # a fresh copy: new times, same photos
    os.utime(copy / "images" / "0.jpg", (1e9, 1e9))
    assert _source_stamp(copy) == _source_stamp(tmp_path / "a")
    # rs-process-data's report (its timings) and its COLMAP work folder do not count
    (copy / "process_report.json").write_text('{"timings_s": {"matching": 35.2}}')
    (copy / "colmap").mkdir()
    (copy / "colmap" / "database.db").write_bytes(b"pages")
    assert _source_stamp(copy) == _source_stamp(tmp_path / "a")
    (copy / "images" / "1.jpg").write_bytes(bytes([9]) * 100)  # same size, other content
    assert _source_stamp(copy) != _source_stamp(tmp_path / "a")


def test_photos_are_posed_into_the_same_benchmark_scenes_every_time(tmp_path):
    # A capture of photos without poses, posed in two separate scene caches: the same posed
    # folder and the same rainy scene, to the bit (rs-bench poses with --deterministic).
    import imageio.v3 as iio

    from rainyscape.synth import generate

    sim = generate(tmp_path / "sim", "demo", rows=1, cols=12, width=192, height=192, seed=0)
    photos = tmp_path / "captures" / "orbit" / "images"
    photos.mkdir(parents=True)
    for path in sorted((sim / "images_wo_rain").glob("*.png")):
        iio.imwrite(photos / f"{path.stem}.jpg", iio.imread(path), quality=95)
    capture = Capture("orbit", photos.parent, posed=False)
    made = [rainy_scene(capture, "light", "static", tmp_path / f"cache{k}") for k in (1, 2)]
    assert made[0][1].name == made[1][1].name
    posed = [next((tmp_path / f"cache{k}").glob("capture-orbit-posed-*")) for k in (1, 2)]
    assert posed[0].name == posed[1].name
    assert (posed[0] / "transforms.json").read_bytes() == (posed[1] / "transforms.json").read_bytes()
    assert len(json.loads((posed[0] / "transforms.json").read_text())["frames"]) >= 10
