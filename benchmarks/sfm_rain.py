"""Does rain hurt SfM? Registration of clean vs rainy renders of the same simulator trajectory.

For each preset the simulator renders one hand-held-like video sweep in dynamic rain (rain moves
between frames, like a real clip); the clean and the rainy frames are each written as an .mp4
and posed with rs-process-data's video path. Reported per clip: frames registered, sparse
points, mean reprojection error, and camera error against the simulator after a similarity
(Umeyama) alignment: centre RMSE as a % of the trajectory extent, the largest rotation error,
and the largest error of the rotation between consecutive frames (free of the alignment).

Usage: python benchmarks/sfm_rain.py [--presets demo street plaza] [--frames 24] [--size 192]
       [--max-features 1024] [--threads 2] [--out DIR]
"""

from __future__ import annotations

import argparse
import csv
import json
import tempfile
import time
from pathlib import Path

import imageio.v3 as iio
import numpy as np


def simulator_c2w(sim: Path, size: int) -> np.ndarray:
    from rainyscape.dataparsers.maya_math import maya_cameras

    with open(sim / "cameras.csv", newline="") as fh:
        rows = np.array([[float(v) for v in row[1:]] for row in list(csv.reader(fh))[1:]])
    cams = maya_cameras(rows[:, 0:3], rows[:, 3:6], rows[:, 6], rows[:, 7], rows[:, 8], size, size)
    return cams.c2w.double().numpy()


def pose_clip(clip: Path, scene: Path, truth: np.ndarray, frames: int, max_features: int, threads: int) -> dict:
    from rainyscape.errors import DataError
    from rainyscape.process.align import aligned_pose_errors, rotation_angle_deg
    from rainyscape.dataparsers.colmap_model import colmap_c2w, posed_images, read_model
    from rainyscape.process.frames import FrameOptions
    from rainyscape.process.pipeline import ProcessOptions, process_video
    from rainyscape.process.sfm import SfmOptions

    options = ProcessOptions(frames=FrameOptions(num_frames=frames),
                             sfm=SfmOptions(max_features=max_features, num_threads=threads),
                             overwrite=True, progress=False)
    start = time.perf_counter()
    try:
        result = process_video(clip, scene, options)
    except DataError as exc:
        return {"registered": f"failed: {exc}", "seconds": round(time.perf_counter() - start, 1)}
    seconds = time.perf_counter() - start
    report = json.loads((scene / "process_report.json").read_text())
    source = {f["name"]: int(f["source"]) for f in report["frames"]}
    views = posed_images(read_model(scene / "sparse" / "0"))
    est = np.stack([colmap_c2w(v) for v in views])
    ref = truth[[source[v.name] for v in views]]
    errors = aligned_pose_errors(est, ref)
    consecutive = rotation_angle_deg(np.einsum("nji,njk->nik", est[:-1, :3, :3], est[1:, :3, :3]),
                                     np.einsum("nji,njk->nik", ref[:-1, :3, :3], ref[1:, :3, :3]))
    reg = result.registration
    return {"registered": f"{len(reg.registered)}/{reg.total}", "points": reg.num_points,
            "reproj_px": round(reg.mean_reprojection_error, 3),
            "centre_rmse_pct": round(100 * errors.center_rmse_fraction, 3),
            "rot_max_deg": round(float(errors.rotation_deg.max()), 3),
            "rel_rot_max_deg": round(float(consecutive.max()), 3), "seconds": round(seconds, 1)}


def main() -> None:
    from rainyscape.synth import generate

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--presets", nargs="+", default=["demo", "street", "plaza"])
    parser.add_argument("--frames", type=int, default=24)
    parser.add_argument("--size", type=int, default=192)
    parser.add_argument("--max-features", type=int, default=1024)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default="", help="work folder to keep (default: temporary)")
    args = parser.parse_args()
    work = Path(args.out) if args.out else Path(tempfile.mkdtemp(prefix="rs_sfm_rain_"))
    rows = []
    for preset in args.presets:
        sim = generate(work / preset / "sim", preset, rows=1, cols=args.frames, width=args.size,
                       height=args.size, mode="dynamic", trajectory="video", seed=args.seed, force=True)
        info = json.loads((sim / "scene.json").read_text())
        truth = simulator_c2w(sim, args.size)
        for kind, folder in (("clean", "images_wo_rain"), ("rainy", "images_rain")):
            frames = np.stack([iio.imread(p) for p in sorted((sim / folder).glob("*.png"))])
            clip = work / preset / f"{kind}.mp4"
            iio.imwrite(clip, frames, fps=10, codec="libx264", macro_block_size=1)
            result = pose_clip(clip, work / preset / kind, truth, args.frames, args.max_features, args.threads)
            row = {"preset": preset, "clip": kind,
                   "rainy_psnr_db": info["metrics"]["psnr_rainy_vs_clean"] if kind == "rainy" else None,
                   **result}
            rows.append(row)
            print(json.dumps(row), flush=True)
    keys = ["preset", "clip", "rainy_psnr_db", "registered", "points", "reproj_px", "centre_rmse_pct",
            "rot_max_deg", "rel_rot_max_deg", "seconds"]
    print("\n| " + " | ".join(keys) + " |\n|" + "---|" * len(keys))
    for row in rows:
        print("| " + " | ".join("" if row.get(k) is None else str(row.get(k)) for k in keys) + " |")


if __name__ == "__main__":
    main()
