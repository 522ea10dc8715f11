"""The argument layer every rs-* command parses through (rainyscape/cli/args.py)."""

from __future__ import annotations

import importlib
from dataclasses import dataclass

import pytest

from rainyscape.cli import run_cli
from rainyscape.cli.args import Command, help_text, opt, parse
from rainyscape.errors import ConfigError

COMMANDS = ["train", "eval", "render", "export", "bench", "synth", "process_data"]


@dataclass
class Toy:
    name: str = opt("x", "a name")
    count: int = opt(3, "how many")
    scale: float | None = opt(None, "a scale")
    video: bool = opt(True, "make a video")
    crop: tuple[float, float, float, float] = opt((0.0, 0.0, 0.0, 0.0), "four fractions")


TOY = Command("rs-toy", "rs-toy: a command for tests.\n\nUsage:\n  rs-toy [key=value ...]", Toy,
              actions=("--list",))


def test_key_values_are_typed_and_defaults_fill_the_rest():
    args = parse(["count=7", "scale=0.5", "crop=0.1,0,0,0.2"], TOY)
    assert args.options == Toy(name="x", count=7, scale=0.5, video=True, crop=(0.1, 0.0, 0.0, 0.2))
    assert args.values == {"count": 7, "scale": 0.5, "crop": (0.1, 0.0, 0.0, 0.2)}
    assert args.given["count"] == "count=7" and not args.help


def test_bool_options_are_flags_too():
    assert parse(["--no-video"], TOY).options.video is False
    assert parse(["video=false", "--video"], TOY).options.video is True
    args = parse(["--list", "-h"], TOY)
    assert args.actions == {"--list", "-h"} and args.help


@pytest.mark.parametrize("argv, message", [
    (["cont=2"], "rs-toy: unknown key 'cont'. Did you mean 'count'? Valid keys: name, count, scale, video, crop"),
    (["count=two"], "count: cannot read 'two' as int"),
    (["--vidoe"], "unknown option --vidoe. Did you mean '--video'?"),
    (["--count", "2"], "--count takes a value: write count=VALUE"),
    (["crop=0.1,0.2"], "crop: expected 4 values, got 2"),
    (["stray"], "rs-toy: unexpected argument 'stray'"),
])
def test_mistakes_are_named_with_the_valid_choices(argv, message):
    with pytest.raises(ConfigError) as err:
        parse(argv, TOY)
    assert message in str(err.value)


def test_dashed_commands_read_key_value_pairs_after_the_flag():
    dashed = Command("rs-toy", "", Toy, dashed=True, positional="KIND")
    args = parse(["video", "--count", "5", "--crop", "0.1", "0", "0", "0.3", "--scale=2", "name=y"], dashed)
    assert args.positional == ["video"]
    assert args.options == Toy(name="y", count=5, scale=2.0, crop=(0.1, 0.0, 0.0, 0.3))
    assert args.given["count"] == "--count 5" and args.given["crop"] == "--crop 0.1 0 0 0.3"
    with pytest.raises(ConfigError, match="--crop expects 4 values"):
        parse(["--crop", "0.1"], dashed)


def test_overrides_pass_through_in_order():
    dotted = Command("rs-toy", "", Toy, overrides="dotted")
    args = parse(["b.x=1", "count=2", "a.y=2"], dotted)
    assert args.overrides == ["b.x=1", "a.y=2"] and args.options.count == 2
    with pytest.raises(ConfigError, match="Did you mean 'count'"):
        parse(["cont=2"], dotted)
    assert parse(["data=/x", "field.k=1"], Command("rs-toy", "", Toy, overrides="any")).overrides == \
        ["data=/x", "field.k=1"]


def test_help_is_the_docstring_then_every_option_with_its_default():
    text = help_text(TOY)
    assert text.startswith("rs-toy: a command for tests.\n\nUsage:")
    assert "Options (key=value; defaults shown):" in text
    lines = {line.split()[0]: line for line in text.splitlines() if line.startswith("  ") and "=" in line}
    assert lines["count=3"].endswith("how many") and "scale=none" in lines
    assert "(--no-video)" in lines["video=true"] and "crop=0.0,0.0,0.0,0.0" in lines


@pytest.mark.parametrize("name", COMMANDS)
def test_every_command_parses_through_the_layer(name, capsys):
    module = importlib.import_module(f"rainyscape.cli.{name}")
    assert isinstance(module.COMMAND, Command) and module.COMMAND.doc == module.__doc__
    assert run_cli(module.main, ["--help"]) == 0
    out = capsys.readouterr().out
    assert out.startswith(f"rs-{name.replace('_', '-')}: ") and "Options (key=value; defaults shown):" in out
    assert run_cli(module.main, ["--frobnicate"]) == 2
    assert "unknown option --frobnicate" in capsys.readouterr().err


def test_process_data_takes_key_values_as_well_as_dashed_options(tmp_path, capsys):
    from rainyscape.cli.process_data import main

    empty = tmp_path / "photos"
    empty.mkdir()
    for argv in (["images", "--data", str(empty), "--output-dir", str(tmp_path / "a")],
                 ["images", f"data={empty}", f"output_dir={tmp_path / 'b'}"],
                 ["images", f"--data={empty}", f"output_dir={tmp_path / 'c'}", "--overwrite"]):
        assert run_cli(main, argv) == 2
        assert "no images found" in capsys.readouterr().err
    assert run_cli(main, ["video", f"data={empty}"]) == 2
    assert "--output-dir required" in capsys.readouterr().err
    assert run_cli(main, ["images", f"data={empty}", "output_dir=x", "num_frames=4"]) == 2
    assert "num_frames=4: only for a video" in capsys.readouterr().err
    assert run_cli(main, [f"data={empty}", "output_dir=x"]) == 2
    assert "video or images" in capsys.readouterr().err
