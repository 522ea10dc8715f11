"""Measured rain strength of the presets (rainy vs clean images) at 128 and 512 px.

Produced by ``python benchmarks/synth.py --only presets`` on simulator version
``MEASURED_VERSION`` (every preset at its default camera array, mean over the views);
``rs-synth --list`` shows it only while the simulator still is that version
(docs/benchmarks.md, Simulator).
"""

from __future__ import annotations

MEASURED_VERSION = "4"
# preset -> {width px: (PSNR dB, SSIM)}, means over the preset's views
PRESET_STRENGTH: dict[str, dict[int, tuple[float, float]]] = {
    "demo": {128: (25.87, 0.879), 512: (26.15, 0.900)},
    "yard": {128: (29.74, 0.944), 512: (30.15, 0.956)},
    "crossroad": {128: (25.96, 0.884), 512: (26.17, 0.892)},
    "street": {128: (23.66, 0.819), 512: (23.91, 0.848)},
    "bridge": {128: (24.83, 0.812), 512: (25.19, 0.849)},
    "plaza": {128: (20.71, 0.721), 512: (20.89, 0.735)},
}
