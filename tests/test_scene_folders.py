"""Scene folders with their own layout: the parser's options reach rs-bench's cells (auto
resolved per scene), ``dataparser=NAME`` picks the parser there, and the colmap parser takes
``clean=`` like the others (rs-train then scores against the clean photos)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest
import torch

from rainyscape.comparison.matrix import CLEAN_IMAGES, build_cells, cell_config, clean_views
from rainyscape.comparison.options import BenchOptions
from rainyscape.comparison.plan import plan_bench
from rainyscape.cli import run_cli
from rainyscape.cli.args import parse
from rainyscape.cli.bench import COMMAND as BENCH
from rainyscape.cli.bench import main as bench_main
from rainyscape.cli.train import main as train_main
from rainyscape.dataparsers.colmap import ColmapParser
from rainyscape.errors import ConfigError
from rainyscape.imaging.metrics import psnr


def write_colmap(scene, root: Path, images: str = "images", clean: str = "photos_clean") -> Path:
    """``scene`` (a parsed SceneData) as a COLMAP text model: one PINHOLE camera a view,
    its rainy images in ``images/`` and its clean ones in ``clean/``, no sparse points."""
    from scipy.spatial.transform import Rotation

    from rainyscape.dataparsers.writers import original_c2w

    model = root / "sparse" / "0"
    model.mkdir(parents=True)
    cams = scene.cameras
    cameras, poses = [], []
    for k, c2w in enumerate(original_c2w(scene)):
        w2c = np.linalg.inv(c2w)
        x, y, z, w = Rotation.from_matrix(w2c[:3, :3]).as_quat()
        t = w2c[:3, 3]
        cameras.append(f"{k + 1} PINHOLE {cams.width} {cams.height} {cams.fx[k]:.8f} {cams.fy[k]:.8f} "
                       f"{cams.cx[k]:.8f} {cams.cy[k]:.8f}")
        poses.append(f"{k + 1} {w} {x} {y} {z} {t[0]} {t[1]} {t[2]} {k + 1} v{k:03d}.png\n\n")  # no 2D points
    (model / "cameras.txt").write_text("\n".join(cameras) + "\n")
    (model / "images.txt").write_text("".join(poses))
    (model / "points3D.txt").write_text("")
    for folder, stack in ((images, scene.images), (clean, scene.clean_images)):
        (root / folder).mkdir()
        for k, img in enumerate(stack):
            iio.imwrite(root / folder / f"v{k:03d}.png", img.numpy())
    return root


def test_colmap_clean_images_are_undistorted_and_cropped_like_the_rainy_ones(tmp_path):
    from test_colmap_parser import CAMERAS_TXT, write_scene

    root = write_scene(tmp_path)
    cams = CAMERAS_TXT.replace("3 PINHOLE 8 6 9 9 4 3", "3 SIMPLE_RADIAL 8 6 9 4 3 0.05")
    (root / "sparse" / "0" / "cameras.txt").write_text(cams)
    shutil.copytree(root / "images", root / "clean")  # the same pixels: the same result
    scene = ColmapParser(ColmapParser.Config(normalize=False, holdout_every=0, clean="clean")).parse(root)
    assert scene.metadata["undistorted_on_load"] is True and scene.clean_images is not None
    assert torch.equal(scene.clean_images, scene.images)
    assert ColmapParser(ColmapParser.Config(normalize=False)).parse(root).clean_images is None  # auto: no sibling
    (root / "clean" / "b.png").unlink()
    from rainyscape.errors import DataError

    with pytest.raises(DataError, match="no clean image named like b.png"):
        ColmapParser(ColmapParser.Config(clean="clean")).parse(root)


@pytest.mark.slow
def test_rs_train_on_a_colmap_scene_scores_against_the_clean_photos(tmp_path, tiny_scene, capsys):
    root = write_colmap(tiny_scene, tmp_path / "colmap")
    read = ColmapParser(ColmapParser.Config(clean="photos_clean")).parse(root)  # the scene as written
    assert torch.equal(read.clean_images, tiny_scene.clean_images) and torch.equal(read.images, tiny_scene.images)
    assert torch.allclose(read.cameras.c2w, tiny_scene.cameras.c2w, atol=1e-5)
    out = tmp_path / "out"
    code = run_cli(train_main, ["method=nerf", f"data={root}", "dataparser.clean=photos_clean",
                                "trainer.max_iters=4", "trainer.eval_every=0", "trainer.final_eval_views=0",
                                "trainer.progress=false", f"trainer.output_dir={out}", "trainer.device=cpu"])
    assert code == 0, capsys.readouterr().err
    run = next(out.glob("*/*/*/metrics.json")).parent
    summary = json.loads((run / "metrics.json").read_text())["summary"]
    # the rainy training inputs against the clean photos (the same split: the same names, in order)
    expected = np.mean([psnr(tiny_scene.images[i] / 255, tiny_scene.clean_images[i] / 255).item()
                        for i in tiny_scene.train_indices])
    assert summary["rainy_input_psnr"] == pytest.approx(expected, abs=0.05)
    assert 15 < summary["rainy_input_psnr"] < 60  # rain against clean photos, not the images themselves
    assert "train_psnr" in summary and "colmap" in (run / "config.yml").read_text()


@pytest.fixture(scope="module")
def renamed_clean(tmp_path_factory, tiny_scene):
    """A transforms.json scene whose clean photos sit in images_clean/ (not the _wo_rain sibling)."""
    from rainyscape.dataparsers.writers import write_transforms_json

    root = write_transforms_json(tiny_scene, tmp_path_factory.mktemp("folders") / "tj")
    (root / CLEAN_IMAGES).rename(root / "images_clean")
    return root


def test_bench_plan_passes_dataparser_options_to_folder_cells(renamed_clean):
    plan = plan_bench(BenchOptions(methods="nerf", scenes=str(renamed_clean), iters=2),
                      ["dataparser.clean=images_clean"])
    cells = {c.label: c for c in plan.cells()}
    assert set(cells) == {"nerf", "nerf on clean views"}  # the clean photos give the ceiling row
    cfg = cell_config(cells["nerf"])
    assert cfg.dataparser.name == "transforms-json" and cfg.dataparser.options.clean == "images_clean"
    ceiling = cell_config(cells["nerf on clean views"]).dataparser.options
    assert ceiling.images == "images_clean" and ceiling.clean == "images_clean"
    with pytest.raises(ConfigError, match="finds no clean images"):  # without it nothing scores
        plan_bench(BenchOptions(methods="nerf", scenes=str(renamed_clean), iters=2), [])


def test_bench_dataparser_names_the_parser_of_folder_cells(renamed_clean, tmp_path):
    # a folder both parsers read: auto would pick the COLMAP model
    both = tmp_path / "both"
    shutil.copytree(renamed_clean, both)
    (both / "sparse" / "0").mkdir(parents=True)
    args = parse(["methods=nerf", f"scenes={both}", "iters=2", "dataparser=transforms-json",
                  "dataparser.clean=images_clean"], BENCH)
    assert args.options.dataparser == "transforms-json"
    plan = plan_bench(args.options, args.overrides)
    assert all(cell_config(c).dataparser.name == "transforms-json" for c in plan.cells())
    assert clean_views(str(both), args.overrides)[0] == "colmap"  # without dataparser=, auto's pick
    assert clean_views(str(both), ["dataparser=transforms-json", "dataparser.clean=images_clean"]) == \
        ("transforms-json", "images_clean")
    with pytest.raises(ConfigError, match="yard is simulated"):
        plan_bench(BenchOptions(methods="nerf", scenes=f"{both},yard", dataparser="transforms-json"), [])


def test_auto_resolves_per_scene_for_simulated_and_folder_cells(renamed_clean):
    cells = build_cells(["nerf"], [("sim", ""), ("tj", str(renamed_clean))], ["dataparser.clean=images_clean"])
    parsers = {c.key: c.overrides[0] for c in cells if not c.clean}
    assert parsers == {"sim/nerf": "dataparser=maya-csv", "tj/nerf": "dataparser=transforms-json"}
    plain = build_cells(["nerf"], [("tj", str(renamed_clean))], ["trainer.max_iters=3"])
    assert plain[-1].overrides == ["trainer.max_iters=3"]  # no parser options: the config stays as it was


@pytest.mark.slow
def test_rs_bench_trains_a_scene_folder_with_its_clean_folder(renamed_clean, tmp_path, capsys):
    out = tmp_path / "results"
    code = run_cli(bench_main, ["methods=nerf", f"scenes={renamed_clean}", "dataparser.clean=images_clean",
                                "iters=2", f"out={out}", "name=f", "device=cpu", "trainer.eval_every=0"])
    assert code == 0, capsys.readouterr().err
    cells = json.loads((out / "f.json").read_text())["cells"]
    plain, ceiling = cells["tj/nerf"], cells["tj/nerf on clean views"]
    assert plain["status"] == ceiling["status"] == "finished"
    assert 15 < plain["summary"]["rainy_input_psnr"] < 60  # scored against images_clean
    assert ceiling["summary"]["rainy_input_psnr"] > 60  # trained on them: its input is clean
