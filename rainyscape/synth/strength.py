"""Measured rain strength of the presets at their default size (rainy vs clean images).

Produced by ``python benchmarks/synth.py`` on simulator version ``MEASURED_VERSION``; shown
by ``rs-synth --list`` only while the simulator still is that version.
"""

from __future__ import annotations

MEASURED_VERSION = ""
PRESET_STRENGTH: dict[str, tuple[float, float]] = {}  # preset -> (PSNR dB, SSIM)
