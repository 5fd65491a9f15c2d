"""Bootstrap confidence intervals over sequences for the pooled per-pair means of `toolkit eval`.

The pairs of one sequence share their reference image (and, in `eval synth`, their source frame), so they are
not independent: resampling pairs would understate the spread. The unit resampled here is the sequence. A
resample draws as many sequences as there are, with replacement; its statistic is the same pooled mean the
report shows (the mean over every pair of the drawn sequences, a sequence drawn twice counting twice, values
that are NaN left out as the report leaves them out). The interval is the percentile interval of the
resampled statistics. One resample matrix serves every metric and every model of a group, so the rows of a
report are resampled alike and their intervals can be read side by side.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Mapping, Sequence

import numpy as np

from toolkit.evaluation.runner import PAIR_VALUES, ModelResult, grouped_pairs

Interval = tuple[float, float]


@dataclass(frozen=True)
class BootstrapSettings:
    """How intervals are drawn: ``resamples`` draws, a two-sided ``level`` (0.95 = the 2.5 and 97.5
    percentiles), and the ``seed`` of the draws (the same seed gives the same intervals)."""

    resamples: int = 1000
    level: float = 0.95
    seed: int = 0

    def to_dict(self) -> dict[str, object]:
        return {"unit": "sequence", "resamples": self.resamples, "level": self.level, "seed": self.seed,
                "method": "percentile"}


def resample_weights(num_sequences: int, settings: BootstrapSettings) -> np.ndarray:
    """``[resamples, num_sequences]`` int: how often each sequence is drawn in each resample (each row sums to
    ``num_sequences``)."""
    rng = np.random.default_rng([settings.seed, num_sequences])
    drawn = rng.integers(0, num_sequences, size=(settings.resamples, num_sequences))
    flat = (drawn + num_sequences * np.arange(settings.resamples)[:, None]).ravel()
    return np.bincount(flat, minlength=settings.resamples * num_sequences).reshape(settings.resamples, num_sequences)


def pooled_mean_interval(values: Sequence[Sequence[float]], weights: np.ndarray, level: float) -> Interval | None:
    """Percentile interval of the pooled mean under the resamples ``weights`` (`resample_weights`).

    ``values[s]`` are the per-pair values of sequence s (any count; NaN = undefined, left out). Returns None
    when no value is defined; a resample drawing only undefined values is left out of the percentiles.
    """
    sums = np.array([np.nansum(np.asarray(v, dtype=np.float64)) for v in values])
    counts = np.array([np.count_nonzero(np.isfinite(np.asarray(v, dtype=np.float64))) for v in values])
    if counts.sum() == 0:
        return None
    totals, numbers = weights @ sums, weights @ counts
    means = totals[numbers > 0] / numbers[numbers > 0]
    tail = 50.0 * (1.0 - level)
    low, high = np.percentile(means, [tail, 100.0 - tail])
    return float(low), float(high)


def bootstrap_mean_interval(values: Sequence[Sequence[float]],
                            settings: BootstrapSettings = BootstrapSettings()) -> Interval | None:
    """The interval of the pooled mean of ``values`` (one list of per-pair values per sequence)."""
    return pooled_mean_interval(values, resample_weights(len(values), settings), settings.level)


def metric_intervals(sequences: Mapping[str, Sequence[object]], metrics: Mapping[str, Callable[[object], float]],
                     settings: BootstrapSettings) -> dict[str, list[float] | None]:
    """``{metric: [low, high] or None}`` for one group: ``sequences`` maps a sequence name to its pairs'
    metric records, ``metrics`` a metric name to the per-pair value (NaN = undefined). Sequences are taken
    in name order, so the intervals do not depend on the order the pairs came in."""
    names = sorted(sequences)
    if not names:
        return {key: None for key in metrics}
    weights = resample_weights(len(names), settings)
    intervals: dict[str, list[float] | None] = {}
    for key, value_of in metrics.items():
        interval = pooled_mean_interval([[value_of(m) for m in sequences[n]] for n in names], weights, settings.level)
        intervals[key] = None if interval is None else list(interval)
    return intervals


# The metrics that get an interval: every dataset number but the keypoint count, which describes the model.
INTERVAL_METRICS = ("repeatability", "localisation_error", "nn_map", "matching_score", "homography_1px",
                    "homography_3px", "homography_5px")


def sequence_of(pair_name: str) -> str:
    """``"v_x_1a2b3c4d/1-3"`` -> ``"v_x_1a2b3c4d"``: a pair's sequence, as `read_hpatches` names pairs."""
    return pair_name.rsplit("/", 1)[0]


def add_intervals(summaries: dict[str, dict[str, object]], result: ModelResult,
                  settings: BootstrapSettings) -> None:
    """Put ``intervals`` (`metric_intervals` of `INTERVAL_METRICS`) into each group's summary of ``result``."""
    for group, pairs in grouped_pairs(result).items():
        sequences: dict[str, list[object]] = {}
        for name, metrics in pairs.items():
            sequences.setdefault(sequence_of(name), []).append(metrics)
        summaries[group]["intervals"] = metric_intervals(
            sequences, {key: PAIR_VALUES[key] for key in INTERVAL_METRICS}, settings)
