"""How long the training record stayed at each temperature: where it is too thin to pin the drift down.

The drift model's own error at a temperature is the noise of the record averaged over the time
the record spent there, so it depends on the seconds per degC, not on the sensor's noise: the
noise floor of a 60 s block scales with the same noise. On the survey's 100 simulated sensors one
chamber cycle at 1 degC/min (each degC passed twice, about 130 s) left the 90th percentile at 1.21x
the floor as deployed; two cycles (about 255 s) 1.14x, and so did one cycle with half the noise
variance in the training record alone (1.16x; docs/results/survey.md). ``train.py`` prints the
thinnest degC of the record and logs it.
"""
from __future__ import annotations

from typing import Any, Iterable

import numpy as np

BIN_C = 1.0  # the temperature bins the time is counted in
ENOUGH_S_PER_C = 240.0  # two cycles at 1 degC/min: what met the survey's goals


def seconds_per_degc(records: Iterable[tuple[np.ndarray, np.ndarray]], low_c: float, high_c: float,
                     bin_c: float = BIN_C) -> tuple[np.ndarray, np.ndarray]:
    """Bins of ``bin_c`` from ``low_c`` up, and the seconds the records spent in each (per degC).

    Parameters
    ----------
    records
        ``(time_s, temp_c)`` of each recording (several runs add up); NaN temperatures are not counted.
    low_c, high_c
        The trained range: only the bins wholly inside it are counted (the edges' bins are partial).

    Returns
    -------
    edges_c, seconds_per_c
        The bins' lower edges, degC, and the time in each, s per degC.
    """
    edges = np.arange(np.ceil(low_c / bin_c) * bin_c, high_c + 1e-9, bin_c)
    if len(edges) < 2:
        return edges[:0], np.zeros(0)
    seconds = np.zeros(len(edges) - 1)
    for time_s, temp_c in records:
        dt_s = float(np.median(np.diff(time_s))) if len(time_s) > 1 else 0.0
        temp_c = np.asarray(temp_c, dtype=float)
        seconds += np.histogram(temp_c[np.isfinite(temp_c)], edges)[0] * dt_s
    return edges[:-1], seconds / bin_c


def thinnest(data: Any) -> dict[str, float]:
    """``data/min_s_per_degc`` and ``data/thinnest_c`` (the bin's lower edge) of a training set's recordings."""
    runs = getattr(data, "runs", None)
    recordings = [r.recording for r in runs] if runs else [getattr(data, "recording", None)]
    if None in recordings or not hasattr(data, "temp_range_c"):
        return {}
    edges, seconds = seconds_per_degc(((r.time_s, r.temp_c) for r in recordings), *data.temp_range_c)
    if not len(seconds):
        return {}
    k = int(np.argmin(seconds))
    return {"data/min_s_per_degc": float(seconds[k]), "data/thinnest_c": float(edges[k])}


def describe(figures: dict[str, float]) -> str | None:
    """The line ``train.py`` prints: the thinnest degC, and what the survey needed."""
    if "data/min_s_per_degc" not in figures:
        return None
    low = figures["data/thinnest_c"]
    text = (f"record: {figures['data/min_s_per_degc']:.0f} s per degC at the least ({low:g}..{low + BIN_C:g} degC)")
    if figures["data/min_s_per_degc"] < ENOUGH_S_PER_C:
        text += (f"; under {ENOUGH_S_PER_C:.0f} s a knee a few degC wide there is fitted to a share of the noise "
                 "floor (the survey's sensors: 90th percentile 1.21x the floor at 130 s, 1.14x at 255 s); a second "
                 "cycle helps (docs/guides/record.md)")
    return text


__all__ = ["BIN_C", "ENOUGH_S_PER_C", "describe", "seconds_per_degc", "thinnest"]
