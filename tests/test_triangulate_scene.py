"""Sparse points for scenes that ship none: the cache (keyed by the training views, never in
the scene folder), the wiring into training (a 3DGS run logs and reports its triangulated
points; field.init=random triangulates nothing) and ground-truth depth staying out of
training unless asked for, and out of every benchmark."""

from __future__ import annotations

import dataclasses
import json
import shutil
from pathlib import Path

import numpy as np
import pytest

FERN_VIEWS = 8


def shared_data() -> Path | None:
    here = Path(__file__).resolve().parents[1]
    for root in (here.parent / "shared" / "data", Path("/work/shared/data")):
        if root.is_dir():
            return root
    return None


def snapshot(folder: Path) -> dict[str, tuple[int, int]]:
    return {str(p.relative_to(folder)): (p.stat().st_size, p.stat().st_mtime_ns)
            for p in sorted(folder.rglob("*"))}


@pytest.fixture(scope="module")
def fern_dir(tmp_path_factory) -> Path:
    """A copy of LLFF fern's first eight photos (images_8) with their poses: a scene folder a
    user could own, without a point cloud."""
    root = shared_data()
    source = root / "real" / "fern" if root else None
    if source is None or not (source / "poses_bounds.npy").is_file():
        pytest.skip("the LLFF fern capture is not in ../shared/data/real/fern")
    folder = tmp_path_factory.mktemp("fern") / "fern"
    (folder / "images_8").mkdir(parents=True)
    for path in sorted((source / "images_8").iterdir())[:FERN_VIEWS]:
        shutil.copy(path, folder / "images_8" / path.name)
    np.save(folder / "poses_bounds.npy", np.load(source / "poses_bounds.npy")[:FERN_VIEWS])
    return folder


@pytest.fixture
def cache(tmp_path, monkeypatch) -> Path:
    monkeypatch.setenv("RAINYSCAPE_CACHE", str(tmp_path / "cache"))
    return tmp_path / "cache" / "sparse-points"


def parse_fern(folder: Path, holdout_every: int = 0):
    from rainyscape.dataparsers.llff import LLFFConfig, LLFFParser

    return LLFFParser(LLFFConfig(downscale=16, holdout_every=holdout_every)).parse(folder)


def test_points_are_cached_by_training_views_and_never_written_into_the_scene(fern_dir, cache):
    from rainyscape.process.scene_points import SOURCE, with_sparse_points

    before = snapshot(fern_dir)
    scene = parse_fern(fern_dir)
    assert scene.points is None and scene.points_source == "none"
    first = with_sparse_points(scene)
    assert first.points_source == SOURCE and len(first.points) >= 100
    assert first.points.shape[1] == 3 and first.point_colors.shape == first.points.shape
    report = first.metadata["sparse_points"]
    assert report["cached"] is False and report["views"] == FERN_VIEWS and report["used"] is True
    assert len(list(cache.glob("*.npz"))) == 1 and len(list(cache.glob("*.json"))) == 1

    again = with_sparse_points(parse_fern(fern_dir))
    assert again.metadata["sparse_points"]["cached"] is True  # found, not triangulated again
    assert np.array_equal(again.points.numpy(), first.points.numpy())
    assert np.array_equal(again.point_colors.numpy(), first.point_colors.numpy())
    assert len(list(cache.glob("*.npz"))) == 1

    # another split is another set of training views: triangulated anew, from those only
    split = with_sparse_points(parse_fern(fern_dir, holdout_every=4))
    assert split.metadata["sparse_points"]["cached"] is False
    assert split.metadata["sparse_points"]["views"] == len(split.train_indices) == 6
    assert len(list(cache.glob("*.npz"))) == 2
    assert snapshot(fern_dir) == before  # the scene folder is exactly as it was


def test_a_scene_with_points_keeps_them(fern_dir, cache):
    import torch

    from rainyscape.process.scene_points import with_sparse_points

    scene = parse_fern(fern_dir)
    given = dataclasses.replace(scene, points=torch.zeros(10, 3), points_source="colmap model")
    assert with_sparse_points(given) is given
    assert not cache.exists()


def _train(fern_dir: Path, out: Path, *extra: str, method: str = "3dgs"):
    from rainyscape.config import method_config
    from rainyscape.workflow import train_and_evaluate

    cfg = method_config(method, [f"data={fern_dir}", "dataparser.downscale=16", "trainer.max_iters=2",
                                 f"trainer.output_dir={out}", "trainer.device=cpu", "trainer.progress=false",
                                 "trainer.eval_every=0", "trainer.final_eval_views=1", *extra])
    return train_and_evaluate(cfg).run_dir


def _points_record(run: Path) -> dict:
    from rainyscape.eval.report import read_points_record

    record = read_points_record(run)
    assert record is not None
    return record


def test_a_3dgs_run_starts_from_triangulated_points_and_says_so(fern_dir, cache, tmp_path, capsys):
    from rainyscape.eval.report import read_log
    from rainyscape.process.scene_points import SOURCE

    run = _train(fern_dir, tmp_path / "runs")
    record = _points_record(run)
    assert record["source"] == SOURCE and record["points"] >= 100 and record["field_init"] == "auto"
    tri = record["triangulation"]
    held = len(range(7, FERN_VIEWS, 8))  # the default split holds out every 8th view
    assert tri["views"] == FERN_VIEWS - held and tri["points"] == record["points"]
    assert f"sparse points: {record['points']}, {SOURCE}" in capsys.readouterr().err
    train, _ = read_log(run)
    assert train and all("loss" in r for r in train)  # the record is not a training step
    assert "Initial sparse points: " + str(record["points"]) in (run / "report.html").read_text()

    # field.init=random: the field wants no points, nothing is triangulated
    for path in cache.glob("*"):
        path.unlink()
    record = _points_record(_train(fern_dir, tmp_path / "random", "field.init=random"))
    assert record == {"points": 0, "source": "none", "field_init": "random"}
    assert not list(cache.glob("*.npz"))


def test_ground_truth_depth_starts_nothing_unless_asked(tiny_scene_dir):
    from rainyscape.dataparsers.maya_csv import MayaCsvConfig, MayaCsvParser

    assert MayaCsvConfig().points_from_depth is False
    scene = MayaCsvParser(MayaCsvConfig()).parse(tiny_scene_dir)
    assert scene.points is None and scene.points_source == "none"
    assert scene.depths is not None  # still there for evaluation
    explicit = MayaCsvParser(MayaCsvConfig(points_from_depth=True)).parse(tiny_scene_dir)
    assert explicit.points is not None and "ground-truth depth" in explicit.points_source
    # the ray bounds too: any posed capture's without points, not the true depth's
    radius = float(scene.cameras.centers.norm(dim=-1).max())
    assert (scene.near, scene.far) == pytest.approx((0.05 * radius, 2.5 * radius))
    assert (explicit.near, explicit.far) != pytest.approx((scene.near, scene.far))


def test_the_points_cache_tells_scene_bounds_apart(fern_dir, cache):
    from rainyscape.process.scene_points import with_sparse_points

    scene = parse_fern(fern_dir)
    with_sparse_points(scene)
    # the bounds choose the view pairs, so other bounds are another triangulation
    other = with_sparse_points(dataclasses.replace(scene, far=scene.far * 2))
    assert other.metadata["sparse_points"]["cached"] is False
    assert len(list(cache.glob("*.npz"))) == 2


def test_rs_bench_refuses_ground_truth_depth_points():
    from rainyscape.comparison.options import BenchOptions
    from rainyscape.comparison.plan import plan_bench
    from rainyscape.errors import ConfigError

    with pytest.raises(ConfigError, match="points_from_depth=true starts 3DGS from the simulator's ground-truth"):
        plan_bench(BenchOptions(methods="3dgs", scenes="yard"),
                   ["dataparser=maya-csv", "dataparser.points_from_depth=true"])


def test_a_grid_run_boxed_by_triangulated_points_reloads_with_them(fern_dir, cache, tmp_path):
    """The grid's lattice is shaped to the points' box, so a trained run is rebuilt from the
    scene completed as training completed it (workflow.load_trained); the bare scene's box
    would not fit the checkpoint, and that is one line naming it."""
    from rainyscape.engine.run import load_run
    from rainyscape.errors import RainyScapeError
    from rainyscape.workflow import load_trained

    run = _train(fern_dir, tmp_path / "runs", "field.layout=contract", method="nerf")  # box=auto
    pipeline, step = load_trained(run, device="cpu")
    assert step == 2 and pipeline.scene.points is not None and len(pipeline.scene.points) >= 100
    with pytest.raises(RainyScapeError, match="does not fit this run's config"):
        load_run(run, device="cpu")
