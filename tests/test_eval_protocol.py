"""The evaluation protocol on a pipeline whose every metric is known in advance."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from rainyscape.eval.metric_keys import RAIN_KEPT, RAIN_RECOVERED
from rainyscape.eval.protocol import evaluate_pipeline, write_metrics
from rainyscape.eval.rain_stats import correlation
from rainyscape.eval.views import quick_eval
from rainyscape.imaging.angles import angle_difference_deg, mean_angle_deg
from rainyscape.imaging.metrics import psnr, ssim
from _eval_fixtures import OFFSET, make_pipeline


def test_every_field_of_the_protocol(tmp_path):
    pipe = make_pipeline()
    (tmp_path / "config.yml").write_text("method: fake\n")
    m = evaluate_pipeline(pipe, tmp_path)
    s = m["summary"]
    known = -10 * math.log10(OFFSET ** 2)
    assert s["train_psnr"] == pytest.approx(known, abs=0.05)
    assert s["heldout_psnr"] == pytest.approx(known, abs=0.05)
    for key in ("train_psnr_in_rain", "train_psnr_dry", "heldout_psnr_in_rain", "heldout_psnr_dry"):
        assert s[key] == pytest.approx(known, abs=0.05)  # the render is off by OFFSET everywhere
    assert s["rainy_input_psnr_in_rain"] < s["rainy_input_psnr"]  # the input errs only there
    scene = pipe.scene
    rainy = scene.images[scene.train_indices].permute(0, 3, 1, 2).float() / 255
    clean = scene.clean_images[scene.train_indices].permute(0, 3, 1, 2).float() / 255
    floor = [float(psnr(r, c)) for r, c in zip(rainy, clean)]
    assert s["rainy_input_psnr"] == pytest.approx(sum(floor) / len(floor), abs=1e-4)
    assert s["rainy_input_ssim"] == pytest.approx(float(ssim(rainy, clean, reduction="none").mean()), abs=1e-5)
    # the "keep" post-process returns the rainy input: its row equals the floor
    assert s["train_keep_psnr"] == pytest.approx(s["rainy_input_psnr"], abs=1e-6)
    assert "heldout_keep_psnr" not in s
    assert s["train_psnr_vs_rainy"] < s["train_psnr"]
    # the rain head predicts the true layer: same angle, perfect correlation
    assert s["rain_correlation"] == pytest.approx(1.0, abs=1e-6)
    assert s["rain_angle_error_deg"] == 0.0
    assert s["rain_angle_deg"] == pytest.approx(s["rain_angle_true_deg"])
    assert 0 <= s["rain_angle_deg"] < 180
    assert s["train_rain_recovered"] == pytest.approx(1.0, abs=1e-4)  # ... and all of its amount
    assert s["train_keep_rain_kept"] == pytest.approx(1.0, abs=1e-4)  # the input keeps all the rain
    assert s["train_rain_kept"] > 0 and s["heldout_rain_kept"] > 0  # clean + OFFSET: above clean
    # LPIPS is either measured or reported unavailable with a reason, never estimated
    if m["lpips"]["available"]:
        assert 0 <= s["train_lpips"] < 1
    else:
        assert m["lpips"]["reason"] and not any(k.endswith("lpips") for k in s)
    views = {r["view"]: r for r in m["per_view"]}
    assert len(views) == scene.num_images
    assert views["003.png"]["split"] == "heldout" and "rain_angle_deg" not in views["003.png"]
    assert m["postprocess"] == ["keep"] and m["has_clean"] and m["has_rain_head"]
    strips = sorted(p.name for p in (tmp_path / "renders" / "strips").glob("*.png"))
    assert strips == ["000.png", "001.png", "002.png"]


def test_without_a_rain_head_or_clean_images():
    pipe = make_pipeline(with_rain=False)
    s = evaluate_pipeline(pipe)["summary"]
    assert "rain_angle_deg" not in s and "rain_correlation" not in s
    assert "rain_angle_true_deg" in s  # the true layer's angle is known all the same
    pipe.scene.clean_images = None
    pipe.scene.rain_layers = None
    m = evaluate_pipeline(pipe)
    assert set(m["summary"]) == {"train_psnr_vs_rainy", "heldout_psnr_vs_rainy"}
    assert not m["has_clean"]


def test_write_metrics_writes_json_and_report(tmp_path):
    pipe = make_pipeline()
    (tmp_path / "config.yml").write_text("method: fake\n")
    write_metrics(tmp_path, evaluate_pipeline(pipe, tmp_path))
    assert json.loads((tmp_path / "metrics.json").read_text())["summary"]["train_psnr"] > 25
    assert (tmp_path / "report.html").is_file()
    assert not list(tmp_path.glob("*.tmp"))


def test_angle_and_correlation_helpers():
    assert angle_difference_deg(5, 175) == pytest.approx(10)
    assert angle_difference_deg(90, 0) == pytest.approx(90)
    assert mean_angle_deg([178, 4]) == pytest.approx(1.0, abs=1e-6)
    assert mean_angle_deg([]) is None
    a = torch.rand(3, 8, 8, generator=torch.Generator().manual_seed(0))
    assert correlation(a, 2 * a + 1) == pytest.approx(1.0)
    assert correlation(a, -a) == pytest.approx(-1.0)
    assert correlation(a, torch.ones_like(a)) is None


def test_multi_direction_rain_reports_every_direction():
    from rainyscape.config import LossConfig
    from rainyscape.losses.agr import AdaptiveGradientRotation

    pipe = make_pipeline()
    agr_cfg = AdaptiveGradientRotation.Config(top_k=2)
    pipe.losses = {"agr": (LossConfig("agr", options=agr_cfg), AdaptiveGradientRotation(agr_cfg))}
    rows = evaluate_pipeline(pipe)["per_view"]
    train = [r for r in rows if r["split"] == "train"]
    assert all(len(r["rain_angles_deg"]) == 2 and r["rain_angles_deg"][0] == r["rain_angle_deg"] for r in train)


def test_quick_eval_is_psnr_of_the_first_views_vs_rainy_and_clean():
    pipe = make_pipeline()
    scene = pipe.scene
    known = -10 * math.log10(OFFSET ** 2)
    ev = quick_eval(pipe, views=2)
    assert set(ev) == {"train_psnr_rainy", "train_psnr_clean", "heldout_psnr_rainy", "heldout_psnr_clean"}
    assert ev["train_psnr_clean"] == pytest.approx(known, abs=0.05)
    assert ev["heldout_psnr_clean"] == pytest.approx(known, abs=0.05)
    rendered = (scene.clean_images.permute(0, 3, 1, 2).float() / 255).clamp(0, 1 - OFFSET) + OFFSET
    rainy = scene.images.permute(0, 3, 1, 2).float() / 255
    first_two = [float(psnr(rendered[i], rainy[i])) for i in scene.train_indices[:2]]
    assert ev["train_psnr_rainy"] == pytest.approx(sum(first_two) / 2, abs=1e-4)
    assert ev["heldout_psnr_rainy"] == pytest.approx(float(psnr(rendered[3], rainy[3])), abs=1e-4)
    scene.clean_images = None  # no clean images: the rainy PSNR only
    assert set(quick_eval(pipe, views=1)) == {"train_psnr_rainy", "heldout_psnr_rainy"}
    assert quick_eval(pipe, views=0) == {}


def test_two_direction_rain_is_matched_whichever_direction_dominates():
    """The bridge preset's rain falls in two directions of about equal strength: the angle
    error pairs both, so a prediction whose stronger direction is the truth's weaker one is
    still right; one-direction rain compares the strongest directions as before."""
    from rainyscape.eval.rain_stats import view_rain_stats
    from rainyscape.eval.views import ViewImages
    from rainyscape.testing.streaks import streak_layer

    g = torch.Generator().manual_seed(3)
    a, b = streak_layer(64, 70, 24, g), streak_layer(64, 115, 24, g)
    blank = torch.zeros(3, 64, 64)

    def stats(true_rain, predicted, directions):
        v = ViewImages(0, "v", "train", blank + true_rain[0], blank, None, rain=predicted[0], true_rain=true_rain[0])
        return view_rain_stats(v, {}, directions)

    swapped = stats(a + 0.8 * b, 0.8 * a + b, 2)
    assert angle_difference_deg(swapped["rain_angle_deg"], swapped["rain_angle_true_deg"]) > 30  # dominance flipped
    assert len(swapped["rain_angles_true_deg"]) == 2 and swapped["rain_angle_error_deg"] <= 3.0
    assert stats(a + 0.8 * b, 0.8 * a + b, 1)["rain_angle_error_deg"] > 30  # strongest against strongest
    single = stats(a, 0.5 * a + b, 1)  # one true direction: the prediction's strongest is wrong
    assert "rain_angles_true_deg" not in single and single["rain_angle_error_deg"] > 30


def test_each_views_rain_is_measured_near_its_own_down():
    """With the AGR's fall prior evaluation measures a view's predicted rain near that view's
    down (``view_options``): streaks at 80 degrees under horizontal edges read 80 in view 1
    (upright) and 0 in view 0 (its down along the image's x)."""
    from rainyscape.eval.rain_stats import view_rain_stats
    from rainyscape.eval.views import ViewImages
    from rainyscape.testing.streaks import streak_layer

    g = torch.Generator().manual_seed(0)
    rain = streak_layer(64, 80.0, 12, g)
    rain[..., 2::6, :] += 0.8
    rain = rain.reshape(1, 64, 64).expand(3, 64, 64)
    options = {"max_tilt": 45.0, "down": torch.tensor([0.0, math.pi / 2])}
    found = [view_rain_stats(ViewImages(i, "v", "train", rain, rain, None, rain=rain), options)["rain_angle_deg"]
             for i in (0, 1)]
    assert angle_difference_deg(found[0], 0.0) <= 3.0 and angle_difference_deg(found[1], 80.0) <= 3.0


def test_the_simulator_records_how_many_directions_its_rain_falls_in(tmp_path, tiny_scene_dir):
    from rainyscape.dataparsers.truth import simulated_rain

    record = simulated_rain(tiny_scene_dir)
    assert record["rain_directions"] == 1 and len(record["rain_falls"]) == 1  # and where it falls
    assert abs(np.linalg.norm(record["rain_falls"][0]) - 1) < 1e-5 and record["rain_falls"][0][1] < -0.8
    (tmp_path / "scene.json").write_text(json.dumps({"rain": {"wind2_deg": 20.0, "mix": 0.45},
                                                     "rain_falls": [[0.0, -1.0], [1.0, 0.0]]}))
    assert simulated_rain(tmp_path) == {"rain_directions": 2}  # malformed directions are left out
    (tmp_path / "scene.json").write_text("{not json")
    assert simulated_rain(tmp_path) == {} and simulated_rain(tmp_path / "absent") == {}


def test_psnr_in_rain_and_on_dry_pixels():
    """The render's error on the pixels the true rain covers and on the others, separately:
    an error of 0.1 under the rain and 0.01 elsewhere reads 20 dB and 40 dB."""
    from rainyscape.eval.perceptual import LpipsMetric
    from rainyscape.eval.protocol import view_metrics
    from rainyscape.eval.views import ViewImages

    clean = torch.full((3, 8, 8), 0.5)
    true_rain = torch.zeros(3, 8, 8)
    true_rain[1, :, 2] = 0.3  # one streak, one channel is enough
    wet = true_rain.amax(0) > 0
    rendered = clean + torch.where(wet, 0.1, 0.01)
    fused = torch.where(wet, rendered, clean)
    v = ViewImages(0, "v", "train", clean + true_rain, rendered, None, clean=clean, true_rain=true_rain,
                   post={"fusion": fused})
    row = view_metrics(v, LpipsMetric(None, "not needed"), {})
    assert row["train_psnr_in_rain"] == pytest.approx(20.0, abs=1e-3)
    assert row["train_psnr_dry"] == pytest.approx(40.0, abs=1e-3)
    assert row["rainy_input_psnr_in_rain"] == pytest.approx(-10 * math.log10(0.3 ** 2 / 3), abs=1e-3)
    assert row["train_fusion_psnr_in_rain"] == pytest.approx(20.0, abs=1e-3) and row["train_fusion_psnr_dry"] == 120.0
    dry = ViewImages(0, "v", "heldout", clean, rendered, None, clean=clean, true_rain=torch.zeros(3, 8, 8))
    assert view_metrics(dry, LpipsMetric(None, "not needed"), {})["heldout_psnr_in_rain"] is None


def test_rain_shares_say_where_the_true_rain_went():
    """Under a streak of true rain 0.3: a render 0.1 above clean keeps a third of it, a
    predicted rain of 0.15 recovers half; a fusion that keeps the rainy input there keeps it
    all; the dry pixels (render off by 0.01) do not count."""
    from rainyscape.eval.perceptual import LpipsMetric
    from rainyscape.eval.protocol import rain_shares, view_metrics
    from rainyscape.eval.views import ViewImages

    clean = torch.full((3, 8, 8), 0.5)
    true_rain = torch.zeros(3, 8, 8)
    true_rain[:, :, 2] = 0.3
    wet = true_rain.amax(0) > 0
    rendered = clean + torch.where(wet, 0.1, 0.01)
    rain = torch.where(wet, 0.15, 0.05).expand(3, 8, 8)
    v = ViewImages(0, "v", "train", clean + true_rain, rendered, None, clean=clean, true_rain=true_rain,
                   rain=rain, post={"keep": clean + true_rain})
    row = view_metrics(v, LpipsMetric(None, "not needed"), {})
    assert row["train_rain_kept"] == pytest.approx(1 / 3, abs=1e-6)
    assert row["train_rain_recovered"] == pytest.approx(0.5, abs=1e-6)
    assert row["train_keep_rain_kept"] == pytest.approx(1.0, abs=1e-6)
    assert "train_keep_rain_recovered" not in row
    darker = rain_shares(clean - true_rain, clean, true_rain, wet)
    assert darker == {RAIN_KEPT: pytest.approx(-1.0)}  # a render darker than clean reads below 0
    assert rain_shares(rendered, clean, torch.zeros(3, 8, 8), torch.zeros(8, 8, dtype=torch.bool),
                       rain) == {RAIN_KEPT: None, RAIN_RECOVERED: None}
