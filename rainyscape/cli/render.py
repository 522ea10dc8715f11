"""rs-render: images and a video of a trained run.

Usage:
  rs-render RUN_DIR [views=all|train|heldout|NAME,...] [path=views|spiral] [frames=60] [fps=15]
                    [device=auto] [data=MOVED_SCENE] [--no-video]
  rs-render RUN_DIR --embedding-study [patch=100] [variance=0.5] [seed=0]

Writes under RUN_DIR/renders/: clean/ (renders), rain/ (predicted rain maps), error/
(|render - ground truth|), depth/ (.png and raw .npy), strips/ (rainy | render | ground
truth | rain map) and path.mp4 (a camera path through the training views, or a spiral).
--embedding-study writes embedding_study.png (the paper's Fig. 8: predicted rain with
N(0, variance) noise on the scene state s, the view vector v and the camera vector p)
and embedding_study.json. The run's report.html is refreshed afterwards.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass

from rainyscape.cli import run_cli
from rainyscape.cli.args import DEVICES, READ_OOM_HINT, SEED_MAX, Command, opt, parse, print_help, run_dir


@dataclass
class RenderArgs:
    views: str = opt("all", "comma-separated view names / indices, or all | train | heldout")
    video: bool = opt(True, "render path.mp4 along a camera path")
    path: str = opt("views", "the video's camera path: views (through the training views) | spiral",
                    choices=("views", "spiral"))
    frames: int = opt(60, "video frames", lo=1, hi=100_000)
    fps: int = opt(15, "video frames per second", lo=1, hi=240)
    device: str = opt("auto", "the device to render on", choices=DEVICES)
    data: str = opt("", "the scene folder, if it moved since training (config.yml names the old one)")
    embedding_study: bool = opt(False, "the paper's Fig. 8 instead of the renders")
    patch: int = opt(100, "embedding study: side of the centred window (pixels)", lo=1, hi=8192)
    variance: float = opt(0.5, "embedding study: variance of the noise added to s, v, p", lo=0.0, hi=100.0)
    seed: int = opt(0, "embedding study: noise seed", lo=0, hi=SEED_MAX)


COMMAND = Command("rs-render", __doc__, RenderArgs, positional="RUN_DIR", oom_hint=READ_OOM_HINT)


def main(argv: list[str]) -> int:
    args = parse(argv, COMMAND)
    if args.help:
        return print_help(COMMAND)
    folder, opts = run_dir(args, COMMAND), args.options
    from rainyscape.workflow import load_trained
    from rainyscape.eval.report import write_report
    from rainyscape.formats.output import check_writable

    check_writable(folder, "rs-render writes renders/ and report.html there")

    pipeline, step = load_trained(folder, opts.device, data=opts.data)
    if opts.embedding_study:
        from rainyscape.eval.embedding import write_embedding_study

        out = write_embedding_study(pipeline, folder, patch=opts.patch, variance=opts.variance,
                                    seed=opts.seed)
        print(f"wrote {out} and {out.with_suffix('.json')}")
    else:
        from rainyscape.eval.run_renders import RenderOptions, render_run

        result = render_run(pipeline, folder, RenderOptions(opts.views, opts.video, opts.path,
                                                            opts.frames, opts.fps))
        files = ", ".join(f"{n} {k}" for k, n in result["files"].items())
        print(f"{result['folder']} (step {step}): {files}")
        if "video" in result:
            print(f"video: {result['video']}")
    print(f"report: {write_report(folder)}")
    return 0


def entry() -> None:
    sys.exit(run_cli(main))


if __name__ == "__main__":
    entry()
