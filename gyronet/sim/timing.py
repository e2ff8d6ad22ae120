"""Damaged sample clocks for tests: stamp jitter, clock drift, rate changes, from a simulation and its truth.

A recording's ``time_s`` is what its logger stamped. Two things can be wrong with it: the stamps
(a host clock's jitter or drift over samples taken steadily) or the sampling itself (a rate that
changes, samples taken irregularly). The first kind moves ``time_s`` and leaves the truth's own
time; the second picks rows of a simulation made at a higher rate, so the truth stays exact at
every kept sample. Every function returns new column dicts and never touches its input.
"""
from __future__ import annotations

import logging

import numpy as np

log = logging.getLogger(__name__)


def rate_change_rows(n: int, step_before: int, step_after: int, at_fraction: float) -> np.ndarray:
    """Rows of a simulation sampled every ``step_before`` rows up to ``at_fraction`` of it, then every
    ``step_after`` (a simulation at 20 Hz with steps 2 then 1: 10 Hz, then 20 Hz)."""
    cut = int(round(at_fraction * n))
    before = np.arange(0, cut, int(step_before))
    start = before[-1] + int(step_after) if len(before) else 0
    return np.concatenate([before, np.arange(start, n, int(step_after))])


def irregular_rows(n: int, step: int, jitter_fraction: float, rng: np.random.Generator) -> np.ndarray:
    """Rows every ``step`` of a simulation, each taken up to ``jitter_fraction`` of a period early or
    late (the samples themselves irregular, the stamps exact): ``step`` must resolve the fraction."""
    nominal = np.arange(0, n - step, step)
    offset = np.round(rng.uniform(-jitter_fraction, jitter_fraction, len(nominal)) * step).astype(int)
    rows = np.clip(nominal + offset, 0, n - 1)
    return np.unique(rows)


def jitter_stamps(time_s: np.ndarray, jitter_fraction: float, rng: np.random.Generator) -> np.ndarray:
    """Stamps of samples off by up to ``jitter_fraction`` of the local period either way (a host clock's
    jitter; the period: the shorter interval beside each sample); strictly increasing for a fraction
    under 0.5."""
    intervals = np.diff(time_s)
    if len(intervals) == 0:
        return time_s.copy()
    period_s = np.minimum(np.concatenate([intervals[:1], intervals]), np.concatenate([intervals, intervals[-1:]]))
    return time_s + rng.uniform(-jitter_fraction, jitter_fraction, len(time_s)) * period_s


def drift_stamps(time_s: np.ndarray, offset_ppm: float = 0.0, end_fraction: float = 0.0) -> np.ndarray:
    """Stamps of a clock that runs ``offset_ppm`` fast and whose rate error grows linearly to
    ``end_fraction`` at the end of the file (stamped interval / true interval = 1 + ppm + growth)."""
    elapsed_s = time_s - time_s[0]
    total_s = max(float(elapsed_s[-1]), 1e-12)
    # stamp' = 1 + ppm 1e-6 + end_fraction t / T  ->  stamp = t (1 + ppm 1e-6) + end_fraction t^2 / (2 T)
    return time_s[0] + elapsed_s * (1.0 + offset_ppm * 1e-6) + end_fraction * elapsed_s**2 / (2.0 * total_s)
