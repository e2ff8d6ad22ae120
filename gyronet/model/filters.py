"""The feature extractor's recursive filters: explicit state, batch or one sample, sound across gaps.

Each filter is a linear recursion run by ``scipy.signal.lfilter`` with explicit state on a block,
or by ``step`` on one live sample: the same direct-form-II-transposed operations in the same
order in plain floats, so both give the same numbers and a live sample costs microseconds.
Across a gap (lost samples) each filter restarts from its own prediction or from a clean
estimate, never by dividing an error by the gap, so no loss pattern can make one diverge.
"""
from __future__ import annotations

import logging
import math

import numpy as np
from scipy import signal

log = logging.getLogger(__name__)


def _df2t_step(b: list[float], a: list[float], value: float, z: list[float]) -> tuple[float, list[float]]:
    """One step of scipy's DF2T (``a[0] == 1``; b, a padded to the order + 1)."""
    order = len(z)
    y = z[0] + value * b[0]
    new = [z[i + 1] + value * b[i + 1] - y * a[i + 1] for i in range(order - 1)]
    new.append(value * b[order] - y * a[order])
    return y, new


class _Recursion:
    """``b, a`` with state ``zi``, as an lfilter block or a plain-float step."""

    def __init__(self, b: np.ndarray, a: np.ndarray):
        order = len(a) - 1
        self.b, self.a = np.asarray(b, dtype=np.float64) / a[0], np.asarray(a, dtype=np.float64) / a[0]
        self._b_list = [*self.b.tolist(), *[0.0] * (order + 1 - len(self.b))]
        self._a_list = self.a.tolist()
        self.zi: list[float] = [0.0] * order

    def run(self, x: np.ndarray) -> np.ndarray:
        y, zi = signal.lfilter(self.b, self.a, x, zi=np.asarray(self.zi, dtype=np.float64))
        self.zi = zi.tolist()
        return y

    def step(self, value: float) -> float:
        y, self.zi = _df2t_step(self._b_list, self._a_list, value, self.zi)
        return y


class Lag:
    """First-order lag y' = (x - y) / tau, exact for a sample-and-hold input, across gaps too."""

    def __init__(self, tau_s: float, dt_s: float):
        self.tau_s = tau_s
        decay = np.exp(-dt_s / tau_s)
        # y[n] = decay * y[n-1] + (1 - decay) * x[n]
        self._filter = _Recursion(np.array([1.0 - decay]), np.array([1.0, -decay]))
        self.last_y = 0.0

    def restart(self, x0: float, gap_s: float | None) -> None:
        """Start at x0 (power-on, ``gap_s`` None) or relax towards x0 over a gap of ``gap_s``.

        With the input held at x0 over the gap, the output at x0 is exactly
        ``x0 + (y_old - x0) exp(-gap / tau)``: a contraction, so no gap of any length amplifies.
        """
        first_y = x0 if gap_s is None else x0 + (self.last_y - x0) * math.exp(-gap_s / self.tau_s)
        # the DF2T step gives y = zi[0] + b[0] x0
        self._filter.zi = [first_y - self._filter._b_list[0] * x0]

    def run(self, x: np.ndarray) -> np.ndarray:
        y = self._filter.run(x)
        self.last_y = float(y[-1])
        return y

    def step(self, x: float) -> float:
        self.last_y = self._filter.step(x)
        return self.last_y


class RateTracker:
    """Critically damped alpha-beta tracker: level and slope of a quantised, noisy signal.

    A type-2 loop: on a constant ramp the slope estimate has no lag and no bias, which a
    differentiated low-pass filter cannot give; where the ramp curves (a constant second
    derivative) it is 2 tau late. Both poles sit at exp(-dt/tau).

    Across a gap no longer than ``tau_s`` the state predicts through it (level + slope * gap,
    slope kept) and the next sample updates that prior as usual, so the error carried over is
    the state's own, never divided by the gap. After a longer gap the tracker has forgotten its
    past anyway: it restarts at the new sample with the mean slope over the gap, clipped to
    ``max_slope``, whose error is at most (level error + sample noise) / tau.

    References
    ----------
    Kalata, P. R. (1984). The tracking index: a generalized parameter for alpha-beta and
    alpha-beta-gamma target trackers. IEEE Trans. AES-20(2), 174-182.
    """

    def __init__(self, tau_s: float, dt_s: float, max_slope: float = math.inf):
        theta = np.exp(-dt_s / tau_s)
        alpha, beta = 1.0 - theta**2, (1.0 - theta) ** 2
        # x = (I - K H) F x_prev + K z, with x = [level, slope], F = [[1, dt], [0, 1]], K = [alpha, beta/dt]
        gain = np.array([[alpha], [beta / dt_s]])
        transition = (np.eye(2) - gain @ np.array([[1.0, 0.0]])) @ np.array([[1.0, dt_s], [0.0, 1.0]])
        num, den = signal.ss2tf(transition, gain, transition, gain)
        self._level, self._slope = _Recursion(num[0], den), _Recursion(num[1], den)
        self.tau_s, self.dt_s, self.max_slope = tau_s, dt_s, max_slope
        # the state of a steady ramp (past inputs z0 - slope0 dt k) is linear in (z0, slope0)
        b_level, b_slope, a = self._level.b, self._slope.b, self._level.a
        order = len(a) - 1
        ones, back = np.ones(order), -dt_s * np.arange(1, order + 1)
        self._level_state = (signal.lfiltic(b_level, a, ones, ones), signal.lfiltic(b_level, a, back, back))
        self._slope_state = (signal.lfiltic(b_slope, a, np.zeros(order), ones), signal.lfiltic(b_slope, a, ones, back))
        self.last_level = self.last_slope = 0.0
        self.last_run = np.zeros(0)

    def prior(self, z0: float, slope0: float) -> None:
        """Set the state to a steady ramp that predicts z0 with slope0 for the next sample."""
        self._level.zi = (z0 * self._level_state[0] + slope0 * self._level_state[1]).tolist()
        self._slope.zi = (z0 * self._slope_state[0] + slope0 * self._slope_state[1]).tolist()

    def restart(self, z0: float, gap_s: float | None) -> None:
        """Before the first sample after power-on (``gap_s`` None) or after a gap of ``gap_s``."""
        if gap_s is None:
            self.prior(z0, 0.0)
        elif gap_s <= self.tau_s:
            # bridged: prior level = level + slope * gap, slope kept
            self.prior(self.last_level + self.last_slope * gap_s, self.last_slope)
        else:
            self.prior(z0, min(max((z0 - self.last_level) / gap_s, -self.max_slope), self.max_slope))

    def run(self, z: np.ndarray) -> np.ndarray:
        """Slope estimates for the samples ``z`` (the level is kept as state)."""
        level, slope = self._level.run(z), self._slope.run(z)
        self.last_level, self.last_slope = float(level[-1]), float(slope[-1])
        self.last_run = slope  # read by a LaggedRate that shares this tracker
        return slope

    def step(self, z: float) -> float:
        self.last_level, self.last_slope = self._level.step(z), self._slope.step(z)
        return self.last_slope


class LaggedRate:
    """dT/dt (``RateTracker``) through a first-order lag of ``lag_s``: the rate of ``lag(T, lag_s)``.

    Both filters are linear, so this is also the slope of the lagged temperature: the input of an
    axis that sees the die through a thermal path of its own (``gyronet.training.axis_lag``). On a
    restart the lag starts (power-on) or relaxes over the gap (``Lag.restart``) at the tracker's
    first slope after it.

    ``shared``: the tracker is an unlagged rate feature's, run (and restarted) before this one on the
    same samples, so this reads its slope rather than running the same tracker twice.
    """

    def __init__(self, tracker: RateTracker, lag: Lag, shared: bool = False):
        self.tracker, self.lag, self.shared = tracker, lag, shared
        self.tau_s, self.lag_s = tracker.tau_s, lag.tau_s
        self._restart: tuple[float | None] | None = None  # the gap of a restart not yet applied

    def restart(self, z0: float, gap_s: float | None) -> None:
        if not self.shared:
            self.tracker.restart(z0, gap_s)
        self._restart = (gap_s,)

    def _slope_in(self, slope: float) -> None:
        if self._restart is not None:
            self.lag.restart(slope, self._restart[0])
            self._restart = None

    def run(self, z: np.ndarray) -> np.ndarray:
        slope = self.tracker.last_run if self.shared else self.tracker.run(z)
        self._slope_in(float(slope[0]))
        return self.lag.run(slope)

    def step(self, z: float) -> float:
        slope = self.tracker.last_slope if self.shared else self.tracker.step(z)
        self._slope_in(slope)
        return self.lag.step(slope)
