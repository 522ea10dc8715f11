"""Config: dotted overrides, types, clear errors with exit codes, YAML round trip."""

from __future__ import annotations

import os
import subprocess

import pytest

from _plugins import install_toy_plugin
from rainyscape import config, registry
from rainyscape.errors import ConfigError


@pytest.fixture(autouse=True)
def toy_plugin(tmp_path_factory, monkeypatch):
    path = install_toy_plugin(tmp_path_factory.mktemp("plugin"))
    monkeypatch.syspath_prepend(str(path))
    monkeypatch.delenv("RAINYSCAPE_PLUGINS", raising=False)
    registry.clear_cache()
    yield path
    registry.clear_cache()


def test_nested_overrides_are_typed():
    cfg = config.method_config("toy", [
        "field.hidden=8", "field.lr=5e-3", "trainer.max_iters=7", "trainer.progress=false",
        "losses.mean-abs.weight=0.5", "losses.mean-abs.phases=warmup,joint", "trainer.device=cpu"])
    assert cfg.field.options.hidden == 8 and isinstance(cfg.field.options.hidden, int)
    assert cfg.field.options.lr == pytest.approx(5e-3)
    assert cfg.trainer.max_iters == 7 and cfg.trainer.progress is False
    assert cfg.losses["mean-abs"].weight == 0.5
    assert cfg.losses["mean-abs"].phases == ("warmup", "joint")


def test_method_defaults_are_applied_and_swap_resets_options():
    cfg = config.method_config("toy")
    assert cfg.field.options.hidden == 16  # the method's own default
    swapped = config.method_config("toy", ["field=direction"])
    assert swapped.field.options.hidden == 32  # the component's default
    both = config.method_config("toy", ["field.hidden=4", "field=direction"])  # swap first, then set
    assert both.field.options.hidden == 4


def test_loss_terms_can_be_dropped_and_added():
    cfg = config.method_config("toy", ["losses.mean-abs=none"])
    assert cfg.losses == {}
    cfg = config.method_config("toy", ["losses.mean-abs=none", "losses.mean-abs.weight=2"])
    assert cfg.losses["mean-abs"].weight == 2.0
    assert cfg.losses["mean-abs"].phases == ("warmup", "joint")  # the loss class's defaults
    # a term under a key of its own: the loss its name override names
    cfg = config.method_config("toy", ["losses.second.name=mean-abs", "losses.second.weight=3"])
    assert cfg.losses["second"].name == "mean-abs" and cfg.losses["second"].weight == 3.0
    assert cfg.losses["mean-abs"].weight == 1.0  # the method's own term is untouched


@pytest.mark.parametrize("override, message", [
    ("field.hiden=3", "unknown key 'field.hiden'. Did you mean 'hidden'?"),
    ("trainer.max_iter=3", "Did you mean 'max_iters'?"),
    ("trainer.max_iters=abc", "trainer.max_iters: cannot read 'abc' as int"),
    ("trainer.max_iters=2.5", "cannot read '2.5' as int"),
    ("trainer.progress=maybe", "cannot read 'maybe' as bool"),
    ("losses.mean-abs.phases=warmup,later", "unknown phase 'later'"),
    ("losses.mean-abs.detach=both", "is not one of"),
    ("fiel.hidden=3", "Did you mean 'field'?"),
    ("field=directon", "unknown field 'directon'. Did you mean 'direction'?"),
    ("novalue", "expected key=value"),
])
def test_bad_overrides_give_clear_errors(override, message):
    with pytest.raises(ConfigError) as err:
        config.method_config("toy", [override])
    assert message in str(err.value)


def test_yaml_round_trip_is_equal(tmp_path):
    cfg = config.method_config("toy", ["field.hidden=12", "trainer.seed=3", "data=/some/where"])
    path = tmp_path / "config.yml"
    config.save_yaml(cfg, path)
    text = path.read_text()
    assert "!!python" not in text and "rainyscape_version" in text  # plain data only
    assert config.load_yaml(path) == cfg


def test_profile_picks_the_recipe_by_device_and_is_recorded(tmp_path):
    cpu = config.method_config("toy", ["trainer.device=cpu"])
    assert (cpu.profile, cpu.trainer.max_iters, cpu.field.options.hidden) == ("cpu", 20, 16)
    gpu = config.method_config("toy", ["trainer.device=cuda"])  # auto: a CUDA run gets the gpu recipe
    assert (gpu.profile, gpu.trainer.max_iters, gpu.field.options.hidden) == ("gpu", 400, 64)
    forced = config.method_config("toy", ["profile=gpu", "trainer.device=cpu", "field.hidden=8"])
    assert (forced.profile, forced.trainer.max_iters, forced.field.options.hidden) == ("gpu", 400, 8)
    config.save_yaml(forced, tmp_path / "config.yml")
    assert "profile: gpu" in (tmp_path / "config.yml").read_text()
    assert config.load_yaml(tmp_path / "config.yml") == forced
    with pytest.raises(ConfigError, match="'tpu' is not one of auto, cpu, gpu"):
        config.method_config("toy", ["profile=tpu"])


def test_yaml_with_unknown_key_is_rejected(tmp_path):
    cfg = config.method_config("toy")
    data = config.to_dict(cfg)
    data["field"]["bogus"] = 1
    with pytest.raises(ConfigError, match="unknown key 'field.bogus'"):
        config.from_dict(data)


def test_method_help_prints_full_tree(toy_plugin):
    env = dict(os.environ, PYTHONPATH=str(toy_plugin))
    out = subprocess.run(["rs-train", "method=toy", "--help"], capture_output=True, text=True, env=env)
    assert out.returncode == 0, out.stderr
    assert "field.hidden = 16" in out.stdout and "trainer.max_iters = 20" in out.stdout
    assert "losses.mean-abs.weight = 1.0" in out.stdout


@pytest.mark.parametrize("args, message", [
    (["method=toy", "trainer.max_iters=abc"], "cannot read 'abc' as int"),
    (["method=toy", "data=/no/such/folder"], "no such scene folder"),
    (["method=nosuch"], "unknown method 'nosuch'"),
    (["trainer.max_iters=3"], "which method?"),
    (["method=toy", "--frobnicate"], "unknown option --frobnicate"),
])
def test_cli_errors_exit_non_zero_before_work(toy_plugin, tmp_path, args, message):
    env = dict(os.environ, PYTHONPATH=str(toy_plugin))
    out = subprocess.run(["rs-train", *args, f"trainer.output_dir={tmp_path}/outputs"],
                         capture_output=True, text=True, env=env, cwd=tmp_path)
    assert out.returncode == 2
    assert message in out.stderr and "Traceback" not in out.stderr
    assert not (tmp_path / "outputs").exists() or not any((tmp_path / "outputs").rglob("config.yml"))


def test_run_length_is_steps_per_training_view_within_bounds():
    from rainyscape.config import TrainerConfig, describe_run_length, run_length

    rule = TrainerConfig(max_iters=3000, iters_per_view=100, min_iters=1500)
    assert [run_length(rule, v) for v in (5, 17, 30, 50)] == [1500, 1700, 3000, 3000]
    assert run_length(TrainerConfig(max_iters=700, iters_per_view=0), 50) == 700  # no rule
    assert run_length(TrainerConfig(max_iters=700, iters_per_view=10, min_iters=5000), 3) == 700  # max wins
    assert "100 steps per training view" in describe_run_length(rule)


def test_a_ray_fields_run_length_follows_its_training_pixels():
    from rainyscape.config import TrainerConfig, describe_run_length, method_config, run_length

    rule = TrainerConfig(max_iters=3000, iters_per_mpixel=7500, min_iters=2000)
    # 16 views of 128 px (0.26 Mpx) at the floor, 18 of 252 x 189 (0.86 Mpx) at the cap, between them in proportion
    assert [run_length(rule, v, px) for v, px in ((16, 16 * 128 * 128), (18, 18 * 252 * 189), (10, 320_000))] \
        == [2000, 3000, 2400]
    assert "7500 steps per million training pixels" in describe_run_length(rule)
    nerf = method_config("nerf", []).trainer  # the recipe's rule, and every grid method's
    assert (nerf.min_iters, nerf.max_iters, nerf.iters_per_mpixel) == (2000, 3000, 7500)
    for name in ("robust-nerf", "rainyscape-nerf"):
        assert method_config(name, []).trainer == nerf


def test_the_scene_resolves_the_run_length_and_config_yml_records_it(toy_plugin, tiny_scene_dir, tmp_path):
    args = ["rs-train", "method=toy", f"data={tiny_scene_dir}", f"trainer.output_dir={tmp_path}",
            "trainer.max_iters=100", "trainer.iters_per_view=2", "trainer.min_iters=0"]
    done = subprocess.run(args, capture_output=True, text=True, env=dict(os.environ, PYTHONPATH=str(toy_plugin)))
    assert done.returncode == 0, done.stderr
    (run,) = [p.parent for p in tmp_path.rglob("config.yml")]
    cfg = config.load_yaml(run / "config.yml")
    assert cfg.trainer.max_iters == 2 * 11  # 12 views, the 8th held out
    assert '"step": 22' in (run / "status.json").read_text()
