"""The cells of a benchmark: every method on every scene, plus the paper's loss ablation."""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass, field
from pathlib import Path

from rainyscape.errors import ConfigError

# The field's ceiling: a method trained on a scene's clean views at the same budget. A
# simulated scene, or a real capture with simulated rain, keeps them in CLEAN_IMAGES; a scene
# folder may name its own with dataparser.clean=FOLDER.
CLEAN_IMAGES = "images_wo_rain"
# parsers that train on a folder of clean views with images= and score against it with clean=
CLEAN_FORMATS = ("maya-csv", "transforms-json", "llff", "colmap")
SIMULATED_FORMAT = "maya-csv"  # what the simulator writes: the format of a scene not simulated yet
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


def given(overrides: list[str], key: str) -> str | None:
    """The value the last ``key=value`` of ``overrides`` gives ``key`` (None: not given)."""
    found = None
    for o in overrides:
        k, eq, v = o.partition("=")
        if eq and k == key:
            found = v
    return found


def named_parser(overrides: list[str]) -> str | None:
    """The dataparser ``overrides`` name (None: none, or ``auto``, which resolves per scene)."""
    name = given(overrides, "dataparser")
    return None if name in (None, "", "auto") else name


def scene_format(data: str) -> str | None:
    """The dataparser ``dataparser=auto`` picks for a cell's scene folder: the simulator's
    format for a scene not simulated yet (``""``, or a folder not there yet); None when the
    folder's format cannot be told (the cell's own parser then says why)."""
    from rainyscape.dataparsers.auto import detect_format
    from rainyscape.errors import DataError

    folder = Path(data)
    if not data or not folder.is_dir():
        return SIMULATED_FORMAT
    try:
        return detect_format(folder)
    except DataError:
        return None


def parser_overrides(data: str, overrides: list[str]) -> list[str]:
    """``dataparser=FORMAT`` for a cell whose overrides set dataparser options without naming
    a parser: auto resolves per scene, and the scene's parser then takes its own options (as
    rs-train does when it sees the folder). Nothing otherwise, so a cell's config (and its
    fingerprint) stays what it was."""
    if named_parser(overrides) or not any(o.partition("=")[0].startswith("dataparser.") for o in overrides):
        return []
    fmt = scene_format(data)
    return [f"dataparser={fmt}"] if fmt else []


def clean_views(data: str, overrides: list[str] = ()) -> tuple[str, str] | None:
    """(dataparser, folder of clean views) that train a cell on its scene's clean views, None
    when the scene has none: the parser the overrides name, else the scene's format; the
    folder ``dataparser.clean=`` names, else CLEAN_IMAGES. A scene not simulated yet will be
    a simulated one, with them."""
    fmt = named_parser(overrides) or scene_format(data)
    clean = given(overrides, "dataparser.clean")
    if clean == "":  # clean= (none): nothing to train on, nothing to score against
        return None
    clean = CLEAN_IMAGES if clean in (None, "auto") else clean
    folder = Path(data)
    if fmt not in CLEAN_FORMATS or (data and folder.is_dir() and not (folder / clean).is_dir()):
        return None
    return fmt, clean


def has_clean_views(data: str, overrides: list[str] = ()) -> bool:
    return clean_views(data, overrides) is not None


def clean_overrides(data: str, overrides: list[str] = ()) -> list[str]:
    """The overrides that train a cell on the scene's clean views (and score against them)."""
    fmt, clean = clean_views(data, overrides)
    return [f"dataparser={fmt}", f"dataparser.images={clean}", f"dataparser.clean={clean}"]


def build_cells(methods: list[str], scenes: list[tuple[str, str]], overrides: list[str],
                ablation: tuple[str, str] | None = None, ablation_method: str = "rainyscape-nerf",
                method_overrides: dict[str, list[str]] | None = None, ceiling: list[str] = ()) -> list[Cell]:
    """The cells of ``methods`` x ``scenes`` ((label, folder) pairs), first the ``ceiling``
    methods trained on each scene's clean views (where it has them), and with ``ablation``,
    the loss ablation. Each cell's overrides: ``method_overrides[method]`` (e.g. a scene set's
    step count for that method's field), then ``overrides`` (the command's: they win); before
    them, the scene's own parser when they set dataparser options (:func:`parser_overrides`),
    and after them, for a ceiling, what trains it on the clean views (:func:`clean_overrides`)."""
    per = method_overrides or {}

    def given_to(m: str) -> list[str]:  # the overrides the command gives method m's cells
        return per.get(m, []) + list(overrides)

    cells = [Cell(f"{label}/{m}{CEILING}", label, data, m, given_to(m) + clean_overrides(data, given_to(m)),
                  f"{m}{CEILING}", clean=True)
             for label, data in scenes for m in ceiling if has_clean_views(data, given_to(m))]
    cells += [Cell(f"{label}/{m}", label, data, m, parser_overrides(data, given_to(m)) + given_to(m), m)
              for label, data in scenes for m in methods]
    if ablation is not None:
        label, data = ablation
        variants = {variant: given_to(ablation_method) + extra for variant, extra in ABLATIONS.items()}
        cells += [Cell(f"ablation/{label}/{variant}", label, data, ablation_method,
                       parser_overrides(data, o) + o, variant) for variant, o in variants.items()]
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
                          "3DGS from the simulator's ground-truth depth and takes the ray bounds from it, which "
                          "no capture has; a "
                          "benchmark never uses it (its 3DGS rows start from points triangulated "
                          "from the training views)")
    return cfg


def validate_cells(cells: list[Cell]) -> None:
    """Every cell's config must build before anything trains (typos fail at once)."""
    for cell in cells:
        cell_config(cell)
