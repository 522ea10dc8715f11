"""The paper's Fig. 8: how the rain embedding steers the predicted rain.

For a few training views, the rain head predicts a patch (100 x 100 in the paper) with its
learnt embedding and with Gaussian noise of variance 0.5 added to one part of it: the scene
state s (Δs), the view vector v_i (Δv) or the camera vector p_i (Δp). The heads it works
on expose those as ``scene_state`` (D,), ``view_states`` (N, D) and ``camera_vectors`` (N, P)
(:class:`rainyscape.rain.head.RainPredictor` does).
"""

from __future__ import annotations

import copy
import json
import math
from pathlib import Path

import torch
from torch import Tensor

from rainyscape.cameras import Window
from rainyscape.components import HasEmbeddings
from rainyscape.engine.pipeline import Pipeline
from rainyscape.engine.run_folder import RunFolder
from rainyscape.errors import ConfigError
from rainyscape.eval.images import grid, save_png, to_uint8
from rainyscape.eval.rain_stats import streak_angle_deg
from rainyscape.eval.views import to_float

PERTURBATIONS = {"s": "scene_state", "v": "view_states", "p": "camera_vectors"}  # paper: Δs, Δv, Δp
NOISE_VARIANCE = 0.5  # the paper's
RAIN_PRESENT = 0.05  # a pixel "has rain" above this intensity (for the density statistic)


def perturbed_head(head: torch.nn.Module, attr: str, view: int, variance: float,
                   generator: torch.Generator) -> torch.nn.Module:
    """A copy of ``head`` whose ``attr`` (for ``view`` when it is per view) has N(0, variance)
    noise added; the original is untouched."""
    out = copy.deepcopy(head)
    tensor: Tensor = getattr(out, attr)
    target = tensor if tensor.ndim == 1 else tensor[view]
    noise = torch.randn(target.shape, generator=generator) * math.sqrt(variance)
    with torch.no_grad():
        target.add_(noise.to(target))
    return out


def centre_window(width: int, height: int, size: int) -> Window:
    w, h = min(size, width), min(size, height)
    return Window(torch.tensor([(width - w) // 2]), torch.tensor([(height - h) // 2]), w, h)


def rain_stats(rain: Tensor) -> dict:
    """Mean intensity, fraction of rainy pixels and dominant streak angle of a rain patch."""
    return {"mean": float(rain.mean()), "density": float((rain.mean(0) > RAIN_PRESENT).float().mean()),
            "angle_deg": streak_angle_deg(rain, {})}


@torch.no_grad()
def embedding_study(pipeline: Pipeline, views: list[int] | None = None, patch: int = 100,
                    variance: float = NOISE_VARIANCE, seed: int = 0) -> tuple[list[list], list[dict]]:
    """Panels (rows of (label, image)) and statistics of the study."""
    head = pipeline.rain_head
    if head is None:
        raise ConfigError(f"method {pipeline.config.method} has no rain head: no embedding to study")
    if not isinstance(head, HasEmbeddings):
        raise ConfigError(f"rain head '{pipeline.config.rain_head.name}' does not expose "
                          f"{', '.join(PERTURBATIONS.values())}; the embedding study needs them")
    head.eval()
    scene = pipeline.scene
    views = views if views is not None else list(scene.train_indices[:2])
    win = centre_window(scene.width, scene.height, patch)
    gen = torch.Generator().manual_seed(seed)
    rows, stats = [], []
    for i in views:
        ids = torch.tensor([i], device=pipeline.device)
        rainy = win.crop(to_float(scene.images[i], pipeline.device)[None])[0]
        row = [(f"{Path(scene.image_names[i]).stem} rainy", to_uint8(rainy))]
        variants = [("learnt", head)] + [(f"{name} + noise", perturbed_head(head, attr, i, variance, gen))
                                         for name, attr in PERTURBATIONS.items()]
        for label, model in variants:
            rain = model(ids, win)[0]
            row.append((label, to_uint8(rain)))
            stats.append({"view": scene.image_names[i], "embedding": label, **rain_stats(rain)})
        rows.append(row)
    return rows, stats


def write_embedding_study(pipeline: Pipeline, run_dir: Path, **kwargs) -> Path:
    """``renders/embedding_study.png`` (the grid) and ``.json`` (its statistics)."""
    rows, stats = embedding_study(pipeline, **kwargs)
    out = RunFolder(run_dir).renders / "embedding_study.png"
    save_png(out, grid(rows))
    out.with_suffix(".json").write_text(json.dumps(stats, indent=2))
    return out
