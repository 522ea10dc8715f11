"""rs-process-data: pose a video or a folder of photos with pycolmap; write a scene folder.

Usage:
  rs-process-data video  --data clip.mp4 --output-dir scene/ [options]
  rs-process-data images --data photos/  --output-dir scene/ [options]
then: rs-train method=rainyscape-3dgs data=scene/

video: a video clip (the sharpest frame of each window is kept); images: a folder of photos
of one scene, one camera. Options are written --key VALUE (as after nerfstudio's
ns-process-data) or key=value: --output-dir scene/ and output_dir=scene/ are the same.
The scene folder holds images/, sparse/0/, transforms.json and process_report.json;
rs-train reads it with the colmap dataparser.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass

from rainyscape.cli import run_cli
from rainyscape.cli.args import SEED_MAX, Command, opt, parse, print_help
from rainyscape.process.sfm import CAMERA_MODELS, MATCHERS

KINDS = ("video", "images")


@dataclass
class ProcessArgs:
    data: str = opt("", "the video file (video) or the folder of photos (images)")
    output_dir: str = opt("", "scene folder to write")
    num_frames: int = opt(100, "video: frames kept, spread over the clip", lo=2, hi=100_000)
    crop: tuple[float, float, float, float] = opt((0.0, 0.0, 0.0, 0.0),
                                                  "fractions of the frame cut from the top, bottom, left, right",
                                                  lo=0.0, hi=1.0)
    max_side: int = opt(0, "downsize so the longer side is at most this many pixels (0: keep)", lo=0, hi=65536)
    camera_model: str = opt("SIMPLE_RADIAL", "COLMAP camera model fitted before undistortion",
                            choices=CAMERA_MODELS)
    camera_per_image: bool = opt(False, "one camera per frame instead of one shared camera")
    matcher: str = opt("", "feature matching (default: sequential for video, exhaustive for images)",
                       choices=("", *MATCHERS))
    overlap: int = opt(10, "sequential matching: neighbours matched per frame", lo=1, hi=10_000)
    loop_detection: bool = opt(True, "sequential matching: detect loops")
    vocab_tree: str = opt("", "COLMAP vocabulary tree for loop detection (default: built from the clip)")
    max_features: int = opt(8192, "SIFT features per frame", lo=64, hi=1_000_000)
    affine_shape: bool = opt(True, "SIFT with affine shape estimation (features that survive the viewpoint "
                                   "changes of an orbit)")
    domain_size_pooling: bool = opt(False, "DSP-SIFT descriptors (slower)")
    exif_focal: bool = opt(True, "photos: start from the focal length their EXIF gives")
    retry: bool = opt(True, "when frames are left out, map again with relaxed registration "
                            "thresholds and keep the model that registers more")
    min_registered: float = opt(0.5, "fail when fewer frames than this fraction register", hi=1.0, above=0.0)
    init_min_tri_angle: float = opt(16.0, "degrees of parallax the first frame pair needs (lower it, "
                                          "e.g. to 4, for narrow baselines such as a stereo pair)",
                                    above=0.0, hi=90.0)
    num_threads: int = opt(-1, "CPU threads (-1: all)", lo=-1, hi=1024)
    seed: int = opt(0, "random seed", lo=0, hi=SEED_MAX)
    deterministic: bool = opt(False, "one thread in every SfM step: the same input gives the same poses "
                                     "to the bit (slower)")
    overwrite: bool = opt(False, "replace the scene rs-process-data wrote in the output folder; other files are kept")
    quiet: bool = opt(False, "no progress output")
    verbose: bool = opt(False, "show COLMAP's own log")


COMMAND = Command("rs-process-data", __doc__, ProcessArgs, dashed=True, positional="video|images")


def main(argv: list[str]) -> int:
    from pathlib import Path

    from rainyscape.errors import ConfigError

    args = parse(argv, COMMAND)
    if args.help:
        return print_help(COMMAND)
    if len(args.positional) != 1 or args.positional[0] not in KINDS:
        raise ConfigError(f"rs-process-data: say what to process first: video or images, got "
                          f"{' '.join(args.positional) or 'nothing'} (see rs-process-data --help)")
    kind, opts = args.positional[0], args.options
    missing = [f"--{k.replace('_', '-')}" for k in ("data", "output_dir") if not getattr(opts, k)]
    if missing:
        raise ConfigError(f"rs-process-data {kind}: {' and '.join(missing)} required "
                          f"(e.g. --data clip.mp4 --output-dir scene/)")
    if kind == "video" and opts.num_frames < 2:
        raise ConfigError(f"{args.given['num_frames']}: SfM needs at least 2 frames")
    if kind == "images" and "num_frames" in args.given:
        raise ConfigError(f"{args.given['num_frames']}: only for a video (images keeps every photo)")

    from rainyscape.process.frames import FrameOptions
    from rainyscape.process.pipeline import ProcessOptions, process_images, process_video
    from rainyscape.process.sfm import SfmOptions

    frames = FrameOptions(num_frames=opts.num_frames if kind == "video" else 0, crop=opts.crop,
                          max_side=opts.max_side)
    sfm = SfmOptions(camera_model=opts.camera_model, single_camera=not opts.camera_per_image,
                     matcher=opts.matcher or ("sequential" if kind == "video" else "exhaustive"),
                     overlap=opts.overlap, loop_detection=opts.loop_detection, vocab_tree=opts.vocab_tree,
                     max_features=opts.max_features, affine_shape=opts.affine_shape,
                     domain_size_pooling=opts.domain_size_pooling, exif_focal=opts.exif_focal,
                     retry=opts.retry, min_registered=opts.min_registered,
                     init_min_tri_angle=opts.init_min_tri_angle,
                     num_threads=opts.num_threads, seed=opts.seed,
                     deterministic=opts.deterministic, verbose=opts.verbose)
    options = ProcessOptions(frames=frames, sfm=sfm, overwrite=opts.overwrite, progress=not opts.quiet)
    run = process_video if kind == "video" else process_images
    result = run(Path(opts.data), Path(opts.output_dir), options)
    print(f"{result.scene_dir}: {result.registration.summary()}")
    return 0


def entry() -> None:
    sys.exit(run_cli(main))


if __name__ == "__main__":
    entry()
