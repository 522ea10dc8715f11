"""One view of a trained pipeline: its render, its predicted rain (tile by tile), the bundle of
images evaluation and renders use, and the quick PSNR check the trainer logs during training."""

from __future__ import annotations

import random
import sys
from dataclasses import dataclass, field
from typing import Iterable

import torch
from torch import Tensor

from rainyscape.cameras import Cameras, Window
from rainyscape.components import RenderOutput
from rainyscape.engine.pipeline import Pipeline
from rainyscape.eval.metric_keys import quick_key
from rainyscape.eval.summary import mean_of
from rainyscape.imaging.metrics import psnr


def progress(items: list, what: str, unit: str = "view") -> Iterable:
    """A console progress bar with its ETA over ``items`` (only when stderr is a terminal)."""
    from tqdm import tqdm

    return tqdm(items, desc=what, unit=unit, file=sys.stderr, disable=None, leave=False)


# The end-of-run evaluation's subset is drawn with this seed, the same for every run: two
# evaluations of the same weights measure the same views, and runs of one scene are comparable.
EVAL_VIEW_SEED = 31


def stratified(items: list, count: int, seed: int) -> list:
    """``count`` of ``items`` (all if fewer), one from each of ``count`` equal runs of
    consecutive items, at a position drawn with ``seed``: spread over the whole list (a rig's
    views are ordered around it), and the same for the same seed anywhere."""
    if count <= 0 or count >= len(items):
        return list(items)
    rng = random.Random(seed)
    edges = [round(k * len(items) / count) for k in range(count + 1)]
    return [items[rng.randrange(edges[k], edges[k + 1])] for k in range(count)]


def choose_views(train: list[int], heldout: list[int], count: int, seed: int = EVAL_VIEW_SEED) -> list[int]:
    """A fixed subset of up to ``count`` views (0: all): half from each split where both have
    enough (unused room goes to the other), each split's share drawn by :func:`stratified` with
    ``seed``; training views first."""
    if count <= 0:
        return list(train) + list(heldout)
    n_held = min(len(heldout), count // 2 if train else count)
    n_train = min(len(train), count - n_held)
    n_held = min(len(heldout), count - n_train)  # unused train room goes to held-out views
    return stratified(list(train), n_train, seed) + stratified(list(heldout), n_held, seed + 1)


def to_float(u8: Tensor, device) -> Tensor:
    """uint8 (H, W, 3) -> float (3, H, W) in [0, 1]."""
    return u8.to(device).permute(2, 0, 1).float() / 255.0


@torch.no_grad()
def render_cameras(pipeline: Pipeline, cameras: Cameras) -> RenderOutput:
    """Full-resolution render of one camera (fields chunk rays, so memory stays bounded)."""
    pipeline.field.eval()
    cams = cameras.to(pipeline.device)
    return pipeline.field.render(cams, Window.full(cams))


def render_view(pipeline: Pipeline, index: int) -> RenderOutput:
    return render_cameras(pipeline, pipeline.scene.cameras[[index]])


def render_image(pipeline: Pipeline, index: int) -> Tensor:
    """Full-resolution render (3, H, W) of view ``index``."""
    return render_view(pipeline, index).rgb[0].clamp(0, 1)


@torch.no_grad()
def predict_layer(pipeline: Pipeline, index: int, tile: int = 128) -> Tensor:
    """The rain head's own prediction (C, H, W) for view ``index``, computed tile by tile
    (bounded memory)."""
    head = pipeline.rain_head
    head.eval()
    h, w = pipeline.scene.height, pipeline.scene.width
    out = None
    ids = torch.tensor([index], device=pipeline.device)
    for y in range(0, h, tile):
        for x in range(0, w, tile):
            th, tw = min(tile, h - y), min(tile, w - x)
            win = Window(torch.tensor([x]), torch.tensor([y]), tw, th)
            part = head(ids, win)[0]
            if out is None:
                out = torch.zeros(part.shape[0], h, w, device=pipeline.device)
            out[:, y:y + th, x:x + tw] = part
    return out


@torch.no_grad()
def predict_rain(pipeline: Pipeline, index: int, rendered: Tensor | None = None, tile: int = 128) -> Tensor:
    """Predicted rain layer (3, H, W) of view ``index``: what the head's layer adds to the
    render ``rendered`` (3, H, W; rendered here when not given). For an additive head that is
    its prediction itself; an occluding (colour, alpha) layer adds its colour minus what it
    hides."""
    layer = predict_layer(pipeline, index, tile)
    if rendered is None:
        rendered = render_image(pipeline, index)
    return (pipeline.rain_head.composite(rendered[None], layer[None]) - rendered[None])[0]


@dataclass
class ViewImages:
    """Everything evaluation and renders need for one view, (3, H, W) floats."""

    index: int
    name: str
    split: str  # "train" | "heldout"
    rainy: Tensor
    rendered: Tensor
    depth: Tensor | None  # (1, H, W)
    clean: Tensor | None = None
    rain: Tensor | None = None  # predicted rain layer (training views with a rain head)
    true_rain: Tensor | None = None
    post: dict[str, Tensor] = field(default_factory=dict)  # post-processed renders by key


@torch.no_grad()
def view_images(pipeline: Pipeline, index: int) -> ViewImages:
    scene, dev = pipeline.scene, pipeline.device
    split = "train" if index in set(scene.train_indices) else "heldout"
    out = render_view(pipeline, index)
    v = ViewImages(index, scene.image_names[index], split, to_float(scene.images[index], dev),
                   out.rgb[0].clamp(0, 1), None if out.depth is None else out.depth[0])
    if scene.clean_images is not None:
        v.clean = to_float(scene.clean_images[index], dev)
    if scene.rain_layers is not None:
        v.true_rain = scene.rain_layers[index].to(dev).permute(2, 0, 1).float()
    if split == "train":
        if pipeline.rain_head is not None:
            v.rain = predict_rain(pipeline, index, v.rendered)
        for key, post in pipeline.postprocess.items():
            v.post[key] = post(v.rendered, v.rain, v.rainy).clamp(0, 1)
    return v


@torch.no_grad()
def quick_eval(pipeline: Pipeline, views: int) -> dict:
    """PSNR of the first ``views`` training and held-out renders vs the rainy and the clean
    images (the paper's Fig. 2 curves), under :func:`quick_key`: the clean ones only when the
    scene has clean images, a split without views left out."""
    scene, dev = pipeline.scene, pipeline.device
    out: dict[str, float] = {}
    for split, indices in (("train", scene.train_indices), ("heldout", scene.eval_indices)):
        picked = indices[:views]
        if not picked:
            continue
        clean_vals, rainy_vals = [], []
        for i in picked:
            rgb = render_image(pipeline, i)
            rainy_vals.append(float(psnr(rgb, to_float(scene.images[i], dev))))
            if scene.clean_images is not None:
                clean_vals.append(float(psnr(rgb, to_float(scene.clean_images[i], dev))))
        out[quick_key(split, "rainy")] = mean_of(rainy_vals)
        if clean_vals:
            out[quick_key(split, "clean")] = mean_of(clean_vals)
    return out
