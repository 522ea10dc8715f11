"""Training budgets: how many steps a cell trains and how many pixels (rays) each step sees,
computed from its typed config before anything trains, and the check that methods sharing a
field see the same budget.

A step of phase ``p`` sees ``p.patches`` windows of ``p.patch_size``² pixels, or of
``width x height`` pixels when ``patch_size`` is 0 (whole views), and ``p.rays`` single
rays besides. The budget of a run is its
step count and the mean pixels per step over the run, each phase weighted by the steps it
runs (``rainyscape.engine.phases.PhaseSchedule``, as the trainer schedules it).

Methods are compared within a *family*, the field they train (``grid``: nerf, robust-nerf,
rainyscape-nerf; ``gaussians``: 3dgs, robust-3dgs, rainyscape-3dgs): within a family a table
must give every method the same steps and the same mean pixels per step, or a method's gain
may be its larger batch. Families differ in what a step costs, so different families in one
table may have different budgets.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

from rainyscape.config import PhaseConfig, PipelineConfig, run_length
from rainyscape.engine.phases import PhaseSchedule
from rainyscape.errors import ConfigError


@dataclass(frozen=True)
class PhaseBudget:
    name: str
    steps: int
    pixels: int  # pixels (rays) per step


@dataclass(frozen=True)
class Budget:
    family: str  # the field component
    steps: int
    pixels_per_step: float  # mean over the run, phases weighted by their steps
    phases: tuple[PhaseBudget, ...]
    width: int = 0  # the image size whole-view phases were counted at
    height: int = 0

    def short(self) -> str:
        """``1500 × 1024``: steps × mean pixels per step."""
        return f"{self.steps} × {self.pixels_per_step:.0f}"

    def describe(self) -> str:
        """``1500 steps × 2560 px/step (warmup 750 × 1024, joint 750 × 4096)``."""
        text = f"{self.steps} steps × {self.pixels_per_step:.0f} px/step"
        if len(self.phases) > 1:
            text += " (" + ", ".join(f"{p.name} {p.steps} × {p.pixels}" for p in self.phases) + ")"
        return text

    def same_as(self, other: "Budget") -> bool:
        return self.steps == other.steps and abs(self.pixels_per_step - other.pixels_per_step) < 1e-6

    def to_dict(self) -> dict:
        return asdict(self)

    @staticmethod
    def from_dict(d: dict) -> "Budget":
        phases = tuple(PhaseBudget(**p) for p in d.get("phases", ()))
        return Budget(d["family"], int(d["steps"]), float(d["pixels_per_step"]), phases,
                      int(d.get("width", 0)), int(d.get("height", 0)))


def phase_pixels(phase: PhaseConfig, width: int, height: int) -> int:
    """Pixels (rays) one step of ``phase`` sees on ``width`` x ``height`` images."""
    return phase.patches * (width * height if phase.patch_size == 0 else phase.patch_size ** 2) + phase.rays


def cell_budget(cfg: PipelineConfig, width: int, height: int, train_views: int) -> Budget:
    """The budget of a typed config on ``train_views`` training images of ``width`` x
    ``height`` pixels (as the dataparser delivers them, after any downscale). A run stopped
    early by ``trainer.stop_at`` counts the steps it runs."""
    max_iters = run_length(cfg.trainer, train_views, train_views * width * height)
    steps = min(cfg.trainer.stop_at, max_iters) if cfg.trainer.stop_at else max_iters
    schedule = PhaseSchedule.of(cfg.phases, max_iters)
    phases, start = [], 0
    for name, phase, end in zip(schedule.names, schedule.configs, schedule.ends):
        n = max(0, min(end, steps) - start)
        start = max(start, end)
        phases.append(PhaseBudget(name, n, phase_pixels(phase, width, height)))
    mean = sum(p.steps * p.pixels for p in phases) / steps if steps else 0.0
    return Budget(cfg.field.name, steps, mean, tuple(p for p in phases if p.steps), width, height)


@dataclass(frozen=True)
class Mismatch:
    """Methods of one family whose budgets differ, on the scenes where they do (the same
    difference on several scenes is one mismatch)."""

    scenes: tuple[str, ...]
    family: str
    budgets: tuple[tuple[str, Budget], ...]  # (method, budget): every method of the family

    def describe(self) -> str:
        cells = "; ".join(f"{m}: {b.describe()}" for m, b in self.budgets)
        where = "scene" + ("s " if len(self.scenes) > 1 else " ") + ", ".join(self.scenes)
        return f"field '{self.family}' on {where}: {cells}"


def budget_mismatches(budgets: list[tuple[str, str, Budget]]) -> list[Mismatch]:
    """Groups of (cell key ``scene/method``, scene, budget) that share a scene and a field
    family but not a budget (steps or mean pixels per step); one per difference, with the
    scenes it occurs on."""
    groups: dict[tuple[str, str], list[tuple[str, Budget]]] = {}
    for key, scene, b in budgets:
        groups.setdefault((scene, b.family), []).append((key.split("/", 1)[-1], b))
    merged: dict[tuple, list[str]] = {}
    for (scene, family), items in groups.items():
        if any(not b.same_as(items[0][1]) for _, b in items[1:]):
            merged.setdefault((family, tuple(items)), []).append(scene)
    return [Mismatch(tuple(scenes), family, items) for (family, items), scenes in merged.items()]


def check_budgets(budgets: list[tuple[str, str, Budget]], allow_unequal: bool = False) -> list[Mismatch]:
    """Refuse (ConfigError) a table whose methods of one field family differ in budget, naming
    the cells and their budgets, unless ``allow_unequal``; returns the mismatches."""
    bad = budget_mismatches(budgets)
    if bad and not allow_unequal:
        lines = "\n  ".join(m.describe() for m in bad)
        raise ConfigError("rs-bench: methods that train the same field must have equal budgets (steps and "
                          f"pixels per step), and these differ:\n  {lines}\nGive them the same steps and "
                          "pixels per step (phases' patches x patch size, weighted by their length), or pass "
                          "allow_unequal=true to run anyway (the tables then print the difference in their "
                          "budget column).")
    return bad
