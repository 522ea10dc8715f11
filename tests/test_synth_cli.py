"""rs-synth command line and the cached demo scene."""

from __future__ import annotations

import json

import pytest

from rainyscape.cli import run_cli
from rainyscape.cli.synth import main
from rainyscape.synth import demo


def test_cli_writes_a_scene_and_reports_its_strength(tmp_path, capsys):
    out = tmp_path / "s"
    code = run_cli(main, ["preset=yard", f"out={out}", "rows=1", "cols=2", "width=24", "height=16",
                          "density=3", "wind_deg=20", "seed=3"])
    assert code == 0
    text = capsys.readouterr().out
    assert "rainy vs clean: PSNR" in text and "SSIM" in text
    info = json.loads((out / "scene.json").read_text())
    assert (info["width"], info["height"], info["seed"]) == (24, 16, 3)
    assert info["rain"]["density"] == 3.0 and info["rain"]["wind_deg"] == 20.0
    assert f"{info['metrics']['psnr_rainy_vs_clean']:.2f} dB" in text
    # never overwrite: a second run into the same folder fails unless force=true
    assert run_cli(main, ["preset=yard", f"out={out}", "rows=1", "cols=1", "width=8"]) == 2
    assert "not empty" in capsys.readouterr().err
    assert run_cli(main, ["preset=yard", f"out={out}", "rows=1", "cols=1", "width=8", "force=true"]) == 0


@pytest.mark.parametrize("args,message", [
    (["out=x", "densty=3"], "unknown key 'densty'. Did you mean 'density'?"),
    (["out=x", "rows=two"], "rows: cannot read 'two'"),
    (["out=x", "rows=0"], "rows: must be between 1 and 100, got 0"),
    (["preset=demo"], "where to write?"),
    (["out=x", "--fast"], "unknown option --fast"),
])
def test_cli_rejects_bad_arguments(args, message, capsys):
    assert run_cli(main, args) == 2
    assert message in capsys.readouterr().err


def test_cli_lists_presets(capsys):
    assert run_cli(main, ["--list"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert "at 128 px" in lines[0] and "at 512 px" in lines[0]
    assert sorted(line.split()[0] for line in lines[1:]) == ["bridge", "crossroad", "demo", "plaza", "street", "yard"]
    assert all(line.count(" dB / ") == 2 for line in lines[1:])  # measured at 128 and 512 px, this version


def test_demo_scene_is_cached_and_never_left_half_written(tmp_path, monkeypatch):
    monkeypatch.setenv("RAINYSCAPE_CACHE", str(tmp_path / "cache"))
    calls = []
    real = demo.generate

    def tiny(out, preset, force=False, **size):
        calls.append(out)
        return real(out, preset, rows=1, cols=2, width=16, height=16, force=force)

    def interrupted(out, preset, force=False, **size):
        real(out, preset, rows=1, cols=1, width=8, height=8, force=force)
        raise KeyboardInterrupt

    monkeypatch.setattr(demo, "generate", interrupted)
    with pytest.raises(KeyboardInterrupt):
        demo.ensure_demo_scene(verbose=False)
    assert not demo.demo_path().exists()
    assert list((tmp_path / "cache").iterdir()) == []  # the temporary folder is gone too
    monkeypatch.setattr(demo, "generate", tiny)
    path = demo.ensure_demo_scene(verbose=False)
    assert path == demo.demo_path() and (path / "scene.json").is_file()
    assert demo.SIM_VERSION in path.name
    assert demo.ensure_demo_scene(verbose=False) == path and len(calls) == 1
