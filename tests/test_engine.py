"""Engine: a plugin field trains end to end; run folders; checkpoints; exact resume."""

from __future__ import annotations

import json
import os
import subprocess
from pathlib import Path

import pytest
import torch

from _plugins import install_toy_plugin
from rainyscape import config, registry
from rainyscape.engine.checkpoint import list_checkpoints, save_checkpoint
from rainyscape.engine.run import load_run
from rainyscape.workflow import train_and_evaluate


@pytest.fixture
def toy_env(tmp_path, monkeypatch):
    path = install_toy_plugin(tmp_path / "plugin")
    monkeypatch.syspath_prepend(str(path))
    monkeypatch.delenv("RAINYSCAPE_PLUGINS", raising=False)
    registry.clear_cache()
    yield dict(os.environ, PYTHONPATH=str(path))
    registry.clear_cache()


def _run_dirs(root: Path) -> list[Path]:
    return sorted(p.parent for p in root.rglob("config.yml"))


def test_plugin_field_trains_through_the_cli(toy_env, tiny_scene_dir, tmp_path):
    out_root = tmp_path / "outputs"
    args = ["rs-train", "method=toy", f"data={tiny_scene_dir}", f"trainer.output_dir={out_root}",
            "trainer.max_iters=40", "trainer.log_every=1", "trainer.keep_checkpoints=2"]
    done = subprocess.run(args, capture_output=True, text=True, env=toy_env)
    assert done.returncode == 0, done.stderr
    (run,) = _run_dirs(out_root)
    assert run.parent.name == "toy"
    assert json.loads((run / "status.json").read_text())["state"] == "finished"
    assert [p.name for p in list_checkpoints(run / "checkpoints")] == ["step-0000030.pt", "step-0000040.pt"]
    assert not list((run / "checkpoints").glob("*.tmp"))
    records = [json.loads(line) for line in (run / "log.jsonl").read_text().splitlines()]
    losses = [r["loss"] for r in records if "loss" in r]
    assert len(losses) == 40 and sum(losses[-5:]) < sum(losses[:5])  # it really fits
    metrics = json.loads((run / "metrics.json").read_text())
    assert metrics["summary"]["train_psnr_vs_rainy"] > 5
    # A second identical run gets a new folder; nothing is overwritten.
    again = subprocess.run(args, capture_output=True, text=True, env=toy_env)
    assert again.returncode == 0, again.stderr
    assert len(_run_dirs(out_root)) == 2


def test_bad_scene_folder_fails_before_creating_a_run(toy_env, tmp_path):
    empty = tmp_path / "empty_scene"
    empty.mkdir()
    out = subprocess.run(["rs-train", "method=toy", f"data={empty}",
                          f"trainer.output_dir={tmp_path}/outputs"],
                         capture_output=True, text=True, env=toy_env)
    assert out.returncode == 2
    assert str(empty) in out.stderr and "Traceback" not in out.stderr
    assert not _run_dirs(tmp_path)


def test_checkpoints_are_atomic_and_pruned(tmp_path):
    for step in (1, 2, 3):
        save_checkpoint(tmp_path, step, {"x": torch.tensor([step])}, keep=2)
    assert [p.name for p in list_checkpoints(tmp_path)] == ["step-0000002.pt", "step-0000003.pt"]
    assert not list(tmp_path.glob("*.tmp"))


def _params(pipeline) -> dict[str, torch.Tensor]:
    out = {f"field.{k}": v.clone() for k, v in pipeline.field.state_dict().items()}
    if pipeline.rain_head is not None:
        out.update({f"rain.{k}": v.clone() for k, v in pipeline.rain_head.state_dict().items()})
    return out


# the grid field's recipe lattice (512) is for fitting, not for these mechanics tests
SMALL_GRID = ["field.resolution_final=64"]

RESUME_CASES = {
    "toy": ["trainer.max_iters=12"],
    # rain head, Langevin noise and joint phase across the split: latents must resume exactly
    "rainyscape-nerf": ["trainer.max_iters=12", "phases.warmup.end=0.5",
                        "phases.warmup.patches=4", "phases.joint.patch_size=16", *SMALL_GRID],
    # RobustNeRF's threshold, pool and residual map: the trimmed rays must be the same ones
    "robust-nerf": ["trainer.max_iters=12", *SMALL_GRID],
}


@pytest.mark.parametrize("method", sorted(RESUME_CASES))
def test_resume_reaches_the_same_parameters(method, toy_env, tiny_scene_dir, tmp_path):
    common = [f"data={tiny_scene_dir}", "trainer.device=cpu", "trainer.progress=false",
              "trainer.eval_every=0", "trainer.checkpoint_every=0", *RESUME_CASES[method]]
    full_cfg = config.method_config(method, common + [f"trainer.output_dir={tmp_path}/a"])
    full = train_and_evaluate(full_cfg)
    split_cfg = config.method_config(method, common + [f"trainer.output_dir={tmp_path}/b", "trainer.stop_at=7"])
    first = train_and_evaluate(split_cfg)
    assert json.loads((first.run_dir / "status.json").read_text())["state"] == "stopped"
    resumed_cfg = config.load_yaml(first.run_dir / "config.yml")
    resumed_cfg.trainer.stop_at = 0
    train_and_evaluate(resumed_cfg, run_dir=first.run_dir)
    a, step_a = load_run(full.run_dir, device="cpu")
    b, step_b = load_run(first.run_dir, device="cpu")
    assert step_a == step_b == full_cfg.trainer.max_iters
    pa, pb = _params(a), _params(b)
    assert pa.keys() == pb.keys()
    for key in pa:
        assert torch.allclose(pa[key], pb[key], atol=1e-6, rtol=0), key


def test_plugin_field_gets_the_rain_module_for_free(toy_env, tiny_scene_dir, tmp_path):
    """A third-party field swapped into a built-in rain method, with a plugin loss added."""
    cfg = config.method_config("rainyscape-nerf", [
        f"data={tiny_scene_dir}", "field=direction", "losses.mean-abs.weight=0.5",
        "losses.mean-abs.phases=warmup", "trainer.max_iters=16", "phases.joint.patch_size=16",
        "trainer.eval_every=0", "trainer.log_every=1", "trainer.progress=false",
        f"trainer.output_dir={tmp_path}"])
    result = train_and_evaluate(cfg)
    assert json.loads((result.run_dir / "status.json").read_text())["state"] == "finished"
    records = [json.loads(line) for line in (result.run_dir / "log.jsonl").read_text().splitlines()]
    joint = [r for r in records if r.get("phase") == "joint" and "terms" in r]
    assert joint and {"likelihood", "reconstruction", "tv", "agr"} <= set(joint[-1]["terms"])
    warm = [r for r in records if r.get("phase") == "warmup" and "terms" in r]
    assert "mean-abs" in warm[-1]["terms"]


def test_plugin_rain_head_trains_through_a_builtin_rain_method(toy_env, tiny_scene_dir, tmp_path):
    """A third-party rain head (one class, one entry point) replaces the built-in one in
    rainyscape-nerf: it predicts R in the joint phase and the rain losses train it."""
    out_root = tmp_path / "outputs"
    args = ["rs-train", "method=rainyscape-nerf", "rain_head=toy-rain", f"data={tiny_scene_dir}",
            f"trainer.output_dir={out_root}", "trainer.max_iters=16", "phases.warmup.end=0.5",
            "phases.joint.patch_size=16",
            "trainer.eval_every=0", "trainer.log_every=1", "trainer.progress=false", "trainer.device=cpu",
            *SMALL_GRID]
    done = subprocess.run(args, capture_output=True, text=True, env=toy_env)
    assert done.returncode == 0, done.stderr
    (run,) = _run_dirs(out_root)
    records = [json.loads(line) for line in (run / "log.jsonl").read_text().splitlines()]
    joint = [r for r in records if r.get("phase") == "joint" and "terms" in r]
    assert len(joint) == 8 and {"likelihood", "reconstruction", "agr"} <= set(joint[-1]["terms"])
    pipeline, _ = load_run(run, device="cpu")
    assert type(pipeline.rain_head).__name__ == "ToyRain"
    assert not torch.equal(pipeline.rain_head.maps, torch.full_like(pipeline.rain_head.maps, -4.0))


def _gradient_norms(trainer) -> dict[str, list[float]]:
    """Each model's gradient norm at every step it takes (what its optimisers step on),
    recorded from then on into the returned dict."""
    norms: dict[str, list[float]] = {}

    def record(key: str, params: list) -> None:
        grads = [p.grad.norm() for p in params if p.grad is not None]
        if grads:
            norms.setdefault(key, []).append(float(torch.linalg.vector_norm(torch.stack(grads))))

    for key, groups in trainer.groups.items():
        params = [p for g in groups for p in g.params]
        trainer.optimizers[groups[0].name].register_step_pre_hook(
            lambda *_, key=key, params=params: record(key, params))
    return norms


@pytest.mark.parametrize("clip", [0.0, 1e-3])
def test_phase_grad_clip_bounds_each_models_gradient_norm(tiny_scene, tmp_path, clip):
    """``phases.NAME.grad_clip``: what each model's optimisers step on has at most that norm
    (the authors' 3DGS joint phase clips at 1); 0 leaves the gradients alone."""
    from rainyscape.engine.pipeline import build_pipeline
    from rainyscape.engine.trainer import Trainer

    cfg = config.method_config("rainyscape-3dgs", [
        "trainer.max_iters=4", "phases.warmup.end=0.5", f"phases.joint.grad_clip={clip}", "field.init_fill=0",
        "rain_head.latent_patch_size=16", "rain_head.latent_steps=1", "rain_head.lowres_channels=[8,8,8,8]",
        "rain_head.highres_channels=4",
        "trainer.eval_every=0", "trainer.checkpoint_every=0", "trainer.progress=false"])
    torch.manual_seed(0)
    trainer = Trainer(build_pipeline(cfg, tiny_scene, torch.device("cpu")), tmp_path)
    norms = _gradient_norms(trainer)
    trainer.train()
    joint = {key: values[-1] for key, values in norms.items()}  # the last step is a joint one
    assert {"field", "rain_head"} <= set(joint)
    if clip:
        assert all(n <= clip * 1.001 for n in joint.values()), joint
    else:
        assert max(joint.values()) > 1e-3, joint  # the clip above acts on gradients this large


def test_rainyscape_nerf_field_gradients_keep_their_scale_across_the_phase_switch(tiny_scene, tmp_path):
    """The warm-up term weighs the field's squared error as the joint phase's reconstruction
    term does, so the field's gradients keep their scale when the rain terms take over. At
    weight 1 they jumped 500x there, and Adam's second moments, tuned to the warm-up, let the
    field take steps up to 6x its rate for hundreds of steps (docs/rain.md)."""
    from rainyscape.engine.pipeline import build_pipeline
    from rainyscape.engine.trainer import Trainer

    cfg = config.method_config("rainyscape-nerf", [
        "trainer.max_iters=8", "field.resolution_final=32", "rain_head.latent_steps=1",
        "trainer.eval_every=0", "trainer.checkpoint_every=0", "trainer.progress=false"])
    torch.manual_seed(0)
    trainer = Trainer(build_pipeline(cfg, tiny_scene, torch.device("cpu")), tmp_path)
    norms = _gradient_norms(trainer)
    trainer.train()
    warmup, joint = norms["field"][:4], norms["field"][4:]  # warm-up: the first half of the run
    assert len(joint) == 4
    ratio = (sum(joint) / 4) / (sum(warmup[-2:]) / 2)
    assert 0.2 < ratio < 5, (warmup, joint)


def test_a_cpu_trainer_flushes_denormal_numbers_to_zero(tiny_scene, tmp_path):
    """Adam's moments of texels no ray reaches decay below float32's normal range, where
    arithmetic takes the slow path (a 512^3 grid step twice as long): a CPU trainer makes
    that range zero."""
    from rainyscape.engine.device import flush_denormals
    from rainyscape.engine.pipeline import build_pipeline
    from rainyscape.engine.trainer import Trainer

    tiny = torch.tensor([1e-30])
    torch.set_flush_denormal(False)
    try:
        assert float(tiny * 1e-10) > 0  # 1e-40: a denormal, kept
        if not flush_denormals(torch.device("cpu")):
            pytest.skip("this CPU cannot flush denormals")
        torch.set_flush_denormal(False)
        cfg = config.method_config("nerf", ["trainer.max_iters=1", "trainer.eval_every=0",
                                            "trainer.checkpoint_every=0", "trainer.progress=false"])
        Trainer(build_pipeline(cfg, tiny_scene, torch.device("cpu")), tmp_path)
        assert float(tiny * 1e-10) == 0.0
        assert float(tiny * 1e-5) > 0  # normal numbers are untouched
    finally:
        torch.set_flush_denormal(False)
    assert not flush_denormals(torch.device("meta"))  # not a CPU: nothing changes
