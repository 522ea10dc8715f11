"""The metric schema: every key of metrics.json comes from one record (eval/metric_keys.py),
per-view rows and the summary share it, and no other module spells a key."""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

from rainyscape.eval.metric_keys import (ANGLE_ERROR, COVERAGE, CORRELATION, LPIPS, PSNR, PSNR_IN_RAIN,
                                         PSNR_VS_RAINY, RAIN_ANGLE, RAIN_KEPT, SSIM, control, post, rain_stat,
                                         rainy_input, render)
from rainyscape.eval.summary import summarize

ROOT = Path(__file__).resolve().parents[1] / "rainyscape"


def test_keys_are_the_ones_metrics_json_has_always_had():
    assert render(PSNR).key == "train_psnr" and render(SSIM, "heldout").key == "heldout_ssim"
    assert rainy_input(LPIPS).key == "rainy_input_lpips" and rainy_input(PSNR_IN_RAIN).key == "rainy_input_psnr_in_rain"
    assert post(PSNR, "rain-mask-fusion").key == "train_rain-mask-fusion_psnr"
    assert post(COVERAGE, "rain-mask-fusion").key == "train_rain-mask-fusion_coverage"
    assert control(SSIM, "rain-mask-fusion").key == "train_rain-mask-fusion_random_ssim"
    assert render(PSNR_VS_RAINY, "heldout").key == "heldout_psnr_vs_rainy"
    assert render(RAIN_KEPT).key == "train_rain_kept" and post(RAIN_KEPT, "keep").key == "train_keep_rain_kept"
    assert rain_stat(RAIN_ANGLE).key == "rain_angle_deg" and rain_stat(ANGLE_ERROR).key == "rain_angle_error_deg"


def test_measures_format_at_their_precision():
    assert PSNR.format(23.456) == "23.46" and PSNR.format(-4.2, signed=True) == "-4.20"
    assert SSIM.format(0.81234) == "0.812" and SSIM.format(0.1, signed=True) == "+0.100"
    assert LPIPS.format(None) == "n/a" and PSNR.text(20.0) == "20.00 dB" and PSNR.text(None) == "n/a"
    assert (PSNR.arrow, LPIPS.arrow, COVERAGE.arrow) == ("↑", "↓", "")


def test_the_summary_is_the_mean_of_each_key_over_the_views_that_have_it():
    rows = [{"view": "a", "split": "train", "train_psnr": 20.0, "rain_angle_deg": 178.0, "rain_correlation": None},
            {"view": "b", "split": "train", "train_psnr": 30.0, "rain_angle_deg": 4.0, "rain_correlation": None,
             "train_rain_kept": None},
            {"view": "c", "split": "heldout", "heldout_psnr": 25.0}]
    s = summarize(rows)
    assert s["train_psnr"] == 25.0 and s["heldout_psnr"] == 25.0
    assert s["rain_angle_deg"] == pytest.approx(1.0, abs=1e-6)  # a circular mean: 178 and 4 deg meet at 1
    assert s["rain_correlation"] is None  # a rain statistic says "no streaks" with None ...
    assert "train_rain_kept" not in s  # ... any other mean of nothing is left out
    assert list(s) == sorted(s)
    assert CORRELATION.name == "rain_correlation"


# metrics.json key forms (the simulator's scene.json and the training log have their own records)
KEY_TEXT = re.compile(r"rainy_input|_random_|(?<!rain)_coverage\b|psnr_in_rain|psnr_dry|psnr_vs_rainy|rain_kept|"
                      r"rain_recovered|rain_angle|rain_correlation|residual_angle|\b(train|heldout)_(psnr|ssim|lpips)\b")


def _spelled_keys(path: Path) -> list[str]:
    """String constants (and f-string parts) of ``path`` that spell a metric key; docstrings
    and comments may name keys."""
    tree = ast.parse(path.read_text())
    docs = {id(n.body[0].value) for n in ast.walk(tree)
            if isinstance(n, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef))
            and n.body and isinstance(n.body[0], ast.Expr) and isinstance(n.body[0].value, ast.Constant)}
    return [f"{path.relative_to(ROOT.parent)}:{n.lineno}: {n.value!r}" for n in ast.walk(tree)
            if isinstance(n, ast.Constant) and isinstance(n.value, str) and id(n) not in docs
            and KEY_TEXT.search(n.value)]


def test_no_module_but_the_schema_spells_a_metric_key():
    assert _spelled_keys(ROOT / "eval" / "metric_keys.py")  # the check sees keys where they are
    found = [hit for p in sorted(ROOT.rglob("*.py"))
             if p.name != "metric_keys.py" and "synth" not in p.relative_to(ROOT).parts
             for hit in _spelled_keys(p)]
    assert not found, "use rainyscape.eval.metric_keys (a Metric's key):\n" + "\n".join(found)
