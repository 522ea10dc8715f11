"""rainyscape.formats: the one binary PLY writer and reader."""

from __future__ import annotations

import numpy as np
import pytest

from rainyscape.errors import DataError
from rainyscape.formats.ply import read_ply, write_ply


def test_named_columns_round_trip_with_their_types(tmp_path):
    rng = np.random.default_rng(0)
    cols = {"x": rng.normal(size=5).astype(np.float32), "red": np.arange(5, dtype=np.uint8),
            "id": np.arange(5, dtype=np.int32) - 2, "w": rng.normal(size=5)}
    write_ply(tmp_path / "a.ply", cols)
    header = (tmp_path / "a.ply").read_bytes().split(b"end_header")[0].decode()
    assert header.splitlines()[1:] == ["format binary_little_endian 1.0", "element vertex 5",
                                       "property float x", "property uchar red",
                                       "property int id", "property double w"]
    back = read_ply(tmp_path / "a.ply")
    assert list(back) == list(cols)
    for name, col in cols.items():
        assert back[name].dtype == col.dtype and np.array_equal(back[name], col), name


def test_a_generic_reader_opens_it(tmp_path):
    trimesh = pytest.importorskip("trimesh")
    xyz = np.array([[0.5, -0.25, 1.0], [-1.0, 0.5, 2.0]], np.float32)
    rgb = np.array([[255, 0, 0], [0, 128, 255]], np.uint8)
    write_ply(tmp_path / "p.ply", {"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2],
                                   "red": rgb[:, 0], "green": rgb[:, 1], "blue": rgb[:, 2]})
    cloud = trimesh.load(tmp_path / "p.ply")
    np.testing.assert_allclose(cloud.vertices, xyz)
    assert cloud.colors[:, :3].tolist() == rgb.tolist()


def test_bad_columns_and_bad_files(tmp_path):
    with pytest.raises(ValueError, match="one length"):
        write_ply(tmp_path / "b.ply", {"x": np.zeros(3, np.float32), "y": np.zeros(2, np.float32)})
    with pytest.raises(ValueError, match="no PLY type"):
        write_ply(tmp_path / "b.ply", {"x": np.zeros(3, np.complex64)})
    path = tmp_path / "c.ply"
    path.write_text("hello")
    with pytest.raises(DataError, match="c.ply: not a PLY file"):
        read_ply(path)
    path.write_bytes(b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nend_header\n1\n")
    with pytest.raises(DataError, match="binary little-endian"):
        read_ply(path)
    write_ply(path, {"x": np.zeros(4, np.float32)})
    path.write_bytes(path.read_bytes()[:-3])
    with pytest.raises(DataError, match="truncated"):
        read_ply(path)
    with pytest.raises(DataError, match="cannot read"):
        read_ply(tmp_path / "missing.ply")
