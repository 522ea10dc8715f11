"""Registry: lazy entry-point discovery, third-party and broken plugins, clear errors."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from _plugins import install_toy_plugin
from rainyscape import registry
from rainyscape.errors import PluginError


def _env(plugin_dir) -> dict:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(plugin_dir), env.get("PYTHONPATH", "")]))
    env.pop("RAINYSCAPE_PLUGINS", None)
    return env


@pytest.fixture
def toy_on_path(tmp_path, monkeypatch):
    install_toy_plugin(tmp_path)
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.delenv("RAINYSCAPE_PLUGINS", raising=False)
    registry.clear_cache()
    yield tmp_path
    registry.clear_cache()
    for mod in [m for m in sys.modules if m.startswith("rs_toy_plugin")]:
        del sys.modules[mod]


def test_list_shows_builtins_and_plugin_with_origin(tmp_path):
    install_toy_plugin(tmp_path)
    out = subprocess.run(["rs-train", "--list"], capture_output=True, text=True, env=_env(tmp_path))
    assert out.returncode == 0, out.stderr
    rows = [line.split() for line in out.stdout.splitlines()]
    plugin_rows = {(r[0], r[1]): " ".join(r[2:4]) for r in rows if len(r) >= 4}
    assert plugin_rows[("field", "direction")] == "rs-toy-plugin 0.1.0"
    assert plugin_rows[("loss", "mean-abs")] == "rs-toy-plugin 0.1.0"
    assert plugin_rows[("method", "toy")] == "rs-toy-plugin 0.1.0"
    assert plugin_rows[("dataparser", "auto")].startswith("rainyscape ")
    # The broken plugin is reported once on stderr, skipped, and the others still load.
    assert out.stderr.count("broken-field") == 1
    assert "skipping broken plugin" in out.stderr and "missing_module" in out.stderr
    assert ("field", "broken-field") not in plugin_rows


def test_listing_names_imports_nothing(tmp_path):
    install_toy_plugin(tmp_path)
    code = ("import sys; from rainyscape import registry; "
            "names = registry.names('field'); "
            "print('direction' in names, 'rs_toy_plugin' in sys.modules, 'torch' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=_env(tmp_path))
    assert out.stdout.split() == ["True", "False", "False"], out.stderr


def test_train_help_does_not_import_torch():
    code = ("import sys, contextlib, io; from rainyscape.cli.train import main; "
            "buf = io.StringIO(); ctx = contextlib.redirect_stdout(buf); ctx.__enter__(); "
            "main(['--help']); ctx.__exit__(None, None, None); print('torch' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert out.stdout.strip() == "False", out.stderr


def test_loaded_plugin_is_the_class(toy_on_path):
    cls = registry.load("field", "direction")
    assert cls.__name__ == "DirectionField"
    assert registry.describe(cls).startswith("Colour as a function")


def test_unknown_name_suggests_close_match(toy_on_path):
    with pytest.raises(PluginError) as err:
        registry.load("field", "directon")
    assert "Did you mean 'direction'" in str(err.value)
    assert "Known fields:" in str(err.value)


def test_broken_plugin_error_names_it(toy_on_path):
    with pytest.raises(PluginError) as err:
        registry.load("field", "broken-field")
    msg = str(err.value)
    assert "broken-field" in msg and "rs-toy-plugin 0.1.0" in msg and "ModuleNotFoundError" in msg
    # and the working plugin of the same distribution still loads
    assert registry.load("loss", "mean-abs").__name__ == "MeanAbsolute"


def test_env_var_registers_without_packaging(tmp_path, monkeypatch):
    (tmp_path / "devplug.py").write_text("class Thing:\n    '''A dev-only loss.'''\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setenv("RAINYSCAPE_PLUGINS", "loss:dev-thing=devplug:Thing")
    registry.clear_cache()
    try:
        entry = registry.entries("loss")["dev-thing"]
        assert entry.origin == "RAINYSCAPE_PLUGINS"
        assert registry.load("loss", "dev-thing").__name__ == "Thing"
    finally:
        monkeypatch.delenv("RAINYSCAPE_PLUGINS")
        registry.clear_cache()


def test_env_var_malformed_is_a_clear_error(monkeypatch):
    monkeypatch.setenv("RAINYSCAPE_PLUGINS", "field-without-target")
    registry.clear_cache()
    try:
        with pytest.raises(PluginError, match="expected kind:name=module:attribute"):
            registry.entries("field")
    finally:
        monkeypatch.delenv("RAINYSCAPE_PLUGINS")
        registry.clear_cache()
