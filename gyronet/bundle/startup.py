"""The run's own offset from its first still seconds, as a flight controller calibrates its gyro at boot.

Every power-up of a MEMS gyro has its own turn-on bias (and every fixture orientation its own
g-sensitivity term); no temperature model trained on other runs can predict it. ``StartupOffset``
assumes the first ``still_s`` seconds of a stream are still: it averages the compensated rate
(gyro minus drift) over them, subtracts the true rate during the test (the static rate, e.g. the
Earth's), and removes that offset from every later sample. It sits inside
``Compensator.process``, so offline files and live streams give the same numbers.

Motion in the window would bias the offset by (mean rate of the motion) x (its duration / still_s),
so the window is checked before its offset is used: the rate is averaged over 1 s bins and any bin
that departs from the window's median by more than ``max(motion_dps, 6 sigma)`` is refused, where
sigma is the bins' own robust spread (1.4826 x MAD, per axis). Six sigma keeps false alarms
negligible on a still sensor (p ~ 2e-9 per bin and axis: ~1e-5 over a 600 s window); the
``motion_dps`` floor (0.5 deg/s by default, about 4x the 1 s noise of a consumer MEMS gyro at
1 Hz and far below what handling a device produces, tens of deg/s) keeps a window that is mostly
still from being refused for one noisy bin. A constant rotation over the whole window looks like a
bias to any method and cannot be detected.

The offset carries the window's white noise into every later sample, a constant error of variance
(the window's first differences' mean square / 2) / (its samples): ``widen`` adds it to the error
bar of a bundle calibrated without a start-up window (on a 10 Hz gyro of 6 deg/sqrt(h), 4 mdps).
"""
from __future__ import annotations

import logging
import math
from typing import Any, Sequence

import numpy as np

from gyronet.errors import GyronetError

log = logging.getLogger(__name__)

BIN_S = 1.0  # the motion test's averaging bin
N_SIGMA = 6.0


class StartupMotionError(GyronetError):
    """The start-up window that should be still is not."""


def _number(value: Any, name: str) -> float:
    """``value`` as a float, or one line naming the setting (``startup.still_s=10min`` was a TypeError)."""
    try:
        return float(value)
    except (TypeError, ValueError):
        raise GyronetError(f"startup.{name} must be a number, got {value!r}") from None


class StartupOffset:
    """Estimate one offset per axis over the first ``still_s`` s of a stream and apply it from then on.

    Parameters
    ----------
    still_s
        Length of the window assumed still, s (> 0).
    motion_dps
        Floor of the motion test, deg/s: a 1 s mean may depart this much from the window's median.
    static_rate_dps
        True rate during the window (e.g. the Earth's rate on the sensor's axes), deg/s, shape (3,).
    """

    def __init__(self, still_s: float, motion_dps: float = 0.5, static_rate_dps: Sequence[float] = (0.0, 0.0, 0.0)):
        still_s, motion_dps = _number(still_s, "still_s"), _number(motion_dps, "motion_dps")
        if not (math.isfinite(still_s) and still_s > 0):
            raise GyronetError(f"startup.still_s must be a positive number of seconds, got {still_s}")
        if not (math.isfinite(motion_dps) and motion_dps > 0):
            raise GyronetError(f"startup.motion_dps must be positive, got {motion_dps}")
        self.still_s, self.motion_dps = still_s, motion_dps
        try:
            self.static_rate_dps = np.asarray(static_rate_dps, dtype=np.float64).reshape(3)
        except (TypeError, ValueError):
            raise GyronetError(f"startup.static_rate_dps needs 3 numbers (x, y, z, deg/s), got {static_rate_dps!r}") \
                from None
        if not np.isfinite(self.static_rate_dps).all():  # a NaN here made every output of its axis NaN, exit 0
            raise GyronetError(f"startup.static_rate_dps needs 3 finite numbers (x, y, z, deg/s), got "
                               f"{self.static_rate_dps.tolist()!r}")
        self.n_bins = max(1, int(math.ceil(self.still_s / BIN_S)))
        self.reset()

    def reset(self) -> None:
        """Start a new run: forget the window and the offset."""
        self.start_time_s: float | None = None
        self.offset_dps: np.ndarray | None = None
        self.noise_var_dps2: np.ndarray | None = None  # of the offset: the window mean's white noise
        self._sums = np.zeros((self.n_bins, 3))
        self._counts = np.zeros(self.n_bins, dtype=np.int64)
        self._diff_sq, self._last = np.zeros(3), None
        self._end_row = 0

    @property
    def done(self) -> bool:
        """True once the window is complete and its offset is applied."""
        return self.offset_dps is not None

    def process(self, time_s: np.ndarray, rate_dps: np.ndarray, valid: np.ndarray | None = None) -> np.ndarray:
        """The next samples' rate (n, 3), deg/s, minus the offset once known; window samples pass unchanged.

        ``valid`` (n,) marks the rows that may enter the window's mean (flagged input does not).
        """
        time_s = np.asarray(time_s, dtype=np.float64)
        self._end_row = 0  # of this chunk: the rows from it on have the offset removed
        if len(time_s) == 0:
            return rate_dps
        if self.offset_dps is None:
            # a stamp that is no time (NaN, inf: a flagged row) neither starts nor ends the window
            finite = np.isfinite(time_s)
            if self.start_time_s is None:
                if not finite.any():
                    self._end_row = len(time_s)
                    return rate_dps
                self.start_time_s = float(time_s[np.argmax(finite)])
            elapsed_s = time_s - self.start_time_s
            past = np.flatnonzero(finite & (elapsed_s >= self.still_s))
            n_in = int(past[0]) if len(past) else len(time_s)
            self._end_row = n_in
            if n_in:
                rows = finite[:n_in] if valid is None else finite[:n_in] & np.asarray(valid[:n_in], dtype=bool)
                bins = np.clip((elapsed_s[:n_in][rows] // BIN_S).astype(np.int64), 0, self.n_bins - 1)
                np.add.at(self._sums, bins, rate_dps[:n_in][rows])
                np.add.at(self._counts, bins, 1)
                self._add_differences(rate_dps[:n_in][rows])
            if n_in == len(time_s):
                return rate_dps
            self._finish()
            out = rate_dps.copy()
            out[n_in:] -= self.offset_dps
            return out
        return rate_dps - self.offset_dps

    def widen(self, sigma_dps: np.ndarray) -> np.ndarray:
        """``sigma_dps`` (n, 3) of the chunk ``process`` last had, with the offset's noise added in quadrature on
        the rows it was removed from."""
        if self.offset_dps is None:
            return sigma_dps
        out = sigma_dps.copy()
        out[self._end_row:] = np.sqrt(out[self._end_row:] ** 2 + self.noise_var_dps2)
        return out

    def _add_differences(self, rate_dps: np.ndarray) -> None:
        """First differences of the window's good samples, in order (the first against the last chunk's last)."""
        if not len(rate_dps):
            return
        steps = np.diff(rate_dps if self._last is None else np.vstack([self._last, rate_dps]), axis=0)
        self._diff_sq += (steps ** 2).sum(0)
        self._last = rate_dps[-1].copy()

    def require_done(self, source: str) -> None:
        """Raise when a finished record ended inside its start-up window."""
        if not self.done:
            raise GyronetError(f"{source}: shorter than startup.still_s={self.still_s:g} s, so no start-up "
                               f"offset could be estimated")

    def _finish(self) -> None:
        counts = self._counts
        if not counts.any():  # every window sample flagged: nothing measured, nothing removed (as in the C export)
            log.warning("no good sample in the start-up window (startup.still_s=%g): no offset is removed", self.still_s)
            self.offset_dps, self.noise_var_dps2 = np.zeros(3), np.zeros(3)
            return
        filled = counts > 0
        means = self._sums[filled] / counts[filled, None]
        median = np.median(means, axis=0)
        sigma = 1.4826 * np.median(np.abs(means - median), axis=0)
        bound = np.maximum(self.motion_dps, N_SIGMA * sigma)
        departure = np.abs(means - median)
        if np.any(departure > bound):
            bin_, axis = np.unravel_index(int(np.argmax(departure / bound)), departure.shape)
            at_s = float(np.flatnonzero(filled)[bin_] * BIN_S)
            raise StartupMotionError(
                f"motion in the start-up window (startup.still_s={self.still_s:g}): the {'xyz'[axis]} rate "
                f"departs from the window's median by {departure[bin_, axis]:.3g} deg/s at {at_s:g} s after "
                f"the start (bound {bound[axis]:.3g} deg/s); keep the sensor still for the first "
                f"{self.still_s:g} s, or lower startup.still_s")
        span_s = float(np.ptp(np.flatnonzero(filled)) + 1) * BIN_S
        if span_s < 0.5 * self.still_s:
            log.warning("the start-up window's good samples span %g s of its %g s (%d samples: a gap or a restart "
                        "inside it): its offset is poorly measured and may bias every later sample", span_s,
                        self.still_s, int(counts.sum()))
        # offset = mean(gyro - drift) - static rate, over every window sample
        self.offset_dps = self._sums.sum(0) / counts.sum() - self.static_rate_dps
        self.noise_var_dps2 = self._diff_sq / (2.0 * max(counts.sum() - 1, 1)) / counts.sum()
        log.info("start-up offset over the first %g s (%d samples): %s deg/s, its noise %s mdps", self.still_s,
                 int(counts.sum()), ", ".join(f"{a}={v:+.4g}" for a, v in zip("xyz", self.offset_dps)),
                 "/".join(f"{1e3 * v:.2g}" for v in np.sqrt(self.noise_var_dps2)))


__all__ = ["StartupMotionError", "StartupOffset"]
