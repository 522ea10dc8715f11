"""rs-export: a trained run to standard files, in the input's world frame.

Usage:
  rs-export RUN_DIR [what=auto|mesh|gaussians|cameras] [format=ply|glb] [resolution=128]
                    [level=DENSITY] [out=RUN_DIR/export] [device=auto] [data=MOVED_SCENE]
                    [--no-images] [force=true]

what=auto exports the field (Gaussians: the standard 3DGS point_cloud.ply; density fields:
a marching-cubes mesh) and the cameras. Meshes: the density is sampled on a lattice over
the scene box (resolution samples along its longest side) and cut at ``level`` (default:
the density at which one lattice step is half opaque). Cameras: nerfstudio transforms.json
with the de-rained render of every view under images/ (--no-images: cameras only).
A non-empty out folder (a scene of yours, say) is refused unless force=true: the export
would replace transforms.json and images/ there.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path

from rainyscape.cli import run_cli
from rainyscape.cli.args import Command, opt, parse, print_help, run_dir


@dataclass
class ExportArgs:
    what: str = opt("auto", "auto | mesh | gaussians | cameras")
    format: str = opt("ply", "mesh file format: ply | glb")
    resolution: int = opt(128, "mesh: lattice samples along the scene box's longest side", lo=8, hi=2048)
    level: float | None = opt(None, "mesh: density of the surface (default: one step half opaque)")
    out: str = opt("", "output folder (default: RUN_DIR/export)")
    images: bool = opt(True, "cameras: the de-rained render of every view under images/")
    device: str = opt("auto", "auto | cpu | cuda")
    data: str = opt("", "the scene folder, if it moved since training (config.yml names the old one)")
    force: bool = opt(False, "write into a non-empty out folder (replacing what the export writes)")


COMMAND = Command("rs-export", __doc__, ExportArgs, positional="RUN_DIR")


def check_output_folder(out: Path, force: bool) -> None:
    """Refuse to write into a folder that already holds files, unless ``force``."""
    from rainyscape.errors import DataError

    if out.exists() and (not out.is_dir() or any(out.iterdir())) and not force:
        raise DataError(f"{out}: folder exists and is not empty; choose another out= or pass "
                        "force=true (the export writes transforms.json and images/ there)")


def main(argv: list[str]) -> int:
    from rainyscape.errors import ConfigError

    args = parse(argv, COMMAND)
    if args.help:
        return print_help(COMMAND)
    folder, opts = run_dir(args, COMMAND), args.options
    if opts.what not in ("auto", "mesh", "gaussians", "cameras"):
        raise ConfigError(f"rs-export: what must be auto, mesh, gaussians or cameras, got '{opts.what}'")
    if opts.format not in ("ply", "glb"):
        raise ConfigError(f"rs-export: format must be ply or glb, got '{opts.format}'")
    out = Path(opts.out).expanduser() if opts.out else folder / "export"
    check_output_folder(out, opts.force)
    from rainyscape.components import PlyExportable
    from rainyscape.engine.run import load_run
    from rainyscape.eval import export

    pipeline, step = load_run(folder, opts.device, data=opts.data)
    what = opts.what
    if what == "auto":
        what = "gaussians" if isinstance(pipeline.field, PlyExportable) else "mesh"
    results = []
    if what == "gaussians":
        results.append(export.export_gaussians(pipeline, out / "point_cloud.ply"))
    elif what == "mesh":
        results.append(export.export_mesh(pipeline, out / f"mesh.{opts.format}", opts.resolution, opts.level))
    if opts.what in ("auto", "cameras"):
        results.append(export.export_cameras(pipeline, out, images=opts.images))
    for result in results:
        print("  " + ", ".join(f"{k}: {v}" for k, v in result.items()))
    print(f"exported {folder} (step {step}) to {out}")
    return 0


def entry() -> None:
    sys.exit(run_cli(main))


if __name__ == "__main__":
    entry()
