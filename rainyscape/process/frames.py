"""Video or photo folder -> a folder of EXIF-free PNG frames, ready for SfM.

From a video, ``num_frames`` frames are spread evenly over the clip: the clip is cut into that
many consecutive windows and the sharpest frame of each window (variance of the Laplacian) is
kept, so motion-blurred frames are skipped. Decoding streams through the clip once (after a
counting pass), holding one candidate per window, so long clips do not fill the memory.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from rainyscape.dataparsers.images import IMAGE_SUFFIXES, natural_key, write_png
from rainyscape.errors import DataError

MIN_VIEWS = 2  # two-view geometry is the least SfM can start from
# A "35 mm equivalent" focal length is the one giving a 36 x 24 mm frame the same diagonal field
# of view (the EXIF standard's definition), so it converts through the image diagonal.
FULL_FRAME_DIAGONAL_MM = math.hypot(36.0, 24.0)
EXIF_IFD, FOCAL_35MM_TAG = 0x8769, 0xA405  # Exif sub-IFD; FocalLengthIn35mmFilm


@dataclass
class FrameOptions:
    num_frames: int = 100  # frames kept from a video (all frames if the clip is shorter)
    crop: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)  # fractions cut: top, bottom, left, right
    max_side: int = 0  # downsize so the longer side is at most this (0: keep the size)


@dataclass
class Frame:
    name: str  # file name written in the frames folder
    source: str  # video frame index or the original file name
    sharpness: float
    focal_px: float | None = None  # focal length from the photo's EXIF, in pixels of the written frame


def laplacian_variance(rgb: np.ndarray) -> float:
    """Sharpness score: variance of the Laplacian of the grey image (higher is sharper)."""
    grey = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
    return float(cv2.Laplacian(grey, cv2.CV_64F).var())


def frame_windows(total: int, target: int) -> np.ndarray:
    """Window index of each of ``total`` frames when cut into ``min(target, total)`` even windows."""
    count = max(1, min(target, total))
    return (np.arange(total) * count) // total


def check_crop(crop: tuple[float, float, float, float]) -> None:
    top, bottom, left, right = crop
    if min(crop) < 0 or top + bottom >= 1 or left + right >= 1:
        raise DataError(f"crop {tuple(crop)}: fractions must be >= 0 and leave part of the image "
                        "(top + bottom < 1, left + right < 1)")


def prepare_frame(rgb: np.ndarray, options: FrameOptions) -> np.ndarray:
    """Crop by fractions, then downsize (area averaging) to ``max_side``."""
    h, w = rgb.shape[:2]
    top, bottom, left, right = options.crop
    y0, y1 = int(round(top * h)), h - int(round(bottom * h))
    x0, x1 = int(round(left * w)), w - int(round(right * w))
    rgb = rgb[y0:y1, x0:x1]
    side = max(rgb.shape[:2])
    if 0 < options.max_side < side:
        f = options.max_side / side
        size = (max(1, round(rgb.shape[1] * f)), max(1, round(rgb.shape[0] * f)))
        rgb = cv2.resize(rgb, size, interpolation=cv2.INTER_AREA)
    return np.ascontiguousarray(rgb)


def frame_scale(shape: tuple[int, int], options: FrameOptions) -> float:
    """Pixels of the written frame per pixel of the original (``shape``: its height, width):
    the resize after the crop (a crop alone keeps the focal length in pixels)."""
    h, w = shape
    top, bottom, left, right = options.crop
    ch = h - int(round(top * h)) - int(round(bottom * h))
    cw = w - int(round(left * w)) - int(round(right * w))
    side = max(ch, cw)
    if 0 < options.max_side < side:
        return max(1, round(cw * options.max_side / side)) / cw
    return 1.0


def exif_focal_35mm(path: Path) -> float | None:
    """The photo's 35 mm equivalent focal length (EXIF FocalLengthIn35mmFilm, mm), if stored."""
    try:
        from PIL import Image

        with Image.open(path) as im:
            value = im.getexif().get_ifd(EXIF_IFD).get(FOCAL_35MM_TAG)
        value = float(value) if value is not None else 0.0
    except Exception:  # noqa: BLE001 - no or unreadable EXIF: no prior, SfM estimates the focal length
        return None
    return value if math.isfinite(value) and value > 0 else None


def focal_pixels(focal_35mm: float, width: int, height: int) -> float:
    """A 35 mm equivalent focal length in pixels of a ``width`` x ``height`` image."""
    return focal_35mm / FULL_FRAME_DIAGONAL_MM * math.hypot(width, height)


def shared_focal(frames: list[Frame], tolerance: float = 0.01) -> float | None:
    """The focal length (pixels) every frame's EXIF agrees on, within ``tolerance``; None when
    a frame has none or they differ (a zoom, mixed cameras: SfM estimates it)."""
    focals = [f.focal_px for f in frames]
    if not focals or any(f is None for f in focals):
        return None
    lo, hi = min(focals), max(focals)
    return float(np.median(focals)) if hi <= lo * (1 + tolerance) else None


def _ffmpeg_reason(exc: Exception) -> str:
    """The last meaningful line of an ffmpeg failure."""
    lines = [ln.strip() for ln in str(exc).splitlines() if ln.strip()]
    for line in reversed(lines):
        if "Error" in line or "error" in line or "matches no streams" in line:
            return re.sub(r"^\[.*?\]\s*", "", line)
    return lines[-1] if lines else type(exc).__name__


def count_video_frames(path: Path) -> int:
    import imageio_ffmpeg

    if not path.is_file():
        raise DataError(f"{path}: no such video file")
    try:
        frames, _ = imageio_ffmpeg.count_frames_and_secs(str(path))
    except (RuntimeError, OSError) as exc:
        raise DataError(f"{path}: cannot read the video ({_ffmpeg_reason(exc)})") from None
    return int(frames or 0)


def check_video(video: Path) -> int:
    """The clip's frame count, after checking it is a readable video with enough frames
    (DataError naming the file otherwise). Reads the file only."""
    total = count_video_frames(video)
    if total == 0:
        raise DataError(f"{video}: the video has no frames")
    if total < MIN_VIEWS:
        raise DataError(f"{video}: too few frames ({total}); SfM needs at least {MIN_VIEWS} views")
    return total


def extract_video_frames(video: Path, out_dir: Path, options: FrameOptions,
                         progress: bool = True, total: int | None = None) -> list[Frame]:
    """Write the sharpest frame of each window of the clip as ``frame_00001.png`` ...
    (``total``: the frame count :func:`check_video` returned, to skip counting again)."""
    import imageio_ffmpeg
    from tqdm import tqdm

    check_crop(options.crop)
    total = total or check_video(video)
    windows = frame_windows(total, options.num_frames)
    best: dict[int, tuple[float, int, np.ndarray]] = {}
    reader = imageio_ffmpeg.read_frames(str(video))
    try:
        meta = next(reader)
        width, height = meta["size"]
        bar = tqdm(total=total, desc="reading frames", unit="frame", disable=not progress)
        for index, raw in enumerate(reader):
            bar.update(1)
            if index >= total:  # the counting pass and the decoder may disagree by a frame
                break
            rgb = np.frombuffer(raw, np.uint8).reshape(height, width, 3)
            frame = prepare_frame(rgb, options)
            score = laplacian_variance(frame)
            window = int(windows[index])
            if window not in best or score > best[window][0]:
                best[window] = (score, index, frame)
        bar.close()
    except (RuntimeError, OSError) as exc:
        raise DataError(f"{video}: decoding failed ({_ffmpeg_reason(exc)})") from None
    finally:
        reader.close()
    if len(best) < MIN_VIEWS:
        raise DataError(f"{video}: too few decodable frames ({len(best)}); SfM needs at least {MIN_VIEWS}")
    out_dir.mkdir(parents=True, exist_ok=True)
    frames = []
    for k, window in enumerate(sorted(best)):
        score, index, rgb = best[window]
        name = f"frame_{k + 1:05d}.png"
        write_png(out_dir / name, rgb)  # PNG: no EXIF block
        frames.append(Frame(name, str(index), score))
    return frames


def list_photos(folder: Path) -> list[Path]:
    """The photos of ``folder`` in natural order, after checking there are enough of them and
    no two share a name (DataError naming the folder otherwise). Reads the listing only."""
    if not folder.is_dir():
        raise DataError(f"{folder}: no such folder")
    files = sorted((p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES
                    and not p.name.startswith(".")), key=lambda p: natural_key(p.name))
    if not files:
        raise DataError(f"{folder}: no images found (looked for {', '.join(IMAGE_SUFFIXES)})")
    if len(files) < MIN_VIEWS:
        raise DataError(f"{folder}: too few images ({len(files)}); SfM needs at least {MIN_VIEWS} views")
    stems = [p.stem for p in files]
    duplicates = sorted({s for s in stems if stems.count(s) > 1})
    if duplicates:
        raise DataError(f"{folder}: several images share the name '{duplicates[0]}' "
                        "(different extensions); rename them")
    return files


def read_photo(path: Path) -> np.ndarray:
    """A photo as RGB uint8, turned upright by its EXIF orientation (phones store it so)."""
    import imageio.v3 as iio

    try:
        img = iio.imread(path, plugin="pillow", rotate=True)
    except Exception as exc:  # noqa: BLE001 - any decoder failure is a bad input file
        raise DataError(f"{path}: cannot read the image ({exc})") from None
    img = np.asarray(img)
    if img.dtype == np.uint16:
        img = (img // 257).astype(np.uint8)
    if img.dtype != np.uint8:
        raise DataError(f"{path}: unsupported pixel type {img.dtype}")
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, axis=-1)
    if img.ndim != 3 or img.shape[-1] not in (3, 4):
        raise DataError(f"{path}: unsupported image shape {img.shape}")
    return np.ascontiguousarray(img[..., :3])


def copy_photos(folder: Path, out_dir: Path, options: FrameOptions, progress: bool = True) -> list[Frame]:
    """Write every photo of ``folder`` as ``<stem>.png`` (upright, cropped, resized, no EXIF),
    keeping the focal length its EXIF gives (in pixels of the written frame) on its Frame."""
    from tqdm import tqdm

    check_crop(options.crop)
    files = list_photos(folder)
    out_dir.mkdir(parents=True, exist_ok=True)
    frames, sizes = [], {}
    for path in tqdm(files, desc="reading photos", unit="image", disable=not progress):
        photo = read_photo(path)
        rgb = prepare_frame(photo, options)
        sizes.setdefault(rgb.shape[:2], path.name)
        name = f"{path.stem}.png"
        write_png(out_dir / name, rgb)  # PNG: no EXIF block
        f35 = exif_focal_35mm(path)
        # The diagonal is the same before and after the EXIF turn.
        focal = focal_pixels(f35, photo.shape[1], photo.shape[0]) * frame_scale(photo.shape[:2], options) if f35 else None
        frames.append(Frame(name, path.name, laplacian_variance(rgb), focal))
    if len(sizes) > 1:
        shown = ", ".join(f"{n} is {w}x{h}" for (h, w), n in sizes.items())
        raise DataError(f"{folder}: the photos differ in size ({shown}); one scene needs one size "
                        "(one camera and orientation)")
    return frames
