"""The one schema of evaluation's numbers: what each is (a :class:`Measure`: name, unit,
direction, how a table prints it) and which images and views it is measured on (a
:class:`Metric`, whose ``key`` is its name in ``metrics.json``). The protocol writes per-view
rows and the summary under these keys; the summary, the run's report and the benchmark tables
read them through the same records. No other module spells a metric key.

``metrics.json`` keys (the same in ``per_view`` rows and, as means over views, in ``summary``):
  rainy_input_{psnr,ssim,lpips}   rainy training inputs vs clean: the floor to beat
  train_{psnr,ssim,lpips}         renders at training views vs clean (the paper's numbers)
  train_<pp>_{psnr,ssim,lpips}    the same after post-process <pp> (the config's key)
  train_<pp>_coverage             mask fusions: share of pixels its mask takes from the render
  train_<pp>_random_{psnr,ssim,lpips}  the fusion control: the same fusion with a mask of random
                                  pixels of the same coverage (seeded per view); a fused gain
                                  that the control also shows comes from copying the input
  heldout_{psnr,ssim,lpips}       renders at held-out views vs clean (novel views)
  {train,heldout}_psnr_vs_rainy   renders vs the rainy images (how much rain was fitted)
  {train,heldout}_psnr_{in_rain,dry}, train_<pp>_psnr_{in_rain,dry}, rainy_input_psnr_in_rain
                                  simulated scenes: PSNR vs clean on the pixels the true rain
                                  covers and on the others: is what a method loses rain left
                                  in, or the rest of the scene?
  {train,heldout}_rain_kept, train_<pp>_rain_kept, train_rain_recovered
                                  shares of the true rain the image still shows / the
                                  predicted rain holds
  rain_angle_deg, residual_angle_deg, rain_angle_true_deg, rain_angle_error_deg,
  rain_correlation                the rain statistics of the training views (no split prefix)
  rain_angles_deg, rain_angles_true_deg   per view only: every direction (multi-direction rain)

The log's periodic evaluation (``eval`` records of log.jsonl) uses :func:`quick_key`.
"""

from __future__ import annotations

from dataclasses import dataclass

SPLITS = ("train", "heldout")
RAIN_STATS = ""  # the split of the rain statistics: the training views, keys without a prefix


@dataclass(frozen=True)
class Measure:
    """What a number measures and how it reads."""

    name: str  # the last part of its keys
    title: str  # what a table or report calls it
    unit: str = ""  # "dB", "deg" or "" (a ratio, a share)
    better: str = ""  # "higher" | "lower" | "" (a description, not a score)
    digits: int = 3  # decimals a table prints
    angle: bool = False  # a direction: averaged as one (circular mean over 180 degrees)

    @property
    def arrow(self) -> str:
        return {"higher": "↑", "lower": "↓"}.get(self.better, "")

    def format(self, value: float | None, signed: bool = False, missing: str = "n/a") -> str:
        """``value`` at this measure's precision (``signed``: with its sign, for differences)."""
        if value is None:
            return missing
        return f"{value:{'+' if signed else ''}.{self.digits}f}"

    def text(self, value: float | None) -> str:
        """``value`` with its unit, for a sentence ("23.26 dB"; "n/a")."""
        return self.format(value) + (f" {self.unit}" if self.unit and value is not None else "")


PSNR = Measure("psnr", "PSNR", "dB", "higher", 2)
SSIM = Measure("ssim", "SSIM", "", "higher", 3)
LPIPS = Measure("lpips", "LPIPS", "", "lower", 3)
IMAGE_MEASURES = (PSNR, SSIM, LPIPS)  # an image against the clean one: every table's columns
PSNR_VS_RAINY = Measure("psnr_vs_rainy", "PSNR vs the rainy image", "dB", "", 2)
PSNR_IN_RAIN = Measure("psnr_in_rain", "PSNR on the pixels in rain", "dB", "higher", 2)
PSNR_DRY = Measure("psnr_dry", "PSNR on the dry pixels", "dB", "higher", 2)
RAIN_KEPT = Measure("rain_kept", "share of the true rain the render still shows", "", "lower", 3)
RAIN_RECOVERED = Measure("rain_recovered", "share of the true rain the predicted rain holds", "", "higher", 3)
COVERAGE = Measure("coverage", "share of the pixels the fusion takes from the render", "", "", 3)
RAIN_ANGLE = Measure("rain_angle_deg", "predicted rain streak angle (deg)", "deg", "", 1, angle=True)
RAIN_ANGLES = Measure("rain_angles_deg", "predicted rain streak angles (deg)", "deg", "", 1, angle=True)
RESIDUAL_ANGLE = Measure("residual_angle_deg", "streak angle of the residual I - B (deg)", "deg", "", 1, angle=True)
TRUE_ANGLE = Measure("rain_angle_true_deg", "true rain streak angle (deg)", "deg", "", 1, angle=True)
TRUE_ANGLES = Measure("rain_angles_true_deg", "true rain streak angles (deg)", "deg", "", 1, angle=True)
ANGLE_ERROR = Measure("rain_angle_error_deg", "angle error, predicted vs true (deg)", "deg", "lower", 1)
CORRELATION = Measure("rain_correlation", "correlation, predicted vs true rain layer", "", "higher", 2)


@dataclass(frozen=True)
class Metric:
    """One number of ``metrics.json``: a measure of one image, on the views of one split."""

    measure: Measure
    split: str = "train"  # "train" | "heldout" | RAIN_STATS
    image: str = "render"  # "render" | "input" (the rainy input) | "post" | "control" (its random mask)
    post: str = ""  # the post-process's config key (image "post" or "control")

    @property
    def key(self) -> str:
        """The key in per-view rows and in the summary (see the module docstring)."""
        m = self.measure.name
        if self.split == RAIN_STATS:
            return m
        if self.image == "input":
            return f"rainy_input_{m}"
        if self.image == "post":
            return f"train_{self.post}_{m}"
        if self.image == "control":
            return f"train_{self.post}_random_{m}"
        return f"{self.split}_{m}"

    def of(self, values: dict) -> float | None:
        """This metric's value in a summary or per-view row (None when absent)."""
        return values.get(self.key)


def render(measure: Measure, split: str = "train") -> Metric:
    """The field's render at the views of ``split``."""
    return Metric(measure, split)


def rainy_input(measure: Measure) -> Metric:
    """The rainy training inputs themselves (against the clean images: the floor)."""
    return Metric(measure, "train", "input")


def post(measure: Measure, key: str) -> Metric:
    """The render after post-process ``key`` (training views: it needs the input image)."""
    return Metric(measure, "train", "post", key)


def control(measure: Measure, key: str) -> Metric:
    """Post-process ``key``'s random-mask control (training views)."""
    return Metric(measure, "train", "control", key)


def rain_stat(measure: Measure) -> Metric:
    """A rain statistic of the training views."""
    return Metric(measure, RAIN_STATS)


# Rain statistics whose mean may be None: "the predicted rain has no streaks", not "not measured".
RAIN_STAT_KEYS = frozenset(rain_stat(m).key for m in (RAIN_ANGLE, RESIDUAL_ANGLE, TRUE_ANGLE, ANGLE_ERROR,
                                                       CORRELATION))
ANGLE_KEYS = frozenset(rain_stat(m).key for m in (RAIN_ANGLE, RESIDUAL_ANGLE, TRUE_ANGLE))  # circular means


def quick_key(split: str, against: str) -> str:
    """Key of the periodic evaluation's PSNR (log.jsonl ``eval`` records) of the renders at the
    first views of ``split`` against the ``clean`` or the ``rainy`` images."""
    return f"{split}_psnr_{against}"
