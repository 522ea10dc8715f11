"""Structure from motion with the pycolmap wheel (no colmap binary): features, matching,
incremental mapping, choice of the largest model, registration check and undistortion.

Choices for handheld captures (measured on a 44-photo phone orbit, docs/process.md): SIFT
with affine shape estimation, whose features survive the large viewpoint changes of an orbit
(33 -> 42 photos registered), the focal length from the photos' EXIF as a prior, and, when
frames are left out, a second mapping with relaxed registration thresholds (kept only when it
registers more).

pycolmap 4.x API. Loop detection in sequential matching needs a vocabulary tree; when the user
gives none (the stock trees are downloads), one is built from the clip's own SIFT descriptors,
which is enough to find revisited places within one capture.
"""

from __future__ import annotations

import contextlib
import math
import os
import shutil
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator

import numpy as np

from rainyscape.errors import ConfigError, DataError

# Perspective models SfM may fit; undistortion turns each into PINHOLE.
CAMERA_MODELS = ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV", "FULL_OPENCV")
MATCHERS = ("sequential", "exhaustive")
WARN_FRACTION = 0.8  # fewer registered frames than this fraction: warn
SMALL_SET = 5  # fewer frames than this: keep points seen by two frames only
MIN_VOCAB_DESCRIPTORS = 6400  # fewer SIFT descriptors in the clip: no loop detection
# The retry's registration threshold: 2D-3D inliers a frame needs (COLMAP's default: 30).
RELAXED_ABS_POSE_MIN_INLIERS = 15


@dataclass
class SfmOptions:
    camera_model: str = "SIMPLE_RADIAL"
    single_camera: bool = True  # one shared camera for all frames (a video, one phone)
    matcher: str = "sequential"  # sequential (video) or exhaustive (small photo sets)
    overlap: int = 10  # sequential: frames matched with the next `overlap` (and 2^k further)
    loop_detection: bool = True  # sequential: also match revisited places
    vocab_tree: str = ""  # COLMAP vocabulary tree for loop detection (empty: build one)
    max_features: int = 8192  # SIFT features per image
    affine_shape: bool = True  # SIFT with affine shape estimation: robust to viewpoint change
    domain_size_pooling: bool = False  # DSP-SIFT descriptors (costlier; no gain measured with affine shape)
    retry: bool = True  # frames left out: map again with relaxed registration, keep the better model
    min_registered: float = 0.5  # fail when fewer frames than this fraction register
    init_min_tri_angle: float = 16.0  # degrees; lower it for narrow baselines (a stereo pair)
    exif_focal: bool = True  # start from the focal length the photos' EXIF gives (when they agree)
    focal_prior: float = 0.0  # focal length in pixels the frames were taken with, 0: unknown
    num_threads: int = -1  # -1: all cores
    seed: int = 0
    # One thread in every step that decides the poses: the same photos then give the same poses
    # to the bit from run to run (another CPU may still round differently). With several, the
    # database numbers the images in the order their features finish, and the matcher's and
    # bundle adjustment's results depend on how their threads interleave: the clock orbit's
    # camera matrices moved by up to 0.06 from run to run (docs/process.md, "Same photos, same
    # poses").
    deterministic: bool = False
    verbose: bool = False  # show COLMAP's own log

    @property
    def threads(self) -> int:
        """The threads each COLMAP step that decides the poses gets."""
        return 1 if self.deterministic else self.num_threads

    def validate(self) -> None:
        if self.camera_model not in CAMERA_MODELS:
            raise ConfigError(f"camera model '{self.camera_model}' is not one of {', '.join(CAMERA_MODELS)}")
        if self.matcher not in MATCHERS:
            raise ConfigError(f"matcher '{self.matcher}' is not one of {', '.join(MATCHERS)}")
        if self.max_features < 64:
            raise ConfigError(f"max_features={self.max_features}: use at least 64")
        if not 0 < self.init_min_tri_angle < 90:
            raise ConfigError(f"init_min_tri_angle={self.init_min_tri_angle}: degrees in (0, 90)")
        if not 0 < self.min_registered <= 1:
            raise ConfigError(f"min_registered={self.min_registered}: a fraction in (0, 1]")
        if self.vocab_tree and not Path(self.vocab_tree).is_file():
            raise ConfigError(f"{self.vocab_tree}: no such vocabulary tree file")


@dataclass
class Registration:
    """How well SfM went: the registration report."""

    total: int  # frames given to SfM
    registered: list[str]  # names of registered frames, sorted
    unregistered: list[str]
    mean_reprojection_error: float  # pixels
    num_points: int
    model_sizes: list[int]  # registered frames of every model found, largest first
    attempts: list[dict] = field(default_factory=list)  # each mapping tried: settings, registered, kept

    @property
    def fraction(self) -> float:
        return len(self.registered) / self.total if self.total else 0.0

    def summary(self) -> str:
        text = (f"registered {len(self.registered)}/{self.total} frames ({100 * self.fraction:.0f} %), "
                f"{self.num_points} points, mean reprojection error "
                f"{self.mean_reprojection_error:.2f} px")
        if len(self.model_sizes) > 1:
            text += (f"; {len(self.model_sizes)} separate models of {self.model_sizes} frames, "
                     "kept the largest")
        if len(self.attempts) > 1:
            text += "; " + ", ".join(f"{a['mapper']} mapping: {a['registered']}" + (" (kept)" if a["kept"] else "")
                                     for a in self.attempts)
        return text

    def to_json(self) -> dict:
        return {"total": self.total, "registered": len(self.registered),
                "fraction": round(self.fraction, 4),
                "mean_reprojection_error_px": round(self.mean_reprojection_error, 4),
                "num_points": self.num_points, "model_sizes": self.model_sizes,
                "unregistered": self.unregistered, "attempts": self.attempts}


@contextlib.contextmanager
def colmap_log(verbose: bool) -> Iterator[None]:
    """Silence COLMAP's INFO / WARNING log unless asked for it."""
    import pycolmap

    before = pycolmap.logging.minloglevel
    pycolmap.logging.minloglevel = 0 if verbose else 3  # failures are reported by us
    try:
        yield
    finally:
        pycolmap.logging.minloglevel = before


@contextlib.contextmanager
def native_stderr_silenced() -> Iterator[None]:
    """Discard what C++ code writes to file descriptor 2 (Python's own stderr is flushed first)."""
    sys.stderr.flush()
    saved = os.dup(2)
    with open(os.devnull, "w") as devnull:
        os.dup2(devnull.fileno(), 2)
        try:
            yield
        finally:
            os.dup2(saved, 2)
            os.close(saved)


def extract_features(database: Path, image_dir: Path, names: list[str], opts: SfmOptions) -> None:
    import pycolmap

    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = opts.camera_model
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.sift.max_num_features = opts.max_features
    extraction.sift.estimate_affine_shape = opts.affine_shape
    extraction.sift.domain_size_pooling = opts.domain_size_pooling
    extraction.num_threads = opts.threads
    mode = pycolmap.CameraMode.SINGLE if opts.single_camera else pycolmap.CameraMode.PER_IMAGE
    pycolmap.extract_features(database, image_dir, image_names=names, camera_mode=mode,
                              reader_options=reader, extraction_options=extraction)
    if opts.focal_prior > 0:
        set_focal_prior(database, opts.focal_prior)


def set_focal_prior(database: Path, focal: float) -> None:
    """Start every camera from a known focal length, marked as a prior: verification then
    fits essential matrices (calibrated pairs) instead of fundamental ones, and the mapper
    starts from the right field of view (PNG frames carry no EXIF for COLMAP to read)."""
    import pycolmap

    with pycolmap.Database.open(database) as db:
        for cam in db.read_all_cameras():
            params = np.array(cam.params, dtype=np.float64)
            params[list(cam.focal_length_idxs())] = focal
            cam.params = params
            cam.has_prior_focal_length = True
            db.update_camera(cam)


def build_vocab_tree(database: Path, out_path: Path, seed: int, num_threads: int,
                     max_descriptors: int = 200_000) -> Path | None:
    """A small vocabulary tree from the database's own SIFT descriptors (for loop detection);
    None when the frames have too few features to be worth one."""
    import pycolmap

    with pycolmap.Database.open(database) as db:
        descs = [db.read_descriptors(im.image_id).to_float().data for im in db.read_all_images()]
    data = np.concatenate([d for d in descs if len(d)] or [np.zeros((0, 128), np.float32)])
    if len(data) < MIN_VOCAB_DESCRIPTORS:
        return None
    if len(data) > max_descriptors:
        data = data[np.random.default_rng(seed).choice(len(data), max_descriptors, replace=False)]
    index = pycolmap.VisualIndex.create(128, 64)  # SIFT descriptors, 64-d Hamming embedding
    build = pycolmap.VisualIndex.BuildOptions()
    # About 100 descriptors per visual word: a vocabulary one capture can support.
    build.num_visual_words = int(np.clip(len(data) // 100, 64, 16384))
    build.num_iterations = 20
    build.num_rounds = 1
    build.num_threads = num_threads
    descriptors = pycolmap.FeatureDescriptorsFloat(pycolmap.FeatureExtractorType.SIFT,
                                                   np.ascontiguousarray(data, np.float32))
    with native_stderr_silenced():  # faiss warns that a small vocabulary has few points per word
        index.build(build, descriptors)
    index.write(out_path)
    return out_path


def match_features(database: Path, work_dir: Path, opts: SfmOptions) -> None:
    import pycolmap

    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = opts.threads
    verification = pycolmap.TwoViewGeometryOptions()
    verification.ransac.random_seed = opts.seed
    if opts.matcher == "exhaustive":
        pycolmap.match_exhaustive(database, matching_options=matching,
                                  verification_options=verification)
        return
    pairing = pycolmap.SequentialPairingOptions()
    pairing.overlap = opts.overlap
    pairing.num_threads = opts.threads
    tree = None
    if opts.loop_detection:
        tree = Path(opts.vocab_tree) if opts.vocab_tree else build_vocab_tree(
            database, work_dir / "vocab_tree.bin", opts.seed, opts.threads)
    if tree is not None:
        pairing.loop_detection = True
        pairing.vocab_tree_path = tree
        pairing.loop_detection_period = max(1, opts.overlap // 2)
    pycolmap.match_sequential(database, matching_options=matching, pairing_options=pairing,
                              verification_options=verification)


def incremental_mapping(database: Path, image_dir: Path, out_dir: Path, opts: SfmOptions,
                        total: int, progress: bool, relaxed: bool = False) -> dict:
    """Incremental SfM; returns every model found, keyed by its index. ``relaxed``: frames
    register with fewer 2D-3D inliers, and points seen by two frames are kept (they are the
    3D points a weakly connected frame can register against)."""
    import pycolmap
    from tqdm import tqdm

    pipeline = pycolmap.IncrementalPipelineOptions()
    pipeline.num_threads = opts.threads
    pipeline.random_seed = opts.seed
    pipeline.min_model_size = min(pipeline.min_model_size, max(2, total // 2))
    pipeline.extract_colors = True
    pipeline.mapper.init_min_tri_angle = opts.init_min_tri_angle
    # In a handful of photos most points are seen twice only; COLMAP's default drops those.
    pipeline.triangulation.ignore_two_view_tracks = total >= SMALL_SET and not relaxed
    if relaxed:
        pipeline.mapper.abs_pose_min_num_inliers = RELAXED_ABS_POSE_MIN_INLIERS
    out_dir.mkdir(parents=True, exist_ok=True)
    bar = tqdm(total=total, desc="registering", unit="frame", disable=not progress)
    try:  # the callback fires as each frame after the initial pair is tried
        models = pycolmap.incremental_mapping(database, image_dir, out_dir, pipeline,
                                              next_image_callback=lambda: bar.update(1))
        bar.n = max((m.num_reg_images() for m in models.values()), default=0)
        bar.refresh()
    finally:
        bar.close()
    return dict(models)


def mapping_attempt(name: str, report: "Registration", kept: bool) -> dict:
    return {"mapper": name, "registered": len(report.registered),
            "mean_reprojection_error_px": round(report.mean_reprojection_error, 4),
            "num_points": report.num_points, "kept": kept}


def largest_model(models: dict):
    """The model with the most registered frames (ties: the most points), with its index."""
    if not models:
        return None, None
    key = max(models, key=lambda k: (models[k].num_reg_images(), models[k].num_points3D()))
    return key, models[key]


def registration_report(model, names: list[str], models: dict) -> Registration:
    registered = sorted(model.images[i].name for i in model.reg_image_ids()) if model else []
    done = set(registered)
    sizes = sorted((m.num_reg_images() for m in models.values()), reverse=True)
    return Registration(
        total=len(names), registered=registered, unregistered=[n for n in names if n not in done],
        mean_reprojection_error=float(model.compute_mean_reprojection_error()) if model else float("nan"),
        num_points=int(model.num_points3D()) if model else 0, model_sizes=sizes)


def check_registration(report: Registration, opts: SfmOptions, source: Path) -> str | None:
    """Raise when too few frames registered; return a warning line below 80 %."""
    need = max(2, math.ceil(opts.min_registered * report.total))
    if len(report.registered) == 0:
        raise DataError(
            f"{source}: SfM registered no frames. The camera may be static (no parallax between "
            "frames), or the frames lack texture or overlap; move the camera sideways around the "
            "scene, or give more frames (--num-frames)")
    if len(report.registered) < need:
        raise DataError(
            f"{source}: SfM registered only {len(report.registered)} of {report.total} frames "
            f"(at least {need} needed, --min-registered {opts.min_registered}); "
            f"{_remedies(opts)}")
    if report.fraction < WARN_FRACTION:
        return (f"warning: only {100 * report.fraction:.0f} % of the frames registered "
                f"({len(report.registered)}/{report.total}); unregistered: "
                f"{', '.join(report.unregistered[:8])}{' ...' if len(report.unregistered) > 8 else ''}"
                f"; {_remedies(opts)}")
    return None


def _remedies(opts: SfmOptions) -> str:
    tips = ["more frames or photos, closer together (--num-frames for a video)",
            "full-size frames (heavy rain needs them; check --max-side)"]
    if opts.matcher == "sequential":
        tips.append("--matcher exhaustive")
    return "try " + ", ".join(tips)


def undistort(model_dir: Path, image_dir: Path, scene_dir: Path, num_threads: int) -> None:
    """Pinhole images into ``scene/images`` and their model into ``scene/sparse/0``."""
    import pycolmap

    tmp = scene_dir / "colmap" / "undistorted"
    shutil.rmtree(tmp, ignore_errors=True)
    pycolmap.undistort_images(tmp, model_dir, image_dir, output_type="COLMAP", num_threads=num_threads)
    (scene_dir / "sparse").mkdir(parents=True, exist_ok=True)
    shutil.move(str(tmp / "images"), str(scene_dir / "images"))
    shutil.move(str(tmp / "sparse"), str(scene_dir / "sparse" / "0"))
    shutil.rmtree(tmp)  # the MVS scaffolding (stereo/, scripts) is not needed
