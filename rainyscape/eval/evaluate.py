"""Transitional: the names that code outside eval/ still imports from here.

The evaluation protocol lives in :mod:`rainyscape.eval.protocol`, view rendering in
:mod:`rainyscape.eval.views`. ``engine/run.py`` and ``tests/test_gaussians.py`` import these
three names from this module until they are re-pointed; then this module goes.
"""

from rainyscape.eval.protocol import evaluate_pipeline, write_metrics
from rainyscape.eval.views import render_image

__all__ = ["evaluate_pipeline", "render_image", "write_metrics"]
