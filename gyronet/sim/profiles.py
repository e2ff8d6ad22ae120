"""Thermal chamber profiles: the chamber air temperature against time.

A profile is a list of knots (time, temperature) joined by straight ramps and holds, sampled at
``fs_hz`` and smoothed by a moving average of ``corner_s`` so that the corners are rounded the
way a real chamber controller rounds them (the middle of each ramp keeps its exact rate).

========= ====================================================================================
kind      what
========= ====================================================================================
paper     60 degC hold 1 h, then -1 degC/min steps of 10 degC with a 1 h dwell at 50, 40, ...,
          -40 degC: 12.67 h, the test of the paper
cycle     down and up through ``setpoints_c`` (25 -> -40 -> 60 -> 25 degC) with a dwell at every
          multiple of ``step_c`` on the way: the same temperatures reached heating and cooling
random    random setpoints in [``low_c``, ``high_c``], ramp rates and dwells drawn from ranges
constant  one temperature, for noise (Allan) tests
========= ====================================================================================
"""
from __future__ import annotations

import inspect
import logging
import math
from typing import Callable, Sequence

import numpy as np
from scipy.ndimage import uniform_filter1d

from gyronet.errors import GyronetError

log = logging.getLogger(__name__)

Knots = tuple[np.ndarray, np.ndarray]
MAX_SAMPLES = 50_000_000  # about 8 GB of recording and truth columns: 58 days at 10 Hz, 14 h at 1 kHz
RANGES = {"random": ("rate_c_per_min", "dwell_s")}  # options given as (low, high); a number: low = high


def _knots_from_setpoints(setpoints_c: Sequence[float], rates_c_per_min: Sequence[float],
                          dwells_s: Sequence[float]) -> Knots:
    """Knots for: dwell at setpoint 0, ramp to setpoint 1 at rate 0, dwell, ramp, ..."""
    time_s, temp_c = [0.0], [float(setpoints_c[0])]
    now_s = float(dwells_s[0])
    time_s.append(now_s)
    temp_c.append(float(setpoints_c[0]))
    for k in range(1, len(setpoints_c)):
        step_c = abs(float(setpoints_c[k]) - float(setpoints_c[k - 1]))
        now_s += 60.0 * step_c / float(rates_c_per_min[k - 1])
        time_s.append(now_s)
        temp_c.append(float(setpoints_c[k]))
        if dwells_s[k] > 0:
            now_s += float(dwells_s[k])
            time_s.append(now_s)
            temp_c.append(float(setpoints_c[k]))
    return np.asarray(time_s), np.asarray(temp_c)


def _paper_knots(rng: np.random.Generator | None, start_c: float = 60.0, stop_c: float = -40.0,
                 step_c: float = 10.0, rate_c_per_min: float = 1.0, dwell_s: float = 3600.0,
                 duration_s: float | None = None) -> Knots:
    """The paper's staircase: a dwell at every ``step_c`` from ``start_c`` to ``stop_c``."""
    n_steps = int(round(abs(stop_c - start_c) / step_c))
    setpoints = start_c + np.sign(stop_c - start_c) * step_c * np.arange(n_steps + 1)
    return _knots_from_setpoints(setpoints, [rate_c_per_min] * n_steps, [dwell_s] * (n_steps + 1))


def _cycle_knots(rng: np.random.Generator | None,
                 setpoints_c: Sequence[float] = (25.0, -40.0, 60.0, 25.0), step_c: float = 20.0,
                 rate_c_per_min: float = 1.0, dwell_s: float = 1800.0,
                 duration_s: float | None = None) -> Knots:
    """Legs between ``setpoints_c`` with a dwell at each multiple of ``step_c`` on the way."""
    if len(setpoints_c) < 2:
        raise GyronetError("profile 'cycle': setpoints_c needs at least two temperatures")
    stops = [float(setpoints_c[0])]
    for start, end in zip(setpoints_c[:-1], setpoints_c[1:]):
        if step_c and step_c > 0:
            grid = np.arange(np.ceil(min(start, end) / step_c), np.floor(max(start, end) / step_c) + 1)
            inner = [g * step_c for g in grid if min(start, end) < g * step_c < max(start, end)]
            stops += sorted(inner, reverse=end < start)
        stops.append(float(end))
    return _knots_from_setpoints(stops, [rate_c_per_min] * (len(stops) - 1), [dwell_s] * len(stops))


def _random_knots(rng: np.random.Generator | None, low_c: float = -40.0, high_c: float = 60.0,
                  start_c: float = 25.0, rate_c_per_min: Sequence[float] = (0.2, 2.0),
                  dwell_s: Sequence[float] = (600.0, 3600.0), min_step_c: float = 5.0,
                  duration_s: float | None = None) -> Knots:
    """Random setpoints, ramp rates and dwells until ``duration_s`` (default 12 h) is covered."""
    if rng is None:
        raise GyronetError("profile 'random' needs a random generator (a seed)")
    if high_c - low_c < 2 * min_step_c:
        raise GyronetError(f"profile 'random': range [{low_c}, {high_c}] degC is narrower than "
                           f"twice min_step_c={min_step_c}")
    total_s = 12 * 3600.0 if duration_s is None else float(duration_s)
    setpoints, rates, dwells = [float(start_c)], [], [float(rng.uniform(*dwell_s))]
    elapsed_s = dwells[0]
    while elapsed_s < total_s:
        target = float(rng.uniform(low_c, high_c))
        while abs(target - setpoints[-1]) < min_step_c:
            target = float(rng.uniform(low_c, high_c))
        rates.append(float(rng.uniform(*rate_c_per_min)))
        dwells.append(float(rng.uniform(*dwell_s)))
        elapsed_s += 60.0 * abs(target - setpoints[-1]) / rates[-1] + dwells[-1]
        setpoints.append(target)
    return _knots_from_setpoints(setpoints, rates, dwells)


def _constant_knots(rng: np.random.Generator | None, temp_c: float = 25.0,
                    duration_s: float | None = None) -> Knots:
    """A single temperature held for ``duration_s`` (default 1 h)."""
    total_s = 3600.0 if duration_s is None else float(duration_s)
    return np.array([0.0, total_s]), np.array([temp_c, temp_c], dtype=float)


_BUILDERS: dict[str, Callable[..., Knots]] = {
    "paper": _paper_knots,
    "cycle": _cycle_knots,
    "random": _random_knots,
    "constant": _constant_knots,
}
PROFILES = tuple(_BUILDERS)
_DEFAULT_DURATION_S = {"random": 12 * 3600.0, "constant": 3600.0}


def chamber_profile(kind: str, fs_hz: float, rng: np.random.Generator | None = None, *,
                    duration_s: float | None = None, corner_s: float = 120.0,
                    **opts: object) -> tuple[np.ndarray, np.ndarray]:
    """Sample a chamber temperature profile.

    Parameters
    ----------
    kind
        One of ``paper``, ``cycle``, ``random``, ``constant`` (see the module docstring).
    fs_hz
        Sampling rate, Hz.
    rng
        Generator for the ``random`` profile's draws; unused by the others.
    duration_s
        Length of the record, s. ``random`` and ``constant`` are built to this length (defaults
        12 h and 1 h); ``paper`` and ``cycle`` are cut at it or held at their last temperature.
    corner_s
        Width of the moving average that rounds the corners, s (0: sharp corners).
    **opts
        The profile's own options: ``paper``: ``start_c``, ``stop_c``, ``step_c``,
        ``rate_c_per_min``, ``dwell_s``; ``cycle``: ``setpoints_c``, ``step_c``,
        ``rate_c_per_min``, ``dwell_s``; ``random``: ``low_c``, ``high_c``, ``start_c``,
        ``rate_c_per_min`` and ``dwell_s`` as (low, high) ranges, ``min_step_c``;
        ``constant``: ``temp_c``.

    Returns
    -------
    time_s, chamber_c
        Arrays of shape (n,): time from 0 at ``1 / fs_hz`` spacing, s, and chamber temperature,
        degC. ``n = duration * fs_hz``.
    """
    if kind not in _BUILDERS:
        raise GyronetError(f"unknown profile {kind!r}; choose one of {', '.join(PROFILES)}")
    if not fs_hz > 0:
        raise GyronetError(f"fs_hz must be positive, got {fs_hz}")
    known = [p for p in inspect.signature(_BUILDERS[kind]).parameters if p not in ("rng", "duration_s")]
    unknown = sorted(set(opts) - set(known))
    if unknown:
        raise GyronetError(f"profile {kind!r}: unknown option(s) {', '.join(unknown)}; known: "
                           f"{', '.join(known + ['corner_s'])}")
    opts = _checked_options(kind, {**opts, "corner_s": corner_s})
    corner_s = opts.pop("corner_s")
    if duration_s is None:
        duration_s = _DEFAULT_DURATION_S.get(kind)
    if duration_s is not None and not (duration_s > 0 and math.isfinite(duration_s)):
        raise GyronetError(f"duration_s must be a positive, finite number of seconds, got {duration_s}")
    knot_s, knot_c = _BUILDERS[kind](rng, duration_s=duration_s, **opts)
    total_s = float(knot_s[-1]) if duration_s is None else float(duration_s)
    n_samples = total_s * fs_hz + 1e-6  # a float first: fs_hz=1e308 is no integer to floor
    if not n_samples <= MAX_SAMPLES:
        raise GyronetError(f"profile {kind!r}: {total_s:g} s at {fs_hz:g} Hz is {n_samples:.3g} samples, more than "
                           f"the simulator's {MAX_SAMPLES:.0e} (about 8 GB): lower fs_hz or duration_s")
    n_samples = math.floor(n_samples)
    if n_samples < 2:
        raise GyronetError(f"profile {kind!r}: {total_s} s at {fs_hz} Hz gives fewer than 2 samples")
    time_s = np.arange(n_samples) / fs_hz
    chamber_c = np.interp(time_s, knot_s, knot_c)
    window = int(round(corner_s * fs_hz)) | 1  # odd, so the average is centred
    if window > 1:
        chamber_c = uniform_filter1d(chamber_c, size=window, mode="nearest")
    log.debug("profile %s: %d samples, %.3f h", kind, n_samples, total_s / 3600)
    return time_s, chamber_c


def _checked_options(kind: str, opts: dict) -> dict:
    """``opts`` with the rates, dwells and steps checked: a zero rate divided by zero, a negative one ran the ramps
    backwards in time (a wrong history, exit 0), a number where ``random`` takes a range was a TypeError."""
    # option: (least value, whether it may equal it)
    limits = {"rate_c_per_min": (0.0, False), "dwell_s": (0.0, True), "step_c": (0.0, kind == "cycle"),
              "min_step_c": (0.0, True), "corner_s": (0.0, True)}
    checked = dict(opts)
    for name, (least, equal_ok) in limits.items():
        if name not in opts or (name == "step_c" and kind == "cycle" and opts[name] is None):
            continue
        ranged = name in RANGES.get(kind, ())
        value = opts[name]
        values = list(value) if isinstance(value, (list, tuple)) else [value]
        if ranged and len(values) == 1:
            values *= 2
        if len(values) != (2 if ranged else 1) or any(
                isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) for v in values):
            form = "a number or a [low, high] range" if ranged else "a number"
            raise GyronetError(f"profile {kind!r}: {name} must be {form}, got {value!r}")
        if any(v < least or (v == least and not equal_ok) for v in values) or (ranged and values[0] > values[1]):
            bound = f"{'at least' if equal_ok else 'more than'} {least:g}"
            raise GyronetError(f"profile {kind!r}: {name} must be {bound}{' (low <= high)' if ranged else ''}, "
                               f"got {value!r}")
        checked[name] = tuple(float(v) for v in values) if ranged else float(values[0])
    return checked
