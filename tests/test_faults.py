"""Faults and bad input (docs/reliability.md): what a kill, a corrupt file, a second process or
a wrong value does, and that nothing of the user's is lost.

- checkpoints: a crafted one is refused unread; a truncated newest one falls back to the
  previous one; a kill -9 during training or during a checkpoint write, then resume, ends
  with the same parameters as an uninterrupted run;
- run folders: a second rs-train resume= of a folder in use is refused naming the holder;
  a dead owner's "running" status reads as interrupted;
- destructive paths: sentinel files of the user's survive byte for byte;
- a table of bad inputs, each one error line (exit code 2) naming the file or key, no traceback;
  and inputs that must simply work (8 x 8 images, whole-image batches, a single view, ...).

Most cases run the commands in this process (``run_cli``) with the toy plugin's field, which
trains in a fraction of a second; only the kills need real processes.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from _plugins import install_toy_plugin
from rainyscape import config, registry
from rainyscape.cli import run_cli
from rainyscape.engine.checkpoint import list_checkpoints, load_checkpoint
from rainyscape.engine.run import load_run
from rainyscape.engine.run_folder import RunFolder
from rainyscape.errors import RainyScapeError
from rainyscape.workflow import train_and_evaluate

ITERS = 30  # toy runs: checkpoints every 10 steps


# ----------------------------------------------------------------------------- fixtures


@pytest.fixture(scope="module")
def toy_env(tmp_path_factory):
    """The toy plugin installed for this process and for subprocesses (env). One torch thread:
    the toy's tiny steps run ten times faster so on a shared, busy CPU."""
    path = install_toy_plugin(tmp_path_factory.mktemp("plugin"))
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    with pytest.MonkeyPatch.context() as mp:
        mp.syspath_prepend(str(path))
        mp.delenv("RAINYSCAPE_PLUGINS", raising=False)
        registry.clear_cache()
        env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(path), os.environ.get("PYTHONPATH", "")]),
               "OMP_NUM_THREADS": "1"}
        env.pop("RS_TOY_KILL_IN_SAVE", None)
        yield env
    torch.set_num_threads(threads)
    registry.clear_cache()


@pytest.fixture(autouse=True)
def _keep_sigterm():
    """rs-train's main turns SIGTERM into Ctrl-C; put pytest's handler back after each test."""
    handler = signal.getsignal(signal.SIGTERM)
    yield
    signal.signal(signal.SIGTERM, handler)


def _toy_args(scene: Path, out: Path, *extra: str) -> list[str]:
    return [f"data={scene}", f"trainer.output_dir={out}", "trainer.device=cpu", "trainer.progress=false",
            f"trainer.max_iters={ITERS}", "trainer.checkpoint_every=10", "trainer.keep_checkpoints=0",
            "trainer.log_every=1", "trainer.eval_every=0", "phases.warmup.patches=2",
            "phases.warmup.patch_size=8", *extra]


def _train(scene: Path, out: Path, *extra: str, run_dir: Path | None = None) -> Path:
    if run_dir is not None:
        cfg = config.load_yaml(run_dir / "config.yml")
        cfg = config.apply_overrides(cfg, config.parse_overrides(list(extra)))
        return train_and_evaluate(cfg, run_dir).run_dir
    return train_and_evaluate(config.method_config("toy", _toy_args(scene, out, *extra))).run_dir


def _params(run: Path) -> dict[str, torch.Tensor]:
    pipeline, step = load_run(run, device="cpu")
    assert step == ITERS
    return {k: v.clone() for k, v in pipeline.field.state_dict().items()}


def _same_params(a: Path, b: Path) -> None:
    pa, pb = _params(a), _params(b)
    assert pa.keys() == pb.keys()
    for key in pa:
        assert torch.equal(pa[key], pb[key]), key  # CPU, same seed: bit for bit


def _logged_steps(run: Path) -> list[int]:
    records = [json.loads(line) for line in (run / "log.jsonl").read_text().splitlines()]
    return [r["step"] for r in records if "loss" in r]


def _snapshot(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def reference_run(toy_env, tiny_scene_dir, tmp_path_factory):
    """An uninterrupted toy run of ITERS steps (checkpoints at 10, 20, 30)."""
    return _train(tiny_scene_dir, tmp_path_factory.mktemp("reference"))


def _cli(capsys, command: str, *argv: str) -> tuple[int, str]:
    """Run ``command`` (train, eval, render, export) in this process: exit code and stderr."""
    from importlib import import_module

    main = import_module(f"rainyscape.cli.{command}").main
    capsys.readouterr()
    code = run_cli(main, [str(a) for a in argv])
    return code, capsys.readouterr().err


def _one_error_line(err: str) -> str:
    assert "Traceback" not in err, err
    errors = [line for line in err.splitlines() if line.startswith("error:")]
    assert len(errors) == 1 and err.rstrip().endswith(errors[0]), err
    return errors[0]


# --------------------------------------------------------------------------- checkpoints


class _Payload:
    """Unpickling this runs a shell command (what a crafted checkpoint would do)."""

    def __init__(self, sentinel: Path):
        self.sentinel = sentinel

    def __reduce__(self):
        return (os.system, (f"touch {self.sentinel}",))


def test_a_crafted_checkpoint_is_refused_without_running_its_code(reference_run, tmp_path, capsys):
    run = tmp_path / "run"
    shutil.copytree(reference_run, run)
    sentinel = tmp_path / "pwned"
    crafted = run / "checkpoints" / "step-0000030.pt"
    torch.save({"step": 30, "models": {"field": _Payload(sentinel)}, "optimizers": {}, "rng": {}}, crafted)
    with pytest.raises(RainyScapeError, match="refused unread"):
        load_checkpoint(crafted, "cpu")
    code, err = _cli(capsys, "eval", run, "step=30", "device=cpu")
    assert code == 2 and str(crafted) in _one_error_line(err)
    # the newest checkpoint is the crafted one: rs-eval warns and uses the previous one
    code, err = _cli(capsys, "eval", run, "device=cpu")
    assert code == 0 and "step-0000030.pt" in err and "using step-0000020.pt" in err
    assert json.loads((run / "metrics.json").read_text())["step"] == 20
    assert not sentinel.exists()


def test_a_truncated_newest_checkpoint_falls_back_and_resume_matches(reference_run, tiny_scene_dir,
                                                                      tmp_path, capsys):
    run = _train(tiny_scene_dir, tmp_path, "trainer.stop_at=20")
    assert RunFolder(run).status()["state"] == "stopped"
    newest = run / "checkpoints" / "step-0000020.pt"
    data = newest.read_bytes()
    newest.write_bytes(data[: len(data) // 3])
    code, err = _cli(capsys, "train", f"resume={run}", "trainer.stop_at=0")
    assert code == 0, err
    assert "step-0000020.pt" in err and "using step-0000010.pt" in err and "Traceback" not in err
    # set aside for inspection, not deleted
    assert (run / "checkpoints" / "step-0000020.pt.corrupt").read_bytes() == data[: len(data) // 3]
    assert _logged_steps(run) == list(range(1, ITERS + 1))  # the log was cut back to step 10
    assert RunFolder(run).status()["state"] == "finished"
    _same_params(reference_run, run)


def _start_toy_training(scene: Path, out: Path, env: dict, *extra: str) -> subprocess.Popen:
    args = [sys.executable, "-m", "rainyscape.cli.train", "method=toy", *_toy_args(scene, out, *extra)]
    return subprocess.Popen(args, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _wait_for(predicate, proc: subprocess.Popen, timeout: float = 120.0) -> None:
    end = time.monotonic() + timeout
    while not predicate():
        if proc.poll() is not None:
            raise AssertionError(f"the process ended first (exit {proc.returncode}): {proc.stderr.read()}")
        if time.monotonic() > end:
            proc.kill()
            raise AssertionError("timed out")
        time.sleep(0.02)


def _only_run(out: Path) -> Path:
    runs = [p.parent for p in out.rglob("config.yml")]
    assert len(runs) == 1, runs
    return runs[0]


@pytest.mark.parametrize("when", ["training", "checkpoint-write"])
def test_kill_9_then_resume_matches_an_uninterrupted_run(when, reference_run, toy_env, tiny_scene_dir,
                                                          tmp_path, capsys):
    env = dict(toy_env)
    if when == "checkpoint-write":
        env["RS_TOY_KILL_IN_SAVE"] = "2"  # the step-20 checkpoint is half-written, then SIGKILL
        proc = _start_toy_training(tiny_scene_dir, tmp_path, env)
        proc.wait(timeout=300)
        run = _only_run(tmp_path)
        assert (run / "checkpoints" / "step-0000020.pt.tmp").is_file()
    else:
        proc = _start_toy_training(tiny_scene_dir, tmp_path, env, "field.delay=0.05")

        def far_enough() -> bool:
            runs = [p.parent for p in tmp_path.rglob("log.jsonl")]
            return bool(runs) and any(s >= 23 for s in _logged_steps_safe(runs[0]))

        _wait_for(far_enough, proc)
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=60)
        run = _only_run(tmp_path)
    assert proc.returncode == -signal.SIGKILL
    assert [p.name for p in list_checkpoints(run / "checkpoints")][-1] in ("step-0000010.pt", "step-0000020.pt")
    # the killed process left "running"; nobody holds the folder, so it reads as interrupted
    status = RunFolder(run).status()
    assert status["state"] == "interrupted" and str(proc.pid) in status["note"]
    code, err = _cli(capsys, "train", f"resume={run}")
    assert code == 0, err
    assert not list((run / "checkpoints").glob("*.tmp"))
    assert _logged_steps(run) == list(range(1, ITERS + 1))  # no step logged twice
    assert RunFolder(run).status()["state"] == "finished"
    _same_params(reference_run, run)


def _logged_steps_safe(run: Path) -> list[int]:
    try:
        return [json.loads(line).get("step", 0) for line in (run / "log.jsonl").read_text().splitlines()
                if line.endswith("}")]
    except (OSError, ValueError):
        return []


def test_a_second_resume_of_a_busy_run_is_refused_naming_the_holder(toy_env, tiny_scene_dir, tmp_path,
                                                                     capsys):
    run = _train(tiny_scene_dir, tmp_path, "trainer.stop_at=10", "field.delay=0.04")
    args = [sys.executable, "-m", "rainyscape.cli.train", f"resume={run}", "trainer.stop_at=0"]
    first = subprocess.Popen(args, env=toy_env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)

    def holds() -> bool:  # the first resume has the folder once its status names it
        try:
            status = json.loads((run / "status.json").read_text())
        except (OSError, ValueError):
            return False
        return status.get("state") == "running" and status.get("pid") == first.pid

    _wait_for(holds, first)
    code, err = _cli(capsys, "train", f"resume={run}")
    line = _one_error_line(err)
    assert code == 2 and "in use by rs-train" in line and f"pid {first.pid}" in line
    assert first.wait(timeout=300) == 0, first.stderr.read()
    assert _logged_steps(run) == list(range(1, ITERS + 1))  # every step once
    assert RunFolder(run).status()["state"] == "finished"
    # a finished run is not re-evaluated silently
    metrics = (run / "metrics.json").read_bytes()
    code, err = _cli(capsys, "train", f"resume={run}")
    assert code == 2 and "force=true" in _one_error_line(err)
    assert (run / "metrics.json").read_bytes() == metrics


# ------------------------------------------------------------------- user files survive


def test_user_files_survive_every_writing_command(reference_run, toy_env, tiny_scene_dir, tmp_path, capsys):
    user = tmp_path / "mine"
    (user / "scene" / "toy").mkdir(parents=True)  # named like the run folder's parents
    (user / "notes.txt").write_text("my notes\n")
    (user / "scene" / "toy" / "README").write_text("not a run\n")
    (user / "transforms.json").write_text('{"mine": true}\n')
    (user / "images").mkdir()
    (user / "images" / "0001.png").write_bytes(b"\x89PNG not really")
    before = _snapshot(user)
    # rs-train into a folder holding the user's files: a new run folder, nothing else touched
    code, err = _cli(capsys, "train", "method=toy", *_toy_args(tiny_scene_dir, user, "trainer.max_iters=5"))
    assert code == 0, err
    run = _only_run(user)
    assert {k: v for k, v in _snapshot(user).items() if k in before} == before
    # files the user put in a run folder survive rs-eval and a resume
    (run / "my_notes.txt").write_text("keep\n")
    (run / "checkpoints" / "mine.pt.tmp").write_text("keep\n")
    in_run = {k: v for k, v in _snapshot(run).items() if k in ("my_notes.txt", "checkpoints/mine.pt.tmp")}
    assert _cli(capsys, "eval", run, "device=cpu")[0] == 0
    code, err = _cli(capsys, "train", f"resume={run}", "trainer.max_iters=8")
    assert code == 0, err
    assert {k: v for k, v in _snapshot(run).items() if k in in_run} == in_run
    # rs-export refuses the user's non-empty folder; force=true replaces what an export writes
    # (transforms.json, images/) as a whole, never a part, and keeps the rest
    code, err = _cli(capsys, "export", run, f"out={user}", "what=cameras", "device=cpu")
    assert code == 2 and str(user) in _one_error_line(err)
    assert {k: v for k, v in _snapshot(user).items() if k in before} == before
    code, err = _cli(capsys, "export", run, f"out={user}", "what=cameras", "device=cpu", "force=true")
    assert code == 0, err
    kept = {k: v for k, v in before.items() if not k.startswith(("transforms.json", "images/"))}
    assert {k: v for k, v in _snapshot(user).items() if k in kept} == kept
    names = [f["file_path"] for f in json.loads((user / "transforms.json").read_text())["frames"]]
    assert sorted(f"images/{p.name}" for p in (user / "images").iterdir()) == sorted(names)  # no old image left


# ------------------------------------------------------------------------- bad input table


@pytest.fixture(scope="module")
def tj_scene(tiny_scene_dir, tmp_path_factory):
    """The tiny scene as a transforms.json scene (images_rain/NNN.png, images_wo_rain/)."""
    from rainyscape.dataparsers.maya_csv import MayaCsvConfig, MayaCsvParser
    from rainyscape.dataparsers.writers import write_transforms_json

    scene = MayaCsvParser(MayaCsvConfig()).parse(tiny_scene_dir)
    return write_transforms_json(scene, tmp_path_factory.mktemp("tj") / "scene")


def _tj_variant(tj_scene: Path, dest: Path, change) -> Path:
    shutil.copytree(tj_scene, dest)
    meta = json.loads((dest / "transforms.json").read_text())
    change(meta)
    (dest / "transforms.json").write_text(json.dumps(meta))
    return dest


def _set(key, value):
    return lambda meta: meta.update({key: value})


def _frame(i, key, value):
    return lambda meta: meta["frames"][i].update({key: value})


def _angle_zero(meta):
    for f in meta["frames"]:
        for k in ("fl_x", "fl_y"):
            f.pop(k)
    meta["camera_angle_x"] = 0


def _scaled_rotation(meta):
    m = np.array(meta["frames"][1]["transform_matrix"])
    m[:3, :3] *= 2
    meta["frames"][1]["transform_matrix"] = m.tolist()


def _truncated_depth(tiny_scene_dir: Path, dest: Path) -> Path:
    shutil.copytree(tiny_scene_dir, dest)
    mat = dest / "depth" / "003.mat"
    mat.write_bytes(mat.read_bytes()[:100])
    return dest


def _run_copy(reference_run: Path, dest: Path, change=None) -> Path:
    shutil.copytree(reference_run, dest)
    if change is not None:
        change(dest)
    return dest


def _drop_rng(run: Path) -> None:
    path = run / "checkpoints" / "step-0000030.pt"
    state = torch.load(path, weights_only=True)
    del state["rng"]
    torch.save(state, path)


def _drop_weights(run: Path) -> None:
    path = run / "checkpoints" / "step-0000030.pt"
    state = torch.load(path, weights_only=True)
    state["models"]["field"].pop(next(iter(state["models"]["field"])))
    torch.save(state, path)


def _same_image(meta):
    meta["frames"][1]["file_path"] = meta["frames"][0]["file_path"]


def _colmap_scene(dest: Path) -> Path:
    """The colmap parser tests' three-view scene with its model in COLMAP's binary format."""
    import pycolmap
    from test_colmap_parser import write_scene

    write_scene(dest)
    model_dir = dest / "sparse" / "0"
    model = pycolmap.Reconstruction()
    model.read(model_dir)
    for f in list(model_dir.iterdir()):
        f.unlink()
    model.write_binary(str(model_dir))
    return dest


def _truncate(name: str, size: int):
    def change(scene: Path) -> None:
        path = scene / "sparse" / "0" / name
        path.write_bytes(path.read_bytes()[:size])
    return change


def _second_model_and_no_cameras(scene: Path) -> None:
    shutil.copytree(scene / "sparse", scene / "colmap" / "sparse")  # a model the parser could fall back on
    (scene / "sparse" / "0" / "cameras.bin").unlink()


def _moved_scene(run: Path) -> None:
    text = (run / "config.yml").read_text()
    data = next(line for line in text.splitlines() if line.startswith("data:"))
    (run / "config.yml").write_text(text.replace(data, "data: /nonexistent/moved_scene"))


# id: (command, argv from the fixtures' paths, what the one error line must name)
BAD_INPUTS = {
    "holdout_every=1": ("train", lambda c: ["method=toy", *c.toy("dataparser.holdout_every=1")],
                        "dataparser.holdout_every=1"),
    "device=gpu": ("train", lambda c: ["method=toy", *c.toy("trainer.device=gpu")], "trainer.device=gpu"),
    "downscale=100": ("train", lambda c: ["method=toy", *c.toy("dataparser.downscale=100")],
                      "dataparser.downscale=100"),
    "downscale=0": ("train", lambda c: ["method=toy", *c.toy("dataparser.downscale=0")], "dataparser.downscale"),
    "log_every=0": ("train", lambda c: ["method=toy", *c.toy("trainer.log_every=0")], "trainer.log_every"),
    "max_iters=0": ("train", lambda c: ["method=toy", *c.toy("trainer.max_iters=0")], "trainer.max_iters"),
    "max_iters=-5": ("train", lambda c: ["method=toy", *c.toy("trainer.max_iters=-5")], "trainer.max_iters"),
    "patch_size<0": ("train", lambda c: ["method=toy", *c.toy("phases.warmup.patch_size=-1")],
                     "phases.warmup.patch_size"),
    "checkpoint_minutes<0": ("train", lambda c: ["method=toy", *c.toy("trainer.checkpoint_minutes=-1")],
                             "trainer.checkpoint_minutes"),
    "field range": ("train", lambda c: ["method=nerf", "field.step_ratio=0"], "field.step_ratio"),
    "auto without data": ("train", lambda c: ["method=nerf", "dataparser.clean=x"], "data="),
    "holdout_file missing": ("train", lambda c: ["method=toy", *c.toy("dataparser.holdout_file=nope.txt")],
                             "nope.txt"),
    "holdout_file unknown name": ("train", lambda c: ["method=toy", *c.toy(f"dataparser.holdout_file={c.held}")],
                                  "099.png"),
    "camera_angle_x: 0": ("train", lambda c: ["method=toy", *c.toy(data=c.tj("angle", _angle_zero))],
                          "camera_angle_x"),
    "zero transform_matrix": ("train", lambda c: ["method=toy", *c.toy(data=c.tj(
        "zero", _frame(2, "transform_matrix", [[0] * 4] * 3 + [[0, 0, 0, 1]])))], "transform_matrix"),
    "non-rotation transform_matrix": ("train", lambda c: ["method=toy", *c.toy(data=c.tj("scaled", _scaled_rotation))],
                                      "transform_matrix"),
    "k1=50": ("train", lambda c: ["method=toy", *c.toy(data=c.tj("k1", _set("k1", 50)))], "k1=50"),
    "val_filenames unknown": ("train", lambda c: ["method=toy", *c.toy(data=c.tj(
        "split", _set("val_filenames", ["images_rain/777.png"])))], "777.png"),
    "truncated depth .mat": ("train", lambda c: ["method=toy", *c.toy(data=c.depth())], "003.mat"),
    "resume not a run": ("train", lambda c: ["resume=/nonexistent/run"], "/nonexistent/run"),
    "resume other keys": ("train", lambda c: [f"resume={c.run()}", "field.hidden=3"], "field.hidden"),
    "checkpoint without rng": ("eval", lambda c: [c.run(_drop_rng), "step=30", "device=cpu"], "rng"),
    "checkpoint missing a weight": ("eval", lambda c: [c.run(_drop_weights), "step=30", "device=cpu"],
                                    "does not fit"),
    "checkpoint step absent": ("eval", lambda c: [c.run(), "step=7", "device=cpu"], "step 7"),
    "eval step<0": ("eval", lambda c: [c.run(), "step=-1"], "step"),
    "scene moved (eval)": ("eval", lambda c: [c.run(_moved_scene), "device=cpu"], "data="),
    "scene moved (render)": ("render", lambda c: [c.run(_moved_scene), "device=cpu"], "data="),
    "scene moved (export)": ("export", lambda c: [c.run(_moved_scene), "device=cpu"], "data="),
    "render frames=0": ("render", lambda c: [c.run(), "frames=0"], "frames"),
    "export resolution=4": ("export", lambda c: [c.run(), "resolution=4"], "resolution"),
    # the third probe (issue 31): cases 8, 10, 13, 14, 16, 17, 18 and option ranges
    "seed=-1": ("train", lambda c: ["method=toy", *c.toy("trainer.seed=-1")], "trainer.seed"),
    "seed=99999999999": ("train", lambda c: ["method=toy", *c.toy("trainer.seed=99999999999")], "trainer.seed"),
    "resume method=": ("train", lambda c: [f"resume={c.run()}", "method=3dgs"], "method=3dgs"),
    "resume output_dir": ("train", lambda c: [f"resume={c.run()}", f"trainer.output_dir={c.tmp}"],
                          "trainer.output_dir"),
    "resume seed": ("train", lambda c: [f"resume={c.run()}", "trainer.seed=3"], "trainer.seed"),
    "force without resume": ("train", lambda c: ["method=toy", *c.toy("force=true")], "force=true"),
    "retired final_eval_share": ("train", lambda c: ["method=toy", *c.toy("trainer.final_eval_share=0")],
                                 "trainer.final_eval_share"),
    "two frames, one image": ("train", lambda c: ["method=toy", *c.toy(data=c.tj("twice", _same_image))],
                              "frames 0 and 1 both use"),
    "resolution_final=100000": ("train", lambda c: ["method=nerf", "field.resolution_final=100000"],
                                "field.resolution_final"),
    "0-byte points3D.bin": ("train", lambda c: ["method=toy", *c.toy(data=c.colmap(_truncate("points3D.bin", 0)))],
                            "sparse/0/points3D.bin: truncated"),
    "truncated cameras.bin": ("train", lambda c: ["method=toy", *c.toy(data=c.colmap(_truncate("cameras.bin", 100)))],
                              "sparse/0/cameras.bin: truncated"),
    "model file deleted": ("train", lambda c: ["method=toy", *c.toy(data=c.colmap(_second_model_and_no_cameras))],
                           "sparse/0/cameras.bin: missing"),
    "eval device=tpu": ("eval", lambda c: [c.run(), "device=tpu"], "device=tpu"),
    "export what=obj": ("export", lambda c: [c.run(), "what=obj"], "what=obj"),
    "render path=loop": ("render", lambda c: [c.run(), "path=loop"], "path=loop"),
}


class _Paths:
    """Builds each case's inputs under its own temporary folder."""

    def __init__(self, tmp: Path, scene: Path, tj_scene: Path, reference_run: Path):
        self.tmp, self.scene, self.tj_scene, self.reference_run = tmp, scene, tj_scene, reference_run
        self.held = tmp / "held.txt"
        self.held.write_text("images_rain/003.png\n099.png\n")

    def toy(self, *extra: str, data: Path | None = None) -> list[str]:
        return _toy_args(data or self.scene, self.tmp / "outputs", "trainer.max_iters=3", *extra)

    def tj(self, name: str, change) -> Path:
        return _tj_variant(self.tj_scene, self.tmp / name, change)

    def depth(self) -> Path:
        return _truncated_depth(self.scene, self.tmp / "depth_scene")

    def run(self, change=None) -> Path:
        return _run_copy(self.reference_run, self.tmp / "run", change)

    def colmap(self, change) -> Path:
        scene = _colmap_scene(self.tmp / "colmap_scene")
        change(scene)
        return scene


@pytest.mark.parametrize("case", sorted(BAD_INPUTS))
def test_bad_input_is_one_error_line_naming_it(case, toy_env, tiny_scene_dir, tj_scene, reference_run,
                                               tmp_path, capsys):
    command, argv, names = BAD_INPUTS[case]
    paths = _Paths(tmp_path, tiny_scene_dir, tj_scene, reference_run)
    args = argv(paths)
    before = _snapshot(tmp_path)
    code, err = _cli(capsys, command, *args)
    line = _one_error_line(err)
    assert code == 2, err
    assert names in line, line
    assert not (tmp_path / "outputs").exists()  # input errors come before a run folder (or its parents)
    assert _snapshot(tmp_path) == before  # the inputs (run copies, scenes) survive byte for byte


# ------------------------------------------------------------------------ inputs that work


def test_awkward_but_valid_inputs_train_and_evaluate(toy_env, tiny_scene_dir, tj_scene, tmp_path, capsys):
    out = tmp_path / "outputs"
    # 8 x 8 images (SSIM measures them with a window that fits), in rs-train and in rs-eval
    code, err = _cli(capsys, "train", "method=toy",
                     *_toy_args(tiny_scene_dir, out / "small", "trainer.max_iters=3", "dataparser.downscale=6"))
    assert code == 0, err
    small = _only_run(out / "small")
    assert json.loads((small / "metrics.json").read_text())["views"]["width"] == 8
    assert _cli(capsys, "eval", small, "device=cpu")[0] == 0
    # whole images (patch_size=0) with a ray-sized batch: capped, with a word
    code, err = _cli(capsys, "train", "method=toy",
                     *_toy_args(tiny_scene_dir, out / "whole", "trainer.max_iters=2",
                                "phases.warmup.patch_size=0", "phases.warmup.patches=1024"))
    assert code == 0 and "a step takes 1" in err, err
    # dataparser=auto with the detected format's option; a held-out list written as
    # transforms.json writes paths, relative to the scene; a single-view scene warns
    held = tj_scene / "held.txt"
    held.write_text("images_rain/004.png\n./images_rain/008.png\n012\n")
    code, err = _cli(capsys, "train", "method=toy",
                     *_toy_args(tj_scene, out / "auto", "trainer.max_iters=2", "dataparser.clean=images_wo_rain",
                                "dataparser.holdout_file=held.txt"))
    assert code == 0, err
    run = _only_run(out / "auto")
    cfg = config.load_yaml(run / "config.yml")
    assert cfg.dataparser.name == "transforms-json" and cfg.dataparser.options.clean == "images_wo_rain"
    metrics = json.loads((run / "metrics.json").read_text())
    assert metrics["views"]["heldout"] == 3 and metrics["has_clean"]
    single = _tj_variant(tj_scene, tmp_path / "single", lambda m: m.update(frames=m["frames"][:1]))
    code, err = _cli(capsys, "train", "method=toy", *_toy_args(single, out / "single", "trainer.max_iters=2"))
    assert code == 0 and "single view" in err, err


def test_nerfstudio_split_lists_give_the_held_out_views(tj_scene, tmp_path):
    from rainyscape.dataparsers.transforms_json import TransformsJsonConfig, TransformsJsonParser

    def split(change) -> list[int]:
        folder = _tj_variant(tj_scene, tmp_path / f"s{len(list(tmp_path.iterdir()))}", change)
        return TransformsJsonParser(TransformsJsonConfig()).parse(folder).eval_indices

    def lists(meta):
        paths = [f["file_path"] for f in meta["frames"]]
        meta.update(train_filenames=paths[:9], val_filenames=paths[9:11], test_filenames=["./" + paths[11]])

    assert split(lists) == [9, 10, 11]
    assert split(lambda m: m.update(train_filenames=[f["file_path"] for f in m["frames"][:10]])) == [10, 11]


def test_the_end_of_run_evaluation_is_bounded_and_says_which_views(reference_run):
    metrics = json.loads((reference_run / "metrics.json").read_text())
    done = metrics["evaluated"]
    assert len(done["views"]) == 8 and not done["all"]  # trainer.final_eval_views, by default 8 of 12
    # half from each split where it has enough: the one held-out view, and 7 of 11 training views
    assert (done["train"], done["heldout"]) == (7, 1) == (7, metrics["views"]["heldout"])
    assert [r["view"] for r in metrics["per_view"]] == done["views"]
    report = (reference_run / "report.html").read_text()
    assert "Measured on 8 of 12 views: " + ", ".join(done["views"]) in report


# ------------------------------------------------- the third probe (issue 31): nothing lost


def _user_folder(folder: Path) -> dict[str, bytes]:
    """A folder of the user's with files a tool could mistake for its own; its snapshot."""
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "x.md").write_text("# my notes\n")
    (folder / "x.json").write_text('{"mine": true}\n')
    (folder / "images_rain").mkdir(exist_ok=True)
    (folder / "images_rain" / "001.png").write_bytes(b"my photo")
    return _snapshot(folder)


def test_case1_rs_bench_writes_only_its_own_files(toy_env, tiny_scene_dir, tmp_path, capsys):
    from rainyscape.comparison.output import BenchOutput, check_output, is_results_file, start_afresh

    d = tmp_path / "d"
    before = _user_folder(d)
    bench = ["methods=toy", f"scenes={tiny_scene_dir}", "iters=2", f"out={d}", "device=cpu"]
    code, err = _cli(capsys, "bench", *bench, "name=x")  # x.md and x.json are the user's
    assert code == 2 and f"{d / 'x.json'}: not an rs-bench results file" in _one_error_line(err)
    (d / "x.json").write_text('{"cells": {}}')  # one of rs-bench's (an empty benchmark)
    code, err = _cli(capsys, "bench", *bench, "name=x")
    assert code == 2 and f"{d / 'x.md'}: its first line is not '# Benchmark x'" in _one_error_line(err)
    (d / "x.md").write_text("# Benchmark x\n")
    (d / "runs" / "x" / "mine").mkdir(parents=True)
    code, err = _cli(capsys, "bench", *bench, "name=x")
    assert code == 2 and f"{d / 'runs' / 'x' / 'mine'}: not a cell folder" in _one_error_line(err)
    for bad in ("name=../y", "name=y.json"):
        code, err = _cli(capsys, "bench", *bench, bad)
        assert code == 2 and bad in _one_error_line(err)
    (d / "x.json").write_bytes(before["x.json"])
    (d / "x.md").write_bytes(before["x.md"])
    assert {k: v for k, v in _snapshot(d).items()} == before  # refused, each time, before any write
    assert sorted(p.name for p in d.iterdir()) == ["images_rain", "runs", "x.json", "x.md"]
    # force=true: benchmark x starts afresh, its whole output replaced; nothing else touched
    target = BenchOutput(d, "x")
    check_output(target, force=True)
    start_afresh(target)
    assert sorted(p.name for p in d.iterdir()) == ["images_rain", "runs"] and not (d / "runs" / "x").exists()
    assert _snapshot(d) == {"images_rain/001.png": before["images_rain/001.png"]}
    assert not is_results_file(tmp_path / "nope.json")


def test_case2_a_failed_resume_leaves_the_run_as_it_was(reference_run, tmp_path, capsys):
    run = _run_copy(reference_run, tmp_path / "run", _drop_weights)  # its checkpoint does not fit
    before = _snapshot(run)
    code, err = _cli(capsys, "train", f"resume={run}", "trainer.max_iters=42", f"data={tmp_path}")
    assert code == 2 and str(tmp_path) in _one_error_line(err)  # no scene there
    code, err = _cli(capsys, "train", f"resume={run}", "trainer.max_iters=42")
    assert code == 2 and "does not fit" in _one_error_line(err)
    assert _snapshot(run) == before  # config.yml, status.json, the log: byte for byte
    assert RunFolder(run).status()["state"] == "finished"


def test_case3_and_4_rs_synth_replaces_a_whole_scene_or_nothing(tmp_path, capsys, monkeypatch):
    from rainyscape.dataparsers.maya_csv import MayaCsvConfig, MayaCsvParser
    from rainyscape.synth import simulate

    out = tmp_path / "scene"
    small = ["preset=demo", f"out={out}", "width=8", "height=8"]
    assert _cli(capsys, "synth", *small, "rows=2", "cols=3")[0] == 0
    (out / "notes.txt").write_text("mine\n")
    # force=true over a larger scene: the whole scene is replaced, not the views it rewrites
    assert _cli(capsys, "synth", *small, "rows=2", "cols=2", "force=true")[0] == 0
    assert sorted(p.name for p in (out / "images_rain").iterdir()) == ["001.png", "002.png", "003.png", "004.png"]
    assert MayaCsvParser(MayaCsvConfig()).parse(out).num_images == 4 and (out / "notes.txt").read_text() == "mine\n"
    before = _snapshot(out)
    # out of memory half-way: exit 2 with the simulator's knobs, the folder as it was, no leftovers
    real = simulate.Simulation.render_view

    def fail_on_third(self, k):
        if k == 2:
            raise MemoryError("std::bad_alloc")
        return real(self, k)

    monkeypatch.setattr(simulate.Simulation, "render_view", fail_on_third)
    for target, extra in ((out, ["force=true"]), (tmp_path / "new" / "scene", [])):
        code, err = _cli(capsys, "synth", "preset=demo", f"out={target}", "width=8", "rows=2", "cols=2", *extra)
        line = _one_error_line(err)
        assert code == 2 and "out of memory" in line and "width=" in line and "phases" not in line  # case 19
    assert _snapshot(out) == before and sorted(p.name for p in tmp_path.iterdir()) == ["scene"]
    monkeypatch.setattr(simulate.Simulation, "render_view", real)
    assert _cli(capsys, "synth", "preset=demo", f"out={tmp_path / 'new' / 'scene'}", "width=8", "rows=1",
                "cols=1")[0] == 0  # the retry is not refused


def test_case5_and_7_a_file_in_the_way_is_one_line_and_nothing_is_written(reference_run, toy_env,
                                                                          tiny_scene_dir, tmp_path, capsys):
    blocker = tmp_path / "a-file"
    blocker.write_text("mine\n")
    run = _run_copy(reference_run, tmp_path / "run")
    before = _snapshot(tmp_path)
    for command, argv in (
            ("train", ["method=toy", *_toy_args(tiny_scene_dir, blocker / "o", "trainer.max_iters=2")]),
            ("synth", ["preset=demo", f"out={blocker / 's'}", "width=8", "rows=1", "cols=1"]),
            ("export", [run, f"out={blocker / 'e'}", "what=cameras", "device=cpu"]),
            ("bench", ["methods=toy", f"scenes={tiny_scene_dir}", f"out={blocker / 'b'}", "device=cpu"])):
        code, err = _cli(capsys, command, *argv)
        assert code == 2 and f"{blocker} is a file, not a folder" in _one_error_line(err), (command, err)
    assert _snapshot(tmp_path) == before


@pytest.mark.skipif(os.name != "posix" or os.geteuid() == 0,
                    reason="root writes into read-only folders: run the suite as a user to test them")
def test_case5_and_6_read_only_folders_are_refused_before_any_work(reference_run, toy_env, tiny_scene_dir,
                                                                   tmp_path, capsys):
    ro = tmp_path / "read-only"
    ro.mkdir()
    run = _run_copy(reference_run, tmp_path / "run")
    for folder in (run / "checkpoints", run, ro):
        folder.chmod(0o555)
    try:
        before = _snapshot(tmp_path)
        for command, argv, names in (
                ("train", ["method=toy", *_toy_args(tiny_scene_dir, ro / "o", "trainer.max_iters=2")], str(ro)),
                ("train", [f"resume={run}", "trainer.max_iters=40"], str(run)),
                ("synth", ["preset=demo", f"out={ro / 's'}", "width=8", "rows=1", "cols=1"], str(ro)),
                ("export", [run, f"out={ro / 'e'}", "device=cpu"], str(ro)),
                ("bench", ["methods=toy", f"scenes={tiny_scene_dir}", f"out={ro / 'b'}", "device=cpu"], str(ro)),
                ("eval", [run, "device=cpu"], str(run)),  # case 6: before the evaluation, not after
                ("render", [run, "device=cpu"], str(run))):
            code, err = _cli(capsys, command, *argv)
            line = _one_error_line(err)
            assert code == 2 and names in line and "permission denied" in line, (command, err)
        assert _snapshot(tmp_path) == before
    finally:
        for folder in (run / "checkpoints", run, ro):
            folder.chmod(0o755)


def test_a_failed_command_leaves_the_users_folders_as_they_were(reference_run, toy_env, tiny_scene_dir,
                                                                 tmp_path, capsys, monkeypatch):
    from rainyscape.engine.trainer import Trainer
    from rainyscape.eval import export

    out = tmp_path / "outputs"
    before = _user_folder(out)

    def out_of_memory(*args, **kwargs):
        raise MemoryError("std::bad_alloc")

    # a new run that fails before its first checkpoint leaves no run folder behind
    monkeypatch.setattr(Trainer, "train", out_of_memory)
    code, err = _cli(capsys, "train", "method=toy", *_toy_args(tiny_scene_dir, out, "trainer.max_iters=2"))
    assert code == 2 and "out of memory" in _one_error_line(err)
    assert _snapshot(out) == before and sorted(p.name for p in out.iterdir()) == ["images_rain", "x.json", "x.md"]
    # an export that fails half-way (force=true or not) changes nothing in its folder
    run = _run_copy(reference_run, tmp_path / "run")
    real = export.export_cameras

    def half(pipeline, folder, images=True):
        real(pipeline, folder, images)
        raise MemoryError("std::bad_alloc")

    monkeypatch.setattr(export, "export_cameras", half)
    code, err = _cli(capsys, "export", run, f"out={out}", "what=cameras", "device=cpu", "force=true")
    assert code == 2 and "device=cpu" in _one_error_line(err)  # rs-export's own advice
    assert _snapshot(out) == before and not [p for p in tmp_path.iterdir() if ".partial-" in p.name]


def test_case9_every_synth_option_has_a_range(capsys):
    for args, names in ((["density=-3"], "density"), (["opacity=5"], "opacity"), (["haze=2"], "haze"),
                        (["workers=0"], "workers"), (["wind_deg=95"], "wind_deg"), (["rows=0"], "rows"),
                        (["radius_min_mm=3", "radius_max_mm=0.5"], "radius_max_mm: must be at least radius_min_mm (3)"),
                        (["mode=sometimes"], "mode=sometimes"), (["preset=moon"], "preset=moon")):
        code, err = _cli(capsys, "synth", "out=/nonexistent/never-made", *args)
        assert code == 2 and names in _one_error_line(err), args
    assert not Path("/nonexistent/never-made").exists()


def test_case11_and_15_rs_bench_checks_everything_before_it_writes(toy_env, tj_scene, tmp_path, capsys):
    out = tmp_path / "results"
    code, err = _cli(capsys, "bench", "methods=toy", f"scenes={tj_scene}", f"out={out}", "device=tpu")
    assert code == 2 and "device=tpu" in _one_error_line(err)
    if not torch.cuda.is_available():
        code, err = _cli(capsys, "bench", "methods=toy", f"scenes={tj_scene}", f"out={out}", "device=cuda")
        assert code == 2 and "CUDA is not available" in _one_error_line(err)
    # case 15: clean images the parser does not find would make every cell n/a, silently
    scene = tmp_path / "clean-elsewhere"
    shutil.copytree(tj_scene, scene)
    (scene / "images_wo_rain").rename(scene / "images_clean")
    code, err = _cli(capsys, "bench", "methods=toy", f"scenes={scene}", f"out={out}", "device=cpu")
    line = _one_error_line(err)
    assert code == 2 and str(scene) in line and "no clean images" in line
    assert not out.exists()


def test_case12_a_second_rs_bench_of_the_same_results_is_refused(toy_env, tiny_scene_dir, tmp_path, capsys):
    from rainyscape.engine.lock import RunLock

    out = tmp_path / "results"
    out.mkdir()
    with RunLock(out, "rs-bench", name=".x.lock"):  # what the first rs-bench holds while it runs
        code, err = _cli(capsys, "bench", "methods=toy", f"scenes={tiny_scene_dir}", "iters=2", f"out={out}",
                         "name=x", "device=cpu")
    line = _one_error_line(err)
    assert code == 2 and f"benchmark {out / 'x.json'}: in use by rs-bench (pid {os.getpid()}" in line
    assert sorted(p.name for p in out.iterdir()) == [".x.lock"]


def test_a_stopped_rs_bench_stops_its_cells_and_starts_no_more(toy_env, tiny_scene_dir, tmp_path):
    """SIGTERM to rs-bench alone (a scheduler's stop, `kill PID`): the running cell stops with a
    checkpoint to resume from, and the queued cell does not start."""
    second = tmp_path / "second"
    shutil.copytree(tiny_scene_dir, second)
    out = tmp_path / "results"
    args = [sys.executable, "-m", "rainyscape.cli.bench", "methods=toy", f"scenes={tiny_scene_dir},{second}",
            "iters=400", f"out={out}", "name=x", "device=cpu", "jobs=1", "field.delay=0.05",
            "trainer.checkpoint_every=5", "trainer.eval_every=0", "phases.warmup.patches=2",
            "phases.warmup.patch_size=8"]
    proc = subprocess.Popen(args, env=toy_env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)

    def training() -> bool:
        return any(s >= 3 for log in out.rglob("log.jsonl") for s in _logged_steps_safe(log.parent))

    _wait_for(training, proc)
    proc.send_signal(signal.SIGTERM)
    proc.wait(timeout=120)
    assert proc.returncode == 130
    cells = sorted((out / "runs" / "x").iterdir())
    assert len(cells) == 1  # the queued cell never started
    assert not any(str(cells[0]) in " ".join(_cmdline(pid)) for pid in _pids())  # nor runs on
    assert RunFolder(_only_run(cells[0])).status()["state"] == "interrupted"


def _pids() -> list[int]:
    return [int(p.name) for p in Path("/proc").iterdir() if p.name.isdigit()]


def _cmdline(pid: int) -> list[str]:
    try:
        return (Path("/proc") / str(pid) / "cmdline").read_bytes().decode(errors="replace").split("\0")
    except OSError:
        return []


def test_case20_two_evaluations_of_the_same_weights_give_the_same_metrics(reference_run, tmp_path, capsys):
    run = _run_copy(reference_run, tmp_path / "run")
    first = (run / "metrics.json").read_bytes()  # the end-of-run evaluation of the training process
    for _ in range(2):  # evaluated again, each time in this process
        code, err = _cli(capsys, "train", f"resume={run}", "force=true")
        assert code == 0, err
        assert (run / "metrics.json").read_bytes() == first
    assert "evaluating 8 of 12 views (" in err
