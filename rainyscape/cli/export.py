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
A non-empty out folder (a scene of yours, say) is refused unless force=true, which replaces
everything an export writes there (transforms.json, images/, point_cloud.ply, mesh.*) as a
whole and keeps the rest. The export is built beside the folder and moved in when complete: a
failed export leaves the folder as it was.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path

from rainyscape.cli import run_cli
from rainyscape.cli.args import DEVICES, READ_OOM_HINT, Command, opt, parse, print_help, run_dir


@dataclass
class ExportArgs:
    what: str = opt("auto", "what to export", choices=("auto", "mesh", "gaussians", "cameras"))
    format: str = opt("ply", "mesh file format", choices=("ply", "glb"))
    resolution: int = opt(128, "mesh: lattice samples along the scene box's longest side", lo=8, hi=2048)
    level: float | None = opt(None, "mesh: density of the surface (default: one step half opaque)", hi=1e9,
                              above=0.0)
    out: str = opt("", "output folder (default: RUN_DIR/export)")
    images: bool = opt(True, "cameras: the de-rained render of every view under images/")
    device: str = opt("auto", "the device to render on", choices=DEVICES)
    data: str = opt("", "the scene folder, if it moved since training (config.yml names the old one)")
    force: bool = opt(False, "write into a non-empty out folder, replacing everything an export writes "
                             "there (the rest of the folder is kept)")


COMMAND = Command("rs-export", __doc__, ExportArgs, positional="RUN_DIR", oom_hint=READ_OOM_HINT)

# Every entry an export writes in its folder: force=true replaces all of them, those this
# export does not write too, so that the folder holds one export.
EXPORT_ENTRIES = ("transforms.json", "images", "point_cloud.ply", "mesh.ply", "mesh.glb")
WRITES = "an export (transforms.json, images/, point_cloud.ply, mesh.ply, mesh.glb)"


def main(argv: list[str]) -> int:
    args = parse(argv, COMMAND)
    if args.help:
        return print_help(COMMAND)
    folder, opts = run_dir(args, COMMAND), args.options
    from rainyscape.formats.output import check_output_folder, staged_folder

    out = Path(opts.out).expanduser() if opts.out else folder / "export"
    check_output_folder(out, opts.force, WRITES)  # before the run is loaded
    from rainyscape.components import PlyExportable
    from rainyscape.workflow import load_trained
    from rainyscape.eval import export

    pipeline, step = load_trained(folder, opts.device, data=opts.data)
    what = opts.what
    if what == "auto":
        what = "gaussians" if isinstance(pipeline.field, PlyExportable) else "mesh"
    results = []
    # Built beside the folder and moved in when complete: a failed export changes nothing.
    with staged_folder(out, EXPORT_ENTRIES, opts.force, WRITES) as stage:
        if what == "gaussians":
            results.append(export.export_gaussians(pipeline, stage / "point_cloud.ply"))
        elif what == "mesh":
            results.append(export.export_mesh(pipeline, stage / f"mesh.{opts.format}", opts.resolution,
                                              opts.level))
        if opts.what in ("auto", "cameras"):
            results.append(export.export_cameras(pipeline, stage, images=opts.images))
    for result in results:
        print("  " + ", ".join(f"{k}: {str(v).replace(str(stage), str(out))}" for k, v in result.items()))
    print(f"exported {folder} (step {step}) to {out}")
    return 0


def entry() -> None:
    sys.exit(run_cli(main))


if __name__ == "__main__":
    entry()
