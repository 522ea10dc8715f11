"""Sparse points for a posed scene from its own images: SIFT features, matching under the
known epipolar geometry, and COLMAP's triangulation with every camera held fixed (pycolmap
4.x), then point filtering.

This is what 3D Gaussian Splatting starts from when a scene ships no point cloud (LLFF,
transforms.json without one, the simulator's scenes): the same information a COLMAP model
would give, from the images a user has (the rainy training views) and the poses the scene
already holds. No pose or intrinsic is changed; only points are made.

Pairs: every pair of views for small sets; for larger ones each view is matched with the views
whose frustums overlap its own most (:func:`overlap_pairs`), which the known poses tell.
Matching uses the poses too (:func:`epipolar_matches`): candidates must lie on the epipolar
line, so no RANSAC has to estimate a geometry that is already known. On 128 px views this
doubles the points that COLMAP's own matching and verification leave (docs/process.md).
"""

from __future__ import annotations

import math
import tempfile
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from rainyscape.cameras import Cameras
from rainyscape.errors import ConfigError
from rainyscape.process.sfm import colmap_log

SMALL_SET = 5  # fewer views than this: two-view tracks are most of what there is; keep them


@dataclass
class TriangulationOptions:
    max_features: int = 4096  # SIFT features per view
    exhaustive_up_to: int = 30  # views; more: each view matched with its `neighbours` best-overlapping ones
    neighbours: int = 15
    max_epipolar_error: float = 2.0  # pixels (Sampson distance to the known epipolar geometry)
    max_ratio: float = 0.85  # ratio test among the candidates the epipolar geometry leaves
    max_distance: float = 0.7  # descriptor distance (unit SIFT vectors), COLMAP's default
    min_matches: int = 8  # a pair with fewer matches contributes none
    max_reprojection_error: float = 1.5  # pixels, mean over a point's track
    min_track_length: int = 3  # views seeing a point (2 for sets below SMALL_SET views)
    min_angle: float = 2.0  # degrees: widest angle between two rays of a point's track
    num_threads: int = -1  # -1: all cores
    seed: int = 0

    def validate(self) -> None:
        if self.max_features < 64:
            raise ConfigError(f"max_features={self.max_features}: use at least 64")
        if self.neighbours < 1 or self.exhaustive_up_to < 2:
            raise ConfigError("neighbours must be >= 1 and exhaustive_up_to >= 2")
        if self.max_reprojection_error <= 0 or not 0 <= self.min_angle < 90 or self.min_track_length < 2:
            raise ConfigError("max_reprojection_error > 0, min_angle in [0, 90) and min_track_length >= 2")


@dataclass
class TriangulationReport:
    views: int
    pairs: int  # image pairs matched
    verified_pairs: int  # pairs with at least min_matches matches consistent with the known poses
    triangulated: int  # points COLMAP made, before filtering
    points: int  # points kept
    mean_track_length: float  # views per kept point
    mean_reprojection_error: float  # pixels, kept points
    seconds: float
    cached: bool = False

    def summary(self) -> str:
        text = (f"{self.points} points from {self.views} views ({self.verified_pairs}/{self.pairs} "
                f"pairs matched), mean track {self.mean_track_length:.1f} views, mean "
                f"reprojection error {self.mean_reprojection_error:.2f} px")
        return text + (" (cached)" if self.cached else f", {self.seconds:.1f} s")

    def to_json(self) -> dict:
        out = asdict(self)
        for key in ("mean_track_length", "mean_reprojection_error", "seconds"):
            out[key] = round(float(out[key]), 4) if math.isfinite(out[key]) else None
        return out


@dataclass
class SparsePoints:
    points: np.ndarray  # (P, 3) float32, the cameras' world frame
    colors: np.ndarray  # (P, 3) uint8
    report: TriangulationReport


# ----------------------------------------------------------------------------- pure parts


def frustum_samples(cameras: Cameras, near: float, far: float, grid: int = 8, depths: int = 4
                    ) -> np.ndarray:
    """(N, grid * grid * depths, 3) world points filling each camera's frustum: a pixel grid
    at z-depths even in disparity between ``near`` and ``far`` (where the content is)."""
    near = max(float(near), 1e-6)
    far = max(float(far), near * 1.001)
    c2w = cameras.c2w.double().cpu().numpy()
    fx, fy = cameras.fx.double().cpu().numpy(), cameras.fy.double().cpu().numpy()
    cx, cy = cameras.cx.double().cpu().numpy(), cameras.cy.double().cpu().numpy()
    u = (np.arange(grid) + 0.5) / grid * cameras.width
    v = (np.arange(grid) + 0.5) / grid * cameras.height
    z = 1.0 / np.linspace(1.0 / near, 1.0 / far, depths)
    uu, vv, zz = (a.ravel() for a in np.meshgrid(u, v, z, indexing="ij"))
    cam = np.stack([(uu[None] - cx[:, None]) / fx[:, None] * zz, (vv[None] - cy[:, None]) / fy[:, None] * zz,
                    np.broadcast_to(zz, (len(c2w), zz.size))], -1)
    return cam @ c2w[:, :3, :3].transpose(0, 2, 1) + c2w[:, None, :3, 3]


def frustum_overlap(cameras: Cameras, near: float, far: float) -> np.ndarray:
    """(N, N) share of camera i's frustum samples that camera j sees (in its image, in front),
    made symmetric with the smaller of the two shares; 0 on the diagonal."""
    pts = frustum_samples(cameras, near, far)  # (N, S, 3)
    c2w = cameras.c2w.double().cpu().numpy()
    rot, centre = c2w[:, :3, :3], c2w[:, :3, 3]
    fx, fy = cameras.fx.double().cpu().numpy(), cameras.fy.double().cpu().numpy()
    cx, cy = cameras.cx.double().cpu().numpy(), cameras.cy.double().cpu().numpy()
    n = len(c2w)
    share = np.zeros((n, n))
    for j in range(n):  # points of every camera in camera j
        cam = (pts - centre[j]) @ rot[j]  # world -> camera j (R^T (x - c)), row vectors
        z = cam[..., 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = fx[j] * cam[..., 0] / z + cx[j]
            v = fy[j] * cam[..., 1] / z + cy[j]
        seen = (z > 0) & (u >= 0) & (u < cameras.width) & (v >= 0) & (v < cameras.height)
        share[:, j] = seen.mean(-1)
    share = np.minimum(share, share.T)
    np.fill_diagonal(share, 0.0)
    return share


def overlap_pairs(cameras: Cameras, near: float, far: float, neighbours: int,
                  min_share: float = 0.05) -> list[tuple[int, int]]:
    """Pairs (i < j) of each view with its ``neighbours`` views of largest frustum overlap
    (at least ``min_share``), sorted."""
    share = frustum_overlap(cameras, near, far)
    pairs = set()
    for i in range(len(share)):
        order = np.argsort(-share[i], kind="stable")[:neighbours]
        pairs.update((min(i, int(j)), max(i, int(j))) for j in order if share[i, j] >= min_share)
    return sorted(pairs)


def fundamental_matrix(cameras: Cameras, i: int, j: int) -> np.ndarray:
    """F with ``x_j^T F x_i = 0`` for pixels of views i and j (their known poses and intrinsics)."""
    w2c = cameras.w2c().double().cpu().numpy()
    k = cameras.K().double().cpu().numpy()
    rot = w2c[j, :3, :3] @ w2c[i, :3, :3].T  # camera i -> camera j
    t = w2c[j, :3, 3] - rot @ w2c[i, :3, 3]
    cross = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    return np.linalg.inv(k[j]).T @ (cross @ rot) @ np.linalg.inv(k[i])


def sampson_errors(f: np.ndarray, x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
    """(N, M) Sampson distances (pixels^2) of every pairing of points ``x1`` (N, 2) of view 1
    with ``x2`` (M, 2) of view 2 under ``x2^T F x1 = 0``: the first-order squared distance of
    the pairing to the epipolar geometry."""
    h1 = np.concatenate([x1, np.ones((len(x1), 1))], 1)
    h2 = np.concatenate([x2, np.ones((len(x2), 1))], 1)
    l2 = h1 @ f.T  # epipolar lines in view 2 of the points of view 1, (N, 3)
    l1 = h2 @ f  # lines in view 1 of the points of view 2, (M, 3)
    num = (l2 @ h2.T) ** 2
    den = (l2[:, :1] ** 2 + l2[:, 1:2] ** 2) + (l1[:, 0] ** 2 + l1[:, 1] ** 2)[None]
    return num / np.maximum(den, 1e-12)


def epipolar_matches(x1: np.ndarray, d1: np.ndarray, x2: np.ndarray, d2: np.ndarray, f: np.ndarray,
                     options: TriangulationOptions) -> np.ndarray:
    """(K, 2) indices of matched features: each feature's nearest descriptor among the features
    of the other view that lie on its epipolar line (within ``max_epipolar_error``), kept when
    it passes the ratio test among those candidates, the distance limit, and is the nearest
    the other way too. With known poses this replaces RANSAC: the geometry is not estimated
    from the matches, so small images with few features still match."""
    if len(x1) == 0 or len(x2) == 0:
        return np.zeros((0, 2), np.int64)
    dist = np.sqrt(np.clip(2.0 - 2.0 * (d1 @ d2.T), 0.0, None))  # unit descriptors
    dist[sampson_errors(f, x1, x2) > options.max_epipolar_error ** 2] = np.inf
    best = np.argmin(dist, 1)
    rows = np.arange(len(x1))
    d_best = dist[rows, best]
    dist_second = dist.copy()
    dist_second[rows, best] = np.inf
    d_second = dist_second.min(1)
    ok = np.isfinite(d_best) & (d_best <= options.max_distance) & (d_best < options.max_ratio * d_second)
    ok &= np.argmin(dist, 0)[best] == rows  # mutual nearest
    return np.stack([rows[ok], best[ok]], 1)


def max_ray_angles(centers: np.ndarray, points: np.ndarray, tracks: list[np.ndarray]) -> np.ndarray:
    """Widest angle (degrees) between the rays from a point's track cameras to the point."""
    out = np.zeros(len(points))
    for k, (x, views) in enumerate(zip(points, tracks)):
        rays = x[None] - centers[views]
        rays /= np.linalg.norm(rays, axis=-1, keepdims=True).clip(1e-12)
        cos = np.clip(rays @ rays.T, -1.0, 1.0)
        out[k] = math.degrees(math.acos(cos.min()))
    return out


def keep_points(errors: np.ndarray, track_lengths: np.ndarray, angles: np.ndarray,
                options: TriangulationOptions, views: int) -> np.ndarray:
    """Mask of the points precise enough to start from: small reprojection error, seen by
    enough views, from directions far enough apart to fix their depth."""
    min_track = 2 if views < SMALL_SET else options.min_track_length
    return ((errors <= options.max_reprojection_error) & (track_lengths >= min_track)
            & (angles >= options.min_angle))


# --------------------------------------------------------------------------- pycolmap parts


def _write_views(images: np.ndarray, folder: Path) -> list[str]:
    from rainyscape.dataparsers.images import write_png

    folder.mkdir(parents=True, exist_ok=True)
    names = [f"{i:05d}.png" for i in range(len(images))]
    for name, rgb in zip(names, images):
        write_png(folder / name, np.ascontiguousarray(rgb))
    return names


def _extract(database: Path, image_dir: Path, names: list[str], cameras: Cameras,
             options: TriangulationOptions) -> dict[str, object]:
    """SIFT into ``database``, one camera per view set to the view's known intrinsics; returns
    the database images by name."""
    import pycolmap

    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = "PINHOLE"
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.sift.max_num_features = options.max_features
    extraction.num_threads = options.num_threads
    pycolmap.extract_features(database, image_dir, image_names=names,
                              camera_mode=pycolmap.CameraMode.PER_IMAGE,
                              reader_options=reader, extraction_options=extraction)
    with pycolmap.Database.open(database) as db:
        by_name = {im.name: im for im in db.read_all_images()}
        for k, name in enumerate(names):
            cam = db.read_camera(by_name[name].camera_id)
            cam.params = [float(cameras.fx[k]), float(cameras.fy[k]), float(cameras.cx[k]), float(cameras.cy[k])]
            cam.has_prior_focal_length = True  # known, and never refined here
            db.update_camera(cam)
    return by_name


def _unit_descriptors(desc) -> np.ndarray:
    data = np.asarray(desc.to_float().data, np.float32)  # SIFT: L1-root normalised, scaled to uint8
    return data / np.maximum(np.linalg.norm(data, axis=1, keepdims=True), 1e-12)


def _match(database: Path, by_name: dict, names: list[str], cameras: Cameras,
           pairs: list[tuple[int, int]], options: TriangulationOptions) -> int:
    """Match every pair under its known epipolar geometry and store the matches as verified
    (calibrated) two-view geometries; returns the pairs that kept at least ``min_matches``."""
    import pycolmap

    with pycolmap.Database.open(database) as db:
        ids = [by_name[name].image_id for name in names]
        points = [np.asarray(db.read_keypoints(i), np.float64)[:, :2] for i in ids]
        descs = [_unit_descriptors(db.read_descriptors(i)) for i in ids]
        kept = 0
        for i, j in pairs:
            found = epipolar_matches(points[i], descs[i], points[j], descs[j],
                                     fundamental_matrix(cameras, i, j), options)
            if len(found) < options.min_matches:
                continue
            found = found.astype(np.uint32)
            db.write_matches(ids[i], ids[j], found)
            geometry = pycolmap.TwoViewGeometry()
            geometry.config = pycolmap.TwoViewGeometryConfiguration.CALIBRATED
            geometry.inlier_matches = found
            db.write_two_view_geometry(ids[i], ids[j], geometry)
            kept += 1
    return kept


def _posed_model(database: Path, by_name: dict, names: list[str], cameras: Cameras):
    """A reconstruction holding the database's cameras and every view at its known pose."""
    import pycolmap

    w2c = cameras.w2c().double().cpu().numpy()
    model = pycolmap.Reconstruction()
    with pycolmap.Database.open(database) as db:
        for cam in db.read_all_cameras():
            model.add_camera_with_trivial_rig(cam)
    for k, name in enumerate(names):
        im = by_name[name]
        image = pycolmap.Image(name=name, camera_id=im.camera_id, image_id=im.image_id)
        pose = pycolmap.Rigid3d(pycolmap.Rotation3d(w2c[k, :3, :3]), w2c[k, :3, 3])
        model.add_image_with_trivial_frame(image, pose)
    return model


def triangulate_views(images: np.ndarray, cameras: Cameras, near: float, far: float,
                      options: TriangulationOptions | None = None, verbose: bool = False) -> SparsePoints:
    """Sparse points seen in ``images`` ((N, H, W, 3) uint8) by ``cameras`` (their known poses
    and intrinsics, OpenCV convention), in the cameras' world frame. ``near`` / ``far``: the
    z-depth range of the content, for choosing pairs in large sets."""
    import pycolmap

    options = options or TriangulationOptions()
    options.validate()
    images = np.asarray(images)
    n = len(images)
    if n < 2:
        raise ConfigError(f"triangulation needs at least 2 views, got {n}")
    if len(cameras) != n or images.shape[1:3] != (cameras.height, cameras.width):
        raise ValueError(f"{n} images of {images.shape[1:3]} for {len(cameras)} cameras of "
                         f"{cameras.height}x{cameras.width}")
    start = time.perf_counter()
    pairs = ([(i, j) for i in range(n) for j in range(i + 1, n)] if n <= options.exhaustive_up_to
             else overlap_pairs(cameras, near, far, options.neighbours))
    with tempfile.TemporaryDirectory(prefix="rainyscape-triangulate-") as tmp, colmap_log(verbose):
        work = Path(tmp)
        names = _write_views(images, work / "images")
        database = work / "database.db"
        by_name = _extract(database, work / "images", names, cameras, options)
        verified = _match(database, by_name, names, cameras, pairs, options)
        pipeline = pycolmap.IncrementalPipelineOptions()
        pipeline.min_num_matches = options.min_matches  # the matches are verified by the poses
        pipeline.num_threads = options.num_threads
        pipeline.random_seed = options.seed
        pipeline.extract_colors = True
        pipeline.triangulation.ignore_two_view_tracks = n >= SMALL_SET and options.min_track_length > 2
        (work / "model").mkdir()
        model = pycolmap.triangulate_points(_posed_model(database, by_name, names, cameras), database,
                                            work / "images", work / "model", clear_points=True,
                                            options=pipeline, refine_intrinsics=False)
    return _filtered(model, names, cameras, options, n, len(pairs), verified, time.perf_counter() - start)


def _filtered(model, names: list[str], cameras: Cameras, options: TriangulationOptions, n: int,
              num_pairs: int, verified: int, seconds: float) -> SparsePoints:
    """The model's points that pass :func:`keep_points`, with the report."""
    view_of = {model.images[i].image_id: names.index(model.images[i].name) for i in model.reg_image_ids()}
    ids = sorted(model.point3D_ids())
    pts = [model.points3D[i] for i in ids]
    xyz = np.array([p.xyz for p in pts], np.float64).reshape(-1, 3)
    rgb = np.array([p.color for p in pts], np.uint8).reshape(-1, 3)
    errors = np.array([p.error for p in pts], np.float64)
    tracks = [np.array(sorted({view_of[e.image_id] for e in p.track.elements}), int) for p in pts]
    lengths = np.array([len(p.track.elements) for p in pts], int)
    centers = cameras.centers.double().cpu().numpy()
    keep = keep_points(errors, lengths, max_ray_angles(centers, xyz, tracks), options, n)
    kept = int(keep.sum())
    report = TriangulationReport(
        views=n, pairs=num_pairs, verified_pairs=verified, triangulated=len(pts), points=kept,
        mean_track_length=float(lengths[keep].mean()) if kept else float("nan"),
        mean_reprojection_error=float(errors[keep].mean()) if kept else float("nan"), seconds=seconds)
    return SparsePoints(xyz[keep].astype(np.float32), rgb[keep], report)
