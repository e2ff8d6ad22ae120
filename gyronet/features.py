"""Causal drift-model inputs, computed from samples up to now by one stateful extractor.

The batch path (training, ``compensate.py``) and the live path (``stream.py``) call the same
``FeatureExtractor.process`` with the same state, on a whole recording or on one sample at a
time, so both give the same numbers. Every filter here is a linear recursion run by
``scipy.signal.lfilter`` with explicit state, so a chunk of one sample costs microseconds and a
recording of a million samples costs milliseconds.

A feature is a small dict (a "spec") that ``meta.json`` stores, so a bundle rebuilds exactly
the extractor it was trained with:

========== ================================================================= ====================
kind       what                                                              default name
========== ================================================================= ====================
temp       the measured temperature                                          ``temp_c``
rate       dT/dt from a critically damped alpha-beta tracker, ``tau_s``      ``temp_rate_c_per_s``
product    T * dT/dt: the paper's "T times the change of T" per second       ``temp_x_rate_c2_per_s``
lag        ``source`` through a first-order lag of ``tau_s``                 ``<source>_lag<tau>s``
column     a recording column as it is (or lagged, with ``tau_s`` > 0)       ``<source>``
hysteresis play (backlash) operator of half-width ``width``: source - play   ``<source>_play<w>``
power      ``source`` ** ``exponent`` about ``centre``                       ``<source>_pow<k>``
time       time since the start: exp(-t/``tau_s``) or, without tau, hours    ``warmup<tau>s``/``age_h``
========== ================================================================= ====================

The product uses dT/dt per second: with a per-sample change dT the paper's T*dT is this
feature times the sample interval, a constant factor the model absorbs.
"""
from __future__ import annotations

import logging
from typing import Any, Mapping, Sequence

import numpy as np
from scipy import signal

log = logging.getLogger(__name__)

PAPER_FEATURES: list[dict[str, Any]] = [
    {"kind": "temp"},
    {"kind": "rate", "tau_s": 5.0},
    {"kind": "product"},
]

GAP_FACTOR = 1.5  # an interval longer than this many sample periods is a break in the record


def feature_name(spec: Mapping[str, Any]) -> str:
    """The column name of a feature spec (``name`` if given, else from its kind and parameters)."""
    if "name" in spec:
        return str(spec["name"])
    kind, source = spec["kind"], spec.get("source", "temp_c")
    if kind == "temp":
        return "temp_c"
    if kind == "rate":
        return "temp_rate_c_per_s" if source == "temp_c" else f"{source}_rate_per_s"
    if kind == "product":
        return "temp_x_rate_c2_per_s"
    if kind == "lag":
        return f"{source}_lag{spec['tau_s']:g}s"
    if kind == "column":
        tau_s = float(spec.get("tau_s", 0.0))
        return source if tau_s == 0 else f"{source}_lag{tau_s:g}s"
    if kind == "hysteresis":
        return f"{source}_play{spec['width']:g}"
    if kind == "power":
        return f"{source}_pow{spec['exponent']:g}"
    if kind == "time":
        return f"warmup{spec['tau_s']:g}s" if spec.get("tau_s") else "age_h"
    raise ValueError(f"unknown feature kind {kind!r}")


def required_columns(specs: Sequence[Mapping[str, Any]]) -> list[str]:
    """Recording columns that a list of specs reads (always ``time_s`` and ``temp_c``)."""
    needed = ["time_s", "temp_c"]
    for spec in specs:
        source = spec.get("source", "temp_c")
        if spec["kind"] in ("lag", "column", "hysteresis", "power", "rate") and source not in needed:
            needed.append(source)
    return needed


def _lfilter(b: np.ndarray, a: np.ndarray, x: np.ndarray, zi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``scipy.signal.lfilter`` with state; one live sample takes a plain-float path ten times faster.

    The short path is the direct-form-II-transposed step scipy runs (``a[0] == 1``), with the same
    operations in the same order, so both paths give the same numbers.
    """
    if len(x) != 1 or a[0] != 1.0:
        return signal.lfilter(b, a, x, zi=zi)
    order = len(zi)
    b_list = [*b.tolist(), *[0.0] * (order + 1 - len(b))]
    a_list = [*a.tolist(), *[0.0] * (order + 1 - len(a))]
    value = float(x[0])
    z = zi.tolist()
    y = z[0] + value * b_list[0]
    for i in range(order - 1):
        z[i] = z[i + 1] + value * b_list[i + 1] - y * a_list[i + 1]
    z[order - 1] = value * b_list[order] - y * a_list[order]
    return np.array([y]), np.array(z)


class _Lag:
    """First-order lag y' = (x - y) / tau, exact for a sample-and-hold input; restarts across gaps."""

    def __init__(self, tau_s: float, dt_s: float):
        self.tau_s = tau_s
        decay = np.exp(-dt_s / tau_s)
        # y[n] = decay * y[n-1] + (1 - decay) * x[n]
        self.b, self.a = np.array([1.0 - decay]), np.array([1.0, -decay])
        self.zi: np.ndarray | None = None
        self.last_y = 0.0

    def restart(self, x0: float, gap_s: float | None) -> None:
        # after a gap the lag has relaxed towards the new input: y = x0 + (y_old - x0) e^(-gap/tau)
        y0 = x0 if gap_s is None else x0 + (self.last_y - x0) * np.exp(-gap_s / self.tau_s)
        # state that makes the first output equal decay * y0 + (1 - decay) * x0
        self.zi = np.array([-self.a[1] * y0])

    def run(self, x: np.ndarray) -> np.ndarray:
        y, self.zi = _lfilter(self.b, self.a, x, self.zi)
        self.last_y = float(y[-1])
        return y


class _RateTracker:
    """Critically damped alpha-beta tracker: level and slope of a quantised, noisy signal.

    A type-2 loop: on a constant ramp the slope estimate has no lag and no bias, which a
    differentiated low-pass filter cannot give. Both poles sit at exp(-dt/tau).

    References
    ----------
    Kalata, P. R. (1984). The tracking index: a generalized parameter for alpha-beta and
    alpha-beta-gamma target trackers. IEEE Trans. AES-20(2), 174-182.
    """

    def __init__(self, tau_s: float, dt_s: float):
        theta = np.exp(-dt_s / tau_s)
        alpha, beta = 1.0 - theta**2, (1.0 - theta) ** 2
        # x = (I - K H) F x_prev + K z, with x = [level, slope], F = [[1, dt], [0, 1]], K = [alpha, beta/dt]
        gain = np.array([[alpha], [beta / dt_s]])
        transition = (np.eye(2) - gain @ np.array([[1.0, 0.0]])) @ np.array([[1.0, dt_s], [0.0, 1.0]])
        num, den = signal.ss2tf(transition, gain, transition, gain)
        self.b_level, self.b_slope, self.a = num[0], num[1], den
        self.dt_s = dt_s
        self.zi: tuple[np.ndarray, np.ndarray] | None = None
        self.last_level = 0.0

    def restart(self, z0: float, slope0: float) -> None:
        """Set the state to a steady ramp through z0 with slope0 (the tracker follows it exactly)."""
        order = len(self.a) - 1
        past_z = z0 - slope0 * self.dt_s * np.arange(1, order + 1)
        self.zi = (signal.lfiltic(self.b_level, self.a, past_z, past_z),
                   signal.lfiltic(self.b_slope, self.a, np.full(order, slope0), past_z))

    def run(self, z: np.ndarray) -> np.ndarray:
        level, zi_level = _lfilter(self.b_level, self.a, z, self.zi[0])
        slope, zi_slope = _lfilter(self.b_slope, self.a, z, self.zi[1])
        self.zi = (zi_level, zi_slope)
        self.last_level = float(level[-1])
        return slope


class FeatureExtractor:
    """Turn recording columns into model inputs, causally, keeping state between calls.

    Parameters
    ----------
    specs
        Feature specs (see the module docstring); order is the column order of the output.
    fs_hz
        Nominal sampling rate the filters are designed for. Intervals longer than
        ``GAP_FACTOR / fs_hz`` are breaks: filters restart from the first sample after them.
    """

    def __init__(self, specs: Sequence[Mapping[str, Any]], fs_hz: float):
        self.specs = [dict(s) for s in specs]
        self.names = [feature_name(s) for s in self.specs]
        if len(set(self.names)) != len(self.names):
            raise ValueError(f"duplicate feature names in {self.names}")
        self.fs_hz = float(fs_hz)
        self.dt_s = 1.0 / self.fs_hz
        self.columns = required_columns(self.specs)
        self._filters: dict[int, Any] = {}
        self._play: dict[int, float] = {}
        self.reset()

    def reset(self) -> None:
        """Forget the past, as at power-on."""
        self._last_time_s: float | None = None
        self._start_time_s: float | None = None
        self._filters.clear()
        self._play.clear()
        for i, spec in enumerate(self.specs):
            if spec["kind"] == "rate":
                self._filters[i] = _RateTracker(float(spec.get("tau_s", 5.0)), self.dt_s)
            elif spec["kind"] == "lag" or (spec["kind"] == "column" and float(spec.get("tau_s", 0)) > 0):
                self._filters[i] = _Lag(float(spec["tau_s"]), self.dt_s)

    def process(self, columns: Mapping[str, np.ndarray]) -> np.ndarray:
        """Features of the next samples.

        Parameters
        ----------
        columns
            At least ``self.columns``, each of shape (n,), in time order, continuing the previous call.

        Returns
        -------
        np.ndarray
            Shape (n, len(self.names)), float64.
        """
        time_s = np.asarray(columns["time_s"], dtype=np.float64)
        out = np.empty((len(time_s), len(self.specs)))
        if len(time_s) == 0:
            return out
        for start, stop in self._segments(time_s):
            chunk = {k: np.asarray(columns[k], dtype=np.float64)[start:stop] for k in self.columns}
            out[start:stop] = self._run_segment(chunk, restart=start > 0 or self._needs_restart(time_s[0]))
            self._last_time_s = float(time_s[stop - 1])
        return out

    def _needs_restart(self, first_time_s: float) -> bool:
        return self._last_time_s is None or first_time_s - self._last_time_s > GAP_FACTOR * self.dt_s

    def _segments(self, time_s: np.ndarray) -> list[tuple[int, int]]:
        if len(time_s) == 1:
            return [(0, 1)]
        breaks = np.flatnonzero(np.diff(time_s) > GAP_FACTOR * self.dt_s) + 1
        edges = [0, *breaks.tolist(), len(time_s)]
        return list(zip(edges[:-1], edges[1:]))

    def _run_segment(self, chunk: Mapping[str, np.ndarray], restart: bool) -> np.ndarray:
        time_s = chunk["time_s"]
        if self._start_time_s is None:
            self._start_time_s = float(time_s[0])
        gap_s = None if self._last_time_s is None else float(time_s[0]) - self._last_time_s
        done: dict[str, np.ndarray] = {}
        for i, spec in enumerate(self.specs):
            done[self.names[i]] = self._one(i, spec, chunk, done, restart, gap_s)
        return np.column_stack([done[n] for n in self.names])

    def _one(self, i: int, spec: Mapping[str, Any], chunk: Mapping[str, np.ndarray],
             done: Mapping[str, np.ndarray], restart: bool, gap_s: float | None) -> np.ndarray:
        kind, source = spec["kind"], spec.get("source", "temp_c")
        x = chunk.get(source)
        if kind in ("temp", "column") and i not in self._filters:
            return chunk["temp_c"] if kind == "temp" else x
        if kind in ("lag", "column"):
            lag = self._filters[i]
            if restart:
                lag.restart(float(x[0]), gap_s)
            return lag.run(x)
        if kind == "rate":
            tracker = self._filters[i]
            if restart:
                # across a gap, the mean slope over the gap; at power-on, flat
                slope0 = 0.0 if gap_s is None else (float(x[0]) - tracker.last_level) / gap_s
                tracker.restart(float(x[0]), slope0)
            return tracker.run(x)
        if kind == "product":
            rate = next((v for n, v in done.items() if self._kind_of(n) == "rate"), None)
            if rate is None:
                raise ValueError("a 'product' feature needs a 'rate' feature before it")
            return chunk["temp_c"] * rate
        if kind == "power":
            return (x - float(spec.get("centre", 0.0))) ** float(spec["exponent"])
        if kind == "hysteresis":
            return x - self._run_play(i, x, float(spec["width"]), restart and gap_s is None)
        if kind == "time":
            elapsed_s = chunk["time_s"] - self._start_time_s
            tau_s = spec.get("tau_s")
            return np.exp(-elapsed_s / float(tau_s)) if tau_s else elapsed_s / 3600.0
        raise ValueError(f"unknown feature kind {kind!r}")

    def _kind_of(self, name: str) -> str:
        return self.specs[self.names.index(name)]["kind"]

    def _run_play(self, i: int, x: np.ndarray, width: float, power_on: bool) -> np.ndarray:
        """Play operator: the output follows x only when x leaves the band [p - w, p + w]."""
        play = float(x[0]) if power_on or i not in self._play else self._play[i]
        out = np.empty_like(x)
        for n, value in enumerate(x.tolist()):
            play = min(max(play, value - width), value + width)
            out[n] = play
        self._play[i] = play
        return out
