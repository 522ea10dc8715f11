"""How far the AGR term's rain direction in the network updates is from the true rain's.

For each finished run on a simulated scene (one that records where its drops fall, scene.json's
``rain_falls``), reads the directions the AGR term logged per view during training
(``<term>.streak_deg/view<i>`` in log.jsonl: what the network update held R to, not a latent
update's crop) and compares each with the view's true streak angle from the simulator's
geometry (rainyscape.eval.rain_stats.fall_angles_deg). Prints the mean error over all logged
updates and over the last half of them. One-direction rain only (a two-direction scene is
skipped: its logged first angle is not matched to a direction).

    python benchmarks/rain_update_angles.py RUN_DIR [RUN_DIR ...]
"""

from __future__ import annotations

import json
import re
import sys
from pathlib import Path

import torch

from rainyscape.eval.rain_stats import fall_angles_deg, true_rain_falls
from rainyscape.imaging.angles import angle_difference_deg
from rainyscape.workflow import load_trained

LOGGED = re.compile(r"streak_deg/view(\d+)$")


def logged_angles(log: Path) -> list[tuple[int, int, float]]:
    """(step, view, degrees) of every first-direction angle in a training log."""
    out = []

    def walk(record: dict, step: int) -> None:
        for key, value in record.items():
            if isinstance(value, dict):
                walk(value, step)
            elif (m := LOGGED.search(key)) and isinstance(value, (int, float)):
                out.append((step, int(m.group(1)), float(value)))

    for line in log.read_text().splitlines():
        record = json.loads(line)
        walk(record, int(record.get("step", 0)))
    return out


def update_angle_errors(run_dir: Path) -> tuple[str, list[float]] | None:
    """The scene's name and the errors (degrees) of the logged angles in step order; None for a
    scene without one recorded fall direction."""
    pipeline, _ = load_trained(run_dir, device="cpu")
    scene = pipeline.scene
    falls = true_rain_falls(scene)
    if falls is None or len(falls) != 1 or scene.rain_layers is None:
        return None
    truth = {}
    for i in scene.train_indices:
        rain = scene.rain_layers[i].permute(2, 0, 1).float()
        truth[i] = fall_angles_deg(scene.cameras[i], falls, rain)[0]
    errors = [angle_difference_deg(a, truth[v]) for _, v, a in sorted(logged_angles(run_dir / "log.jsonl"))
              if v in truth]
    return scene.name, errors


def main(argv: list[str]) -> int:
    if not argv:
        print(__doc__)
        return 2
    with torch.no_grad():
        for run in argv:
            found = update_angle_errors(Path(run))
            if found is None:
                print(f"{run}: no one recorded fall direction (not an rs-synth one-direction scene); skipped")
                continue
            name, errors = found
            if not errors:
                print(f"{name}: no AGR angles in the log")
                continue
            late = errors[len(errors) // 2:]
            print(f"{name}: {len(errors)} logged updates, mean error {sum(errors) / len(errors):.2f} deg, "
                  f"last half {sum(late) / len(late):.2f} deg")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
