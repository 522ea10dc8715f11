"""rs-bench-merge: results files trained apart, tabulated together."""

from __future__ import annotations

import json
import subprocess

from rainyscape.comparison.budget import Budget

GAUSS = Budget("gaussians", 10, 100.0, ()).to_dict()


def _record(scene: str, label: str, psnr: float, fingerprint: str = "f") -> dict:
    return {"status": "finished", "scene": scene, "method": label.split(" ")[0], "label": label,
            "fingerprint": fingerprint, "overrides": [], "budget": GAUSS, "summary": {"train_psnr": psnr}}


def _results(path, command: str, cells: dict) -> str:
    path.write_text(json.dumps({"cells": cells, "command": command, "machine": {"cpu": "test", "cores": 2}}))
    return str(path)


def _merge(*args: str):
    return subprocess.run(["rs-bench-merge", *args], capture_output=True, text=True)


def test_the_gap_share_is_computed_over_files_trained_apart(tmp_path):
    # the plain field and its ceiling in one run, the rain method in another
    plain = _results(tmp_path / "plain.json", "rs-bench methods=3dgs ceiling=auto", {
        "yard/3dgs on clean views": _record("yard", "3dgs on clean views", 31.0),
        "plaza/3dgs on clean views": _record("plaza", "3dgs on clean views", 33.0),
        "yard/3dgs": _record("yard", "3dgs", 30.0), "plaza/3dgs": _record("plaza", "3dgs", 25.0)})
    rain = _results(tmp_path / "rain.json", "rs-bench methods=rainyscape-3dgs", {
        "yard/rainyscape-3dgs": _record("yard", "rainyscape-3dgs", 29.5),
        "plaza/rainyscape-3dgs": _record("plaza", "rainyscape-3dgs", 28.0),
        "plaza/3dgs": _record("plaza", "3dgs", 25.0),  # the same cell again, the same config: kept once
        "yard/robust-3dgs": {"status": "failed", "scene": "yard", "method": "robust-3dgs"}})
    out = tmp_path / "tables" / "set.md"
    done = _merge(plain, rain, f"out={out}", "name=the-set")
    assert done.returncode == 0, done.stderr
    assert "| rainyscape-3dgs (over 3dgs) | -0.50 / 1.00 | +3.00 / 8.00 | +1.25 / 4.50 |" in done.stdout
    assert "# Benchmark the-set" in done.stdout and "(plain.json); rs-bench methods=rainyscape-3dgs" in done.stdout
    assert "robust-3dgs" not in done.stdout  # an unfinished cell is not a row
    assert out.read_text().rstrip() == done.stdout.rstrip()
    again = _merge(plain, rain, f"out={out}")
    assert again.returncode == 2 and "exists; pass force=true" in again.stderr
    assert out.read_text().rstrip() == done.stdout.rstrip()  # the user's file is kept


def test_a_cell_trained_two_ways_or_a_bad_file_is_refused_by_name(tmp_path):
    one = _results(tmp_path / "one.json", "a", {"yard/3dgs": _record("yard", "3dgs", 30.0, "aaa")})
    two = _results(tmp_path / "two.json", "b", {"yard/3dgs": _record("yard", "3dgs", 29.0, "bbb")})
    done = _merge(one, two)
    assert done.returncode == 2 and "Traceback" not in done.stderr
    assert f"{two}: cell yard/3dgs was also trained, with another config, in {one}" in done.stderr
    (tmp_path / "notes.json").write_text("[1, 2]")
    for bad, why in ((tmp_path / "missing.json", "no such results file"),
                     (tmp_path / "notes.json", "not an rs-bench results file")):
        done = _merge(one, str(bad))
        assert done.returncode == 2 and f"{bad}: {why}" in done.stderr and "Traceback" not in done.stderr
    done = _merge(one, f"out={one}")
    assert done.returncode == 2 and "name a .md file" in done.stderr
