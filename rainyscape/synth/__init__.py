"""Rainy-scene simulator: textured trimesh scenes, embree ray casting and a 3D rain field.

``generate(out_dir, preset=..., ...)`` writes the paper's Maya layout (docs/data.md);
``demo.ensure_demo_scene()`` returns the cached embedded demo scene.
"""

from rainyscape.synth.simulate import SIM_VERSION, generate

__all__ = ["SIM_VERSION", "generate"]
