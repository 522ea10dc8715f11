"""auto: pick the dataparser from what a scene folder contains."""

from __future__ import annotations

from dataclasses import asdict, fields
from pathlib import Path

from rainyscape import registry
from rainyscape.components import DataParser
from rainyscape.dataparsers.base import CommonParserConfig
from rainyscape.errors import DataError
from rainyscape.scene import SceneData

# (what marks the format, dataparser name), checked in this order. A COLMAP model wins over
# the transforms.json that rs-process-data writes beside it: it also carries sparse points.
MARKERS: list[tuple[tuple[str, ...], str]] = [
    (("cameras.csv",), "maya-csv"),
    (("poses_bounds.npy",), "llff"),
    (("sparse", "cameras.bin", "cameras.txt"), "colmap"),
    (("transforms.json",), "transforms-json"),
]


def detect_format(path: Path) -> str:
    """Name of the dataparser for the folder ``path``; DataError when nothing matches."""
    if not path.is_dir():
        raise DataError(f"{path}: no such scene folder")
    for markers, name in MARKERS:
        if any((path / m).exists() for m in markers):
            return name
    raise DataError(
        f"{path}: cannot tell the scene format: expected cameras.csv (maya-csv), poses_bounds.npy "
        "(llff), transforms.json (transforms-json) or sparse/ / cameras.bin (colmap); "
        "choose one with dataparser=NAME")


class AutoParser(DataParser):
    """Detects the format and forwards the common options to that format's parser."""

    description = "detect the format (maya-csv, llff, transforms-json, colmap) from the folder"
    Config = CommonParserConfig

    def __init__(self, config: CommonParserConfig | None = None):
        super().__init__(config or CommonParserConfig())

    @staticmethod
    def resolve(path: str | Path) -> str:
        """The dataparser that reads ``path`` (the config layer asks, to accept that
        parser's options under ``dataparser=auto``)."""
        return detect_format(Path(path).expanduser())

    def parse(self, path: Path) -> SceneData:
        path = Path(path)
        name = detect_format(path)
        cls = registry.load("dataparser", name)
        target = getattr(cls, "Config", CommonParserConfig)
        common = {f.name for f in fields(CommonParserConfig)}
        options = {k: v for k, v in asdict(self.config).items() if k in common}
        scene = cls(target(**options)).parse(path)
        scene.metadata.setdefault("dataparser", name)
        return scene
