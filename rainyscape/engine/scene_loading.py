"""Reading a run's scene folder with the dataparser its config names."""

from __future__ import annotations

from pathlib import Path

from rainyscape import registry
from rainyscape.components import DataParser
from rainyscape.config import PipelineConfig
from rainyscape.config.schema import require_typed
from rainyscape.errors import DataError
from rainyscape.scene import SceneData


def load_scene(config: PipelineConfig, path: Path) -> SceneData:
    """Parse the scene folder ``path`` with the config's dataparser (DataError naming it when
    it is not there)."""
    require_typed(config, "the scene")
    if not Path(path).exists():
        raise DataError(f"{path}: no such scene folder (data=)")
    parser_cls = registry.load("dataparser", config.dataparser.name)
    parser: DataParser = parser_cls(config.dataparser.options)
    return parser.parse(Path(path))
