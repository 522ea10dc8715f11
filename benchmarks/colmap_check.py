"""What checking a COLMAP binary model whole costs (dataparsers/colmap_model.py:
check_binary_model walks every record before pycolmap reads the files).

Writes a synthetic model (N points with a track of 4 views each, 100 images with 2000
keypoints each, one camera) into a temporary folder and times the walk in CPU seconds.

  OMP_NUM_THREADS=1 python benchmarks/colmap_check.py [N_POINTS]
"""

from __future__ import annotations

import struct
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from rainyscape.dataparsers.colmap_model import check_binary_model


def write_model(folder: Path, points: int, images: int = 100, keypoints: int = 2000, track: int = 4) -> None:
    (folder / "cameras.bin").write_bytes(struct.pack("<QIiQQ4d", 1, 1, 1, 640, 480, 500, 500, 320, 240))
    image = b"".join(struct.pack("<I7dI", i + 1, 1, 0, 0, 0, 0, 0, 0, 1) + f"{i:05d}.png".encode() + b"\0"
                     + struct.pack("<Q", keypoints) + bytes(24 * keypoints) for i in range(images))
    (folder / "images.bin").write_bytes(struct.pack("<Q", images) + image)
    rec = np.zeros(points, dtype=[("id", "<u8"), ("xyz", "<f8", 3), ("rgb", "u1", 3), ("err", "<f8"),
                                  ("track_length", "<u8"), ("track", "<u4", 2 * track)])
    rec["id"], rec["track_length"] = np.arange(points), track
    (folder / "points3D.bin").write_bytes(struct.pack("<Q", points) + rec.tobytes())


def main(points: int) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        write_model(folder, points)
        size = sum(p.stat().st_size for p in folder.iterdir()) / 1e6
        start_cpu, start = time.process_time(), time.perf_counter()
        check_binary_model(folder)
        print(f"{points} points, 100 images, {size:.0f} MB: checked in {time.process_time() - start_cpu:.2f} s CPU "
              f"({time.perf_counter() - start:.2f} s wall)")


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 500_000)
