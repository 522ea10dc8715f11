"""Install the toy third-party plugin (tests/toy_plugin) into a folder as a real distribution."""

from __future__ import annotations

import shutil
from pathlib import Path

TOY_SOURCE = Path(__file__).parent / "toy_plugin" / "rs_toy_plugin"

ENTRY_POINTS = """\
[rainyscape.fields]
direction = rs_toy_plugin:DirectionField
broken-field = rs_toy_plugin.missing_module:Nothing

[rainyscape.rain_heads]
toy-rain = rs_toy_plugin:ToyRain

[rainyscape.losses]
mean-abs = rs_toy_plugin:MeanAbsolute

[rainyscape.methods]
toy = rs_toy_plugin:toy_method
"""


def install_toy_plugin(dest: Path) -> Path:
    """Copy the package and write ``rs_toy_plugin-0.1.0.dist-info`` (METADATA, entry_points.txt)
    into ``dest``; putting ``dest`` on sys.path / PYTHONPATH installs it."""
    dest = Path(dest)
    shutil.copytree(TOY_SOURCE, dest / "rs_toy_plugin", dirs_exist_ok=True)
    info = dest / "rs_toy_plugin-0.1.0.dist-info"
    info.mkdir(exist_ok=True)
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: rs-toy-plugin\nVersion: 0.1.0\n")
    (info / "entry_points.txt").write_text(ENTRY_POINTS)
    (info / "top_level.txt").write_text("rs_toy_plugin\n")
    return dest
