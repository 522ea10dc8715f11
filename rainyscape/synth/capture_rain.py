"""Rain added to a real capture in its own cameras: the scenes of the real-photo benchmarks.

A capture (photos and their poses, no rain) becomes a rainy scene folder a user could train
on, with the photos as the ground truth: the simulator's 3D drop field (rain.py) is placed
in front of the capture's cameras and rendered through each camera's own intrinsics and pose,
then composited over the photo (I = B (1 - A) + C A, as for the simulated scenes).

What a real capture does not tell, and how it is chosen:

- **Up.** Rain falls along the world's down. A capture's frame has no known up, so up is
  the cameras' mean up axis (a photographer holds the phone upright).
- **Metres.** A capture's units are arbitrary (COLMAP, LLFF). The capture is read at the scale
  where its nearest surface is ``surface_m`` metres from the cameras (default 8 m: a garden
  or street, the distances of the simulator's presets).
- **Occlusion.** There is no dense depth: each view's depth is one plane at that nearest
  surface, so rain falls between the lens and the scene and never through it. (Real rain
  also falls behind the nearest surface; here it does not, which leaves the scene's own
  pixels rain-free beyond it rather than hiding streaks behind leaves.)
- **Strength.** Drop density is calibrated per capture so that the rainy photos score the
  level's label PSNR against the clean ones (light 30 dB, medium 26, heavy 21: the presets'
  labels), since the same drops weigh differently on bright and dark photos.

Static mode: one field at one instant seen by every camera (a camera array, the paper's
Maya data). Dynamic mode: view k sees the field at time k / fps (a video's rain).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch

from rainyscape.cameras import Cameras, world_up
from rainyscape.errors import ConfigError
from rainyscape.scene import SceneData
from rainyscape.synth import layout
from rainyscape.synth.params import SIM_VERSION, RainConfig
from rainyscape.synth.presets import PRESETS
from rainyscape.synth.rain import DropField, RainLayer, make_drop_field, render_rain

# Rain levels: a preset's rain (drop sizes, wind, exposure) and its label strength.
LEVEL_PRESETS = {"light": "yard", "medium": "crossroad", "heavy": "plaza"}
MODES = ("static", "dynamic")
CALIBRATION_VIEWS = 6  # views the density is calibrated on
CALIBRATION_STEPS = 12  # bisection steps on log(density)
CALIBRATION_TOLERANCE_DB = 0.25


@dataclass(frozen=True)
class CaptureRain:
    level: str = "medium"  # light | medium | heavy (LEVEL_PRESETS)
    mode: str = "static"  # static (one instant) | dynamic (moves between views)
    seed: int = 0
    surface_m: float = 8.0  # the capture is read at the scale where its nearest surface is this far

    def validate(self) -> None:
        if self.level not in LEVEL_PRESETS:
            raise ConfigError(f"rain level '{self.level}' is not one of {', '.join(LEVEL_PRESETS)}")
        if self.mode not in MODES:
            raise ConfigError(f"rain mode '{self.mode}' is not one of {', '.join(MODES)}")
        if not self.surface_m > 1.0:
            raise ConfigError(f"surface_m={self.surface_m}: the nearest surface must be beyond "
                              "the 1 m near clip of the rain")

    @property
    def label_db(self) -> float:
        return PRESETS[LEVEL_PRESETS[self.level]].label_db

    def base_rain(self) -> RainConfig:
        return replace(RainConfig(), **PRESETS[LEVEL_PRESETS[self.level]].rain)


def rain_frame(c2w: np.ndarray) -> np.ndarray:
    """Rotation (3, 3) from the capture's world to a frame whose +y is up (the simulator's
    convention: rain falls along -y); x and z span the horizontal plane."""
    y = world_up(c2w)
    forward = c2w[:, :3, 2].mean(0)
    forward -= y * (forward @ y)
    if np.linalg.norm(forward) < 1e-6:  # cameras looking straight down: any horizontal axis
        forward = np.cross(y, [1.0, 0.0, 0.0] if abs(y[0]) < 0.9 else [0.0, 0.0, 1.0])
    z = forward / np.linalg.norm(forward)
    x = np.cross(y, z)
    return np.stack([x, y, z])


def nearest_surface(scene: SceneData) -> np.ndarray:
    """Per view, the z-depth (the scene's normalised units) of its nearest surface: a low
    percentile of the depths of the sparse points it sees when the scene has them, else the
    scene's near bound."""
    out = np.full(scene.num_images, float(scene.near))
    if scene.points is None or len(scene.points) < 20:
        return out
    uv, z = scene.cameras.project(scene.points.float())
    inside = ((z > 0) & (uv[..., 0] >= 0) & (uv[..., 0] < scene.width)
              & (uv[..., 1] >= 0) & (uv[..., 1] < scene.height))
    for i in range(scene.num_images):
        seen = z[i][inside[i]]
        if seen.numel() >= 20:
            out[i] = float(torch.quantile(seen, 0.02))
    return out


@dataclass
class RainRig:
    """The capture's cameras in metres in the rain frame, and each view's surface depth."""

    cameras: Cameras
    surface: np.ndarray  # (N,) metres
    metres_per_unit: float  # of the scene's normalised world
    rotation: np.ndarray  # (3, 3) from the scene's normalised world to the rain frame


def rain_rig(scene: SceneData, surface_m: float) -> RainRig:
    """Every camera in the rain frame (+y up), in metres: the scale puts the median view's
    nearest surface at ``surface_m``. The scene's normalisation is a similarity, so the
    normalised world serves as well as the capture's own."""
    c2w = scene.cameras.c2w.double().numpy()
    near = nearest_surface(scene)
    metres = surface_m / float(np.median(near))
    rot = rain_frame(c2w)
    out = np.zeros_like(c2w)
    out[:, :3, :3] = rot @ c2w[:, :3, :3]
    out[:, :3, 3] = metres * (c2w[:, :3, 3] - c2w[:, :3, 3].mean(0)) @ rot.T
    out[:, 3, 3] = 1.0
    cams = scene.cameras
    rig_cams = Cameras(torch.from_numpy(out).float(), cams.fx.clone(), cams.fy.clone(),
                       cams.cx.clone(), cams.cy.clone(), cams.width, cams.height)
    return RainRig(rig_cams, near * metres, metres, rot)


def drop_box(rig: RainRig, margin_m: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """The rain volume: the cameras and every view's frustum out to its nearest surface."""
    cams = rig.cameras
    c2w = cams.c2w.double().numpy()
    pts = [c2w[:, :3, 3]]
    w, h = cams.width, cams.height
    for u, v in ((0, 0), (w, 0), (0, h), (w, h)):
        x = (u - cams.cx.double().numpy()) / cams.fx.double().numpy()
        y = (v - cams.cy.double().numpy()) / cams.fy.double().numpy()
        d = np.stack([x, y, np.ones_like(x)], -1) * rig.surface[:, None]
        pts.append(np.einsum("nij,nj->ni", c2w[:, :3, :3], d) + c2w[:, :3, 3])
    pts = np.concatenate(pts)
    return pts.min(0) - margin_m, pts.max(0) + margin_m


def drop_colour(clean: torch.Tensor) -> np.ndarray:
    """Rain's colour: the bright sky a drop refracts; here the capture's bright tones (the
    mean of its brightest 5 % of pixels), as the presets use the mean sky."""
    px = clean.reshape(-1, 3).float() / 255.0
    lum = px.mean(-1)
    bright = px[lum >= torch.quantile(lum[:: max(1, len(lum) // 200_000)], 0.95)]
    return bright.mean(0).double().numpy()


def _render(rig: RainRig, cfg: RainConfig, k: int, time_s: float, drops, colour: np.ndarray) -> RainLayer:
    depth = np.full((rig.cameras.height, rig.cameras.width, 1), rig.surface[k], np.float32)
    return render_rain(drops, rig.cameras, k, depth, time_s, cfg, colour)


def _composite(layer: RainLayer, clean8: np.ndarray) -> np.ndarray:
    return layout.to_uint8(layer.composite(clean8.astype(np.float64) / 255.0))


def calibrate_density(rig: RainRig, clean: torch.Tensor, cfg: RainConfig, times: list[float],
                      label_db: float, seed: int, colour: np.ndarray) -> tuple[float, float]:
    """The density (drops per m^3) at which the rainy views score ``label_db`` against the
    clean ones (mean over a few spread views), by bisection on log density; and that score."""
    from rainyscape.synth.simulate import rain_strength

    lo_box, hi_box = drop_box(rig)
    views = np.unique(np.linspace(0, len(clean) - 1, min(CALIBRATION_VIEWS, len(clean))).round().astype(int))

    def strength(density: float) -> float:
        c = replace(cfg, density=density)
        drops = make_drop_field(lo_box, hi_box, c, seed)
        scores = [rain_strength(_composite(_render(rig, c, int(k), times[k], drops, colour),
                                           clean[k].numpy()), clean[k].numpy())[0] for k in views]
        return float(np.mean(scores))

    lo, hi = math.log(1e-3), math.log(50.0)
    best = (float("inf"), 1.0, 0.0)
    for _ in range(CALIBRATION_STEPS):
        mid = 0.5 * (lo + hi)
        score = strength(math.exp(mid))
        best = min(best, (abs(score - label_db), math.exp(mid), score))
        if abs(score - label_db) < CALIBRATION_TOLERANCE_DB:
            break
        if score > label_db:  # too little rain
            lo = mid
        else:
            hi = mid
    return best[1], best[2]


def capture_falls(scene: SceneData, rig: RainRig, drops: DropField) -> np.ndarray:
    """(K, 3) the drops' fall directions in the capture's own world frame (transforms.json's):
    out of the rain frame, then out of the scene's normalisation."""
    normalised = drops.fall_directions() @ rig.rotation
    return normalised @ scene.transform[:3, :3].double().numpy()


def add_rain(scene: SceneData, out: str | Path, rain: CaptureRain) -> Path:
    """Write ``scene`` (its images are the clean photos) with rain as a transforms.json scene
    folder: ``images_rain/`` (training), ``images_wo_rain/`` (the photos), ``rain/`` (the true
    rain, RGBA as the simulator writes it), ``transforms.json`` (the capture's poses and
    intrinsics, in its own world frame) and ``scene.json`` (how the rain was made, and the
    rainy-vs-clean metrics). The capture's sparse points are not copied: they came from the
    clean photos, and training must find its own in the rainy ones."""
    from rainyscape.dataparsers.writers import transforms_meta
    from rainyscape.dataparsers.transforms_json import write_transforms
    from rainyscape.synth.simulate import rain_statistics, rain_strength

    rain.validate()
    out = Path(out)
    rig = rain_rig(scene, rain.surface_m)
    clean = scene.images
    n = len(clean)
    base = rain.base_rain()
    times = [k / base.fps if rain.mode == "dynamic" else 0.0 for k in range(n)]
    colour = np.clip(base.brightness * drop_colour(clean), 0.0, 1.0)
    density, calibrated = calibrate_density(rig, clean, base, times, rain.label_db, rain.seed, colour)
    cfg = replace(base, density=density)
    lo_box, hi_box = drop_box(rig)
    drops = make_drop_field(lo_box, hi_box, cfg, rain.seed)
    for sub in (layout.RAINY_DIR, layout.CLEAN_DIR, layout.RAIN_DIR):
        (out / sub).mkdir(parents=True, exist_ok=True)
    stems = [Path(name).stem for name in scene.image_names]
    per_view = []
    for k in range(n):
        layer = _render(rig, cfg, k, times[k], drops, colour)
        clean8 = clean[k].numpy()
        rainy8 = _composite(layer, clean8)
        layout.write_view(out, stems[k], rainy8, clean8, None, layer.alpha, layer.color)
        p_db, s = rain_strength(rainy8, clean8)
        coverage, mean_share = rain_statistics(layer.alpha, rainy8, clean8)
        per_view.append({"name": f"{stems[k]}.png", "psnr": round(p_db, 3), "ssim": round(s, 4),
                         "rain_coverage": round(coverage, 4), "rain_mean_share": round(mean_share, 4),
                         "streaks": layer.streaks, "time_s": times[k]})
    meta = transforms_meta(scene, [f"{layout.RAINY_DIR}/{s}.png" for s in stems])
    held = set(scene.eval_indices)
    meta["train_filenames"] = [f"{layout.RAINY_DIR}/{s}.png" for i, s in enumerate(stems) if i not in held]
    meta["test_filenames"] = [f"{layout.RAINY_DIR}/{s}.png" for i, s in enumerate(stems) if i in held]
    write_transforms(out / "transforms.json", meta)
    info = {
        "simulator_version": SIM_VERSION, "kind": "real capture with simulated rain",
        "source": str(scene.source), "capture": scene.name, "level": rain.level, "mode": rain.mode,
        "seed": rain.seed, "width": scene.width, "height": scene.height, "views": n,
        "rain": cfg.to_dict(), "rain_falls": capture_falls(scene, rig, drops).round(6).tolist(),
        "label_db": rain.label_db, "calibrated_db": round(calibrated, 3),
        "drops": len(drops.radii), "drop_box_m": [lo_box.tolist(), hi_box.tolist()],
        "metres_per_unit": rig.metres_per_unit, "surface_m": rain.surface_m,
        "drop_rgb": colour.tolist(),
        "rain_layer": {"folder": layout.RAIN_DIR, "format": "RGBA png: RGB rain colour C, A coverage; "
                       "rainy = clean * (1 - A) + C * A", "contents": "streaks only"},
        "occlusion": "one plane per view at its nearest surface (no dense depth)",
        "metrics": {"psnr_rainy_vs_clean": round(float(np.mean([v["psnr"] for v in per_view])), 3),
                    "ssim_rainy_vs_clean": round(float(np.mean([v["ssim"] for v in per_view])), 4),
                    "rain_coverage": round(float(np.mean([v["rain_coverage"] for v in per_view])), 4),
                    "rain_mean_share": round(float(np.mean([v["rain_mean_share"] for v in per_view])), 4),
                    "per_view": per_view},
    }
    layout.write_scene_json(out / "scene.json", info)  # written last: marks a complete scene
    return out
