"""rs-process-data never deletes what it did not write: sentinel user files survive byte for
byte every refusal and every failure (real files, real pycolmap for the SfM failure).

The successful --overwrite of an earlier scene is in test_process_video.py (it needs photos
that register)."""

from __future__ import annotations

import json
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest

from rainyscape.cli import run_cli
from rainyscape.cli.process_data import main as process_main
from rainyscape.errors import DataError
from rainyscape.formats import output as moves_module
from rainyscape.process.output import REPORT, WRITTEN_KEY, is_record, scene_files, staged_scene

FAST = ["--max-features", "1024", "--num-threads", "2", "--quiet"]


def snapshot(root: Path) -> dict[str, bytes | None]:
    """Every file (its bytes) and folder (None) below ``root``, by relative path."""
    return {p.relative_to(root).as_posix(): (None if p.is_dir() else p.read_bytes())
            for p in sorted(root.rglob("*"))}


def noise_photos(folder: Path, count: int = 3) -> Path:
    """Photos with nothing in common: SfM extracts and matches features, then registers none."""
    folder.mkdir(parents=True)
    rng = np.random.default_rng(0)
    for k in range(count):
        iio.imwrite(folder / f"{k}.png", rng.integers(0, 256, (64, 64, 3), dtype=np.uint8))
    return folder


def texture_video(path: Path, count: int = 3) -> Path:
    rng = np.random.default_rng(1)
    frames = rng.integers(0, 256, (count, 64, 64, 3), dtype=np.uint8)
    iio.imwrite(path, frames, fps=10, codec="libx264", macro_block_size=1)
    return path


def user_files(folder: Path) -> None:
    """What a user keeps in a folder: files at the top, in a folder of their own, and in a
    folder named like one the tool writes."""
    (folder / "colmap").mkdir(parents=True)
    (folder / "colmap" / "my.ini").write_text("x\n")
    (folder / "notes.txt").write_text("my notes\n")
    (folder / "renders").mkdir()
    (folder / "renders" / "a.bin").write_bytes(bytes(range(256)))


def earlier_scene(folder: Path) -> None:
    """A scene as an earlier run left it: its entries and a report listing them."""
    (folder / "sparse" / "0").mkdir(parents=True)
    (folder / "sparse" / "0" / "cameras.bin").write_bytes(b"\x01\x02")
    (folder / "images").mkdir()
    (folder / "images" / "0.png").write_bytes(b"png")
    (folder / "transforms.json").write_text("{}")
    (folder / REPORT).write_text(json.dumps({WRITTEN_KEY: scene_files(folder)}))


def cli(args: list[str], capsys) -> tuple[int, list[str]]:
    code = run_cli(process_main, args)
    err = capsys.readouterr().err.strip().splitlines()
    assert not any("Traceback" in line for line in err)
    return code, err


def test_a_missing_video_deletes_nothing_and_writes_nothing(tmp_path, capsys):
    out = tmp_path / "P"
    user_files(out)
    before = snapshot(tmp_path)
    code, err = cli(["video", "--data", str(tmp_path / "fake.mp4"), "--output-dir", str(out)], capsys)
    assert code == 2 and err[-1].startswith("error: ") and "fake.mp4: no such video file" in err[-1]
    assert snapshot(tmp_path) == before


@pytest.mark.parametrize("case, message", [("missing", "no such video file"),
                                           ("unreadable", "cannot read the video"),
                                           ("one_frame", "too few frames")])
def test_bad_input_fails_before_anything_is_written(tmp_path, capsys, case, message):
    video = tmp_path / "clip.mp4"
    if case == "unreadable":
        video.write_text("this is not a video")
    elif case == "one_frame":
        texture_video(video, count=1)
    before = snapshot(tmp_path)
    code, err = cli(["video", "--data", str(video), "--output-dir", str(tmp_path / "new" / "P")], capsys)
    assert code == 2 and len(err) == 1 and message in err[0] and "clip.mp4" in err[0]
    assert snapshot(tmp_path) == before  # not even the output's parent folder


def test_a_folder_of_user_files_is_refused_with_or_without_overwrite(tmp_path, capsys):
    out = tmp_path / "P"
    user_files(out)
    video = texture_video(tmp_path / "clip.mp4")
    before = snapshot(tmp_path)
    code, err = cli(["video", "--data", str(video), "--output-dir", str(out)], capsys)
    assert code == 2 and "not empty" in err[-1] and "--overwrite" in err[-1]
    assert snapshot(tmp_path) == before
    code, err = cli(["video", "--data", str(video), "--output-dir", str(out), "--overwrite"], capsys)
    assert code == 2 and "my.ini: not written by rs-process-data" in err[-1]
    assert snapshot(tmp_path) == before


def test_an_output_folder_holding_the_input_is_refused(tmp_path, capsys):
    out = tmp_path / "P"
    photos = noise_photos(out / "images")
    (out / "notes.txt").write_text("my notes\n")
    before = snapshot(tmp_path)
    code, err = cli(["images", "--data", str(photos), "--output-dir", str(out), "--overwrite"], capsys)
    assert code == 2 and len(err) == 1 and "the output folder contains the input" in err[0]
    code, err = cli(["images", "--data", str(photos), "--output-dir", str(photos / "scene")], capsys)
    assert code == 2 and "inside the input folder" in err[-1]
    video = texture_video(out / "clip.mp4")
    before = snapshot(tmp_path)
    code, err = cli(["video", "--data", str(video), "--output-dir", str(out), "--overwrite"], capsys)
    assert code == 2 and "contains the input" in err[-1]
    assert snapshot(tmp_path) == before


def test_an_output_that_cannot_be_written_is_one_line(tmp_path, capsys):
    photos = noise_photos(tmp_path / "photos")
    (tmp_path / "a_file").write_text("mine\n")
    before = snapshot(tmp_path)
    for out in (tmp_path / "a_file", tmp_path / "a_file" / "scene"):
        code, err = cli(["images", "--data", str(photos), "--output-dir", str(out)], capsys)
        assert code == 2 and len(err) == 1 and err[0].startswith(f"error: {out}: ")
    assert snapshot(tmp_path) == before


def test_a_failure_half_way_through_sfm_leaves_the_output_as_it_was(tmp_path, capsys):
    photos = noise_photos(tmp_path / "photos")
    out = tmp_path / "P"
    earlier_scene(out)
    (out / "notes.txt").write_text("my notes\n")
    before = snapshot(tmp_path)
    code, err = cli(["images", "--data", str(photos), "--output-dir", str(out), "--overwrite", *FAST], capsys)
    assert code == 2 and "registered no frames" in err[-1]  # after features, matching and mapping
    assert snapshot(tmp_path) == before  # the earlier scene too; no staging folder left beside it
    code, err = cli(["images", "--data", str(photos), "--output-dir", str(tmp_path / "a" / "b"), *FAST],
                    capsys)
    assert code == 2 and snapshot(tmp_path) == before  # the parent folders made for it are gone


def test_a_failure_while_moving_into_place_puts_everything_back(tmp_path, monkeypatch):
    out = tmp_path / "P"
    earlier_scene(out)
    (out / "notes.txt").write_text("my notes\n")
    before = snapshot(tmp_path)
    real_move, moves = moves_module.move_entry, []

    def failing_move(src: Path, dst: Path) -> None:
        moves.append(src)
        if len(moves) == 4:  # old images out, new images in, old sparse out, then new sparse fails
            raise OSError(28, "No space left on device")
        real_move(src, dst)

    monkeypatch.setattr(moves_module, "move_entry", failing_move)  # what move_all calls
    with pytest.raises(DataError, match="cannot move the new scene into place .*as it was"):
        with staged_scene(tmp_path / "photos", out, overwrite=True) as staging:
            for name in ("images", "sparse"):
                (staging / name).mkdir()
                (staging / name / "new.bin").write_bytes(b"new")
            (staging / REPORT).write_text(json.dumps({WRITTEN_KEY: scene_files(staging)}))
    assert snapshot(tmp_path) == before


def test_overwrite_replaces_only_the_entries_the_tool_writes(tmp_path):
    out = tmp_path / "P"
    earlier_scene(out)
    (out / "notes.txt").write_text("my notes\n")
    with staged_scene(tmp_path / "photos", out, overwrite=True) as staging:
        (staging / "images").mkdir()
        (staging / "images" / "new.png").write_bytes(b"new")
        (staging / REPORT).write_text(json.dumps({WRITTEN_KEY: scene_files(staging)}))
    after = snapshot(out)
    assert after["notes.txt"] == b"my notes\n" and after["images/new.png"] == b"new"
    assert "images/0.png" not in after  # the earlier run's own file, replaced
    assert "sparse" not in after and "transforms.json" not in after  # one scene, not two mixed
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".P.partial-")]


def test_records_are_the_report_and_the_colmap_work_folder():
    assert is_record(Path("process_report.json")) and is_record(Path("colmap/database.db"))
    assert not is_record(Path("images/001.png")) and not is_record(Path("transforms.json"))
    assert not is_record(Path("sparse/0/images.bin"))
