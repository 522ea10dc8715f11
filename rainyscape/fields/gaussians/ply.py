"""The standard 3DGS ``.ply`` layout (the Inria reference code's), which common viewers read.

One binary little-endian float32 vertex per Gaussian: x y z, nx ny nz (zeros),
f_dc_0..2 (degree-0 SH), f_rest_* (higher SH, channel-major: all of red's coefficients,
then green's, then blue's), opacity (logit), scale_0..2 (log), rot_0..3 (w x y z).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from rainyscape.errors import DataError



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
    data = torch.cat(cols, 1).numpy().astype("<f4")
    names = _names(rest.shape[1])
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {n}"]
    header += [f"property float {name}" for name in names] + ["end_header"]
    path = Path(path)
    with open(path, "wb") as fh:
        fh.write(("\n".join(header) + "\n").encode("ascii"))
        fh.write(np.ascontiguousarray(data).tobytes())


def read_ply(path: Path) -> dict[str, Tensor]:
    """Read a file written in the layout above (any SH degree): the six tensors of
    :func:`write_ply` by name (``means``, ``scales``, ``quats``, ``opacities``, ``sh0``, ``shN``)."""
    path = Path(path)
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise DataError(f"{path}: cannot read ({exc.strerror})") from None
    end = raw.find(b"end_header\n")
    if not raw.startswith(b"ply\n") or end < 0:
        raise DataError(f"{path}: not a PLY file")
    lines = raw[:end].decode("ascii", "replace").splitlines()
    if "format binary_little_endian 1.0" not in lines:
        raise DataError(f"{path}: only binary little-endian Gaussian PLY files are read")
    count = next((int(line.split()[2]) for line in lines if line.startswith("element vertex")), None)
    props = [line.split() for line in lines if line.startswith("property")]
    if count is None or any(p[1] != "float" for p in props):
        raise DataError(f"{path}: expected one vertex element of float properties (3DGS layout)")
    names = [p[2] for p in props]
    rest = sum(name.startswith("f_rest_") for name in names)
    if names != _names(rest) or rest % 3:
        raise DataError(f"{path}: properties are not the 3DGS layout")
    body = raw[end + len(b"end_header\n"):]
    if len(body) < count * len(names) * 4:
        raise DataError(f"{path}: truncated ({len(body)} bytes for {count} Gaussians)")
    data = torch.from_numpy(np.frombuffer(body, "<f4", count * len(names)).reshape(count, -1).copy())
    k1 = rest // 3
    return {
        "means": data[:, 0:3],
        "sh0": data[:, 6:9].reshape(count, 1, 3),
        "shN": data[:, 9:9 + rest].reshape(count, 3, k1).transpose(1, 2).contiguous(),
        "opacities": data[:, 9 + rest],
        "scales": data[:, 10 + rest:13 + rest],
        "quats": data[:, 13 + rest:17 + rest],
    }
