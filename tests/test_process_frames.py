"""Frames from a video or a photo folder, and rs-process-data's errors on bad inputs."""

from __future__ import annotations

from pathlib import Path

import cv2
import imageio.v3 as iio
import numpy as np
import pytest

from rainyscape.cli import run_cli
from rainyscape.cli.process_data import main as process_main
from rainyscape.errors import DataError
from rainyscape.process.frames import (FrameOptions, copy_photos, extract_video_frames,
                                       frame_windows, laplacian_variance, prepare_frame)


def texture(seed: int, size=(64, 64)) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return rng.integers(0, 256, (*size, 3), dtype=np.uint8)


def write_video(path: Path, frames: np.ndarray, fps: int = 10) -> Path:
    iio.imwrite(path, frames, fps=fps, codec="libx264", macro_block_size=1)
    return path


def test_frame_windows_cut_the_clip_evenly():
    assert frame_windows(10, 5).tolist() == [0, 0, 1, 1, 2, 2, 3, 3, 4, 4]
    assert frame_windows(7, 3).tolist() == [0, 0, 0, 1, 1, 2, 2]
    assert frame_windows(3, 10).tolist() == [0, 1, 2]  # shorter clip: every frame


def test_laplacian_variance_ranks_blur_below_sharp():
    sharp = texture(0)
    blurred = cv2.GaussianBlur(sharp, (0, 0), 2.0)
    assert laplacian_variance(sharp) > 5 * laplacian_variance(blurred)


def test_sharpest_frame_of_each_window_is_kept(tmp_path):
    base = texture(1)
    frames, sharp_index = [], [1, 3, 8, 9]  # one sharp frame in each window of three
    for i in range(12):
        frames.append(base if i in sharp_index else cv2.GaussianBlur(base, (0, 0), 2.5))
    video = write_video(tmp_path / "clip.mp4", np.stack(frames))
    kept = extract_video_frames(video, tmp_path / "out", FrameOptions(num_frames=4), progress=False)
    assert [f.source for f in kept] == [str(i) for i in sharp_index]
    assert [f.name for f in kept] == [f"frame_{k:05d}.png" for k in range(1, 5)]
    assert all((tmp_path / "out" / f.name).is_file() for f in kept)


def test_crop_and_max_side():
    rgb = np.zeros((100, 200, 3), np.uint8)
    out = prepare_frame(rgb, FrameOptions(crop=(0.1, 0.1, 0.25, 0.25), max_side=50))
    assert out.shape == (40, 50, 3)  # 80 x 100 after the crop, then the long side to 50


def test_written_pngs_have_no_exif(tmp_path):
    from PIL import Image

    folder = tmp_path / "photos"
    folder.mkdir()
    exif = Image.Exif()
    exif[0x0112] = 6  # orientation: the camera was turned 90 degrees
    for k in range(2):
        Image.fromarray(texture(k, (32, 48))).save(folder / f"p{k}.jpg", exif=exif)
    frames = copy_photos(folder, tmp_path / "out", FrameOptions(), progress=False)
    with Image.open(tmp_path / "out" / frames[0].name) as im:
        assert im.format == "PNG" and not im.getexif()
        assert im.size == (32, 48)  # turned upright by the EXIF orientation


def test_exif_focal_length_becomes_pixels_of_the_written_frame(tmp_path):
    """A 26 mm equivalent lens (a phone's) on a 1080 x 1440 photo is 26 / 43.27 x 1800 px; a
    resize scales it, a crop does not; photos that disagree or lack it give no prior."""
    from PIL import Image

    from rainyscape.process.frames import (Frame, exif_focal_35mm, focal_pixels, frame_scale,
                                           shared_focal)

    assert focal_pixels(26.0, 1080, 1440) == pytest.approx(1081.67, abs=0.01)
    assert frame_scale((1440, 1080), FrameOptions(max_side=720)) == pytest.approx(0.5)
    assert frame_scale((1440, 1080), FrameOptions(crop=(0.25, 0.25, 0, 0))) == 1.0
    # cropped to 720 x 1080, then the long side to 540: half the pixels per unit of angle
    assert frame_scale((1440, 1080), FrameOptions(crop=(0.25, 0.25, 0, 0), max_side=540)) == pytest.approx(0.5)

    folder = tmp_path / "photos"
    folder.mkdir()
    exif = Image.Exif()
    exif.get_ifd(0x8769)[0xA405] = 26  # FocalLengthIn35mmFilm
    for k in range(2):
        Image.fromarray(texture(k, (96, 72))).save(folder / f"p{k}.jpg", exif=exif)
    Image.fromarray(texture(5, (96, 72))).save(tmp_path / "bare.jpg")
    assert exif_focal_35mm(folder / "p0.jpg") == 26.0
    assert exif_focal_35mm(tmp_path / "bare.jpg") is None
    frames = copy_photos(folder, tmp_path / "out", FrameOptions(max_side=48), progress=False)
    expected = focal_pixels(26.0, 72, 96) * 0.5
    assert [f.focal_px for f in frames] == pytest.approx([expected, expected])
    assert shared_focal(frames) == pytest.approx(expected)
    assert shared_focal([*frames, Frame("x.png", "x.jpg", 1.0, None)]) is None  # one without
    assert shared_focal([*frames, Frame("x.png", "x.jpg", 1.0, expected * 1.5)]) is None  # a zoom


@pytest.mark.parametrize("case, message", [
    ("unreadable", "cannot read the video"),
    ("empty", "cannot read the video"),
    ("missing", "no such video file"),
    ("one_frame", "too few frames"),
])
def test_bad_videos_fail_clearly(tmp_path, case, message):
    video = tmp_path / "clip.mp4"
    if case == "unreadable":
        video.write_text("this is not a video")
    elif case == "empty":
        video.write_bytes(b"")
    elif case == "one_frame":
        write_video(video, texture(2)[None])
    with pytest.raises(DataError, match=message):
        extract_video_frames(video, tmp_path / "out", FrameOptions(), progress=False)


@pytest.mark.parametrize("case, message", [
    ("no_images", "no images found"),
    ("one_image", "too few images"),
    ("not_a_folder", "no such folder"),
    ("mixed_sizes", "differ in size"),
    ("broken_image", "cannot read the image"),
])
def test_bad_photo_folders_fail_clearly(tmp_path, case, message):
    folder = tmp_path / "photos"
    if case != "not_a_folder":
        folder.mkdir()
    (folder / "notes.txt").write_text("x") if folder.is_dir() else None
    if case == "one_image":
        iio.imwrite(folder / "a.png", texture(0))
    elif case == "mixed_sizes":
        iio.imwrite(folder / "a.png", texture(0))
        iio.imwrite(folder / "b.png", texture(1, (32, 64)))
    elif case == "broken_image":
        iio.imwrite(folder / "a.png", texture(0))
        (folder / "b.jpg").write_bytes(b"not a jpeg")
    with pytest.raises(DataError, match=message):
        copy_photos(folder, tmp_path / "out", FrameOptions(), progress=False)


def test_cli_reports_bad_input_in_one_line(tmp_path, capsys):
    empty = tmp_path / "photos"
    empty.mkdir()
    code = run_cli(process_main, ["images", "--data", str(empty), "--output-dir", str(tmp_path / "s")])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2
    assert err[-1].startswith("error: ") and "no images found" in err[-1]
    assert not any("Traceback" in line for line in err)


def test_cli_refuses_to_overwrite_a_processed_scene(tmp_path, capsys):
    scene = tmp_path / "scene"
    (scene / "sparse").mkdir(parents=True)
    video = write_video(tmp_path / "clip.mp4", np.stack([texture(k) for k in range(3)]))
    code = run_cli(process_main, ["video", "--data", str(video), "--output-dir", str(scene)])
    assert code == 2 and "--overwrite" in capsys.readouterr().err
    assert (scene / "sparse").is_dir()  # untouched


def test_cli_rejects_bad_options(tmp_path, capsys):
    code = run_cli(process_main, ["video", "--data", "x.mp4", "--output-dir", str(tmp_path),
                                  "--num-frames", "1"])
    assert code == 2 and "--num-frames" in capsys.readouterr().err
    code = run_cli(process_main, ["video", "--data", "x.mp4", "--output-dir", str(tmp_path),
                                  "--camera-model", "FISHEYE_X"])
    assert code == 2  # argparse names the valid choices
