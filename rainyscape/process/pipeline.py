"""Video or photo folder -> posed scene folder (the ``colmap`` dataparser's input).

Scene folder layout (the layout 3DGS and nerfstudio tools read too):
  images/               undistorted pinhole frames (registered ones)
  sparse/0/             their COLMAP model (cameras, images, points3D; binary)
  transforms.json       nerfstudio-compatible cameras; sparse_pc.ply its points
  process_report.json   frames kept, registration report, timings
  colmap/               work files: extracted frames, database, raw models (kept for inspection)
"""

from __future__ import annotations

import contextlib
import json
import shutil
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Iterator

from rainyscape.errors import DataError
from rainyscape.process.frames import Frame, FrameOptions, copy_photos, extract_video_frames
from rainyscape.process.sfm import (Registration, SfmOptions, check_registration,
                                    colmap_log, extract_features, incremental_mapping,
                                    largest_model, match_features, registration_report, undistort)
from rainyscape.process.writers import write_nerfstudio_files

FINISHED_OUTPUTS = ("images", "sparse", "transforms.json", "sparse_pc.ply", "process_report.json")
WORK_DIR = "colmap"


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


def prepare_output(scene_dir: Path, overwrite: bool) -> Path:
    """Make the output folder; clear our own files from an earlier run (only with overwrite)."""
    if scene_dir.exists() and not scene_dir.is_dir():
        raise DataError(f"{scene_dir}: the output path is a file, not a folder")
    done = [n for n in FINISHED_OUTPUTS if (scene_dir / n).exists()]
    if done and not overwrite:
        raise DataError(f"{scene_dir}: already holds a processed scene ({', '.join(done)}); "
                        "pass --overwrite to replace it, or choose another --output-dir")
    for name in (*done, WORK_DIR):
        path = scene_dir / name
        if path.is_dir():
            shutil.rmtree(path)
        elif path.exists():
            path.unlink()
    work = scene_dir / WORK_DIR
    work.mkdir(parents=True)
    return work


def _run(kind: str, source: Path, scene_dir: Path, options: ProcessOptions) -> ProcessResult:
    options.sfm.validate()
    work = prepare_output(scene_dir, options.overwrite)
    frames_dir = work / "frames"
    stages = Stages(count=6, progress=options.progress)
    with stages.stage("frames from the video" if kind == "video" else "reading the photos"):
        if kind == "video":
            frames = extract_video_frames(source, frames_dir, options.frames, options.progress)
        else:
            frames = copy_photos(source, frames_dir, options.frames, options.progress)
    names = [f.name for f in frames]
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
        if options.progress:
            print(f"      {report.summary()}", file=sys.stderr)
        warning = check_registration(report, options.sfm, source)
        if warning and options.progress:
            print(warning, file=sys.stderr)
        with stages.stage("undistorting to pinhole"):
            undistort(work / "sparse" / str(index), frames_dir, scene_dir, options.sfm.num_threads)
    with stages.stage("writing transforms.json"):
        import pycolmap

        write_nerfstudio_files(pycolmap.Reconstruction(scene_dir / "sparse" / "0"), scene_dir)
    cam = next(iter(model.cameras.values()))
    content = {
        "input": str(source), "kind": kind, "model_index": int(index),
        "registration": report.to_json(),
        "camera": {"model": cam.model_name, "params": [float(p) for p in cam.params],
                   "width": cam.width, "height": cam.height},
        "frames": [asdict(f) for f in frames],
        "options": {"frames": asdict(options.frames), "sfm": asdict(options.sfm)},
        "timings_s": stages.timings,
        "warning": warning,
    }
    (scene_dir / "process_report.json").write_text(json.dumps(content, indent=2))
    if options.progress:
        print(f"scene written to {scene_dir} (train with: rs-train method=rainyscape-3dgs "
              f"data={scene_dir})", file=sys.stderr)
    return ProcessResult(scene_dir, frames, report, warning)


def process_video(video: Path, scene_dir: Path, options: ProcessOptions | None = None) -> ProcessResult:
    """Frames of a video -> SfM -> a scene folder."""
    return _run("video", Path(video), Path(scene_dir), options or ProcessOptions())


def process_images(folder: Path, scene_dir: Path, options: ProcessOptions | None = None) -> ProcessResult:
    """A folder of photos -> SfM -> a scene folder."""
    return _run("images", Path(folder), Path(scene_dir), options or ProcessOptions())
