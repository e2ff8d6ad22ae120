"""Rows flagged ``bad_input`` pass the compensator's stateful stages without entering their state.

A flagged row is a glitch: an impossible temperature (``gyronet.guard.TempGuard``) or gyro value
(``gyronet.guard.bad_gyro``). The feature extractor already treats it as a lost sample; this module
does the same for what comes after the model, so that every other row's output is exactly that of
the recording with the flagged rows removed:

- the Kalman stage gives a flagged row its estimate from that row (``KalmanStage.peek``: a gyro
  value that is bad on an axis replaced by that axis's last output) and then forgets it;
- the out-of-range flag of a row whose temperature was rejected is that of the temperature the
  model was evaluated at (the last accepted reading), not of the glitch: the glitch is
  ``bad_input``, and the model did not see it.
"""
from __future__ import annotations

import logging

import numpy as np

log = logging.getLogger(__name__)


def stage_skipping(kalman, rate_dps: np.ndarray, skip: np.ndarray, bad_dps: np.ndarray | None,
                   last_dps: np.ndarray | None) -> tuple[np.ndarray, np.ndarray | None]:
    """Run the Kalman stage (or none) over ``rate_dps`` (n, 3); ``skip`` rows leave its state as it was.

    Parameters
    ----------
    kalman
        A ``gyronet.kalman.KalmanStage`` or None (no stage: the rate passes as is).
    rate_dps
        Compensated rate, deg/s, (n, 3); finite wherever ``bad_dps`` is False.
    skip
        (n,) bool: rows that must not enter the stage's state.
    bad_dps
        (n, 3) bool or None: values to replace by the axis's last output (not finite, out of range).
    last_dps
        The last output of a row that was not skipped (3,), or None at the start of a stream.

    Returns
    -------
    out, last
        The output (n, 3), deg/s, and the new last output of a row that was not skipped.
    """
    out = np.empty_like(rate_dps)
    start = 0
    for row in np.flatnonzero(skip).tolist():
        if row > start:
            out[start:row] = _run(kalman, rate_dps[start:row])
            last_dps = out[row - 1]
        held = np.zeros(rate_dps.shape[1]) if last_dps is None else last_dps
        value = rate_dps[row] if bad_dps is None else np.where(bad_dps[row], held, rate_dps[row])
        out[row] = value if kalman is None else kalman.peek(value[None])[0]
        start = row + 1
    if start < len(rate_dps):
        out[start:] = _run(kalman, rate_dps[start:])
        last_dps = out[-1]
    return out, last_dps


def _run(kalman, rate_dps: np.ndarray) -> np.ndarray:
    return rate_dps if kalman is None else kalman.process(rate_dps)


def held_outside(temp_c: np.ndarray, rejected: np.ndarray, held_c: float | None,
                 temp_range_c: tuple[float, float]) -> tuple[np.ndarray, float | None]:
    """The ``out_of_range`` flags (n,) of the temperatures the model saw, and the last accepted reading.

    An accepted row is flagged when its reading is outside ``temp_range_c``; a rejected row when the
    reading held for it (the last accepted one, ``held_c`` from the previous call at first) is.
    Before any accepted reading, a rejected row is not flagged: its features are the prior's.
    """
    temp_c = np.asarray(temp_c, dtype=np.float64)
    low, high = temp_range_c
    if not rejected.any():
        return (temp_c < low) | (temp_c > high), (float(temp_c[-1]) if len(temp_c) else held_c)
    index = np.maximum.accumulate(np.where(rejected, -1, np.arange(len(temp_c))))
    seen = np.where(index >= 0, temp_c[np.maximum(index, 0)], np.nan if held_c is None else held_c)
    # NaN (no accepted reading yet) compares False: not flagged
    return (seen < low) | (seen > high), (None if np.isnan(seen[-1]) else float(seen[-1]))
