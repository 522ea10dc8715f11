"""Binary little-endian PLY with one ``vertex`` element, as named columns.

The one PLY writer and reader of the package: the 3DGS Gaussians (``fields.gaussians.ply``)
and the sparse points of a processed scene (``process.writers``) both go through it. It sits
in the bottom layer (numpy and ``rainyscape.errors`` only) so that fields, dataparsers and
process can all import it.
"""

from __future__ import annotations

from pathlib import Path
from typing import Mapping

import numpy as np

from rainyscape.errors import DataError

# PLY property type <-> numpy dtype (little-endian).
PLY_TYPES = {"char": "i1", "uchar": "u1", "short": "<i2", "ushort": "<u2", "int": "<i4",
             "uint": "<u4", "float": "<f4", "double": "<f8"}
_ALIASES = {"int8": "char", "uint8": "uchar", "int16": "short", "uint16": "ushort",
            "int32": "int", "uint32": "uint", "float32": "float", "float64": "double"}
_NAMES_OF = {np.dtype(code): name for name, code in PLY_TYPES.items()}
HEADER_END = b"end_header\n"


def write_ply(path: str | Path, columns: Mapping[str, np.ndarray]) -> None:
    """Write one vertex per row: a property per column, in the mapping's order, typed by the
    column's dtype (float32 -> float, uint8 -> uchar, ...). Columns are 1-D, of one length."""
    arrays = {name: np.asarray(col) for name, col in columns.items()}
    if not arrays:
        raise ValueError("write_ply needs at least one column")
    lengths = {a.shape for a in arrays.values()}
    if len(lengths) != 1 or len(next(iter(lengths))) != 1:
        raise ValueError(f"write_ply columns must be 1-D and of one length, got shapes "
                         f"{ {n: a.shape for n, a in arrays.items()} }")
    types = {}
    for name, a in arrays.items():
        key = a.dtype.newbyteorder("<") if a.dtype.byteorder != "|" else a.dtype
        if key not in _NAMES_OF:
            raise ValueError(f"write_ply column '{name}': dtype {a.dtype} has no PLY type")
        types[name] = _NAMES_OF[key]
    count = len(next(iter(arrays.values())))
    rows = np.empty(count, dtype=[(name, PLY_TYPES[t]) for name, t in types.items()])
    for name, a in arrays.items():
        rows[name] = a
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {count}"]
    header += [f"property {t} {name}" for name, t in types.items()] + ["end_header"]
    with open(path, "wb") as fh:
        fh.write(("\n".join(header) + "\n").encode("ascii"))
        fh.write(rows.tobytes())


def read_ply(path: str | Path) -> dict[str, np.ndarray]:
    """The vertex columns of a binary little-endian PLY written as above, by name, in file
    order. DataError (naming the file) for anything else: another format, list properties,
    elements besides ``vertex``, a truncated body."""
    path = Path(path)
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise DataError(f"{path}: cannot read ({exc.strerror})") from None
    end = raw.find(HEADER_END)
    if not raw.startswith(b"ply\n") or end < 0:
        raise DataError(f"{path}: not a PLY file")
    lines = [line.split() for line in raw[:end].decode("ascii", "replace").splitlines()[1:]]
    lines = [w for w in lines if w and w[0] not in ("comment", "obj_info")]
    if ["format", "binary_little_endian", "1.0"] not in lines:
        raise DataError(f"{path}: only binary little-endian PLY files are read")
    elements = [w for w in lines if w[0] == "element"]
    if len(elements) != 1 or elements[0][1] != "vertex" or len(elements[0]) != 3:
        raise DataError(f"{path}: expected one 'vertex' element")
    count = int(elements[0][2])
    dtype = []
    for w in (w for w in lines if w[0] == "property"):
        kind = _ALIASES.get(w[1], w[1]) if len(w) == 3 else None
        if kind not in PLY_TYPES:
            raise DataError(f"{path}: unsupported property '{' '.join(w[1:])}'")
        dtype.append((w[2], PLY_TYPES[kind]))
    dtype = np.dtype(dtype)
    body = raw[end + len(HEADER_END):]
    if len(body) < count * dtype.itemsize:
        raise DataError(f"{path}: truncated ({len(body)} bytes for {count} vertices)")
    rows = np.frombuffer(body, dtype, count)
    return {name: rows[name].copy() for name in dtype.names}
