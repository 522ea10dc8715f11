"""Measured rain strength of the presets at their default size (rainy vs clean images).

Produced by ``python benchmarks/synth.py --only presets`` on simulator version
``MEASURED_VERSION``; ``rs-synth --list`` shows it only while the simulator still is that
version (docs/benchmarks.md, Simulator).
"""

from __future__ import annotations

MEASURED_VERSION = "3"
PRESET_STRENGTH: dict[str, tuple[float, float]] = {  # preset -> (PSNR dB, SSIM), view means
    "demo": (25.97, 0.898),
    "yard": (29.89, 0.930),
    "street": (22.05, 0.817),
    "bridge": (26.51, 0.873),
    "plaza": (21.88, 0.834),
}
