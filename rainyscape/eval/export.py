"""``rs-export``: a trained run to files other tools open, in the input's world frame.

- Gaussian fields: the standard 3DGS ``point_cloud.ply`` (the field's own writer).
- Density fields: a mesh from marching cubes on the density over the scene box, ``.ply``
  or ``.glb`` through trimesh.
- Cameras: nerfstudio ``transforms.json`` (OpenGL camera axes) next to the rendered,
  de-rained images, a dataset other tools can train on.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from rainyscape.dataparsers.transforms_json import write_transforms
from rainyscape.dataparsers.writers import transforms_meta
from rainyscape.components import DensityField, PlyExportable
from rainyscape.engine.pipeline import Pipeline
from rainyscape.errors import ConfigError
from rainyscape.eval.images import save_png, to_uint8
from rainyscape.eval.views import render_image


# ------------------------------------------------------------------------------ mesh


def grid_points(lo: Tensor, hi: Tensor, resolution: int) -> tuple[Tensor, tuple[int, int, int], Tensor]:
    """Voxel-centre lattice over the box [lo, hi]: points (X*Y*Z, 3), shape, spacing (3,).

    The longest side gets ``resolution`` samples; the others keep the same spacing."""
    size = hi - lo
    step = float(size.max()) / max(resolution - 1, 1)
    counts = [max(2, int(math.ceil(float(s) / step)) + 1) for s in size]
    axes = [lo[i] + torch.arange(counts[i], dtype=torch.float32) * step for i in range(3)]
    pts = torch.stack(torch.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    return pts, (counts[0], counts[1], counts[2]), torch.full((3,), step)


@torch.no_grad()
def sample_density(field, points: Tensor, device, chunk: int = 65536) -> Tensor:
    """The field's density at ``points`` (P, 3), in chunks (bounded memory)."""
    out = [field.density(points[i:i + chunk].to(device)).reshape(-1).float().cpu()
           for i in range(0, points.shape[0], chunk)]
    return torch.cat(out)


def default_level(spacing: float) -> float:
    """The density at which one voxel step is half opaque: 1 - exp(-sigma * step) = 0.5."""
    return math.log(2.0) / spacing


def density_mesh(density: np.ndarray, level: float, origin: np.ndarray, spacing: np.ndarray):
    """Marching cubes on a density volume (X, Y, Z) -> trimesh.Trimesh, outward-facing.

    The volume is padded with empty space first, so surfaces that reach the box close
    (the mesh encloses a volume instead of stopping at the box's faces)."""
    import trimesh
    from skimage.measure import marching_cubes

    if not (density.max() > level > density.min()):
        raise ConfigError(f"no surface at density level {level:.3g}: the field's density spans "
                          f"{density.min():.3g} .. {density.max():.3g} (set level=...)")
    padded = np.pad(density, 1, mode="constant", constant_values=min(float(density.min()), 0.0))
    verts, faces, _, _ = marching_cubes(padded, level=level, spacing=tuple(spacing))
    verts = verts - spacing + origin  # undo the one-voxel pad
    mesh = trimesh.Trimesh(vertices=verts, faces=faces, process=True)
    if mesh.volume < 0:  # dense inside: make the normals point out of the dense region
        mesh.invert()
    return mesh


def export_mesh(pipeline: Pipeline, path: Path, resolution: int = 128, level: float | None = None,
                margin: float = 0.05) -> dict:
    field, scene = pipeline.field, pipeline.scene
    if not isinstance(field, DensityField):
        raise ConfigError(f"field '{pipeline.config.field.name}' has no density(points): "
                          "it cannot be meshed")
    box = scene.scene_box.float().cpu()
    pad = (box[1] - box[0]) * margin
    lo, hi = box[0] - pad, box[1] + pad
    points, shape, spacing = grid_points(lo, hi, resolution)
    density = sample_density(field, points, pipeline.device).reshape(shape).numpy()
    level = default_level(float(spacing[0])) if level is None else level
    mesh = density_mesh(density, level, lo.numpy(), spacing.numpy())
    # Back to the input's world frame (normalised = scale * (transform @ x)).
    mesh.vertices = scene.to_original(torch.from_numpy(np.asarray(mesh.vertices)).float()).numpy()
    path.parent.mkdir(parents=True, exist_ok=True)
    mesh.export(path)
    return {"mesh": str(path), "vertices": int(len(mesh.vertices)), "faces": int(len(mesh.faces)),
            "level": level, "resolution": list(shape), "watertight": bool(mesh.is_watertight)}


# --------------------------------------------------------------------------- gaussians


def export_gaussians(pipeline: Pipeline, path: Path) -> dict:
    """The field's standard 3DGS ``.ply`` (Gaussian fields write it themselves)."""
    field = pipeline.field
    if not isinstance(field, PlyExportable):
        raise ConfigError(f"field '{pipeline.config.field.name}' has no export_ply(path): "
                          "it is not a Gaussian field")
    path.parent.mkdir(parents=True, exist_ok=True)
    field.export_ply(path)
    return {"ply": str(path)}


# ----------------------------------------------------------------------------- cameras


def export_cameras(pipeline: Pipeline, out_dir: Path, images: bool = True) -> dict:
    """``transforms.json`` and, with ``images``, the de-rained render of every view."""
    scene = pipeline.scene
    names = [f"images/{Path(n).stem}.png" for n in scene.image_names]
    if images:
        for i, name in enumerate(names):
            save_png(out_dir / name, to_uint8(render_image(pipeline, i)))
    out_dir.mkdir(parents=True, exist_ok=True)
    path = write_transforms(out_dir / "transforms.json", transforms_meta(scene, names))
    return {"transforms": str(path), "images": len(names) if images else 0}
