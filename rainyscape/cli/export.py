"""rs-export: a trained run to standard files, in the input's world frame.

Usage:
  rs-export RUN_DIR [what=auto|mesh|gaussians|cameras] [format=ply|glb] [resolution=128]
                    [level=DENSITY] [out=RUN_DIR/export] [device=auto] [--no-images]

what=auto exports the field (Gaussians: the standard 3DGS point_cloud.ply; density fields:
a marching-cubes mesh) and the cameras. Meshes: the density is sampled on a lattice over
the scene box (resolution samples along its longest side) and cut at ``level`` (default:
the density at which one lattice step is half opaque). Cameras: nerfstudio transforms.json
with the de-rained render of every view under images/ (--no-images: cameras only).
"""

from __future__ import annotations

import sys
from dataclasses import dataclass

from rainyscape.cli import run_cli


@dataclass
class ExportArgs:
    what: str = "auto"
    format: str = "ply"
    resolution: int = 128
    level: float | None = None
    out: str = ""
    device: str = "auto"


def main(argv: list[str]) -> int:
    from pathlib import Path

    from rainyscape.errors import ConfigError
    from rainyscape.eval.cli_args import parse_args, run_dir_arg

    parsed, opts = parse_args(argv, ExportArgs, {"--no-images"}, "rs-export")
    if "--help" in parsed.flags or "-h" in parsed.flags:
        print(__doc__.strip())
        return 0
    run_dir = run_dir_arg(parsed, "rs-export")
    if opts.what not in ("auto", "mesh", "gaussians", "cameras"):
        raise ConfigError(f"rs-export: what must be auto, mesh, gaussians or cameras, got '{opts.what}'")
    if opts.format not in ("ply", "glb"):
        raise ConfigError(f"rs-export: format must be ply or glb, got '{opts.format}'")
    if opts.resolution < 8:
        raise ConfigError(f"rs-export: resolution must be at least 8, got {opts.resolution}")
    from rainyscape.engine.run import load_run
    from rainyscape.components import PlyExportable
    from rainyscape.eval import export

    pipeline, step = load_run(run_dir, opts.device)
    out = Path(opts.out) if opts.out else run_dir / "export"
    what = opts.what
    if what == "auto":
        what = "gaussians" if isinstance(pipeline.field, PlyExportable) else "mesh"
    results = []
    if what == "gaussians":
        results.append(export.export_gaussians(pipeline, out / "point_cloud.ply"))
    elif what == "mesh":
        results.append(export.export_mesh(pipeline, out / f"mesh.{opts.format}", opts.resolution, opts.level))
    if opts.what in ("auto", "cameras"):
        results.append(export.export_cameras(pipeline, out, images="--no-images" not in parsed.flags))
    for result in results:
        print("  " + ", ".join(f"{k}: {v}" for k, v in result.items()))
    print(f"exported {run_dir} (step {step}) to {out}")
    return 0


def entry() -> None:
    sys.exit(run_cli(main))


if __name__ == "__main__":
    entry()
