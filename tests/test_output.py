"""formats/output.py: where a command may write, and building an output beside its folder."""

from __future__ import annotations

import pytest

from rainyscape.errors import DataError
from rainyscape.formats.output import check_can_create, make_folders, remove_made, staged_folder

ENTRIES = ("images", "scene.json", "extra.txt")


def _files(folder):
    return {str(p.relative_to(folder)): p.read_text() for p in sorted(folder.rglob("*")) if p.is_file()}


def _write(stage, views: int) -> None:
    (stage / "images").mkdir()
    for k in range(views):
        (stage / "images" / f"{k}.png").write_text(f"view {k}")
    (stage / "scene.json").write_text(f"{views} views")


def test_a_new_folder_appears_whole_and_its_parents_are_made(tmp_path):
    out = tmp_path / "a" / "b" / "out"
    with staged_folder(out, ENTRIES, force=False, writes="a scene") as stage:
        _write(stage, 2)
        assert not out.exists()  # nothing shows until the block ends
    assert _files(out) == {"images/0.png": "view 0", "images/1.png": "view 1", "scene.json": "2 views"}
    assert sorted(p.name for p in out.parent.iterdir()) == ["out"]  # no staging folder left


def test_force_replaces_every_entry_whole_and_keeps_the_rest(tmp_path):
    out = tmp_path / "out"
    with staged_folder(out, ENTRIES, force=False, writes="a scene") as stage:
        _write(stage, 3)
        (stage / "extra.txt").write_text("only the first run writes this")
    (out / "notes.txt").write_text("mine")
    with pytest.raises(DataError, match=r"not empty \(extra.txt, images, notes.txt, scene.json\).*force=true"):
        with staged_folder(out, ENTRIES, force=False, writes="a scene"):
            pass
    with staged_folder(out, ENTRIES, force=True, writes="a scene", last="scene.json") as stage:
        _write(stage, 1)
    # the old views and the entry this run did not write are gone; the user's file stays
    assert _files(out) == {"images/0.png": "view 0", "notes.txt": "mine", "scene.json": "1 views"}


def test_a_failure_leaves_the_folder_and_its_parents_as_they_were(tmp_path):
    out = tmp_path / "out"
    (out / "images").mkdir(parents=True)
    (out / "images" / "mine.png").write_text("mine")
    before = _files(tmp_path)
    for target, force in ((out, True), (tmp_path / "new" / "deeper" / "out", False)):
        with pytest.raises(MemoryError):
            with staged_folder(target, ENTRIES, force=force, writes="a scene") as stage:
                _write(stage, 2)
                raise MemoryError
    assert _files(tmp_path) == before and sorted(p.name for p in tmp_path.iterdir()) == ["out"]


def test_what_cannot_be_written_is_named_before_any_work(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    with pytest.raises(DataError, match=f"out={blocker / 'a' / 'b'}: {blocker} is a file, not a folder"):
        check_can_create(blocker / "a" / "b", "out")
    with pytest.raises(DataError, match="exists and is not a folder"):
        with staged_folder(blocker, ENTRIES, force=True, writes="a scene"):
            pass
    check_can_create(tmp_path / "not" / "yet", "out")  # creatable: fine, and nothing made
    assert not (tmp_path / "not").exists()
    made = make_folders(tmp_path / "x" / "y")
    assert made == [tmp_path / "x", tmp_path / "x" / "y"]
    remove_made(made)
    assert not (tmp_path / "x").exists()
