"""SceneData: what every dataparser returns and every component is built from."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch
from torch import Tensor

from rainyscape.cameras import Cameras


@dataclass
class SceneData:
    """A posed multi-view capture, in the OpenCV camera convention, after world normalisation.

    ``images`` are the (rainy) inputs training sees. ``clean_images`` and ``rain_layers``
    exist only for evaluation (simulated or paired data) and are never seen by training.
    """

    name: str
    images: Tensor  # (N, H, W, 3) uint8, the rainy inputs
    cameras: Cameras  # N cameras, normalised world
    image_names: list[str]
    train_indices: list[int]
    eval_indices: list[int]
    near: float  # ray bounds in normalised world units
    far: float
    scene_box: Tensor  # (2, 3) axis-aligned bounds (min, max) of the content
    clean_images: Tensor | None = None  # (N, H, W, 3) uint8
    depths: Tensor | None = None  # (N, H, W) float32 z-depth in normalised units (inf: sky)
    rain_layers: Tensor | None = None  # (N, H, W, 3) float32 true additive rain (I - B), if known
    points: Tensor | None = None  # (P, 3) sparse points (3DGS init)
    point_colors: Tensor | None = None  # (P, 3) uint8
    # Where ``points`` came from, for the log and the report: "colmap model", "triangulated
    # (pycolmap, known poses)", "ground-truth depth (...)", or "none ..." when there are none.
    points_source: str = "none"
    forward_facing: bool = False  # LLFF-style capture: NeRF may use NDC
    # normalised = scale * (transform @ original); kept so exports map back to the input frame.
    transform: Tensor = field(default_factory=lambda: torch.eye(4))
    scale: float = 1.0
    source: str = ""  # the folder it was read from
    metadata: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        n = self.images.shape[0]
        if len(self.cameras) != n or len(self.image_names) != n:
            raise ValueError(
                f"{self.name}: {n} images, {len(self.cameras)} cameras, {len(self.image_names)} names")
        if self.images.shape[1:] != (self.cameras.height, self.cameras.width, 3):
            raise ValueError(f"{self.name}: images {tuple(self.images.shape)} do not match cameras "
                             f"{self.cameras.width}x{self.cameras.height}")

    @property
    def num_images(self) -> int:
        return self.images.shape[0]

    @property
    def height(self) -> int:
        return self.cameras.height

    @property
    def width(self) -> int:
        return self.cameras.width

    @property
    def train_pixels(self) -> int:
        """Pixels of the training views in all (a ray field's run length follows them)."""
        return len(self.train_indices) * self.width * self.height

    def to_original(self, points: Tensor) -> Tensor:
        """Map normalised world points (P, 3) back to the input's world frame."""
        hom = torch.cat([points / self.scale, torch.ones_like(points[:, :1])], -1)
        return (hom @ torch.linalg.inv(self.transform).T.to(points))[:, :3]


# A forward-facing capture (LLFF, a camera array): every camera looks within this angle of
# the cameras' mean direction; NeRF fields then work in its NDC
FORWARD_FACING_DEG = 35.0


def faces_forward(c2w: Tensor) -> bool:
    """Whether cameras (N, 4, 4; OpenCV: +z looks forward) all look within
    FORWARD_FACING_DEG of their mean direction."""
    forward = c2w[:, :3, 2].double()
    mean = forward.mean(0)
    if float(mean.norm()) < 1e-9:
        return False
    return bool((forward @ (mean / mean.norm())).min() > math.cos(math.radians(FORWARD_FACING_DEG)))


# Share of the sparse points left out of the content box on each side of each axis. A
# handheld capture's SfM points include the room around it, seen from few views: at 1 % the
# clock orbit's box was 5x wider than the bulk of its points, and the grid field gave the
# clock a texel per two pixels; at 5 % its fit to the photos rose 1.5 dB in the same time
# (docs/benchmarks.md, "The content box"). What falls outside is still modelled, on the
# contracted shell.
CONTENT_QUANTILE = 0.05


def points_box(points: Tensor, quantile: float = CONTENT_QUANTILE) -> Tensor:
    """(2, 3) bounds of the content from sparse points: their ``quantile`` and 1 - ``quantile``
    quantiles per axis (the bulk of the points, not the stray and far ones)."""
    pts = points.float()
    return torch.stack([pts.quantile(quantile, 0), pts.quantile(1.0 - quantile, 0)])


def split_indices(n: int, every: int = 8, explicit: list[int] | None = None) -> tuple[list[int], list[int]]:
    """Train / held-out split: every ``every``-th view held out (0: none), or an explicit list."""
    if explicit is not None:
        held = sorted(set(explicit))
    elif every and every > 0 and n > 1:
        held = list(range(every - 1, n, every)) if n >= every else [n - 1]
    else:
        held = []
    train = [i for i in range(n) if i not in set(held)]
    return train, held


def normalize_poses(c2w: Tensor, camera_radius: float = 3.0) -> tuple[Tensor, float]:
    """Similarity that centres where the cameras look and fixes the camera distance.

    Returns (4x4 translation T, scale) with normalised = scale * (T @ x): the centre is the
    point closest to all optical axes (the camera centroid if the axes are near-parallel),
    and the farthest camera ends up ``camera_radius`` from it.
    """
    centers = c2w[:, :3, 3].double()
    dirs = c2w[:, :3, 2].double()  # OpenCV optical axis
    eye = torch.eye(3, dtype=torch.float64)
    proj = eye[None] - dirs[:, :, None] * dirs[:, None, :]
    a = proj.sum(0)
    b = (proj @ centers[:, :, None]).sum(0)[:, 0]
    if torch.linalg.cond(a) < 1e6:
        focus = torch.linalg.solve(a, b)
    else:
        focus = centers.mean(0)
    transform = torch.eye(4, dtype=torch.float64)
    transform[:3, 3] = -focus
    radius = (centers - focus).norm(dim=-1).max().clamp_min(1e-8)
    scale = float(camera_radius / radius)
    return transform.float(), scale


def apply_normalization(c2w: Tensor, transform: Tensor, scale: float) -> Tensor:
    """Apply normalised = scale * (transform @ x) to camera-to-world matrices (rotation kept)."""
    out = transform.to(c2w)[None] @ c2w
    out = out.clone()
    out[:, :3, 3] *= scale
    return out
