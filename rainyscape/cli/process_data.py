"""rs-process-data: pose a video or a folder of photos with pycolmap; write a scene folder.

Usage:
  rs-process-data video  --data clip.mp4 --output-dir scene/ [options]
  rs-process-data images --data photos/  --output-dir scene/ [options]
then: rs-train method=rainyscape-3dgs data=scene/
"""

from __future__ import annotations

import argparse
import sys

from rainyscape.cli import run_cli


def build_parser() -> argparse.ArgumentParser:
    from rainyscape.process.sfm import CAMERA_MODELS, MATCHERS

    parser = argparse.ArgumentParser(
        prog="rs-process-data", description=__doc__.strip().splitlines()[0],
        epilog="The scene folder holds images/, sparse/0/, transforms.json and "
               "process_report.json; rs-train reads it with the colmap dataparser.")
    subs = parser.add_subparsers(dest="kind", required=True, metavar="{video,images}")
    for kind, helptext in (("video", "a video clip (sharpest frame of each window is kept)"),
                           ("images", "a folder of photos of one scene, one camera")):
        sub = subs.add_parser(kind, help=helptext, description=helptext)
        sub.add_argument("--data", required=True, help="the video file" if kind == "video"
                         else "the folder of photos")
        sub.add_argument("--output-dir", required=True, help="scene folder to write")
        if kind == "video":
            sub.add_argument("--num-frames", type=int, default=100,
                             help="frames kept, spread over the clip (default 100)")
        sub.add_argument("--crop", type=float, nargs=4, default=(0.0, 0.0, 0.0, 0.0),
                         metavar=("TOP", "BOTTOM", "LEFT", "RIGHT"),
                         help="fractions of the frame cut from each side (default none)")
        sub.add_argument("--max-side", type=int, default=0,
                         help="downsize so the longer side is at most this many pixels (0: keep)")
        sub.add_argument("--camera-model", default="SIMPLE_RADIAL", choices=CAMERA_MODELS,
                         help="COLMAP camera model fitted before undistortion (default SIMPLE_RADIAL)")
        sub.add_argument("--camera-per-image", action="store_true",
                         help="one camera per frame instead of one shared camera")
        matcher = "sequential" if kind == "video" else "exhaustive"
        sub.add_argument("--matcher", choices=MATCHERS, default=matcher,
                         help=f"feature matching (default {matcher})")
        sub.add_argument("--overlap", type=int, default=10,
                         help="sequential matching: neighbours matched per frame (default 10)")
        sub.add_argument("--no-loop-detection", action="store_true",
                         help="sequential matching: skip loop detection")
        sub.add_argument("--vocab-tree", default="",
                         help="COLMAP vocabulary tree for loop detection (default: built from the clip)")
        sub.add_argument("--max-features", type=int, default=8192, help="SIFT features per frame")
        sub.add_argument("--min-registered", type=float, default=0.5,
                         help="fail when fewer frames than this fraction register (default 0.5)")
        sub.add_argument("--init-min-tri-angle", type=float, default=16.0,
                         help="degrees of parallax the first frame pair needs (default 16; lower "
                              "it, e.g. to 4, for narrow baselines such as a stereo pair)")
        sub.add_argument("--num-threads", type=int, default=-1, help="CPU threads (-1: all)")
        sub.add_argument("--seed", type=int, default=0)
        sub.add_argument("--overwrite", action="store_true",
                         help="replace a scene already processed in --output-dir")
        sub.add_argument("--quiet", action="store_true", help="no progress output")
        sub.add_argument("--verbose", action="store_true", help="show COLMAP's own log")
    return parser


def main(argv: list[str]) -> int:
    from pathlib import Path

    from rainyscape.errors import ConfigError

    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # argparse printed usage or help already
        return int(exc.code or 0)
    if getattr(args, "num_frames", 2) < 2:
        raise ConfigError(f"--num-frames {args.num_frames}: SfM needs at least 2 frames")
    if args.max_side < 0:
        raise ConfigError(f"--max-side {args.max_side}: must be >= 0")

    from rainyscape.process.frames import FrameOptions
    from rainyscape.process.pipeline import ProcessOptions, process_images, process_video
    from rainyscape.process.sfm import SfmOptions

    frames = FrameOptions(num_frames=getattr(args, "num_frames", 0), crop=tuple(args.crop),
                          max_side=args.max_side)
    sfm = SfmOptions(camera_model=args.camera_model, single_camera=not args.camera_per_image,
                     matcher=args.matcher, overlap=args.overlap,
                     loop_detection=not args.no_loop_detection, vocab_tree=args.vocab_tree,
                     max_features=args.max_features, min_registered=args.min_registered,
                     init_min_tri_angle=args.init_min_tri_angle,
                     num_threads=args.num_threads, seed=args.seed, verbose=args.verbose)
    options = ProcessOptions(frames=frames, sfm=sfm, overwrite=args.overwrite, progress=not args.quiet)
    run = process_video if args.kind == "video" else process_images
    result = run(Path(args.data), Path(args.output_dir), options)
    print(f"{result.scene_dir}: {result.registration.summary()}")
    return 0


def entry() -> None:
    sys.exit(run_cli(main))


if __name__ == "__main__":
    entry()
