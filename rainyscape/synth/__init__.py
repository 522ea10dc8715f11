"""Rainy-scene simulator: textured trimesh scenes, embree ray casting and a 3D rain field.

``generate(out_dir, preset=..., ...)`` writes the paper's Maya layout (docs/data.md);
``demo.ensure_demo_scene()`` returns the cached embedded demo scene. ``generate`` is
imported on first use, so listing presets or parsing options stays light.
"""

from rainyscape.synth.params import SIM_VERSION

__all__ = ["SIM_VERSION", "generate"]


def __getattr__(name: str):
    if name == "generate":
        from rainyscape.synth.simulate import generate

        return generate
    raise AttributeError(f"module 'rainyscape.synth' has no attribute '{name}'")
