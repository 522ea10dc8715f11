"""`generate`: build a scene, place cameras, render clean views and rain, write the layout."""

from __future__ import annotations

import multiprocessing
import os
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import asdict, dataclass, fields, replace
from pathlib import Path

import numpy as np
import torch

from rainyscape.config.schema import SEED_MAX, check_range
from rainyscape.errors import ConfigError
from rainyscape.formats.output import staged_folder
from rainyscape.imaging.metrics import psnr, ssim
from rainyscape.synth import layout
from rainyscape.synth.presets import PRESETS
from rainyscape.synth.params import SIM_VERSION, RainConfig
from rainyscape.synth.rain import make_drop_field, render_rain
from rainyscape.synth.raycast import EDGE_FACTOR, Camera, SceneRenderer, ViewRender, default_samples
from rainyscape.synth.rig import make_rig
from rainyscape.synth.scenes import build_scene
from rainyscape.synth.transients import TransientConfig, transient_mask, view_transients

MODES = ("static", "dynamic")
TRAJECTORIES = ("sphere", "video")


def rain_config(preset_rain: dict, overrides: dict) -> RainConfig:
    """The preset's rain with ``overrides`` (numbers or text), every value range-checked."""
    valid = RainConfig.keys()
    unknown = [k for k in overrides if k not in valid]
    if unknown:
        raise ConfigError(f"unknown rain option '{unknown[0]}'; rain options are {', '.join(valid)}")
    cfg = RainConfig(**preset_rain)
    values = {}
    for key, value in overrides.items():
        try:
            values[key] = float(value)
        except (TypeError, ValueError):
            raise ConfigError(f"rain option {key}: cannot read '{value}' as a number") from None
        if not np.isfinite(values[key]):
            raise ConfigError(f"rain option {key}: {value} is not finite")
    cfg = replace(cfg, **values)
    for f in fields(RainConfig):
        check_range(getattr(cfg, f.name), f.metadata, f.name)
    if cfg.radius_max_mm < cfg.radius_min_mm:
        raise ConfigError(f"radius_max_mm: must be at least radius_min_mm ({cfg.radius_min_mm:g}), "
                          f"got {cfg.radius_max_mm:g}")
    return cfg


def rain_strength(rainy: np.ndarray, clean: np.ndarray) -> tuple[float, float]:
    """PSNR (dB) and SSIM of a rainy uint8 view against its clean version."""
    a = torch.from_numpy(rainy).permute(2, 0, 1)[None].float() / 255.0
    b = torch.from_numpy(clean).permute(2, 0, 1)[None].float() / 255.0
    padding = "valid" if min(rainy.shape[:2]) >= 11 else "same"  # tiny test images
    return float(psnr(a, b)), float(ssim(a, b, padding=padding))


def drop_box(positions: np.ndarray, look_at: np.ndarray, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """The rain volume: every camera and the scene around the look-at point, ground to above
    the highest camera."""
    reach = 0.8 * radius
    lo = np.minimum(positions.min(0), look_at - reach) - 1.5
    hi = np.maximum(positions.max(0), look_at + reach) + 1.5
    lo[1], hi[1] = 0.0, positions[:, 1].max() + 3.0
    return lo, hi


# Every entry of a simulated scene: force=true replaces all of them (haze/ too when this scene
# has none), so the folder holds one scene; scene.json, written last, marks a complete one.
SCENE_ENTRIES = (layout.RAINY_DIR, layout.CLEAN_DIR, layout.DEPTH_DIR, layout.RAIN_DIR, layout.HAZE_DIR,
                 "cameras.csv", "scene.json")
SCENE_WRITES = "a simulated scene (images_rain/, images_wo_rain/, depth/, rain/, haze/, cameras.csv, scene.json)"
# Ranges of the size options (rs-synth's command line checks the same)
LIMITS = {"rows": (1, 100), "cols": (1, 100), "width": (1, 8192), "height": (1, 8192), "workers": (1, 256),
          "seed": (0, SEED_MAX)}


def check_limits(**values) -> None:
    """ConfigError naming the first option outside :data:`LIMITS` (None: the preset's)."""
    for key, value in values.items():
        if value is None:
            continue
        lo, hi = LIMITS[key]
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or not lo <= value <= hi:
            raise ConfigError(f"{key}: must be between {lo} and {hi}, got {value}")


@dataclass(frozen=True)
class Job:
    """Everything that determines a simulation (workers rebuild it from this, deterministically)."""

    preset: str
    rows: int
    cols: int
    width: int
    height: int
    mode: str
    trajectory: str
    seed: int
    rain: RainConfig
    out: str


class Simulation:
    """The scene, cameras and drop field of a job; renders and writes one view at a time."""

    def __init__(self, job: Job):
        self.job = job
        p = PRESETS[job.preset]
        self.spec = build_scene(p.scene, job.seed)
        self.rig = make_rig(self.spec.rig, job.rows, job.cols, job.width, job.height, job.trajectory)
        self.cameras = self.rig.cameras()
        self.renderer = SceneRenderer(self.spec)
        self.transients = TransientConfig.of(p.transients)
        self.look_at = np.asarray(self.spec.rig.look_at, float)
        self.box = drop_box(self.rig.positions, self.look_at, self.spec.rig.radius)
        self.drops = make_drop_field(*self.box, job.rain, job.seed + 1000)
        sky_mean = 0.5 * (np.asarray(self.spec.sky_zenith) + np.asarray(self.spec.sky_horizon))
        self.drop_rgb = np.clip(job.rain.brightness * sky_mean, 0, 1)
        self.fog_rgb = np.asarray(self.spec.sky_horizon, float)
        n = len(self.cameras)
        self.names = layout.view_names(n)
        self.times = [k / job.rain.fps if job.mode == "dynamic" else 0.0 for k in range(n)]

    def __len__(self) -> int:
        return len(self.cameras)

    def render_clean(self, k: int, samples: int | None = None) -> ViewRender:
        """The clean view ``k`` (pixel integrals; ``samples`` per axis, default by image size:
        see render.py)."""
        return self.renderer.render(self.cameras, k, samples=samples, seed=self.job.seed)

    def render_view(self, k: int) -> dict:
        """Render view ``k``, write its files, return its rainy-vs-clean metrics."""
        view = self.render_clean(k)
        if self.transients.any:
            return self.render_transients(k, view)
        cfg = self.job.rain
        rain_layer = render_rain(self.drops, self.cameras, k, view.sub_depth, self.times[k], cfg, self.drop_rgb)
        background = view.rgb
        transmission = None
        if cfg.haze > 0:
            transmission = haze_transmission(view.sub_depth, cfg.haze)
            background = view.rgb * transmission[..., None] + self.fog_rgb * (1 - transmission[..., None])
        clean8 = layout.to_uint8(view.rgb)
        rainy8 = layout.to_uint8(rain_layer.composite(background))
        layout.write_view(Path(self.job.out), self.names[k], rainy8, clean8, view.depth,
                          rain_layer.alpha, rain_layer.color, transmission)
        p_db, s = rain_strength(rainy8, clean8)
        coverage, mean_share = rain_statistics(rain_layer.alpha, layout.to_uint8(rain_layer.composite(view.rgb)), clean8)
        return {"name": f"{self.names[k]}.png", "psnr": round(p_db, 3), "ssim": round(s, 4),
                "rain_coverage": round(coverage, 4), "rain_mean_share": round(mean_share, 4),
                "streaks": rain_layer.streaks, "edge_pixels": round(view.edge_fraction, 4), "time_s": self.times[k]}


    def render_transients(self, k: int, view: ViewRender) -> dict:
        """View ``k`` with its own transient objects in place of rain: the scene rendered again
        with them, with the clean view's samples (so the pixels they leave alone are the clean
        view's, exactly). The rain layer holds them and their shadows, fully opaque: rainy =
        clean (1 - A) + C A with A = 1 where the two renders differ, C the view there."""
        extra = view_transients(self.transients, Camera.of(self.cameras, k), self.job.seed, k)
        observed = view.rgb
        if extra:
            spec = replace(self.spec, parts=self.spec.parts + extra)
            observed = SceneRenderer(spec).render(self.cameras, k, seed=self.job.seed, like=view).rgb
        mask = transient_mask(observed, view.rgb)
        shown = np.where(mask[..., None], observed, view.rgb)
        clean8, rainy8 = layout.to_uint8(view.rgb), layout.to_uint8(shown)
        alpha = mask.astype(np.float64)
        layout.write_view(Path(self.job.out), self.names[k], rainy8, clean8, view.depth, alpha,
                          shown * alpha[..., None])
        p_db, s = rain_strength(rainy8, clean8)
        return {"name": f"{self.names[k]}.png", "psnr": round(p_db, 3), "ssim": round(s, 4),
                "rain_coverage": round(float(mask.mean()), 4), "rain_mean_share": 0.0,
                "streaks": 0, "transient_parts": len(extra), "edge_pixels": round(view.edge_fraction, 4),
                "time_s": self.times[k]}


def haze_transmission(sub_depth: np.ndarray, haze: float) -> np.ndarray:
    """Share of the scene's light that reaches the camera through a uniform fog that loses
    ``haze`` of it over 100 m (mean over the pixel's samples; the sky counts as 300 m)."""
    beta = -np.log(max(1.0 - float(haze), 1e-6)) / 100.0
    return np.exp(-beta * np.minimum(sub_depth, 300.0)).mean(-1)


def rain_statistics(alpha: np.ndarray, rainy8: np.ndarray, clean8: np.ndarray) -> tuple[float, float]:
    """Coverage (share of pixels with rain alpha > 0.02) and the share of the rain's squared
    error that is its per-image mean (a uniform veil has 1, sparse streaks little)."""
    r = rainy8.astype(np.float64) - clean8.astype(np.float64)
    mean_sq = float((r.reshape(-1, 3).mean(0) ** 2).sum())
    sq = float((r ** 2).reshape(-1, 3).mean(0).sum())
    return float((alpha > 0.02).mean()), mean_sq / sq if sq > 0 else 0.0


_WORKER: Simulation | None = None


def _init_worker(job: Job) -> None:
    global _WORKER
    torch.set_num_threads(1)
    _WORKER = Simulation(job)


def _render_in_worker(k: int) -> dict:
    return _WORKER.render_view(k)


def auto_workers(views: int, width: int, height: int) -> int:
    """One process for small jobs (start-up costs more than it saves), else every core."""
    if views * width * height < 4_000_000:
        return 1
    return max(1, min(os.cpu_count() or 1, views, 8))


def _render_all(sim: Simulation, workers: int, progress) -> list[dict]:
    n = len(sim)
    if workers <= 1:
        out = []
        for k in range(n):
            out.append(sim.render_view(k))
            if progress is not None:
                progress(k + 1, n)
        return out
    ctx = multiprocessing.get_context("spawn")  # no fork after torch / OpenMP start
    results: dict[int, dict] = {}
    with ProcessPoolExecutor(workers, mp_context=ctx, initializer=_init_worker,
                             initargs=(sim.job,)) as pool:
        futures = {pool.submit(_render_in_worker, k): k for k in range(n)}
        for fut in as_completed(futures):
            results[futures[fut]] = fut.result()
            if progress is not None:
                progress(len(results), n)
    return [results[k] for k in range(n)]


def generate(out_dir: str | Path, preset: str = "demo", rows: int | None = None, cols: int | None = None,
             width: int | None = None, height: int | None = None, mode: str = "static",
             trajectory: str = "sphere", seed: int = 0, force: bool = False,
             progress=None, workers: int | None = None, **rain_overrides) -> Path:
    """Simulate a rainy multi-view scene into ``out_dir`` (the Maya layout; docs/data.md).

    ``rain_overrides`` are :class:`~rainyscape.synth.params.RainConfig` fields (density,
    wind_deg, ...). ``progress`` is called as progress(done, total) after each view.
    ``workers``: processes rendering views (None: one for small jobs, else every core).
    Returns the folder. Refuses a non-empty folder unless ``force``, which replaces every entry
    of a scene there (:data:`SCENE_ENTRIES`) as a whole and keeps the rest. The scene is built
    in a temporary folder beside ``out_dir`` and moved in when complete: a failure (out of
    memory, an interrupt) leaves ``out_dir`` as it was.
    """
    if preset not in PRESETS:
        raise ConfigError(f"unknown preset '{preset}'; presets are {', '.join(PRESETS)}")
    if mode not in MODES:
        raise ConfigError(f"mode must be one of {', '.join(MODES)}, got '{mode}'")
    if trajectory not in TRAJECTORIES:
        raise ConfigError(f"trajectory must be one of {', '.join(TRAJECTORIES)}, got '{trajectory}'")
    p = PRESETS[preset]
    # None means "the preset's"; 0 or less is an error, never silently the preset's
    check_limits(rows=rows, cols=cols, width=width, height=height, workers=workers, seed=seed)
    rows = p.rows if rows is None else rows
    cols = p.cols if cols is None else cols
    width = p.width if width is None else width
    height = (p.height if width == p.width else width) if height is None else height
    rain = rain_config(p.rain, rain_overrides)
    out = Path(out_dir)
    with staged_folder(out, SCENE_ENTRIES, force, SCENE_WRITES, last="scene.json") as stage:
        _simulate(stage, preset, int(rows), int(cols), int(width), int(height), mode, trajectory, int(seed),
                  rain, workers, progress)
    return out


def _simulate(out: Path, preset: str, rows: int, cols: int, width: int, height: int, mode: str,
              trajectory: str, seed: int, rain: RainConfig, workers: int | None, progress) -> None:
    """Simulate into the (empty, staging) folder ``out``."""
    p = PRESETS[preset]
    started = time.perf_counter()
    job = Job(preset, rows, cols, width, height, mode, trajectory, seed, rain, str(out))
    sim = Simulation(job)
    layout.make_dirs(out)
    n = len(sim)
    workers = auto_workers(n, width, height) if workers is None else int(workers)
    per_view = _render_all(sim, workers, progress)
    rig = sim.rig
    layout.write_cameras_csv(out / "cameras.csv", rig.positions, rig.rotations, np.full(n, rig.focal_mm),
                             np.full(n, rig.h_aperture_mm), np.full(n, rig.v_aperture_mm))
    lo, hi = sim.box
    base_n = default_samples(int(width), int(height))
    info = {
        "simulator_version": SIM_VERSION, "preset": preset, "scene": p.scene, "description": p.description,
        "mode": mode, "trajectory": trajectory, "rows": rows, "cols": cols, "width": width,
        "height": height, "seed": seed, "units": "metres, Y up (Maya)",
        "rain": rain.to_dict(), "rain_falls": sim.drops.fall_directions().round(6).tolist(),
        "drops": len(sim.drops), "drop_box": [lo.tolist(), hi.tolist()],
        "transients": asdict(sim.transients) if sim.transients.any else None,
        "look_at": sim.look_at.tolist(), "sun_dir": list(sim.spec.sun_dir),
        "depth": {"folder": layout.DEPTH_DIR, "key": layout.DEPTH_KEY,
                  "kind": "z-depth along the optical axis of the pixel-centre ray",
                  "units": "world", "sky": "inf"},
        "rain_layer": {"folder": layout.RAIN_DIR, "format": "RGBA png: RGB rain colour C, A coverage; "
                       "rainy = clean * (1 - A) + C * A",
                       "contents": ("transient objects, their shadows and edges (A = 1 there), no rain"
                                    if sim.transients.any else "streaks only")},
        "haze": ({"folder": layout.HAZE_DIR, "format": "grey png: transmission T; rainy = (clean * T + fog * "
                  "(1 - T)) * (1 - A) + C * A", "fog_rgb": sim.fog_rgb.tolist(), "haze": rain.haze}
                 if rain.haze > 0 else None),
        "sampling": {"clean": f"{base_n}x{base_n} prefiltered samples per pixel, at least "
                     f"{base_n * EDGE_FACTOR}x{base_n * EDGE_FACTOR} jittered at edges",
                     "samples": base_n, "edge_factor": EDGE_FACTOR,
                     "edge_pixels": round(float(np.mean([v["edge_pixels"] for v in per_view])), 4)},
        "metrics": {"psnr_rainy_vs_clean": round(float(np.mean([v["psnr"] for v in per_view])), 3),
                    "ssim_rainy_vs_clean": round(float(np.mean([v["ssim"] for v in per_view])), 4),
                    "rain_coverage": round(float(np.mean([v["rain_coverage"] for v in per_view])), 4),
                    "rain_mean_share": round(float(np.mean([v["rain_mean_share"] for v in per_view])), 4),
                    "per_view": per_view},
        "workers": workers,
        "seconds": round(time.perf_counter() - started, 2),
    }
    layout.write_scene_json(out / "scene.json", info)  # written last: marks a complete scene
