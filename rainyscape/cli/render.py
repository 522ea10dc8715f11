"""rs-render: images and a video of a trained run.

Usage:
  rs-render RUN_DIR [views=all|train|heldout|NAME,...] [path=views|spiral] [frames=60] [fps=15]
                    [device=auto] [--no-video]
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


@dataclass
class RenderArgs:
    views: str = "all"
    path: str = "views"
    frames: int = 60
    fps: int = 15
    device: str = "auto"
    patch: int = 100
    variance: float = 0.5
    seed: int = 0


def main(argv: list[str]) -> int:
    from rainyscape.eval.cli_args import parse_args, run_dir_arg
    from rainyscape.errors import ConfigError

    parsed, opts = parse_args(argv, RenderArgs, {"--no-video", "--embedding-study"}, "rs-render")
    if "--help" in parsed.flags or "-h" in parsed.flags:
        print(__doc__.strip())
        return 0
    run_dir = run_dir_arg(parsed, "rs-render")
    if opts.path not in ("views", "spiral"):
        raise ConfigError(f"rs-render: path must be views or spiral, got '{opts.path}'")
    if opts.frames < 1 or opts.fps < 1:
        raise ConfigError("rs-render: frames and fps must be positive")
    from rainyscape.engine.run import load_run
    from rainyscape.eval.report import write_report

    pipeline, step = load_run(run_dir, opts.device)
    if "--embedding-study" in parsed.flags:
        from rainyscape.eval.embedding import write_embedding_study

        out = write_embedding_study(pipeline, run_dir, patch=opts.patch, variance=opts.variance,
                                    seed=opts.seed)
        print(f"wrote {out} and {out.with_suffix('.json')}")
    else:
        from rainyscape.eval.render import RenderOptions, render_run

        result = render_run(pipeline, run_dir, RenderOptions(opts.views, "--no-video" not in parsed.flags,
                                                             opts.path, opts.frames, opts.fps))
        files = ", ".join(f"{n} {k}" for k, n in result["files"].items())
        print(f"{result['folder']} (step {step}): {files}")
        if "video" in result:
            print(f"video: {result['video']}")
    print(f"report: {write_report(run_dir)}")
    return 0


def entry() -> None:
    sys.exit(run_cli(main))


if __name__ == "__main__":
    entry()
