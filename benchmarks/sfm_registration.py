"""Registration of a photo folder under rs-process-data's SfM settings, one row per setting.

For each setting: the photos at ``--max-side`` (as rs-process-data writes them), SIFT into a
database (shared by settings with the same features), exhaustive matching, then incremental
mapping with COLMAP's thresholds and again relaxed (what rs-process-data's retry does). Rows:
registered photos of each mapping, points, mean reprojection error, CPU seconds per stage
(pycolmap runs on ``--threads`` threads; one thread makes CPU and wall time comparable).

  python benchmarks/sfm_registration.py --data ../shared/data/real/watch/images --out /tmp/reg \\
      --max-side 0,1024,720 --settings plain,exif,affine,affine+dsp

Settings: plain (COLMAP's SIFT, no focal prior: rs-process-data before this work), exif (+
the EXIF focal length as a prior), affine (+ affine-shape SIFT: rs-process-data's default),
affine+dsp (+ domain-size pooling), dsp (exif + DSP, no affine shape), and any of them with
``@MODEL`` for another camera model (e.g. affine@OPENCV). Results append to OUT/registration.jsonl.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from dataclasses import replace
from pathlib import Path

SETTINGS = {
    "plain": dict(affine_shape=False, exif_focal=False),
    "exif": dict(affine_shape=False, exif_focal=True),
    "affine": dict(affine_shape=True, exif_focal=True),
    "affine+dsp": dict(affine_shape=True, domain_size_pooling=True, exif_focal=True),
    "dsp": dict(affine_shape=False, domain_size_pooling=True, exif_focal=True),
}


def timed(fn, *args, **kwargs):
    wall, cpu = time.perf_counter(), time.process_time()
    out = fn(*args, **kwargs)
    return out, round(time.perf_counter() - wall, 1), round(time.process_time() - cpu, 1)


def run_setting(data: Path, work: Path, max_side: int, name: str, threads: int) -> dict:
    from rainyscape.process.frames import Frame, FrameOptions, copy_photos, shared_focal
    from rainyscape.process.sfm import (SfmOptions, colmap_log, extract_features, incremental_mapping,
                                        largest_model, match_features, registration_report)

    base, _, model = name.partition("@")
    opts = SfmOptions(matcher="exhaustive", num_threads=threads, **SETTINGS[base])
    if model:
        opts = replace(opts, camera_model=model)
    frames_dir = work / f"frames_{max_side}"
    cached = frames_dir / "frames.json"
    if not cached.is_file():
        frames = copy_photos(data, frames_dir, FrameOptions(max_side=max_side), progress=False)
        cached.write_text(json.dumps([f.focal_px for f in frames]))
    focals = json.loads(cached.read_text())
    names = sorted(p.name for p in frames_dir.glob("*.png"))
    focal = shared_focal([Frame(n, n, 0.0, f) for n, f in zip(names, focals)]) if opts.exif_focal else None
    opts = replace(opts, focal_prior=focal or 0.0)
    row = {"data": str(data), "max_side": max_side, "setting": name, "focal_prior": focal, "threads": threads}
    feats = f"{max_side}_{opts.camera_model}_a{int(opts.affine_shape)}_d{int(opts.domain_size_pooling)}_f{focal or 0:.1f}"
    database = work / f"db_{feats}.db"
    with colmap_log(False):
        if not database.is_file():
            tmp = database.with_suffix(".partial")
            tmp.unlink(missing_ok=True)
            _, row["extract_wall_s"], row["extract_cpu_s"] = timed(extract_features, tmp, frames_dir, names, opts)
            _, row["match_wall_s"], row["match_cpu_s"] = timed(match_features, tmp, work, opts)
            tmp.rename(database)
        for relaxed in (False, True):
            out = work / f"sparse_{feats}_{'relaxed' if relaxed else 'default'}"
            shutil.rmtree(out, ignore_errors=True)
            models, wall, cpu = timed(incremental_mapping, database, frames_dir, out, opts, len(names),
                                      False, relaxed=relaxed)
            _, best = largest_model(models)
            report = registration_report(best, names, models)
            key = "relaxed" if relaxed else "default"
            row[key] = {"registered": len(report.registered), "of": report.total, "points": report.num_points,
                        "mean_reprojection_error_px": round(report.mean_reprojection_error, 3),
                        "model_sizes": report.model_sizes, "unregistered": report.unregistered,
                        "map_wall_s": wall, "map_cpu_s": cpu}
    return row


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, required=True, help="folder of photos")
    parser.add_argument("--out", type=Path, required=True, help="work and results folder")
    parser.add_argument("--max-side", default="0", help="comma-separated sizes (0: full size)")
    parser.add_argument("--settings", default="plain,exif,affine,affine+dsp")
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    for side in (int(s) for s in args.max_side.split(",")):
        for name in args.settings.split(","):
            row = run_setting(args.data, args.out, side, name.strip(), args.threads)
            with open(args.out / "registration.jsonl", "a") as fh:
                fh.write(json.dumps(row) + "\n")
            d, r = row["default"], row["relaxed"]
            print(f"max_side={side or 'full'} {name}: default {d['registered']}/{d['of']} "
                  f"({d['mean_reprojection_error_px']} px), relaxed {r['registered']}/{r['of']} "
                  f"({r['mean_reprojection_error_px']} px); extract {row.get('extract_cpu_s', 'cached')} s, "
                  f"match {row.get('match_cpu_s', 'cached')} s, map {d['map_cpu_s']} + {r['map_cpu_s']} s CPU",
                  flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
