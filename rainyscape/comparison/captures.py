"""Real captures as benchmark scenes (``rs-bench scenes=real``).

A captures folder holds one folder per capture: a posed scene any dataparser reads (LLFF,
COLMAP, transforms.json), or photos without poses (``images/`` or the folder itself), which
are posed once with rs-process-data. Each capture is brought to the benchmark's size (its
longer side about ``REAL_SIDE`` pixels), then given the simulator's rain in its own cameras
at each of ``REAL_VARIANTS`` (synth/capture_rain.py). The photos are the ground truth.

Every step is cached in the bench's scene cache, keyed by what it depends on, and built in a
temporary sibling moved into place when complete.
"""

from __future__ import annotations

import hashlib
import os
import shutil
from dataclasses import dataclass
from pathlib import Path

from rainyscape.errors import ConfigError, DataError

REAL_SIDE = 240  # the CPU size: longer image side in pixels (about)
# (level, mode) of each rainy scene made from a capture: every strength, and rain fixed in 3D
# (a camera array's) as well as rain that moves between views (a video's).
REAL_VARIANTS = (("light", "static"), ("medium", "dynamic"), ("heavy", "static"))
CAPTURES_ENV = "RAINYSCAPE_CAPTURES"
PHOTO_SUFFIXES = (".jpg", ".jpeg", ".png")


@dataclass(frozen=True)
class Capture:
    name: str
    folder: Path
    posed: bool  # a scene folder a dataparser reads; else photos to pose first


def captures_root(option: str) -> Path:
    """The captures folder: ``captures=``, else $RAINYSCAPE_CAPTURES, else the project's
    ``../shared/data/real`` when this is a checkout beside one."""
    candidates = [option] if option else []
    if os.environ.get(CAPTURES_ENV, "").strip():
        candidates.append(os.environ[CAPTURES_ENV].strip())
    if not candidates:
        repo = Path(__file__).resolve().parents[2]
        candidates += [str(Path.cwd() / ".." / "shared" / "data" / "real"),
                       str(repo / ".." / "shared" / "data" / "real")]
    for c in candidates:
        path = Path(c).expanduser()
        if path.is_dir():
            return path.resolve()
    if option:
        raise ConfigError(f"rs-bench: captures={option}: no such folder")
    raise ConfigError("rs-bench: scenes=real needs a folder of real captures: captures=FOLDER "
                      f"(or ${CAPTURES_ENV}); each subfolder a posed scene or a folder of photos")


def find_captures(root: Path) -> list[Capture]:
    """The captures in ``root``, by name: posed scene folders and folders of photos."""
    from rainyscape.dataparsers.auto import detect_format

    found = []
    for folder in sorted(p for p in root.iterdir() if p.is_dir() and not p.name.startswith(".")):
        try:
            detect_format(folder)
            found.append(Capture(folder.name, folder, True))
            continue
        except DataError:
            pass
        if _photos(folder):
            found.append(Capture(folder.name, folder, False))
    if not found:
        raise ConfigError(f"rs-bench: {root} holds no capture (a scene folder, or a folder of photos)")
    return found


def _photos(folder: Path) -> Path | None:
    """The photo folder of an unposed capture: ``images/`` or the folder itself."""
    for candidate in (folder / "images", folder):
        if candidate.is_dir() and any(p.suffix.lower() in PHOTO_SUFFIXES for p in candidate.iterdir()):
            return candidate
    return None


def _digest(*parts) -> str:
    return hashlib.sha1(repr(parts).encode()).hexdigest()[:10]


def _source_stamp(folder: Path) -> tuple:
    """What a capture's cache depends on: its files' names and contents. Not their times: a
    copy of the same photos (a fresh checkout, a re-synced data folder) must find the cache,
    since posing again is slow. Nor what rs-process-data leaves beside the scene: its report
    (how long each step took) and its COLMAP work folder (SQLite pages and a vocabulary tree
    that differ in bytes from run to run when the poses do not), so that a deterministic
    posing of the same photos gives the same rainy scenes."""
    from rainyscape.process.output import is_record

    files = ((p.relative_to(folder), p) for p in folder.rglob("*") if p.is_file())
    return tuple(sorted((str(rel), _file_digest(p)) for rel, p in files if not is_record(rel)))


def _file_digest(path: Path) -> str:
    h = hashlib.sha1()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _build_once(final: Path, build) -> Path:
    """``build(tmp)`` into a temporary sibling of ``final``, moved into place when done."""
    if final.is_dir():
        return final
    final.parent.mkdir(parents=True, exist_ok=True)
    tmp = final.with_name(final.name + ".partial")
    shutil.rmtree(tmp, ignore_errors=True)
    build(tmp)
    tmp.rename(final)
    return final


def posed_folder(capture: Capture, cache: Path) -> Path:
    """The capture as a posed scene folder: itself, or its photos posed with rs-process-data
    (once, cached)."""
    if capture.posed:
        return capture.folder
    from rainyscape.process.pipeline import ProcessOptions, process_images
    from rainyscape.process.sfm import SfmOptions

    # deterministic: a benchmark's scenes must be the same folders in every run
    # (no progress output: it would name the temporary folder the scene is built in)
    options = ProcessOptions(sfm=SfmOptions(deterministic=True), progress=False)
    key = _digest(_source_stamp(capture.folder), options.frames, options.sfm)
    final = cache / f"capture-{capture.name}-posed-{key}"

    def build(tmp: Path) -> None:
        print(f"posing capture '{capture.name}' with rs-process-data into {final} ...", flush=True)
        result = process_images(_photos(capture.folder), tmp, options)
        print(f"  {result.registration.summary()}", flush=True)

    return _build_once(final, build)


def benchmark_downscale(folder: Path, side: int = REAL_SIDE) -> int:
    """The dataparser downscale that brings a posed scene's longer side nearest ``side``
    (an LLFF folder's pre-shrunk ``images_N/`` count: its factors are relative to full size)."""
    from rainyscape.dataparsers.auto import detect_format
    from rainyscape.dataparsers.images import list_images, read_rgb

    fmt = detect_format(folder)
    if fmt == "llff":
        options = {1: folder / "images"}
        options.update({int(p.name.split("_")[1]): p for p in folder.glob("images_*")
                        if p.is_dir() and p.name.split("_")[1].isdigit()})
        k, images = min(((k, p) for k, p in options.items() if p.is_dir() and list_images(p)),
                        key=lambda kp: -kp[0])  # the smallest images on disk
        first = read_rgb(list_images(images)[0])
        return k * max(1, round(max(first.shape[:2]) / side))
    scene = parse_capture(folder, 1)
    return max(1, round(max(scene.width, scene.height) / side))


def parse_capture(folder: Path, downscale: int):
    """The posed capture read by its own format's parser at ``downscale``, every view kept
    in its usual train / held-out split."""
    from rainyscape.dataparsers.auto import AutoParser
    from rainyscape.dataparsers.base import CommonParserConfig

    return AutoParser(CommonParserConfig(downscale=downscale)).parse(folder)


def rainy_scene(capture: Capture, level: str, mode: str, cache: Path) -> tuple[str, Path]:
    """(label, folder) of the capture with rain at ``level`` in ``mode``, made once."""
    from rainyscape.synth.capture_rain import CaptureRain, add_rain
    from rainyscape.synth.params import SIM_VERSION

    rain = CaptureRain(level=level, mode=mode)
    posed = posed_folder(capture, cache)
    label = f"{capture.name}-{level}-{mode}"
    final = cache / f"real-{label}-{REAL_SIDE}px-v{SIM_VERSION}-{_digest(_source_stamp(posed), rain)}"

    def build(tmp: Path) -> None:
        scene = parse_capture(posed, benchmark_downscale(posed))
        print(f"adding {level} {mode} rain to '{capture.name}' ({scene.width} x {scene.height} px, "
              f"{scene.num_images} views) into {final} ...", flush=True)
        add_rain(scene, tmp, rain)

    return label, _build_once(final, build)


def real_scenes(option: str, cache: Path) -> list[tuple[str, Path]]:
    """Every capture of the captures folder at every variant: (label, folder) pairs."""
    root = captures_root(option)
    return [rainy_scene(c, level, mode, cache) for c in find_captures(root) for level, mode in REAL_VARIANTS]
