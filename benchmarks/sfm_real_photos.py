"""rs-process-data on real photos: the Middlebury 2014 "Motorcycle" stereo pair shipped with
scikit-image (the only real multi-view photos installed here), checked against its calibration.

The pair is rectified: the right camera sits 193.001 mm to the right of the left one with the
same orientation; the ground-truth disparity map of the left view gives, for each left pixel,
the column offset of the same surface point in the right photo. The benchmark poses the two
photos through the `images` path and reports the relative rotation, the direction of the
baseline and how well the triangulated tracks agree with the ground-truth disparities.

Usage: python benchmarks/sfm_real_photos.py [--out DIR]
"""

from __future__ import annotations

import argparse
import json
import shutil
import tempfile
from pathlib import Path

import numpy as np


def main() -> None:
    import pycolmap
    import skimage.data
    from scipy.spatial.transform import Rotation

    from rainyscape.dataparsers.colmap_model import colmap_c2w, posed_images
    from rainyscape.process.pipeline import ProcessOptions, process_images
    from rainyscape.process.sfm import SfmOptions

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="", help="scene folder to keep (default: a temporary one)")
    args = parser.parse_args()
    work = Path(args.out) if args.out else Path(tempfile.mkdtemp(prefix="rs_real_"))
    data = Path(skimage.data.__file__).parent
    photos = work / "photos"
    photos.mkdir(parents=True, exist_ok=True)
    for side in ("left", "right"):
        shutil.copy(data / f"motorcycle_{side}.png", photos / f"motorcycle_{side}.png")
    disparity = np.load(data / "motorcycle_disp.npz")["arr_0"]

    options = ProcessOptions(sfm=SfmOptions(matcher="exhaustive", init_min_tri_angle=4.0), overwrite=True)
    result = process_images(photos, work / "scene", options)
    report = json.loads((work / "scene" / "process_report.json").read_text())
    # The model as mapped (before undistortion): its observations are in the photos' pixels.
    model = pycolmap.Reconstruction(work / "scene" / "colmap" / "sparse" / str(report["model_index"]))
    left, right = posed_images(model)
    rel = np.linalg.inv(colmap_c2w(left)) @ colmap_c2w(right)  # right camera in the left frame
    baseline = np.linalg.norm(rel[:3, 3])
    direction = rel[:3, 3] / baseline
    rotation_deg = np.degrees(np.linalg.norm(Rotation.from_matrix(rel[:3, :3]).as_rotvec()))

    # Each point seen in both photos: its horizontal offset against the ground-truth disparity.
    in_left = {p.point3D_id: p.xy for p in left.points2D if p.has_point3D()}
    in_right = {p.point3D_id: p.xy for p in right.points2D if p.has_point3D()}
    both = [k for k in in_left if k in in_right]
    xy_left = np.array([in_left[k] for k in both])
    offset = xy_left[:, 0] - np.array([in_right[k][0] for k in both])
    truth = disparity[xy_left[:, 1].astype(int), xy_left[:, 0].astype(int)]  # centres at +0.5
    known = np.isfinite(truth)
    disparity_err = np.abs(offset[known] - truth[known])
    direction_err = np.degrees(np.arccos(np.clip(direction[0], -1, 1)))

    print(f"scene folder: {work / 'scene'}")
    print(result.registration.summary())
    print(f"relative rotation: {rotation_deg:.3f} deg (rectified pair: 0)")
    print(f"baseline direction in the left camera: {np.round(direction, 4).tolist()} (expected +x)")
    print(f"baseline direction error: {direction_err:.2f} deg")
    print(f"triangulated tracks vs ground-truth disparity over {known.sum()} points: median "
          f"{np.median(disparity_err):.2f} px, 90th percentile {np.quantile(disparity_err, 0.9):.2f} px")
    print("focal length and absolute depth are not observable from a pure sideways translation, "
          "and rectification moved the right principal point by 31 px (one shared camera cannot "
          "model it): neither is compared")


if __name__ == "__main__":
    main()
