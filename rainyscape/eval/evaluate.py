"""The evaluation protocol (DESIGN.md): rainy-input floor, de-raining on training views
(with and without post-processing) and novel held-out views."""

from __future__ import annotations

import json
from pathlib import Path

import torch
from torch import Tensor

from rainyscape.cameras import Window
from rainyscape.engine.pipeline import Pipeline
from rainyscape.eval.metrics import psnr


@torch.no_grad()
def render_image(pipeline: Pipeline, index: int) -> Tensor:
    """Full-resolution render (3, H, W) of view ``index``."""
    pipeline.field.eval()
    cams = pipeline.scene.cameras.to(pipeline.device)[[index]]
    return pipeline.field.render(cams, Window.full(cams)).rgb[0].clamp(0, 1)


@torch.no_grad()
def predict_rain(pipeline: Pipeline, index: int, tile: int = 128) -> Tensor:
    """Predicted rain layer (3, H, W) of view ``index``, computed tile by tile (bounded memory)."""
    head = pipeline.rain_head
    head.eval()
    h, w = pipeline.scene.height, pipeline.scene.width
    out = torch.zeros(3, h, w, device=pipeline.device)
    ids = torch.tensor([index], device=pipeline.device)
    for y in range(0, h, tile):
        for x in range(0, w, tile):
            th, tw = min(tile, h - y), min(tile, w - x)
            win = Window(torch.tensor([x]), torch.tensor([y]), tw, th)
            out[:, y:y + th, x:x + tw] = head(ids, win)[0]
    return out


def _image(u8: Tensor, device) -> Tensor:
    return u8.to(device).permute(2, 0, 1).float() / 255.0


def _mean(values: list[float]) -> float | None:
    return sum(values) / len(values) if values else None


@torch.no_grad()
def evaluate_pipeline(pipeline: Pipeline, run_dir: Path | None = None) -> dict:
    scene, dev = pipeline.scene, pipeline.device
    has_clean = scene.clean_images is not None
    per_view = []
    for split, indices in (("train", scene.train_indices), ("heldout", scene.eval_indices)):
        for i in indices:
            rendered = render_image(pipeline, i)
            rainy = _image(scene.images[i], dev)
            row = {"view": scene.image_names[i], "split": split,
                   "psnr_vs_rainy": float(psnr(rendered, rainy))}
            if has_clean:
                clean = _image(scene.clean_images[i], dev)
                row["psnr"] = float(psnr(rendered, clean))
                if split == "train":
                    row["psnr_rainy_input"] = float(psnr(rainy, clean))
                    if pipeline.rain_head is not None:
                        rain = predict_rain(pipeline, i)
                        for key, post in pipeline.postprocess.items():
                            row[f"psnr_{key}"] = float(psnr(post(rendered, rain, rainy), clean))
            per_view.append(row)
    summary: dict[str, float] = {}
    for split in ("train", "heldout"):
        rows = [r for r in per_view if r["split"] == split]
        keys = sorted({k for r in rows for k in r if k.startswith("psnr")})
        for k in keys:
            value = _mean([r[k] for r in rows if k in r])
            if value is not None:
                summary[f"{split}_{k}"] = value
    return {"summary": summary, "per_view": per_view, "has_clean": has_clean}


def write_metrics(run_dir: Path, metrics: dict) -> Path:
    path = Path(run_dir) / "metrics.json"
    tmp = path.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(metrics, indent=2))
    tmp.replace(path)
    return path
