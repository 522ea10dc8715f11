"""The cells of a benchmark: every method on every scene, plus the paper's loss ablation."""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass, field
from pathlib import Path

from rainyscape.errors import ConfigError

# The field's ceiling: a method trained on a scene's clean views at the same budget (a
# simulated scene, or a real capture with simulated rain: both keep them in CLEAN_IMAGES).
CLEAN_IMAGES = "images_wo_rain"
CLEAN_FORMATS = ("maya-csv", "transforms-json")  # parsers that train on them with images= / clean=
CEILING = " on clean views"

# The paper's loss ablation (Table II): variant label -> overrides of the ablated method.
ABLATIONS: dict[str, list[str]] = {
    "w/o L_rec": ["losses.reconstruction=none"],
    "w/o L_tv": ["losses.tv=none"],
    "w/o L_agr": ["losses.agr=none"],
    "30 bins": ["losses.agr.bins=30"],
    "90 bins": ["losses.agr.bins=90"],
    "full": [],
}


@dataclass
class Cell:
    """One training run of the matrix."""

    key: str  # "<scene>/<method>" or "ablation/<scene>/<variant>"
    scene: str  # the scene's label in the tables
    data: str  # scene folder ("" = the embedded demo)
    method: str
    overrides: list[str] = field(default_factory=list)
    label: str = ""  # row label (the method, or the ablation variant)
    clean: bool = False  # trained on the clean views: the field's ceiling at this budget

    def fingerprint(self) -> str:
        """What makes two cells the same experiment: the scene and the whole config the cell
        trains, so that a changed override, budget or method default reruns the cell rather
        than reading back a run of another config."""
        from rainyscape.config.yaml_io import to_dict

        cfg = to_dict(cell_config(self))
        cfg.pop("rainyscape_version", None)
        text = json.dumps([self.data, cfg], sort_keys=True, default=str)
        return hashlib.sha1(text.encode()).hexdigest()[:12]

    @property
    def folder_name(self) -> str:
        return self.key.replace("/", "__").replace(" ", "_")


def clean_views_format(data: str) -> str | None:
    """The dataparser that trains on a scene folder's clean views (a simulated scene, or a real
    capture given simulated rain), None when it has none. A folder not simulated yet ("")
    will be a simulated one."""
    from rainyscape.dataparsers.auto import detect_format
    from rainyscape.errors import DataError

    folder = Path(data)
    if not data or not folder.is_dir():
        return "maya-csv"
    if not (folder / CLEAN_IMAGES).is_dir():
        return None
    try:
        fmt = detect_format(folder)
    except DataError:
        return None
    return fmt if fmt in CLEAN_FORMATS else None


def has_clean_views(data: str) -> bool:
    return clean_views_format(data) is not None


def clean_overrides(data: str) -> list[str]:
    """The overrides that train a cell on the scene's clean views (and score against them)."""
    return [f"dataparser={clean_views_format(data)}", f"dataparser.images={CLEAN_IMAGES}",
            f"dataparser.clean={CLEAN_IMAGES}"]


def build_cells(methods: list[str], scenes: list[tuple[str, str]], overrides: list[str],
                ablation: tuple[str, str] | None = None, ablation_method: str = "rainyscape-nerf",
                method_overrides: dict[str, list[str]] | None = None, ceiling: list[str] = ()) -> list[Cell]:
    """The cells of ``methods`` x ``scenes`` ((label, folder) pairs), first the ``ceiling``
    methods trained on each scene's clean views (where it has them), and with ``ablation``,
    the loss ablation. Each cell's overrides: ``method_overrides[method]`` (e.g. a scene set's
    step count for that method's field), then ``overrides`` (the command's: they win)."""
    per = method_overrides or {}
    cells = [Cell(f"{label}/{m}{CEILING}", label, data, m, per.get(m, []) + list(overrides) + clean_overrides(data),
                  f"{m}{CEILING}", clean=True)
             for label, data in scenes for m in ceiling if has_clean_views(data)]
    cells += [Cell(f"{label}/{m}", label, data, m, per.get(m, []) + list(overrides), m)
              for label, data in scenes for m in methods]
    if ablation is not None:
        label, data = ablation
        cells += [Cell(f"ablation/{label}/{variant}", label, data, ablation_method,
                       per.get(ablation_method, []) + list(overrides) + extra, variant)
                  for variant, extra in ABLATIONS.items()]
    return cells


def cell_config(cell: Cell):
    """The typed config a cell trains (ConfigError naming the cell when it does not build, or
    when it would start from ground-truth depth)."""
    from rainyscape.config import method_config

    try:
        cfg = method_config(cell.method, [f"data={cell.data}", *cell.overrides])
    except ConfigError as exc:
        raise ConfigError(f"{cell.key.strip('/')}: {exc}") from None
    if getattr(cfg.dataparser.options, "points_from_depth", False):
        raise ConfigError(f"{cell.key.strip('/') or 'rs-bench'}: dataparser.points_from_depth=true starts "
                          "3DGS from the simulator's ground-truth depth, which no capture has; a "
                          "benchmark never uses it (its 3DGS rows start from points triangulated "
                          "from the training views)")
    return cfg


def validate_cells(cells: list[Cell]) -> None:
    """Every cell's config must build before anything trains (typos fail at once)."""
    for cell in cells:
        cell_config(cell)
