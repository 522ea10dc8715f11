"""Named scene sets for ``rs-bench scenes=NAME``: which simulator presets, at what size and
camera array, and the default training budget of each field family.

A set fixes the image size, the camera rows x columns and ``trainer.max_iters`` per field
family; ``scene_width= scene_height= scene_rows= scene_cols= iters=`` and a dotted
``trainer.max_iters=`` still override it. Its presets cover the rain the simulator makes:
light, medium, heavy, slanted by wind, and two directions at once.

- ``cpu``: 128 px, sized so that the six-method table (nerf, robust-nerf, rainyscape-nerf,
  3dgs, robust-3dgs, rainyscape-3dgs) trains in at most an hour on 2 CPU cores with
  ``jobs=2 threads=1`` (the measurement behind it: docs/evaluation.md, "Sizing the cpu set").
- ``paper``: the paper's array (5 x 10 views) at 512 px and its step counts (18k NeRF steps,
  30k for 3DGS): a GPU run.
- ``real``: real photographs with the simulator's rain in their own cameras (comparison/captures.py):
  every capture of the captures folder at about 240 px, at light, medium and heavy strength; the
  photos are the ground truth.
- ``distractors``: no rain; static scenes with objects that are in one view only (people, cars,
  blowing leaves: synth/transients.py), the setting the robust baselines (robust-nerf,
  robust-3dgs, desplat) were built for: each must beat its plain field there. The cpu set's
  size, views and NeRF budget; the Gaussians train the 3DGS CPU recipe's longest run (3000
  steps), as SpotLessSplats' mask blends in over its first 1500 steps whatever the run's
  length (at 1000 steps it had hardly acted: docs/benchmarks.md). The tables' "in rain"
  pixels are the transients' there.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from rainyscape.errors import ConfigError
from rainyscape.methods.gaussians import GS_ITERS
from rainyscape.methods.nerf import NERF_ITERS, NERF_MIN_ITERS

# light, medium, heavy, slanted 30 deg by wind, two directions (docs/simulator.md).
CPU_PRESETS = ("yard", "crossroad", "plaza", "street", "bridge")
# people, cars and pedestrians, leaves and a passer-by (synth/presets.py, no rain)
DISTRACTOR_PRESETS = ("plaza-crowd", "crossroad-traffic", "yard-leaves")


@dataclass(frozen=True)
class SceneSet:
    name: str
    presets: tuple[str, ...]  # simulator presets, in table order
    width: int
    height: int
    rows: int
    cols: int
    iters: dict[str, int] = field(default_factory=dict)  # field family -> trainer.max_iters
    description: str = ""
    captures: bool = False  # scenes made from real captures (comparison/captures.py), not presets


SCENE_SETS: dict[str, SceneSet] = {s.name: s for s in [
    SceneSet("cpu", CPU_PRESETS, width=128, height=128, rows=3, cols=6,
             iters={"grid": NERF_MIN_ITERS, "gaussians": 1500},
             description="five presets (light, medium, heavy, slanted 30 deg, two directions) at 128 px, "
                         "3 x 6 views: the six-method table in at most an hour on 2 CPU cores"),
    SceneSet("paper", CPU_PRESETS, width=512, height=512, rows=5, cols=10,
             iters={"grid": 18000, "gaussians": 30000},
             description="the same presets at the paper's size (5 x 10 views, 512 px) and step counts "
                         "(18k for NeRF, 30k for 3DGS): a GPU run"),
    SceneSet("distractors", DISTRACTOR_PRESETS, width=128, height=128, rows=3, cols=6,
             iters={"grid": NERF_ITERS, "gaussians": GS_ITERS},
             description="three rain-free scenes with transient people, cars and leaves, one set per view, "
                         "at the cpu set's size, each field at its CPU recipe's longest run (the peers' "
                         "masks need the steps): where the robust baselines must beat their plain fields"),
    # every method at its recipe's run for the capture, as for a user's `rs-train`: the
    # Gaussians 100 steps a training view (1500 to 3000), the grid field by its pixels
    SceneSet("real", (), width=0, height=0, rows=0, cols=0, captures=True,
             description="real captures (captures=FOLDER) at about 240 px with simulated rain in their own "
                         "cameras, light / medium / heavy; the photos are the ground truth"),
]}


def scene_set(spec: str) -> SceneSet | None:
    """The set named by ``scenes=`` (None when it lists presets or folders instead). A set
    stands alone: ``scenes=cpu,yard`` is refused."""
    names = [s.strip() for s in spec.split(",") if s.strip()]
    found = [n for n in names if n in SCENE_SETS]
    if found and len(names) > 1:
        raise ConfigError(f"rs-bench: scenes={spec}: a scene set ({found[0]}) cannot be combined with "
                          "other scenes; list presets or folders instead")
    return SCENE_SETS[found[0]] if found else None
