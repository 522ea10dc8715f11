"""Dataparsers: maya-csv, llff, transforms-json and auto on simulator output, and bad input."""

from __future__ import annotations

import csv
import json
import shutil
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from rainyscape import registry
from rainyscape.dataparsers.auto import AutoParser, detect_format
from rainyscape.dataparsers.base import CommonParserConfig
from rainyscape.dataparsers.llff import LLFFConfig, LLFFParser, opencv_to_llff
from rainyscape.dataparsers.maya_csv import MayaCsvConfig, MayaCsvParser
from rainyscape.dataparsers.transforms_json import TransformsJsonConfig, TransformsJsonParser
from rainyscape.dataparsers.writers import original_c2w, write_llff, write_transforms_json
from rainyscape.errors import DataError


def _close(a: torch.Tensor, b: torch.Tensor, atol: float) -> None:
    assert a.shape == b.shape and float((a.float() - b.float()).abs().max()) <= atol


def _same_cameras(a, b, tol=1e-4):
    assert len(a.cameras) == len(b.cameras)
    _close(a.cameras.c2w, b.cameras.c2w, tol)
    for k in ("fx", "fy", "cx", "cy"):
        _close(getattr(a.cameras, k), getattr(b.cameras, k), tol)
    assert (a.width, a.height) == (b.width, b.height)


@pytest.fixture(scope="module")
def exports(tiny_scene, tmp_path_factory):
    root = tmp_path_factory.mktemp("exports")
    return write_llff(tiny_scene, root / "llff"), write_transforms_json(tiny_scene, root / "tj")


def test_maya_csv_reads_everything(tiny_scene, tiny_scene_dir):
    s = tiny_scene
    assert s.images.dtype == torch.uint8 and s.images.shape == (12, 48, 48, 3)
    assert s.clean_images.shape == s.images.shape and s.rain_layers.dtype == torch.float32
    assert s.image_names[:2] == ["001.png", "002.png"]
    assert s.eval_indices == [7] and len(s.train_indices) == 11
    # ground-truth depth becomes points only when asked (the fixture asks: points_from_depth)
    assert MayaCsvParser(MayaCsvConfig()).parse(tiny_scene_dir).points is None
    assert len(s.points) > 1000 and s.point_colors.dtype == torch.uint8
    assert 0 < s.near < s.far
    # normalisation is recorded: mapping back gives the CSV positions
    with open(tiny_scene_dir / "cameras.csv") as fh:
        rows = list(csv.DictReader(fh))
    positions = torch.tensor([[float(r[f"Position {a}"]) for a in "XYZ"] for r in rows])
    _close(s.to_original(s.cameras.centers), positions, 1e-4)
    # depth was scaled with the world: a depth sample lands on a sparse-point-like surface
    finite = torch.isfinite(s.depths)
    assert finite.any() and s.depths[finite].max() < 10 * s.far
    # intrinsics from the film back: f_px = 35 / 36 * 48
    assert s.cameras.fx[0].item() == pytest.approx(35.0 / 36.0 * 48, rel=1e-6)


def test_llff_and_transforms_exports_parse_to_the_same_cameras(tiny_scene, exports):
    llff_dir, tj_dir = exports
    a = LLFFParser().parse(llff_dir)
    b = TransformsJsonParser().parse(tj_dir)
    for other in (a, b):
        _same_cameras(tiny_scene, other)
        assert other.clean_images is not None  # found by the _rain -> _wo_rain convention
        assert torch.equal(other.images, tiny_scene.images)
        assert torch.equal(other.clean_images, tiny_scene.clean_images)
        assert other.eval_indices == tiny_scene.eval_indices
    assert a.metadata["pose_convention"] == "llff"


def test_llff_reads_the_authors_opencv_columns(tiny_scene, exports, tmp_path):
    llff_dir, _ = exports
    authors = tmp_path / "yard_rain"
    shutil.copytree(llff_dir / "images_rain", authors / "images")
    shutil.copytree(llff_dir / "images_wo_rain", tmp_path / "yard_wo_rain" / "images")
    pb = np.load(llff_dir / "poses_bounds.npy")
    mats = pb[:, :15].reshape(-1, 3, 5)
    mats[:, :, :3] = opencv_to_llff(mats[:, :, :3])  # (down, right, back) -> OpenCV columns
    np.save(authors / "poses_bounds.npy", np.concatenate([mats.reshape(-1, 15), pb[:, 15:]], 1))
    s = LLFFParser().parse(authors)
    assert s.metadata["pose_convention"] == "opencv"
    _same_cameras(tiny_scene, s)
    assert s.clean_images is not None and torch.equal(s.clean_images, tiny_scene.clean_images)


def test_llff_uses_prescaled_images_folder(tiny_scene, exports, tmp_path):
    llff_dir, _ = exports
    root = tmp_path / "llff"
    shutil.copytree(llff_dir, root)
    shutil.move(root / "images_rain", root / "images")
    (root / "images_2").mkdir()
    for p in sorted((root / "images").iterdir()):
        img = cv2.imread(str(p))
        cv2.imwrite(str(root / "images_2" / p.name), cv2.resize(img, (24, 24), interpolation=cv2.INTER_AREA))
    s = LLFFParser(LLFFConfig(downscale=2)).parse(root)
    assert s.images.shape == (12, 24, 24, 3) and s.metadata["images"].endswith("images_2")
    assert s.cameras.fx[0].item() == pytest.approx(tiny_scene.cameras.fx[0].item() / 2, rel=1e-5)
    # downscale=4 without images_4/ (the authors' Yard ships images_2/ only): images_2/ shrunk by 2
    (root / "images").rename(root / "originals")
    s = LLFFParser(LLFFConfig(downscale=4)).parse(root)
    assert s.images.shape == (12, 12, 12, 3) and s.metadata["images"].endswith("images_2")
    assert s.cameras.fx[0].item() == pytest.approx(tiny_scene.cameras.fx[0].item() / 4, rel=1e-5)


def test_downscale_and_holdout_options(tiny_scene_dir, tmp_path):
    s = MayaCsvParser(MayaCsvConfig(downscale=2, holdout_every=4)).parse(tiny_scene_dir)
    assert s.images.shape == (12, 24, 24, 3) and s.depths.shape == (12, 24, 24)
    assert s.cameras.cx[0].item() == pytest.approx(12.0)
    assert s.eval_indices == [3, 7, 11]
    listing = tmp_path / "held.txt"
    listing.write_text("002.png\n010\n")
    s = MayaCsvParser(MayaCsvConfig(holdout_file=str(listing))).parse(tiny_scene_dir)
    assert s.eval_indices == [1, 9]
    listing.write_text("099.png\n")
    with pytest.raises(DataError, match="held.txt"):
        MayaCsvParser(MayaCsvConfig(holdout_file=str(listing))).parse(tiny_scene_dir)


def test_transforms_json_blender_angle_and_per_frame_intrinsics(tiny_scene, exports, tmp_path):
    _, tj_dir = exports
    root = tmp_path / "tj"
    shutil.copytree(tj_dir, root)
    meta = json.loads((root / "transforms.json").read_text())
    fx = tiny_scene.cameras.fx[0].item()
    blender = {"camera_angle_x": 2 * np.arctan(0.5 * 48 / fx),
               "frames": [{"file_path": f["file_path"][:-4], "transform_matrix": f["transform_matrix"]}
                          for f in meta["frames"]]}
    (root / "transforms.json").write_text(json.dumps(blender))
    _same_cameras(tiny_scene, TransformsJsonParser().parse(root), tol=1e-3)
    meta["frames"][3]["fl_x"] = 40.0
    (root / "transforms.json").write_text(json.dumps(meta))
    s = TransformsJsonParser(TransformsJsonConfig(normalize=False)).parse(root)
    assert s.cameras.fx[3].item() == 40.0 and s.cameras.fx[2].item() == pytest.approx(fx)
    _close(s.cameras.c2w, torch.from_numpy(original_c2w(tiny_scene)), 1e-4)


def test_one_transforms_writer_shares_or_repeats_intrinsics(tiny_scene, tiny_scene_dir, tmp_path):
    from rainyscape.dataparsers.transforms_json import transforms_content, write_transforms

    c2w = original_c2w(tiny_scene)[:3]
    same = {"fl_x": 30.0, "fl_y": 31.0, "cx": 24.0, "cy": 24.0, "w": 48, "h": 48}
    names = [f"images_rain/{n}" for n in tiny_scene.image_names[:3]]
    shared = transforms_content(c2w, [same] * 3, names, ply_file_path="points.ply",
                                applied_transform=np.eye(4), frame_extras=[{"id": i} for i in range(3)])
    assert {k: shared[k] for k in same} == same and shared["camera_model"] == "PINHOLE"
    assert set(shared["frames"][0]) == {"file_path", "transform_matrix", "id"}
    assert shared["ply_file_path"] == "points.ply" and shared["applied_transform"] == np.eye(4)[:3].tolist()
    per_frame = transforms_content(c2w, [same, {**same, "fl_x": 40.0}, same], names)
    assert "fl_x" not in per_frame and [f["fl_x"] for f in per_frame["frames"]] == [30.0, 40.0, 30.0]
    assert per_frame["fl_y"] == 31.0 and "ply_file_path" not in per_frame
    forced = transforms_content(c2w, [same] * 3, names, per_frame_intrinsics=True)
    assert "fl_x" not in forced and forced["w"] == 48 and forced["frames"][2]["cy"] == 24.0
    root = tmp_path / "tj"
    shutil.copytree(tiny_scene_dir / "images_rain", root / "images_rain")
    write_transforms(root / "transforms.json", shared)
    back = TransformsJsonParser(TransformsJsonConfig(normalize=False, holdout_every=0)).parse(root)
    _close(back.cameras.c2w, torch.from_numpy(c2w), 1e-5)  # OpenCV in, OpenGL on disk, OpenCV out
    assert back.cameras.fx.tolist() == [30.0] * 3
    with pytest.raises(ValueError, match="3 poses, 2 intrinsics"):
        transforms_content(c2w, [same] * 2, names)


def test_transforms_json_undistorts_images(exports, tmp_path):
    _, tj_dir = exports
    root = tmp_path / "tj"
    shutil.copytree(tj_dir, root)
    meta = json.loads((root / "transforms.json").read_text())
    k1 = -0.5
    fx, fy = meta["frames"][0]["fl_x"], meta["frames"][0]["fl_y"]
    k = np.array([[fx, 0, 24.0], [0, fy, 24.0], [0, 0, 1]])
    # a smooth pinhole image, so resampling error is small next to the lens distortion
    ys, xs = np.mgrid[0:48, 0:48].astype(np.float32)
    truth = (128 + 90 * np.sin(xs / 3.0) * np.cos(ys / 4.0)).astype(np.uint8)
    truth = np.repeat(truth[..., None], 3, -1)
    # distorted image: each distorted pixel samples the pinhole image where it really looks
    grid = np.stack([xs, ys], -1).reshape(-1, 1, 2)
    und = cv2.undistortPoints(grid, k, np.array([k1, 0, 0, 0, 0]), P=k).reshape(48, 48, 2)
    distorted = cv2.remap(truth, und[..., 0].astype(np.float32), und[..., 1].astype(np.float32), cv2.INTER_CUBIC)
    for name in ("images_rain", "images_wo_rain"):
        for p in sorted((root / name).iterdir()):
            cv2.imwrite(str(p), distorted)
    meta["k1"] = k1
    meta["camera_model"] = "OPENCV"
    (root / "transforms.json").write_text(json.dumps(meta))
    fixed = TransformsJsonParser().parse(root).clean_images[0].float().numpy()
    inner = (slice(8, 40), slice(8, 40))
    err_fixed = np.abs(fixed - truth)[inner].mean()
    err_distorted = np.abs(distorted.astype(np.float32) - truth)[inner].mean()
    assert err_fixed < 0.3 * err_distorted


def test_auto_detects_each_format(tiny_scene_dir, exports, tmp_path):
    llff_dir, tj_dir = exports
    assert detect_format(tiny_scene_dir) == "maya-csv"
    assert detect_format(llff_dir) == "llff"
    assert detect_format(tj_dir) == "transforms-json"
    (tmp_path / "colmap" / "sparse").mkdir(parents=True)
    assert detect_format(tmp_path / "colmap") == "colmap"
    (tmp_path / "colmap" / "transforms.json").write_text("{}")  # rs-process-data writes both
    assert detect_format(tmp_path / "colmap") == "colmap"
    (tmp_path / "empty").mkdir()
    with pytest.raises(DataError, match="cannot tell the scene format"):
        detect_format(tmp_path / "empty")
    s = AutoParser(CommonParserConfig(holdout_every=3)).parse(llff_dir)
    assert s.metadata["dataparser"] == "llff" and s.eval_indices == [2, 5, 8, 11]
    assert registry.load("dataparser", "maya-csv") is MayaCsvParser


# --------------------------------------------------------------------- bad input


@pytest.fixture()
def scene_copy(tiny_scene_dir, tmp_path):
    dst = tmp_path / "scene"
    shutil.copytree(tiny_scene_dir, dst)
    return dst


def _rewrite_csv(path: Path, edit) -> None:
    with open(path, newline="") as fh:
        rows = list(csv.reader(fh))
    edit(rows)
    with open(path, "w", newline="") as fh:
        csv.writer(fh).writerows(rows)


def _parse_error(folder: Path, config=None) -> str:
    with pytest.raises(DataError) as info:
        MayaCsvParser(config or MayaCsvConfig()).parse(folder)
    return str(info.value)


def _drop_column(rows, name):
    i = rows[0].index(name)
    for r in rows:
        del r[i]


def test_csv_missing_and_extra_columns(scene_copy):
    csv_path = scene_copy / "cameras.csv"
    _rewrite_csv(csv_path, lambda rows: _drop_column(rows, "Vertical Aperture"))
    msg = _parse_error(scene_copy)
    assert "cameras.csv" in msg and "missing column(s) 'Vertical Aperture'" in msg
    _rewrite_csv(csv_path, lambda rows: [r.append("1" if i else "Vertical Aperture") for i, r in enumerate(rows)])
    _rewrite_csv(csv_path, lambda rows: [r.append("0" if i else "Film Gate") for i, r in enumerate(rows)])
    msg = _parse_error(scene_copy)
    assert "cameras.csv" in msg and "unexpected column(s) 'Film Gate'" in msg


@pytest.mark.parametrize("column,value,expect", [
    ("Position Y", "nan", "not a finite number"),
    ("Rotation X", "inf", "not a finite number"),
    ("Focal Length", "thirty-five", "not a number"),
    ("Horizontal Aperture", "1.417", "looks like inches"),
    ("Focal Length", "0.035", "looks like metres"),
    ("Camera Name", "cam1", "cameraShapeN"),
])
def test_csv_bad_values(scene_copy, column, value, expect):
    def edit(rows):
        rows[3][rows[0].index(column)] = value
    _rewrite_csv(scene_copy / "cameras.csv", edit)
    msg = _parse_error(scene_copy)
    assert "cameras.csv" in msg and expect in msg


def test_csv_rotations_in_radians(scene_copy):
    def edit(rows):
        for r in rows[1:]:
            for c in ("Rotation X", "Rotation Y", "Rotation Z"):
                i = rows[0].index(c)
                r[i] = str(np.radians(float(r[i])))
    _rewrite_csv(scene_copy / "cameras.csv", edit)
    assert "looks like radians" in _parse_error(scene_copy)
    assert MayaCsvParser(MayaCsvConfig(check_units=False)).parse(scene_copy).num_images == 12


def test_image_count_and_image_file_problems(scene_copy):
    (scene_copy / "images_rain" / "012.png").unlink()
    msg = _parse_error(scene_copy)
    assert "lists 12 cameras" in msg and "holds 11 images" in msg
    shutil.copy(scene_copy / "images_wo_rain" / "012.png", scene_copy / "images_rain" / "012.png")
    (scene_copy / "images_rain" / "005.png").write_bytes(b"not a png")
    msg = _parse_error(scene_copy)
    assert "005.png" in msg and "cannot read" in msg
    cv2.imwrite(str(scene_copy / "images_rain" / "005.png"), np.zeros((40, 48, 3), np.uint8))
    msg = _parse_error(scene_copy)
    assert "005.png" in msg and "48x40" in msg
    cv2.imwrite(str(scene_copy / "images_rain" / "005.png"), np.zeros((48, 48, 3), np.uint8))
    cv2.imwrite(str(scene_copy / "images_wo_rain" / "006.png"), np.zeros((30, 30, 3), np.uint8))
    msg = _parse_error(scene_copy)
    assert "images_wo_rain/006.png" in msg and "clean image is 30x30" in msg


def test_depth_file_problems(scene_copy):
    import scipy.io

    scipy.io.savemat(scene_copy / "depth" / "003.mat", {"depth": np.ones((10, 10), np.float32)})
    msg = _parse_error(scene_copy)
    assert "003.mat" in msg and "the images are 48x48" in msg
    scipy.io.savemat(scene_copy / "depth" / "003.mat", {"a": np.ones(3), "b": np.ones(3)})
    msg = _parse_error(scene_copy)
    assert "003.mat" in msg and "no 'depth' array" in msg
    assert MayaCsvParser(MayaCsvConfig(depth="")).parse(scene_copy).depths is None


def test_llff_bad_input(exports, tmp_path):
    llff_dir, _ = exports
    root = tmp_path / "llff"
    shutil.copytree(llff_dir, root)
    pb = np.load(root / "poses_bounds.npy")
    np.save(root / "poses_bounds.npy", pb[:, :16])
    with pytest.raises(DataError, match=r"poses_bounds.npy: expected an \(N, 17\) array"):
        LLFFParser().parse(root)
    bad = pb.copy()
    bad[4, 3] = np.nan
    np.save(root / "poses_bounds.npy", bad)
    with pytest.raises(DataError, match="poses_bounds.npy: row 4 holds non-finite"):
        LLFFParser().parse(root)
    np.save(root / "poses_bounds.npy", pb[:10])
    with pytest.raises(DataError, match="holds 10 poses but .*images_rain holds 12 images"):
        LLFFParser().parse(root)
    with pytest.raises(DataError, match="pose_convention"):
        LLFFParser(replace(LLFFConfig(), pose_convention="maya")).parse(root)


def test_transforms_json_bad_input(exports, tmp_path):
    _, tj_dir = exports
    root = tmp_path / "tj"
    shutil.copytree(tj_dir, root)
    path = root / "transforms.json"
    meta = json.loads(path.read_text())
    path.write_text("{not json")
    with pytest.raises(DataError, match="transforms.json: not a readable JSON"):
        TransformsJsonParser().parse(root)
    bad = json.loads(json.dumps(meta))
    bad["frames"][2]["transform_matrix"][0][3] = float("nan")
    path.write_text(json.dumps(bad))
    with pytest.raises(DataError, match="frame 2: transform_matrix holds non-finite"):
        TransformsJsonParser().parse(root)
    bad = json.loads(json.dumps(meta))
    bad["frames"][1]["file_path"] = "images_rain/missing.png"
    path.write_text(json.dumps(bad))
    with pytest.raises(DataError, match="missing.png: image listed in transforms.json not found"):
        TransformsJsonParser().parse(root)
    bad = json.loads(json.dumps(meta))
    for f in bad["frames"]:
        del f["fl_x"], f["fl_y"]
    path.write_text(json.dumps(bad))
    with pytest.raises(DataError, match="no focal length"):
        TransformsJsonParser().parse(root)
    bad = json.loads(json.dumps(meta))
    bad["w"] = 64
    path.write_text(json.dumps(bad))
    with pytest.raises(DataError, match="transforms.json says 64x48"):
        TransformsJsonParser().parse(root)
