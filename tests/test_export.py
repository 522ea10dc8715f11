"""rs-export pieces: marching-cubes meshes that enclose a volume, cameras back in the input frame."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest
import torch
import trimesh

from rainyscape.cameras import opengl_to_opencv
from rainyscape.dataparsers.writers import original_c2w, transforms_meta
from rainyscape.eval.export import export_mesh, grid_points
from rainyscape.scene import apply_normalization
from _eval_fixtures import make_pipeline

HALF = torch.tensor([0.4, 0.2, 0.3])  # a box of 0.8 x 0.4 x 0.6 centred at the origin


def box_density(points: torch.Tensor) -> torch.Tensor:
    return (points.abs() <= HALF).all(-1).float() * 100.0


@pytest.mark.parametrize("fmt", ["ply", "glb"])
def test_box_density_meshes_to_a_closed_surface(tmp_path, fmt):
    pipe = make_pipeline()
    pipe.field.density = box_density
    pipe.scene.scale = 2.0  # the mesh must come back in the input frame: half the size
    info = export_mesh(pipe, tmp_path / f"mesh.{fmt}", resolution=48)
    mesh = trimesh.load(tmp_path / f"mesh.{fmt}", force="mesh")
    assert info["watertight"] and mesh.is_watertight
    expected = float(torch.prod(2 * HALF)) / 2.0 ** 3
    assert mesh.volume > 0
    assert mesh.volume == pytest.approx(expected, rel=0.35)  # within a voxel of the true faces
    np.testing.assert_allclose(mesh.bounds, np.stack([-HALF.numpy(), HALF.numpy()]) / 2, atol=0.05)


def test_density_reaching_the_box_still_closes(tmp_path):
    pipe = make_pipeline()
    pipe.field.density = lambda p: (p[:, 1] < 0).float() * 100.0  # a half space: fills the box floor
    export_mesh(pipe, tmp_path / "ground.ply", resolution=24)
    mesh = trimesh.load(tmp_path / "ground.ply", force="mesh")
    assert mesh.is_watertight and mesh.volume > 0


def test_no_surface_is_a_clear_error(tmp_path):
    from rainyscape.errors import ConfigError

    pipe = make_pipeline()
    pipe.field.density = lambda p: torch.zeros(len(p))
    with pytest.raises(ConfigError, match="no surface"):
        export_mesh(pipe, tmp_path / "m.ply", resolution=16)
    del pipe.field.density
    with pytest.raises(ConfigError, match="has no density"):
        export_mesh(pipe, tmp_path / "m.ply", resolution=16)


def test_grid_points_cover_the_box_with_equal_spacing():
    pts, shape, spacing = grid_points(torch.tensor([0.0, 0, 0]), torch.tensor([2.0, 1, 0.5]), 21)
    assert shape == (21, 11, 6) and pts.shape == (21 * 11 * 6, 3)
    assert float(spacing[0]) == pytest.approx(0.1)
    assert torch.allclose(pts.max(0).values, torch.tensor([2.0, 1.0, 0.5]), atol=1e-5)


def test_transforms_json_puts_cameras_back_in_the_input_frame(tiny_scene, tiny_scene_dir):
    scene = tiny_scene
    names = [f"images/{n}" for n in scene.image_names]
    content = json.loads(json.dumps(transforms_meta(scene, names)))
    assert content["w"] == scene.width
    assert content["frames"][0]["fl_x"] == pytest.approx(float(scene.cameras.fx[0]))
    gl = torch.tensor([f["transform_matrix"] for f in content["frames"]], dtype=torch.float64)
    cv = opengl_to_opencv(gl)
    # re-normalising the exported cameras gives the scene's cameras back
    again = apply_normalization(cv.float(), scene.transform, scene.scale)
    assert torch.allclose(again, scene.cameras.c2w, atol=1e-4)
    # and their centres are the positions of the input's cameras.csv (Maya world units)
    with open(tiny_scene_dir / "cameras.csv") as fh:
        rows = list(csv.DictReader(fh))
    csv_pos = np.array([[float(r["Position X"]), float(r["Position Y"]), float(r["Position Z"])] for r in rows])
    np.testing.assert_allclose(original_c2w(scene)[:, :3, 3], csv_pos, atol=1e-3)


def test_gaussians_export_round_trips_through_the_3dgs_ply(tmp_path, tiny_scene):
    from rainyscape.config import ComponentConfig, PipelineConfig
    from rainyscape.engine.pipeline import Pipeline
    from rainyscape.eval.export import export_gaussians
    from rainyscape.fields.gaussians.field import GaussianField
    from rainyscape.fields.gaussians.ply import read_ply

    field = GaussianField(GaussianField.Config(init_points=500, sh_degree=1), tiny_scene)
    cfg = PipelineConfig(method="3dgs", dataparser=ComponentConfig("auto"), field=ComponentConfig("gaussians"))
    pipe = Pipeline(cfg, tiny_scene, field, {}, {}, {}, torch.device("cpu"))
    info = export_gaussians(pipe, tmp_path / "point_cloud.ply")
    back = read_ply(tmp_path / "point_cloud.ply")
    means = field.params["means"].detach()
    assert info["ply"].endswith("point_cloud.ply") and back["means"].shape == means.shape
    assert torch.allclose(back["means"], tiny_scene.to_original(means), atol=1e-4)  # the input's frame
    assert torch.allclose(back["opacities"].flatten(), field.params["opacities"].detach().flatten(), atol=1e-6)
    # the same file through a generic PLY reader: one vertex per Gaussian
    cloud = trimesh.load(tmp_path / "point_cloud.ply")
    assert len(cloud.vertices) == len(means)


def test_grid_field_density_meshes_a_box(tmp_path, tiny_scene):
    """The real NeRF grid field, its density fitted to a box in the simulated scene, meshes to a
    closed surface of about the box's volume, in the input's world frame."""
    from rainyscape.config import ComponentConfig, PipelineConfig
    from rainyscape.engine.pipeline import Pipeline
    from rainyscape.fields.grid import GridField

    scene = tiny_scene
    field = GridField(GridField.Config(density_shift=-2.0), scene)
    lo, hi = scene.scene_box
    centre, half = (lo + hi) / 2, (hi - lo) * 0.2
    opt = torch.optim.Adam([p for g in field.param_groups() for p in g.params], lr=0.05)
    gen = torch.Generator().manual_seed(0)
    for _ in range(150):  # regress log density onto a box indicator: no rendering needed
        pts = lo + (hi - lo) * torch.rand(4096, 3, generator=gen)
        target = ((pts - centre).abs() <= half).all(-1).float() * 50.0
        loss = ((torch.log1p(field.density(pts)) - torch.log1p(target)) ** 2).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    cfg = PipelineConfig(method="nerf", dataparser=ComponentConfig("auto"), field=ComponentConfig("grid"))
    pipe = Pipeline(cfg, scene, field, {}, {}, {}, torch.device("cpu"))
    export_mesh(pipe, tmp_path / "box.ply", resolution=48)
    mesh = trimesh.load(tmp_path / "box.ply", force="mesh")
    corners = scene.to_original(torch.stack([centre - half, centre + half])).numpy()
    expected = float(np.prod(corners[1] - corners[0]))
    assert mesh.is_watertight and mesh.volume > 0
    assert mesh.volume == pytest.approx(expected, rel=0.4)
    np.testing.assert_allclose(mesh.bounds, corners, atol=0.15 * float(np.max(corners[1] - corners[0])))
