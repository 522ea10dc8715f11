"""The "oracle 3D" row: how high a perfect 3D method can score on a scene.

A simulated scene folder can be rendered again from its ``scene.json``
(``rainyscape.synth.oracle.rerender_clean``). A re-render with an independent sample set
(``ORACLE_SAMPLES`` per pixel axis, not the stored images' count) is what an ideal
reconstruction would render at that view; its PSNR / SSIM against the stored clean images,
on the training and the held-out views as the methods' dataparser splits them, is the
ceiling of that scene's columns (limited only by the ground truth's own sampling noise and
8-bit rounding). Computed once per scene and kept in the results file. Scene folders that the
simulator did not make have no oracle (n/a, with the reason).
"""

from __future__ import annotations

import time
from pathlib import Path

ORACLE_SAMPLES = 3  # base samples per pixel axis of the re-render (the stored views use another count)


def _view_index(name: str, position: int) -> int:
    """0-based simulator view of an image name (``001.png`` is view 0)."""
    stem = Path(name).stem
    return int(stem) - 1 if stem.isdigit() else position


def _stamp(folder: Path) -> float:
    meta = folder / "scene.json"
    return meta.stat().st_mtime if meta.is_file() else 0.0


def cached_oracle(entry: dict | None, folder: str) -> bool:
    """Whether a results-file oracle entry was computed for this folder as it is now (an n/a
    entry only while its reason still holds: a simulator that learnt to re-render gets asked)."""
    same = bool(entry) and entry.get("folder") == folder and entry.get("samples") == ORACLE_SAMPLES \
        and entry.get("stamp") == _stamp(Path(folder))
    return same and (entry.get("available") or entry.get("reason") == unavailable(folder))


def unavailable(folder: str) -> str | None:
    """Why a folder has no oracle, when that is known without rendering (None: try it)."""
    meta = Path(folder) / "scene.json"
    if not meta.is_file():
        return "not a simulated scene folder (no scene.json): no clean scene to re-render"
    if '"preset"' not in meta.read_text():
        return "a real capture: its photos are the ground truth, there is no scene to re-render"
    return None


def na_entry(folder: str, reason: str) -> dict:
    return {"folder": folder, "samples": ORACLE_SAMPLES, "stamp": _stamp(Path(folder)), "available": False,
            "reason": reason}


def scene_oracle(folder: str, cfg) -> dict:
    """The oracle entry of a scene folder: ``available``, and ``train`` / ``heldout``
    {psnr, ssim} means over the views of that split, or the ``reason`` it is n/a. ``cfg``:
    a typed config of the benchmark's cells (its dataparser gives the split and the clean
    images exactly as the methods see them)."""
    path = Path(folder)
    entry = {"folder": folder, "samples": ORACLE_SAMPLES, "stamp": _stamp(path), "available": False}
    reason = unavailable(folder)
    if reason is not None:
        return {**entry, "reason": reason}
    import torch
    import torch.nn.functional as F

    from rainyscape.engine.scene_loading import load_scene
    from rainyscape.errors import RainyScapeError
    from rainyscape.eval.metric_keys import PSNR, SSIM
    from rainyscape.imaging.metrics import psnr, ssim
    from rainyscape.synth.oracle import rerender_clean

    started = time.perf_counter()
    try:
        scene = load_scene(cfg, path)
    except RainyScapeError as exc:
        return {**entry, "reason": str(exc)}
    if scene.clean_images is None:
        return {**entry, "reason": "the scene has no clean images"}
    out = {**entry, "available": True, "views": {}}
    try:
        for split, indices in (("train", scene.train_indices), ("heldout", scene.eval_indices)):
            values = {PSNR.name: [], SSIM.name: []}
            for i in indices:
                img = rerender_clean(path, _view_index(scene.image_names[i], i), samples=ORACLE_SAMPLES)
                pred = torch.from_numpy(img.astype("float32")).permute(2, 0, 1).clamp(0, 1)
                clean = scene.clean_images[i].permute(2, 0, 1).float() / 255.0
                if pred.shape != clean.shape:  # the dataparser downscaled the views: do the same
                    factor = pred.shape[-1] // clean.shape[-1]
                    pred = F.avg_pool2d(pred[None, :, :clean.shape[1] * factor, :clean.shape[2] * factor], factor)[0]
                values[PSNR.name].append(float(psnr(pred, clean)))
                values[SSIM.name].append(float(ssim(pred[None], clean[None])))
            if indices:
                out[split] = {k: sum(v) / len(v) for k, v in values.items()}
            out["views"][split] = len(indices)
    except RainyScapeError as exc:
        return {**entry, "reason": str(exc)}
    out["seconds"] = time.perf_counter() - started
    return out

