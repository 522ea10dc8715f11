"""Video or photo folder -> posed scene folder (the ``colmap`` dataparser's input).

Scene folder layout (the layout 3DGS and nerfstudio tools read too):
  images/               undistorted pinhole frames (registered ones)
  sparse/0/             their COLMAP model (cameras, images, points3D; binary)
  transforms.json       nerfstudio-compatible cameras; sparse_pc.ply its points
  process_report.json   frames kept, registration report, timings, the files written
  colmap/               work files: extracted frames, database, raw models (kept for inspection)

Inputs are checked before anything is written; the scene is built beside the output folder
and moved into place when complete (``process.output``: what may be replaced, and how).
"""

from __future__ import annotations

import contextlib
import json
import sys
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Iterator

from rainyscape.process.frames import (Frame, FrameOptions, check_crop, check_video, copy_photos,
                                       extract_video_frames, list_photos, shared_focal)
from rainyscape.process.output import REPORT, WORK_DIR, WRITTEN_KEY, scene_files, staged_scene
from rainyscape.process.sfm import (RELAXED_ABS_POSE_MIN_INLIERS, Registration, SfmOptions,
                                    check_registration, colmap_log, extract_features,
                                    incremental_mapping, largest_model, mapping_attempt,
                                    match_features, registration_report, undistort)
from rainyscape.process.writers import write_nerfstudio_files


@dataclass
class Stages:
    """Prints one line per stage with its duration; keeps the timings for the report."""

    count: int
    progress: bool = True
    timings: dict[str, float] = field(default_factory=dict)
    _index: int = 0

    @contextlib.contextmanager
    def stage(self, name: str) -> Iterator[None]:
        self._index += 1
        if self.progress:
            print(f"[{self._index}/{self.count}] {name} ...", file=sys.stderr, flush=True)
        start = time.perf_counter()
        yield
        self.timings[name] = round(time.perf_counter() - start, 3)
        if self.progress:
            print(f"      {name}: done in {self.timings[name]:.1f} s", file=sys.stderr, flush=True)


@dataclass
class ProcessOptions:
    frames: FrameOptions = field(default_factory=FrameOptions)
    sfm: SfmOptions = field(default_factory=SfmOptions)
    overwrite: bool = False  # replace a scene already processed in the output folder
    progress: bool = True


@dataclass
class ProcessResult:
    scene_dir: Path
    frames: list[Frame]
    registration: Registration
    warning: str | None


def _run(kind: str, source: Path, scene_dir: Path, options: ProcessOptions) -> ProcessResult:
    options.sfm.validate()
    check_crop(options.frames.crop)
    total = check_video(source) if kind == "video" else len(list_photos(source))
    with staged_scene(source, scene_dir, options.overwrite) as staging:
        frames, report, warning = _build(kind, source, staging, total, options)
    if options.progress:
        print(f"scene written to {scene_dir} (train with: rs-train method=rainyscape-3dgs "
              f"data={scene_dir})", file=sys.stderr)
    return ProcessResult(scene_dir, frames, report, warning)


def _build(kind: str, source: Path, scene_dir: Path, total: int, options: ProcessOptions
           ) -> tuple[list[Frame], Registration, str | None]:
    """The whole scene in ``scene_dir`` (the staging folder)."""
    work = scene_dir / WORK_DIR
    frames_dir = work / "frames"
    stages = Stages(count=6, progress=options.progress)
    with stages.stage("frames from the video" if kind == "video" else "reading the photos"):
        if kind == "video":
            frames = extract_video_frames(source, frames_dir, options.frames, options.progress, total)
        else:
            frames = copy_photos(source, frames_dir, options.frames, options.progress)
    names = [f.name for f in frames]
    focal = shared_focal(frames) if options.sfm.exif_focal and not options.sfm.focal_prior else None
    if focal:
        options = replace(options, sfm=replace(options.sfm, focal_prior=focal))
        if options.progress:
            print(f"      focal length from the photos' EXIF: {focal:.1f} px (a prior SfM refines)",
                  file=sys.stderr)
    database = work / "database.db"
    with colmap_log(options.sfm.verbose):
        with stages.stage(f"SIFT features ({len(names)} frames)"):
            extract_features(database, frames_dir, names, options.sfm)
        with stages.stage(f"{options.sfm.matcher} matching"):
            match_features(database, work, options.sfm)
        with stages.stage("incremental mapping"):
            models = incremental_mapping(database, frames_dir, work / "sparse", options.sfm,
                                         total=len(names), progress=options.progress)
            index, model = largest_model(models)
            report = registration_report(model, names, models)
            model_dir = work / "sparse" / str(index)
        if options.sfm.retry and report.unregistered:
            stages.count += 1  # a stage only runs when frames were left out
            with stages.stage(f"mapping again, relaxed ({len(report.unregistered)} frames left out)"):
                model_dir, model, report = _relaxed_retry(database, frames_dir, work, names, options,
                                                          (model_dir, model, report))
        if options.progress:
            print(f"      {report.summary()}", file=sys.stderr)
        warning = check_registration(report, options.sfm, source)
        if warning and options.progress:
            print(warning, file=sys.stderr)
        with stages.stage("undistorting to pinhole"):
            undistort(model_dir, frames_dir, scene_dir, options.sfm.num_threads)
    with stages.stage("writing transforms.json"):
        import pycolmap

        write_nerfstudio_files(pycolmap.Reconstruction(scene_dir / "sparse" / "0"), scene_dir)
    cam = next(iter(model.cameras.values()))
    content = {
        "input": str(source), "kind": kind, "model": str(model_dir.relative_to(scene_dir)),
        "registration": report.to_json(),
        "camera": {"model": cam.model_name, "params": [float(p) for p in cam.params],
                   "width": cam.width, "height": cam.height},
        "frames": [asdict(f) for f in frames],
        "options": {"frames": asdict(options.frames), "sfm": asdict(options.sfm)},
        "timings_s": stages.timings,
        "warning": warning,
        WRITTEN_KEY: scene_files(scene_dir),
    }
    (scene_dir / REPORT).write_text(json.dumps(content, indent=2))
    return frames, report, warning


def _relaxed_retry(database: Path, frames_dir: Path, work: Path, names: list[str],
                   options: ProcessOptions, first: tuple) -> tuple:
    """Map again with relaxed registration (sfm.incremental_mapping(relaxed=True)); the model
    that registers more frames wins (the first on a tie). Both attempts go into the report."""
    first_dir, first_model, first_report = first
    models = incremental_mapping(database, frames_dir, work / "sparse_relaxed", options.sfm,
                                 total=len(names), progress=options.progress, relaxed=True)
    index, model = largest_model(models)
    report = registration_report(model, names, models)
    better = len(report.registered) > len(first_report.registered)
    attempts = [mapping_attempt("default", first_report, not better),
                mapping_attempt(f"relaxed (abs_pose_min_num_inliers={RELAXED_ABS_POSE_MIN_INLIERS}, "
                                "two-view tracks kept)", report, better)]
    if not better:
        first_report.attempts = attempts
        return first_dir, first_model, first_report
    report.attempts = attempts
    return work / "sparse_relaxed" / str(index), model, report


def process_video(video: Path, scene_dir: Path, options: ProcessOptions | None = None) -> ProcessResult:
    """Frames of a video -> SfM -> a scene folder."""
    return _run("video", Path(video), Path(scene_dir), options or ProcessOptions())


def process_images(folder: Path, scene_dir: Path, options: ProcessOptions | None = None) -> ProcessResult:
    """A folder of photos -> SfM -> a scene folder."""
    return _run("images", Path(folder), Path(scene_dir), options or ProcessOptions())
