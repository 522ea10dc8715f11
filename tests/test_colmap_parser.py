"""The colmap dataparser on a COLMAP text model written by hand for 3 cameras."""

from __future__ import annotations

import json
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest
import torch

from rainyscape.cameras import Cameras
from rainyscape.dataparsers.colmap import ColmapParser, crop_to_common_size, depth_bounds
from rainyscape.errors import DataError

CAMERAS_TXT = """# CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]
1 SIMPLE_PINHOLE 8 6 10 4 3
2 PINHOLE 8 6 11 12 4.5 3.5
3 PINHOLE 8 6 9 9 4 3
"""
# Poses are world-to-camera: identity; 90 degrees about y; 180 degrees about z.
IMAGES_TXT = """# IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME
# POINTS2D[] as (X, Y, POINT3D_ID)
1 1 0 0 0 0 0 5 1 a.png
4.5 3.5 1 2.5 2.5 2
2 0.7071067811865476 0 0.7071067811865476 0 1 2 3 2 b.png
1 1 1
3 0 0 0 1 0 0 4 3 c.png
2 2 2
"""
POINTS_TXT = """# POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)
1 0.5 -0.25 1 255 0 0 0.1 1 0 2 0
2 -1 0.5 2 0 128 255 0.2 1 1 3 0
"""
# Camera-to-world (OpenCV axes) worked out by hand: R^T and -R^T t.
EXPECTED_C2W = np.array([
    [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, -5], [0, 0, 0, 1]],
    [[0, 0, -1, 3], [0, 1, 0, -2], [1, 0, 0, -1], [0, 0, 0, 1]],
    [[-1, 0, 0, 0], [0, -1, 0, 0], [0, 0, 1, -4], [0, 0, 0, 1]],
], dtype=np.float64)


def write_scene(root: Path, sparse: str = "sparse/0") -> Path:
    model = root / sparse
    model.mkdir(parents=True)
    (model / "cameras.txt").write_text(CAMERAS_TXT)
    (model / "images.txt").write_text(IMAGES_TXT)
    (model / "points3D.txt").write_text(POINTS_TXT)
    (root / "images").mkdir()
    for k, name in enumerate(("a.png", "b.png", "c.png")):
        img = np.zeros((6, 8, 3), np.uint8)
        img[..., 0] = 40 * (k + 1)  # tells the views apart
        img[0, 0] = (1, 2, 3)
        iio.imwrite(root / "images" / name, img)
    return root


def parse(root: Path, **options):
    return ColmapParser(ColmapParser.Config(**options)).parse(root)


def test_text_model_parses_to_the_expected_matrices(tmp_path):
    scene = parse(write_scene(tmp_path), normalize=False, holdout_every=0)
    assert scene.image_names == ["a.png", "b.png", "c.png"]
    np.testing.assert_allclose(scene.cameras.c2w.numpy(), EXPECTED_C2W, atol=1e-6)
    np.testing.assert_allclose(scene.cameras.fx.numpy(), [10, 11, 9])
    np.testing.assert_allclose(scene.cameras.fy.numpy(), [10, 12, 9])
    np.testing.assert_allclose(scene.cameras.cx.numpy(), [4, 4.5, 4])
    np.testing.assert_allclose(scene.cameras.cy.numpy(), [3, 3.5, 3])
    assert (scene.width, scene.height) == (8, 6)
    assert scene.images.dtype == torch.uint8
    assert scene.images[:, 2, 2, 0].tolist() == [40, 80, 120]
    assert scene.images[0, 0, 0].tolist() == [1, 2, 3]
    np.testing.assert_allclose(scene.points.numpy(), [[0.5, -0.25, 1], [-1, 0.5, 2]])
    assert scene.point_colors.tolist() == [[255, 0, 0], [0, 128, 255]]
    assert scene.train_indices == [0, 1, 2] and scene.eval_indices == []
    assert scene.metadata["undistorted_on_load"] is False


def test_projection_matches_the_colmap_observation(tmp_path):
    # Point 1 seen by image 1 at (x, y) = (4.5, 3.5): K [R|t] X with pixel centres at +0.5.
    scene = parse(write_scene(tmp_path), normalize=False, holdout_every=0)
    uv, _ = scene.cameras[0].project(scene.points[:1])
    expected = np.array([10 * 0.5 / 6 + 4, 10 * -0.25 / 6 + 3])  # z = 1 + 5
    np.testing.assert_allclose(uv[0, 0].numpy(), expected, atol=1e-5)


def test_normalisation_is_recorded_and_reversible(tmp_path):
    scene = parse(write_scene(tmp_path), normalize=True, camera_radius=3.0, holdout_every=0)
    centers = scene.cameras.centers
    assert centers.norm(dim=-1).max().item() == pytest.approx(3.0, rel=1e-4)
    np.testing.assert_allclose(scene.to_original(centers).numpy(), EXPECTED_C2W[:, :3, 3], atol=1e-5)
    np.testing.assert_allclose(scene.to_original(scene.points).numpy(),
                               [[0.5, -0.25, 1], [-1, 0.5, 2]], atol=1e-5)
    np.testing.assert_allclose(scene.cameras.c2w[:, :3, :3].numpy(), EXPECTED_C2W[:, :3, :3], atol=1e-6)


def test_binary_model_reads_the_same(tmp_path):
    import pycolmap

    text_root = write_scene(tmp_path / "text")
    bin_root = tmp_path / "bin"
    (bin_root / "sparse").mkdir(parents=True)
    pycolmap.Reconstruction(text_root / "sparse" / "0").write_binary(bin_root / "sparse")
    (bin_root / "images").symlink_to(text_root / "images")
    assert (bin_root / "sparse" / "cameras.bin").is_file()
    a = parse(text_root, normalize=False, holdout_every=0)
    b = parse(bin_root, normalize=False, holdout_every=0)
    torch.testing.assert_close(a.cameras.c2w, b.cameras.c2w)
    torch.testing.assert_close(a.points, b.points)


def test_largest_numbered_model_is_chosen(tmp_path):
    root = write_scene(tmp_path)
    small = root / "sparse" / "1"
    small.mkdir()
    (small / "cameras.txt").write_text(CAMERAS_TXT)
    (small / "images.txt").write_text("\n".join(IMAGES_TXT.splitlines()[:4]) + "\n")  # image 1 only
    (small / "points3D.txt").write_text("")
    scene = parse(root, normalize=False, holdout_every=0)
    assert scene.num_images == 3


def test_distorted_camera_is_undistorted_on_load(tmp_path):
    import pycolmap

    root = write_scene(tmp_path)
    cams = CAMERAS_TXT.replace("3 PINHOLE 8 6 9 9 4 3", "3 SIMPLE_RADIAL 8 6 9 4 3 0.05")
    (root / "sparse" / "0" / "cameras.txt").write_text(cams)
    scene = parse(root, normalize=False, holdout_every=0)
    assert scene.metadata["undistorted_on_load"] is True
    pinhole = pycolmap.undistort_camera(pycolmap.UndistortCameraOptions(),
                                        pycolmap.Camera.create_from_model_name(3, "SIMPLE_RADIAL", 9.0, 8, 6))
    assert scene.cameras.fx[2].item() == pytest.approx(pinhole.focal_length_x, rel=1e-5)
    assert scene.width <= 8 and scene.height <= 6  # common size of all views after undistortion


def test_crop_to_common_size_shifts_the_principal_point():
    a, b = np.zeros((6, 8, 3), np.uint8), np.zeros((4, 10, 3), np.uint8)
    b[1:3, 1:9] = 7
    stack, cx, cy = crop_to_common_size([a, b], np.array([4.0, 5.0]), np.array([3.0, 2.0]))
    assert stack.shape == (2, 4, 8, 3)
    assert (stack[1, 1:3] == 7).all()
    np.testing.assert_allclose(cx, [4.0, 4.0])
    np.testing.assert_allclose(cy, [2.0, 2.0])


def test_transforms_json_and_ply_from_the_model(tmp_path):
    import pycolmap
    import trimesh

    from rainyscape.process.writers import write_nerfstudio_files

    root = write_scene(tmp_path)
    write_nerfstudio_files(pycolmap.Reconstruction(root / "sparse" / "0"), root)
    meta = json.loads((root / "transforms.json").read_text())
    assert [f["file_path"] for f in meta["frames"]] == ["images/a.png", "images/b.png", "images/c.png"]
    gl = EXPECTED_C2W[1] @ np.diag([1.0, -1.0, -1.0, 1.0])  # OpenCV -> OpenGL camera axes
    np.testing.assert_allclose(meta["frames"][1]["transform_matrix"], gl, atol=1e-9)
    assert meta["frames"][1]["fl_x"] == 11 and meta["frames"][1]["cy"] == 3.5  # per-frame cameras
    cloud = trimesh.load(root / meta["ply_file_path"])
    np.testing.assert_allclose(cloud.vertices, [[0.5, -0.25, 1], [-1, 0.5, 2]])
    assert cloud.colors[:, :3].tolist() == [[255, 0, 0], [0, 128, 255]]


@pytest.mark.parametrize("breakage, message", [
    ("no_model", "no COLMAP sparse model"),
    ("missing_image", "is missing"),
    ("wrong_size", "but its COLMAP camera"),
    ("no_image_dir", "no image folder"),
    ("corrupt", "cannot read the COLMAP model"),
])
def test_bad_scenes_raise_clear_errors(tmp_path, breakage, message):
    root = write_scene(tmp_path)
    model = root / "sparse" / "0"
    if breakage == "no_model":
        for f in model.iterdir():
            f.unlink()
    elif breakage == "missing_image":
        (root / "images" / "b.png").unlink()
    elif breakage == "wrong_size":
        iio.imwrite(root / "images" / "c.png", np.zeros((5, 8, 3), np.uint8))
    elif breakage == "no_image_dir":
        for f in (root / "images").iterdir():
            f.unlink()
        (root / "images").rmdir()
    elif breakage == "corrupt":
        (model / "cameras.txt").write_text("1 NOT_A_MODEL 8 6 10 4 3\n")
    with pytest.raises(DataError, match=message):
        parse(root)


def test_depth_bounds_come_from_the_points_in_view():
    one = torch.ones(1)
    cam = Cameras(torch.eye(4)[None], 10 * one, 10 * one, 4 * one, 3 * one, 8, 6)
    z = torch.linspace(2.0, 4.0, 101)
    seen = torch.stack([torch.zeros_like(z), torch.zeros_like(z), z], -1)
    behind = seen * torch.tensor([1.0, 1.0, -1.0])  # behind the camera: ignored
    aside = seen + torch.tensor([100.0, 0.0, 0.0])  # outside the image: ignored
    near, far = depth_bounds(cam, torch.cat([seen, behind, aside]))
    assert near == pytest.approx(0.5 * 2.02, rel=1e-3) and far == pytest.approx(1.5 * 3.98, rel=1e-3)
    assert depth_bounds(cam, seen[:5]) is None
