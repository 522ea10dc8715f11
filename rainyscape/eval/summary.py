"""From per-view rows to the ``summary`` of ``metrics.json``: means over views (circular means
for angles), keyed by split."""

from __future__ import annotations

from rainyscape.imaging.angles import mean_angle_deg

ANGLE_KEYS = ("rain_angle_deg", "residual_angle_deg", "rain_angle_true_deg")
RAIN_KEYS = (*ANGLE_KEYS, "rain_correlation", "rain_angle_error_deg")  # training views only, kept without a split prefix


def mean_of(values: list) -> float | None:
    """The mean of the values that are not None (None when there are none)."""
    values = [v for v in values if v is not None]
    return sum(values) / len(values) if values else None


def summarize(rows: list[dict]) -> dict[str, float]:
    """Means over views of every numeric per-view value, keyed ``<split>_<key>`` (the rainy
    floor and the rain statistics, defined on training views only, keep their own names)."""
    summary: dict[str, float] = {}
    for split in ("train", "heldout"):
        rows_s = [r for r in rows if r["split"] == split]
        keys = sorted({k for r in rows_s for k, x in r.items() if isinstance(x, float) or x is None})
        for k in keys:
            values = [r.get(k) for r in rows_s]
            value = mean_angle_deg([x for x in values if x is not None]) if k in ANGLE_KEYS else mean_of(values)
            if k in RAIN_KEYS:  # None stays: "the predicted rain has no streaks", not "not measured"
                summary[k] = value
            elif value is None:
                continue
            elif k.startswith("rainy_input_"):
                summary[k] = value
            else:
                summary[f"{split}_{k}"] = value
    return dict(sorted(summary.items()))
