"""Measured rain strength of the presets (rainy vs clean images) at 128 and 512 px.

Produced by ``python benchmarks/synth.py --only presets`` on simulator version
``MEASURED_VERSION`` (every preset at its default camera array, mean over the views);
``rs-synth --list`` shows it only while the simulator still is that version
(docs/benchmarks.md, Simulator).
"""

from __future__ import annotations

MEASURED_VERSION = "0"  # not measured yet for this version
# preset -> {width px: (PSNR dB, SSIM)}, means over the preset's views
PRESET_STRENGTH: dict[str, dict[int, tuple[float, float]]] = {}
