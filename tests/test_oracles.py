"""benchmarks/oracles: the oracle training rows read the simulator's true rain, and only when
switched on by the environment (docs/rain.md, "What a perfect mask or a perfect rain layer
gives the Gaussians"). Each check runs in a fresh interpreter with the module on PYTHONPATH,
as rs-bench's cells do."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

ORACLES = Path(__file__).resolve().parents[1] / "benchmarks" / "oracles"

CHECK = r"""
import sys, torch
from rainyscape import config
from rainyscape.cameras import Window
from rainyscape.components import LossContext
from rainyscape.dataparsers.maya_csv import MayaCsvConfig, MayaCsvParser
from rainyscape.engine.pipeline import build_pipeline

scene = MayaCsvParser(MayaCsvConfig()).parse(sys.argv[1])
truth = scene.rain_layers.permute(0, 3, 1, 2).float()
cfg = config.method_config("rainyscape-3dgs", ["rain_head.lowres_channels=[8,8,8,8]", "rain_head.highres_channels=4"])
pipeline = build_pipeline(cfg, scene, torch.device("cpu"))
views = torch.tensor([0, 2])
window = Window.full(scene.cameras[views])
rain = pipeline.rain_head(views, window)
print("head", float((rain - 0.5 * truth[views]).abs().max()))

# the plain loss: a render wrong only on the rain's pixels costs nothing
clean = scene.clean_images[views].permute(0, 3, 1, 2).float() / 255
wrong = torch.where(truth[views].amax(1, keepdim=True) > 0.02, 1.0 - clean, clean)
plain = config.method_config("3dgs", ["losses.photometric.ssim_weight=0"])
term = build_pipeline(plain, scene, torch.device("cpu")).losses["photometric"][1]
ctx = LossContext(rendered=wrong, target=clean, layers={}, output=None, view_ids=views, step=0,
                  phase="fit", window=window)
print("mask", float(term(ctx)))
"""


def _run(scene_dir: Path, env: dict) -> dict[str, float]:
    full_env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ORACLES), os.environ.get("PYTHONPATH", "")]), **env}
    out = subprocess.run([sys.executable, "-c", CHECK, str(scene_dir)], env=full_env, capture_output=True,
                         text=True, check=True).stdout
    return {line.split()[0]: float(line.split()[1]) for line in out.splitlines() if line.split()[:1] in (["head"], ["mask"])}


def test_oracles_replace_the_head_and_mask_the_loss_only_when_switched_on(tiny_scene_dir):
    on = _run(tiny_scene_dir, {"RS_ORACLE_RAIN": "0.5", "RS_ORACLE_MASK": "0.02", "RS_ORACLE_DILATE": "0"})
    assert on["head"] < 1e-6  # the head's output is half the true rain
    assert on["mask"] == 0.0  # the rain's pixels are left out of the plain field's L1
    off = _run(tiny_scene_dir, {})
    assert off["head"] > 1e-3 and off["mask"] > 1e-3  # unset: the head predicts, every pixel counts
