"""The standard 3DGS ``.ply`` layout (the Inria reference code's), which common viewers read.

One binary little-endian float32 vertex per Gaussian: x y z, nx ny nz (zeros),
f_dc_0..2 (degree-0 SH), f_rest_* (higher SH, channel-major: all of red's coefficients,
then green's, then blue's), opacity (logit), scale_0..2 (log), rot_0..3 (w x y z).
The bytes go through the package's one PLY writer and reader, :mod:`rainyscape.formats.ply`.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from rainyscape.errors import DataError
from rainyscape.formats import ply


def _names(rest: int) -> list[str]:
    return (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
            + [f"f_rest_{i}" for i in range(rest)]
            + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"])


def write_ply(path: Path, means: Tensor, scales: Tensor, quats: Tensor, opacities: Tensor,
              sh0: Tensor, shN: Tensor) -> None:
    """Write N Gaussians: means (N, 3), log scales (N, 3), quats (N, 4) w x y z, logit
    opacities (N,), SH (N, 1, 3) and (N, K - 1, 3)."""
    n = means.shape[0]
    rest = shN.detach().cpu().float().transpose(1, 2).reshape(n, -1)  # (N, 3 (K - 1)) channel-major
    cols = [means.detach().cpu().float(), torch.zeros(n, 3), sh0.detach().cpu().float().reshape(n, 3),
            rest, opacities.detach().cpu().float().reshape(n, 1), scales.detach().cpu().float(),
            quats.detach().cpu().float()]
    data = torch.cat(cols, 1).numpy().astype(np.float32)
    ply.write_ply(path, dict(zip(_names(rest.shape[1]), data.T)))


def read_ply(path: Path) -> dict[str, Tensor]:
    """Read a file written in the layout above (any SH degree): the six tensors of
    :func:`write_ply` by name (``means``, ``scales``, ``quats``, ``opacities``, ``sh0``, ``shN``)."""
    columns = ply.read_ply(path)
    names = list(columns)
    rest = sum(name.startswith("f_rest_") for name in names)
    if names != _names(rest) or rest % 3 or any(c.dtype != np.float32 for c in columns.values()):
        raise DataError(f"{path}: properties are not the 3DGS layout (float x y z nx ny nz "
                        "f_dc_* f_rest_* opacity scale_* rot_*)")
    data = torch.from_numpy(np.stack(list(columns.values()), 1))
    count, k1 = data.shape[0], rest // 3
    return {
        "means": data[:, 0:3],
        "sh0": data[:, 6:9].reshape(count, 1, 3),
        "shN": data[:, 9:9 + rest].reshape(count, 3, k1).transpose(1, 2).contiguous(),
        "opacities": data[:, 9 + rest],
        "scales": data[:, 10 + rest:13 + rest],
        "quats": data[:, 13 + rest:17 + rest],
    }
