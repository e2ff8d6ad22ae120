"""Which samples may enter the causal filters' state: a physically impossible reading is a lost sample.

One glitch (``temp_c=1e6``, a NaN, a gyro value of 1e300) must corrupt one row, flagged, not the
next hundred. ``TempGuard`` decides, causally and with state carried between calls, which
temperature samples are believable; the feature extractor treats the others as lost samples (its
features for them are the filters' predictions). The bounds are physical, not statistical:

- the reading lies inside ``SENSOR_RANGE_C``, beyond every MEMS sensor's operating range
  (-40..125 degC at most) with a margin;
- it differs from the last accepted reading by at most ``JUMP_C + MAX_TEMP_RATE_C_PER_S * dt``:
  a sensor die with any thermal mass heats or cools far slower than 1 degC/s (a fast chamber
  ramp is 0.03 degC/s, a self-heating warm-up a few tenths of a degC/s at most), and ``JUMP_C`` covers quantisation up
  to a 1 degC LSB and noise. The real records here move at most 0.18 degC between samples, the
  psim-tvc record 0.5 degC across a 300 s break.

A reading that really did step (a sensor re-zeroed, a record pasted from two sessions) is taken
once the readings have agreed with the new level for ``CONFIRM_SAMPLES`` samples and
``CONFIRM_S`` seconds; the filters restart there. A burst of garbage shorter than that is
rejected whole, however consistent it is.

The bound is on the last accepted reading, not on a filter's prediction, so it holds whichever
features a bundle uses and costs a comparison per sample.
"""
from __future__ import annotations

import logging

import numpy as np

from gyronet.errors import RecordingError

log = logging.getLogger(__name__)

SENSOR_RANGE_C = (-80.0, 200.0)
MAX_TEMP_RATE_C_PER_S = 1.0
JUMP_C = 1.5
CONFIRM_SAMPLES = 5
CONFIRM_S = 2.0
GYRO_RANGE_DPS = 1e4  # beyond every MEMS gyro's full scale (+-2000 deg/s typical, 1e4 with margin)
GLITCH_SHARE, GLITCH_ROWS = 0.01, 10  # more impossible temperatures than both: Kelvin or a wrong column


def check_temperatures(recording) -> None:
    """Refuse a file whose temperature no sensor reads on more than 1 % of its rows and more than 10 (Kelvin, a
    wrong column), naming the first line; fewer are glitches this guard leaves out (one in a short file too)."""
    temp_c, (low, high) = recording.columns["temp_c"], SENSOR_RANGE_C
    bad = np.flatnonzero((temp_c < low) | (temp_c > high))
    if bad.size > max(GLITCH_SHARE * len(temp_c), GLITCH_ROWS):
        raise RecordingError(f"{recording.path}: {recording.line_of(int(bad[0]))}: temp_c = "
                             f"{float(temp_c[bad[0]]):.6g} degC is outside any sensor's range ({low:g} .. {high:g}); "
                             f"{bad.size} such sample(s): fix or remove those lines")


def bad_gyro(gyro_dps: np.ndarray) -> np.ndarray:
    """Mask (n, 3) of gyro values that are not finite or beyond ``GYRO_RANGE_DPS``."""
    # NaN compares False: bad too
    return ~(np.abs(np.asarray(gyro_dps, dtype=np.float64)) <= GYRO_RANGE_DPS)


class TempGuard:
    """Accept or reject each temperature sample, causally; see the module docstring for the bounds."""

    def __init__(self) -> None:
        self.reset()

    def reset(self) -> None:
        """Forget the past, as at power-on."""
        self.last_time_s: float | None = None
        self.last_temp_c = 0.0
        # a run of rejected readings that agree with one another: a step being confirmed
        self.n_candidate = 0
        self.candidate_start_s = self.candidate_time_s = 0.0
        self.candidate_temp_c = 0.0

    def check(self, time_s: np.ndarray, temp_c: np.ndarray, finite: np.ndarray | bool = True
              ) -> tuple[np.ndarray, np.ndarray]:
        """Which of the next samples are accepted, and which of those start a confirmed step.

        Parameters
        ----------
        time_s
            Sample times, s, shape (n,), increasing, continuing the previous call.
        temp_c
            Temperature readings, degC, shape (n,).
        finite
            False where another input of the row is unusable (NaN or inf): rejected too.

        Returns
        -------
        accepted, step
            Boolean masks of shape (n,). ``step`` marks accepted samples at which a jump was
            confirmed: the filters restart there as at power-on.
        """
        n = len(time_s)
        accepted, step = np.zeros(n, dtype=bool), np.zeros(n, dtype=bool)
        if n == 1:  # the live path: plain floats
            accepted[0], step[0] = self.step(float(time_s[0]), float(temp_c[0]),
                                              bool(np.all(finite)) and in_sensor_range(float(temp_c[0])))
            return accepted, step
        low, high = SENSOR_RANGE_C
        with np.errstate(invalid="ignore"):
            valid = (temp_c >= low) & (temp_c <= high) & finite
            # a sample within the bound of the one before it, for the runs where that one was accepted
            follows = np.zeros(n, dtype=bool)
            follows[1:] = valid[1:] & (np.abs(temp_c[1:] - temp_c[:-1]) <= JUMP_C + MAX_TEMP_RATE_C_PER_S * np.diff(time_s))
        misfits = np.flatnonzero(~follows)
        i = 0
        while i < n:
            accepted[i], step[i] = self.step(float(time_s[i]), float(temp_c[i]), bool(valid[i]))
            i += 1
            if accepted[i - 1] and self.n_candidate == 0:
                # synced: every sample up to the next misfit follows its accepted predecessor
                stop = int(misfits[np.searchsorted(misfits, i)]) if misfits.size and misfits[-1] >= i else n
                accepted[i:stop] = True
                if stop > i:
                    self.last_time_s, self.last_temp_c = float(time_s[stop - 1]), float(temp_c[stop - 1])
                i = stop
        return accepted, step

    def step(self, time_s: float, temp_c: float, valid: bool) -> tuple[bool, bool]:
        """One sample in plain floats: (accepted, confirmed step); ``valid`` False rejects it outright."""
        if not valid:
            return False, False
        if self.last_time_s is None or abs(temp_c - self.last_temp_c) <= _allowed_c(time_s - self.last_time_s):
            self.last_time_s, self.last_temp_c, self.n_candidate = time_s, temp_c, 0
            return True, False
        agrees = self.n_candidate > 0 and abs(temp_c - self.candidate_temp_c) <= _allowed_c(time_s - self.candidate_time_s)
        self.n_candidate = self.n_candidate + 1 if agrees else 1
        if not agrees:
            self.candidate_start_s = time_s
        self.candidate_time_s, self.candidate_temp_c = time_s, temp_c
        if self.n_candidate < CONFIRM_SAMPLES or time_s - self.candidate_start_s < CONFIRM_S:
            return False, False
        log.debug("temperature step to %.3f degC at %.3f s confirmed: filters restart", temp_c, time_s)
        self.last_time_s, self.last_temp_c, self.n_candidate = time_s, temp_c, 0
        return True, True


def _allowed_c(interval_s: float) -> float:
    return JUMP_C + MAX_TEMP_RATE_C_PER_S * interval_s


def in_sensor_range(temp_c: float) -> bool:
    """True for a finite reading inside ``SENSOR_RANGE_C``."""
    return SENSOR_RANGE_C[0] <= temp_c <= SENSOR_RANGE_C[1]
