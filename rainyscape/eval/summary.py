"""From per-view rows to the ``summary`` of ``metrics.json``: the mean over views of every
number under its key (a circular mean for angles); the keys are the rows' own
(rainyscape/eval/metric_keys.py)."""

from __future__ import annotations

from rainyscape.eval.metric_keys import ANGLE_KEYS, RAIN_STAT_KEYS
from rainyscape.imaging.angles import mean_angle_deg


def mean_of(values: list) -> float | None:
    """The mean of the values that are not None (None when there are none)."""
    values = [v for v in values if v is not None]
    return sum(values) / len(values) if values else None


def summarize(rows: list[dict]) -> dict[str, float]:
    """Per key, the mean over the views whose row has it. A mean of nothing is left out,
    except for the rain statistics, where None says "the predicted rain has no streaks"."""
    summary: dict[str, float] = {}
    keys = sorted({k for r in rows for k, x in r.items() if isinstance(x, float) or x is None})
    for k in keys:
        values = [r[k] for r in rows if k in r]
        value = mean_angle_deg([x for x in values if x is not None]) if k in ANGLE_KEYS else mean_of(values)
        if value is not None or k in RAIN_STAT_KEYS:
            summary[k] = value
    return summary
