"""Sparse points from known poses on real and simulated scenes: counts, tracks, reprojection
error, CPU time, and for simulated scenes the agreement with the ground-truth depth (used to
evaluate the points, never to make them).

  python benchmarks/sfm_triangulate.py --scene fern=../shared/data/real/fern:llff:16 \\
      --scene yard=../shared/data/yard:llff:4 --scene crossroad=SIM:crossroad:3x6:128 --out /tmp/tri

A scene is NAME=FOLDER:PARSER:DOWNSCALE, or NAME=SIM:PRESET:ROWSxCOLS:SIZE for a simulated one
(generated into OUT once). Only the training views (the parser's default split) are used, as
in training. pycolmap runs on ``--threads`` threads. Results append to OUT/triangulation.jsonl.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import torch


def load(spec: str, out: Path):
    name, _, rest = spec.partition("=")
    parts = rest.split(":")
    if parts[0] == "SIM":
        from rainyscape.dataparsers.maya_csv import MayaCsvConfig, MayaCsvParser
        from rainyscape.synth import generate

        preset, grid, size = parts[1], parts[2], int(parts[3])
        rows, cols = (int(x) for x in grid.split("x"))
        folder = out / f"sim_{preset}_{grid}_{size}"
        if not (folder / "scene.json").is_file():
            generate(folder, preset, rows=rows, cols=cols, width=size, height=size, seed=0, force=True)
        return name, MayaCsvParser(MayaCsvConfig()).parse(folder)
    from rainyscape import registry

    folder, parser, downscale = Path(parts[0]), parts[1], int(parts[2]) if len(parts) > 2 else 1
    cls = registry.load("dataparser", parser)
    return name, cls(cls.Config(downscale=downscale)).parse(folder)


def depth_agreement(points: torch.Tensor, scene, views: list[int]) -> dict:
    """Relative z-depth error against the true depth of the closest of the 3 x 3 pixels where
    each point lands in each training view (SIFT features sit on corners)."""
    cams = scene.cameras[views]
    uv, z = cams.project(points)
    errors = []
    for k, v in enumerate(views):
        u, w = uv[k, :, 0], uv[k, :, 1]
        seen = (z[k] > 0) & (u >= 0) & (u < scene.width) & (w >= 0) & (w < scene.height)
        padded = torch.nn.functional.pad(scene.depths[v][None, None], (1, 1, 1, 1), value=math.inf)[0, 0]
        iu, iw = u[seen].long() + 1, w[seen].long() + 1
        around = torch.stack([padded[iw + dy, iu + dx] for dy in (-1, 0, 1) for dx in (-1, 0, 1)], 1)
        rel = (z[k][seen][:, None] - around) / around
        rel = rel[torch.arange(len(rel)), rel.abs().nan_to_num(math.inf).argmin(1)]
        errors.append(rel[torch.isfinite(rel)])
    rel = torch.cat(errors).abs()
    return {"median_rel_depth_error": round(float(rel.median()), 4),
            "within_2pct": round(float((rel < 0.02).float().mean()), 3),
            "within_5pct": round(float((rel < 0.05).float().mean()), 3)}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scene", action="append", required=True)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    from rainyscape.process.triangulate import TriangulationOptions, triangulate_views

    for spec in args.scene:
        name, scene = load(spec, args.out)
        views = list(scene.train_indices)
        wall, cpu = time.perf_counter(), time.process_time()
        result = triangulate_views(scene.images[views].numpy(), scene.cameras[views], scene.near, scene.far,
                                   TriangulationOptions(num_threads=args.threads))
        row = {"scene": name, "spec": spec, "size": f"{scene.width}x{scene.height}", "threads": args.threads,
               **result.report.to_json(), "wall_s": round(time.perf_counter() - wall, 2),
               "cpu_s": round(time.process_time() - cpu, 2)}
        if scene.depths is not None and result.report.points:
            row.update(depth_agreement(torch.from_numpy(result.points), scene, views))
        with open(args.out / "triangulation.jsonl", "a") as fh:
            fh.write(json.dumps(row) + "\n")
        print(f"{name} ({row['size']}): {result.report.summary()}; {row['cpu_s']} s CPU"
              + (f"; depth error median {row['median_rel_depth_error']:.2%}, within 5 %: {row['within_5pct']:.0%}"
                 if "median_rel_depth_error" in row else ""), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
