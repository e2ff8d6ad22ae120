"""Rows flagged ``bad_input`` pass the compensator's stateful stages without entering their state.

A flagged row is a glitch: an impossible temperature (``gyronet.recordings.guard.TempGuard``) or gyro value
(``gyronet.recordings.guard.bad_gyro``). The feature extractor already treats it as a lost sample; this module
does the same for what comes after the model, so that every other row's output is exactly that of
the recording with the flagged rows removed:

- the start-up window leaves it out of its mean (``StartupOffset.process``'s ``valid``);
- the Kalman stage gives a flagged row its estimate from that row (``KalmanStage.peek``: a gyro
  value that is bad on an axis replaced by that axis's last output) and then forgets it.

``out_of_range`` stays the reading's own (as in the C compensator): a glitch outside the trained
range carries both flags.
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
        A ``gyronet.model.kalman.KalmanStage`` or None (no stage: the rate passes as is).
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
