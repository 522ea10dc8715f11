"""rs-process-data end to end on a simulated rainy video: real pycolmap, real files.

A dynamic-rain video trajectory from the simulator (24 frames, 192 px) is written as an .mp4,
posed by `rs-process-data video`, read back by the colmap dataparser and compared with the
simulator's cameras after a similarity (Umeyama) alignment. The same renders also give a
static-camera clip (one view under moving rain) and a folder of JPEG photos (clean renders).
"""

from __future__ import annotations

import csv
import json
import shutil
import sys
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest
import torch

from rainyscape.cli import run_cli
from rainyscape.cli.process_data import main as process_main
from rainyscape.dataparsers.colmap import ColmapParser
from rainyscape.dataparsers.maya_math import maya_cameras
from rainyscape.dataparsers.transforms_json import TransformsJsonConfig, TransformsJsonParser
from rainyscape.process.align import aligned_pose_errors

FRAMES, SIZE = 24, 192
FAST = ["--max-features", "1024", "--num-threads", "2", "--quiet"]


@pytest.fixture(scope="module")
def rainy_video(tmp_path_factory) -> tuple[Path, Path]:
    """(simulator folder, clip.mp4) of a hand-held-like sweep in moving rain."""
    from rainyscape.synth import generate

    root = tmp_path_factory.mktemp("rain_video")
    # Rain pinned to a medium strength (about 27 dB rainy vs clean at 192 px).
    sim = generate(root / "sim", "demo", rows=1, cols=FRAMES, width=SIZE, height=SIZE,
                   mode="dynamic", trajectory="video", seed=0, density=22.0)
    frames = np.stack([iio.imread(p) for p in sorted((sim / "images_rain").glob("*.png"))])
    clip = root / "clip.mp4"
    iio.imwrite(clip, frames, fps=10, codec="libx264", macro_block_size=1)
    return sim, clip


def simulator_c2w(sim: Path) -> np.ndarray:
    """The simulator's cameras (OpenCV camera-to-world) from its cameras.csv."""
    with open(sim / "cameras.csv", newline="") as fh:
        rows = np.array([[float(v) for v in row[1:]] for row in list(csv.reader(fh))[1:]])
    cams = maya_cameras(rows[:, 0:3], rows[:, 3:6], rows[:, 6], rows[:, 7], rows[:, 8], SIZE, SIZE)
    return cams.c2w.double().numpy()


def test_rainy_video_is_posed_like_the_simulator(rainy_video, tmp_path):
    sim, clip = rainy_video
    scene_dir = tmp_path / "scene"
    code = run_cli(process_main, ["video", "--data", str(clip), "--output-dir", str(scene_dir),
                                  "--num-frames", str(FRAMES), *FAST])
    assert code == 0
    report = json.loads((scene_dir / "process_report.json").read_text())
    registration = report["registration"]
    print("registration:", registration, file=sys.stderr)
    assert registration["total"] == FRAMES
    assert registration["registered"] >= 0.9 * FRAMES
    assert registration["mean_reprojection_error_px"] < 1.5

    scene = ColmapParser(ColmapParser.Config(holdout_every=0)).parse(scene_dir)
    assert scene.num_images == registration["registered"]
    assert scene.points is not None and len(scene.points) > 100
    assert scene.point_colors.dtype.is_floating_point is False
    source = {f["name"]: int(f["source"]) for f in report["frames"]}
    truth = simulator_c2w(sim)[[source[name] for name in scene.image_names]]
    errors = aligned_pose_errors(scene.cameras.c2w.double().numpy(), truth)
    print(f"centre RMSE {100 * errors.center_rmse_fraction:.2f} % of the extent, rotation error "
          f"max {errors.rotation_deg.max():.2f} deg", file=sys.stderr)
    assert errors.center_rmse_fraction < 0.02, errors
    assert errors.rotation_deg.max() < 2.0, errors.rotation_deg

    # transforms.json describes the same cameras to other readers (here the transforms-json parser).
    other = TransformsJsonParser(TransformsJsonConfig(holdout_every=0)).parse(scene_dir)
    assert other.image_names == scene.image_names
    torch.testing.assert_close(other.cameras.c2w, scene.cameras.c2w, atol=1e-5, rtol=0)
    torch.testing.assert_close(other.cameras.fx, scene.cameras.fx)


def test_static_camera_fails_clearly(rainy_video, tmp_path, capsys):
    sim, _ = rainy_video
    # One clean view under the rain of eight frames: moving rain, no camera motion.
    clean = iio.imread(sim / "images_wo_rain" / "001.png").astype(np.float32)
    frames = []
    for k in range(1, 9):
        rain = iio.imread(sim / "rain" / f"{k:03d}.png").astype(np.float32) / 255.0
        alpha = rain[..., 3:]
        frames.append(np.clip(clean * (1 - alpha) + 255.0 * rain[..., :3] * alpha, 0, 255).astype(np.uint8))
    clip = tmp_path / "static.mp4"
    iio.imwrite(clip, np.stack(frames), fps=10, codec="libx264", macro_block_size=1)
    code = run_cli(process_main, ["video", "--data", str(clip), "--output-dir", str(tmp_path / "s"), *FAST])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2
    assert err[-1].startswith("error: ") and "registered" in err[-1] and "static" in err[-1]


def test_folder_of_jpeg_photos(rainy_video, tmp_path):
    # Every other clean render as a JPEG photo: 12 photos, twice as far apart as the frames.
    # (Rain on photos this small and far apart splits the model; benchmarks/sfm_rain.py
    # measures what rain does to registration.)
    sim, _ = rainy_video
    photos = tmp_path / "photos"
    photos.mkdir()
    for path in sorted((sim / "images_wo_rain").glob("*.png"))[::2]:
        iio.imwrite(photos / f"IMG_{path.stem}.jpg", iio.imread(path), quality=95)
    scene_dir = tmp_path / "scene"
    code = run_cli(process_main, ["images", "--data", str(photos), "--output-dir", str(scene_dir), *FAST])
    assert code == 0
    report = json.loads((scene_dir / "process_report.json").read_text())
    assert report["registration"]["registered"] == FRAMES // 2
    scene = ColmapParser(ColmapParser.Config(holdout_every=0)).parse(scene_dir)
    assert scene.image_names[0] == "IMG_001.png"
    truth = simulator_c2w(sim)[[int(n[4:7]) - 1 for n in scene.image_names]]
    errors = aligned_pose_errors(scene.cameras.c2w.double().numpy(), truth)
    assert errors.center_rmse_fraction < 0.02 and errors.rotation_deg.max() < 2.0, errors


def test_overwrite_replaces_the_scene_and_nothing_else(rainy_video, tmp_path, capsys):
    from rainyscape.process.output import REPORT, WRITTEN_KEY, scene_files

    sim, _ = rainy_video
    photos = tmp_path / "photos"
    photos.mkdir()
    for path in sorted((sim / "images_wo_rain").glob("*.png"))[::2]:
        shutil.copy(path, photos / path.name)
    scene_dir = tmp_path / "scene"
    args = ["images", "--data", str(photos), "--output-dir", str(scene_dir), *FAST]
    assert run_cli(process_main, args) == 0
    (scene_dir / "notes.txt").write_text("my notes\n")
    (scene_dir / "renders").mkdir()
    (scene_dir / "renders" / "a.bin").write_bytes(bytes(range(256)))
    capsys.readouterr()
    assert run_cli(process_main, args) == 2 and "--overwrite" in capsys.readouterr().err
    (scene_dir / "images" / "001.png").write_bytes(b"stale")  # the earlier run's file, edited
    assert run_cli(process_main, [*args, "--overwrite"]) == 0
    assert (scene_dir / "notes.txt").read_text() == "my notes\n"
    assert (scene_dir / "renders" / "a.bin").read_bytes() == bytes(range(256))
    assert (scene_dir / "images" / "001.png").read_bytes() != b"stale"
    report = json.loads((scene_dir / REPORT).read_text())
    assert report[WRITTEN_KEY] == scene_files(scene_dir)  # user files not claimed
    assert ColmapParser(ColmapParser.Config(holdout_every=0)).parse(scene_dir).num_images == FRAMES // 2
    assert not [p.name for p in tmp_path.iterdir() if ".partial-" in p.name]
    # A file of the user's inside a folder the tool writes: --overwrite refuses, touches nothing.
    (scene_dir / "sparse" / "0" / "my_edit.txt").write_text("mine\n")
    before = {p: p.read_bytes() for p in sorted(scene_dir.rglob("*")) if p.is_file()}
    assert run_cli(process_main, [*args, "--overwrite"]) == 2
    assert "my_edit.txt: not written by rs-process-data" in capsys.readouterr().err
    assert {p: p.read_bytes() for p in sorted(scene_dir.rglob("*")) if p.is_file()} == before
