"""The plan of a benchmark, made before anything is simulated or trained: the methods, the
scenes (a scene set's, or the listed presets and folders, at their sizes), every cell's
overrides (a set's step count per field family, then ``iters=``, then the command's dotted
keys), every cell's budget, and the budget check."""

from __future__ import annotations

from dataclasses import dataclass, field, fields
from pathlib import Path

from rainyscape.comparison.budget import Budget, Mismatch, cell_budget, check_budgets
from rainyscape.comparison.matrix import SIMULATED_FORMAT, Cell, build_cells, cell_config, validate_cells
from rainyscape.comparison.options import BenchOptions
from rainyscape.comparison.scenes import ScenePlan, plan_scene
from rainyscape.comparison.sets import scene_set
from rainyscape.config.overrides import uses_cuda
from rainyscape.config.schema import check_range
from rainyscape.errors import ConfigError

PLAIN_FIELDS = ("nerf", "3dgs")  # ceiling=auto: the fields without a rain model


@dataclass
class BenchPlan:
    methods: list[str]
    scenes: list[ScenePlan]  # the tables' scenes, in order
    ablation: ScenePlan | None
    ablation_method: str
    overrides: list[str]  # every cell's: iters=, then the command's dotted keys
    per_method: dict[str, list[str]]  # before those: the scene set's step count for the method's field
    scene_set: str | None = None
    ceiling: list[str] = field(default_factory=list)  # methods also trained on the clean views
    budgets: dict[str, Budget] = field(default_factory=dict)  # cell key -> budget
    mismatches: list[Mismatch] = field(default_factory=list)  # allowed with allow_unequal=true

    @property
    def plans(self) -> dict[str, ScenePlan]:
        """Every scene by label (the tables' and the ablation's)."""
        out = {p.label: p for p in self.scenes}
        if self.ablation is not None:
            out.setdefault(self.ablation.label, self.ablation)
        return out

    def cells(self, folders: dict[str, str] | None = None) -> list[Cell]:
        """The cells, with each scene's folder (``folders``: label -> folder once resolved)."""
        folders = folders or {label: p.folder for label, p in self.plans.items()}
        ablation = (self.ablation.label, folders[self.ablation.label]) if self.ablation else None
        return build_cells(self.methods, [(p.label, folders[p.label]) for p in self.scenes], self.overrides,
                           ablation, self.ablation_method, self.per_method, self.ceiling)


def split_method_overrides(overrides: list[str], methods: list[str]) -> tuple[list[str], dict[str, list[str]]]:
    """``METHOD:key=value`` goes to that method's cells only (e.g. the paper's joint patch for
    rainyscape-nerf alone); the rest go to every cell."""
    common, per = [], {}
    for o in overrides:
        method, colon, rest = o.partition("=")[0].partition(":")
        if not colon:
            common.append(o)
        elif method not in methods:
            raise ConfigError(f"rs-bench: {o}: {method} is not one of methods= ({', '.join(methods)})")
        else:
            per.setdefault(method, []).append(o[len(method) + 1:])
    return common, per


def ceiling_methods(option: str, methods: list[str]) -> list[str]:
    """The methods rs-bench also trains on the clean views: ``auto`` the plain fields (nerf,
    3dgs) among ``methods``, ``none`` (or "") none, else a listed subset of ``methods`` (the
    ceiling must share its method's budget)."""
    if option == "auto":
        return [m for m in PLAIN_FIELDS if m in methods]
    chosen = [m.strip() for m in option.split(",") if m.strip() and m.strip() != "none"]
    absent = [m for m in chosen if m not in methods]
    if absent:
        raise ConfigError(f"rs-bench: ceiling={option}: {', '.join(absent)} not in methods= ({', '.join(methods)})")
    return chosen


def fixed_length(steps: int) -> list[str]:
    """Overrides that make a run exactly ``steps`` long (whatever its run-length rule)."""
    return [f"trainer.max_iters={steps}", "trainer.iters_per_view=0", "trainer.iters_per_mpixel=0"]


def family_iters(methods: list[str], overrides: list[str], iters: dict[str, int]) -> dict[str, list[str]]:
    """Per method, the ``trainer.max_iters`` override a scene set gives its field family."""
    out = {}
    for m in methods:
        family = cell_config(Cell(m, "", "", m, list(overrides))).field.name
        if family in iters:
            out[m] = fixed_length(iters[family])
    return out


def scene_shape(plan: ScenePlan, cfg) -> tuple[int, int, int]:
    """(width, height, training views) of a scene as the cells' dataparser delivers it (after
    its downscale and held-out split); a folder is parsed to find out, a preset is counted."""
    from rainyscape.scene import split_indices

    options = cfg.dataparser.options
    if plan.preset:
        factor = max(1, int(getattr(options, "downscale", 1) or 1))
        train, _ = split_indices(plan.rows * plan.cols, getattr(options, "holdout_every", 8))
        return plan.width // factor, plan.height // factor, len(train)
    from rainyscape.engine.scene_loading import load_scene

    scene = load_scene(cfg, Path(plan.folder))
    if scene.clean_images is None:  # every cell would score n/a, and say nothing
        raise ConfigError(
            f"{plan.folder}: the {scene.metadata.get('dataparser', cfg.dataparser.name)} parser finds no "
            "clean images there, and rs-bench scores every cell against them; name their folder with "
            "dataparser.clean=FOLDER, or put them beside the rainy images as a '_wo_rain' sibling "
            "(images_rain/ -> images_wo_rain/)")
    return scene.width, scene.height, len(scene.train_indices)


def plan_budgets(cells: list[Cell], plans: dict[str, ScenePlan]) -> dict[str, Budget]:
    """Every cell's training budget from its typed config, before anything is simulated or trained."""
    shapes: dict[str, tuple[int, int, int]] = {}
    budgets = {}
    for cell in cells:
        cfg = cell_config(cell)
        if cell.scene not in shapes:
            shapes[cell.scene] = scene_shape(plans[cell.scene], cfg)
        budgets[cell.key] = cell_budget(cfg, *shapes[cell.scene])
    return budgets


def check_options(opts: BenchOptions) -> None:
    """Every option's range or choices (the command line checks them too; this covers options
    built in code), and that the device is there: a cell on a missing device would fail only
    after the scenes were simulated."""
    for f in fields(BenchOptions):
        check_range(getattr(opts, f.name), f.metadata, f.name)
    if uses_cuda(opts.device):
        import torch

        if not torch.cuda.is_available():
            raise ConfigError(f"device={opts.device}: CUDA is not available here (device=cpu or auto)")


def plan_bench(opts: BenchOptions, overrides: list[str]) -> BenchPlan:
    """Everything about a benchmark that is known before it runs; raises ConfigError on a bad
    option, method or override, and on unequal budgets within a field (unless
    ``opts.allow_unequal``)."""
    check_options(opts)
    methods = [m.strip() for m in opts.methods.split(",") if m.strip()]
    if not methods:
        raise ConfigError("rs-bench: methods= lists no method")
    sset = scene_set(opts.scenes)
    # The recipe is fixed here, for every cell alike, so that the budgets checked below are the
    # ones the cells train with (and a cell's fingerprint says which recipe it ran).
    profile = opts.profile if opts.profile != "auto" else "gpu" if uses_cuda(opts.device) else "cpu"
    # A table measures every view: the cells evaluate every view at the end of their run.
    base = [f"profile={profile}", "trainer.final_eval_views=0"]
    base += fixed_length(opts.iters) if opts.iters else []
    base += [f"dataparser={opts.dataparser}"] if opts.dataparser != "auto" else []
    every = list(dict.fromkeys(methods + ([opts.ablation_method] if opts.ablation else [])))
    overrides, own = split_method_overrides(overrides, every)
    # Every method and override must be valid before any scene is simulated or cell trained;
    # the dataparser's options are checked with each scene's cells (plan_budgets), as only a
    # scene tells which parser reads it.
    generic = [o for o in base + overrides if not o.startswith("dataparser")]
    validate_cells(build_cells(methods, [("", "")], generic, ("", "") if opts.ablation else None,
                               opts.ablation_method, {m: [o for o in v if not o.startswith("dataparser")]
                                                      for m, v in own.items()}))
    per_method = family_iters(every, generic, sset.iters) if sset and not opts.iters else {}
    per_method = {m: per_method.get(m, []) + own.get(m, []) for m in every}
    size = dict(width=opts.scene_width or (sset.width if sset else 0),
                height=opts.scene_height or (sset.height if sset and not opts.scene_width else 0),
                rows=opts.scene_rows or (sset.rows if sset else 0), cols=opts.scene_cols or (sset.cols if sset else 0),
                mode=opts.scene_rain)
    specs = list(sset.presets) if sset else [s.strip() for s in opts.scenes.split(",") if s.strip()]
    if sset and sset.captures:  # made (once, cached) now: their sizes come from the folders
        from rainyscape.comparison.captures import real_scenes

        planned = [ScenePlan(label, folder=str(folder))
                   for label, folder in real_scenes(opts.captures, Path(opts.out) / "scenes")]
    else:
        if not specs:
            raise ConfigError("rs-bench: scenes= lists no scene")
        planned = [plan_scene(s, **size) for s in specs]
    scenes = list({p.label: p for p in planned}.values())
    simulated = [p.label for p in scenes if not p.folder]
    if opts.scene_rain != "static" and not any(p.preset for p in scenes):
        raise ConfigError(f"rs-bench: scene_rain={opts.scene_rain} makes simulated scenes' rain; "
                          f"scenes={opts.scenes} simulates none (a folder keeps its own rain)")
    if opts.dataparser not in ("auto", SIMULATED_FORMAT) and simulated:
        raise ConfigError(f"rs-bench: dataparser={opts.dataparser}: {', '.join(simulated)} "
                          f"{'is' if len(simulated) == 1 else 'are'} simulated in the {SIMULATED_FORMAT} "
                          "layout; dataparser= names the parser of scene folders")
    plan = BenchPlan(methods, scenes, plan_scene(opts.ablation, **size) if opts.ablation else None,
                     opts.ablation_method, base + overrides, per_method, sset.name if sset else None,
                     ceiling_methods(opts.ceiling, methods))
    cells = plan.cells()
    plan.budgets = plan_budgets(cells, plan.plans)
    # a ceiling trains its method's budget by construction: the methods are what must match
    compared = {c.key for c in cells if not c.clean and not c.key.startswith("ablation/")}
    plan.mismatches = check_budgets([(key, key.split("/")[0], b) for key, b in plan.budgets.items()
                                     if key in compared], opts.allow_unequal)
    return plan
