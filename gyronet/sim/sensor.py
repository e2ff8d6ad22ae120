"""The simulated sensor: its die temperature and its deterministic thermal drift.

Die temperature (degC), from the chamber temperature ``T_ch``::

    T_die = lag(T_ch, thermal_tau_s) + self_heating_c * (1 - exp(-t / warmup_tau_s))

where ``lag`` is a first-order low-pass, ``dy/dt = (u - y) / tau``, started settled at
``T_ch(0)`` (the sensor was powered on after soaking in the chamber).

Drift of axis ``a`` (deg/s), with ``x = (T_die - ref_c) / scale_c`` (-1..1 over -40..60 degC)
and ``Tdot = dT_die/dt`` the true die rate (degC/s)::

    drift_a = offset_a + p1_a x + p2_a x^2 + p3_a x^3                  (cubic)
            + knee_a * tanh((T_die - knee_c_a) / knee_width_c_a)      (what a cubic cannot follow)
            + (g_a + h_a x) * Tdot                                    (dT/dt and T * dT/dt terms)

``g`` and ``h`` are ``rate_gain_deg_per_c`` and ``rate_temp_gain_deg_per_c`` (deg/s per
degC/s). Every coefficient is drawn from ``sensor_seed`` alone (:func:`gyronet.sim.draw.draw_sensor`), so one seed
is one physical sensor whatever its thermal history.

Four further terms are zero by default (today's sensors are unchanged) and drawn by the wider
``distribution="survey"`` (:mod:`gyronet.sim.survey_sensor`): a second knee
``knee2_a tanh((T - knee2_c_a) / knee2_width_c_a)``; a per-axis thermal lag ``axis_lag_s`` (axis
``a`` sees ``lag(T_die, axis_lag_s_a)``, not the die temperature the sensor reports); cross-axis
coupling ``drift += C (drift - offset)`` (axis ``a`` carries ``C[a, b]`` of axis ``b``'s thermal
terms); and ``turn_on_bias_std_dps``, the spread of a constant drawn anew each power-up
(:func:`gyronet.sim.run.turn_on_bias_dps`).
"""
from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy import signal

from gyronet.errors import GyronetError

log = logging.getLogger(__name__)

N_AXES = 3
SPEC_RANGE_C = (-40.0, 60.0)  # the range over which ``swing_dps`` is measured


def per_axis(value: Any, name: str) -> np.ndarray:
    """A scalar or three values as a float array of shape (3,)."""
    array = np.asarray(value, dtype=float)
    if array.ndim == 0:
        return np.full(N_AXES, float(array))
    if array.shape != (N_AXES,):
        raise GyronetError(f"{name} must be one number or three (x, y, z), got {value!r}")
    return array.copy()


def first_order_lag(values: np.ndarray, fs_hz: float, tau_s: float) -> np.ndarray:
    """First-order low-pass ``dy/dt = (u - y) / tau``, started settled at ``values[0]``.

    Parameters
    ----------
    values
        Input, shape (n,), sampled at ``fs_hz``.
    fs_hz
        Sampling rate, Hz.
    tau_s
        Time constant, s; 0 returns a copy of the input.

    Returns
    -------
    numpy.ndarray
        Output, shape (n,).
    """
    values = np.asarray(values, dtype=float)
    if tau_s <= 0:
        return values.copy()
    decay = np.exp(-1.0 / (fs_hz * tau_s))
    # y[k] = a y[k-1] + (1 - a) u[k],  y[-1] = u[0]
    out, _ = signal.lfilter([1.0 - decay], [1.0, -decay], values, zi=[decay * values[0]])
    return out


@dataclass(frozen=True)
class SensorModel:
    """The coefficients of one simulated sensor; arrays have one entry per axis (x, y, z)."""

    thermal_tau_s: float
    self_heating_c: float
    warmup_tau_s: float
    offset_dps: np.ndarray
    poly_dps: np.ndarray  # shape (3, 3): coefficients of x, x^2, x^3
    knee_dps: np.ndarray
    knee_c: np.ndarray
    knee_width_c: np.ndarray
    rate_gain_deg_per_c: np.ndarray
    rate_temp_gain_deg_per_c: np.ndarray
    ref_c: float = 10.0
    scale_c: float = 50.0
    # the survey distribution's terms (module docstring); at these defaults they change nothing
    knee2_dps: np.ndarray = field(default_factory=lambda: np.zeros(N_AXES))
    knee2_c: np.ndarray = field(default_factory=lambda: np.zeros(N_AXES))
    knee2_width_c: np.ndarray = field(default_factory=lambda: np.ones(N_AXES))
    axis_lag_s: np.ndarray = field(default_factory=lambda: np.zeros(N_AXES))
    coupling: np.ndarray = field(default_factory=lambda: np.zeros((N_AXES, N_AXES)))  # rows: the axis that gains
    turn_on_bias_std_dps: np.ndarray = field(default_factory=lambda: np.zeros(N_AXES))

    def _static(self, temp_c: np.ndarray) -> np.ndarray:
        """Cubic and knees at temperatures of shape (n, 1) or (n, 3), before the coupling."""
        x = (temp_c - self.ref_c) / self.scale_c
        cubic = self.offset_dps + x * self.poly_dps[:, 0] + x**2 * self.poly_dps[:, 1] \
            + x**3 * self.poly_dps[:, 2]
        bias = cubic + self.knee_dps * np.tanh((temp_c - self.knee_c) / self.knee_width_c)
        if np.any(self.knee2_dps):
            bias = bias + self.knee2_dps * np.tanh((temp_c - self.knee2_c) / self.knee2_width_c)
        return bias

    def _coupled(self, drift_dps: np.ndarray) -> np.ndarray:
        if not np.any(self.coupling):
            return drift_dps
        # drift += C (drift - offset): each axis carries a share of the others' thermal terms
        return drift_dps + (drift_dps - self.offset_dps) @ self.coupling.T

    def static_bias_dps(self, temp_c: np.ndarray) -> np.ndarray:
        """Bias at a settled temperature (no dT/dt terms), shape (n, 3), deg/s; ``temp_c`` (n,) or per axis (n, 3)."""
        return self._coupled(self._static(_columns(temp_c)))

    def drift_dps(self, die_temp_c: np.ndarray, die_rate_c_per_s: np.ndarray) -> np.ndarray:
        """The drift formula of the module docstring, shape (n, 3), deg/s; inputs (n,) or per axis (n, 3)."""
        temp_c = _columns(die_temp_c)
        x = (temp_c - self.ref_c) / self.scale_c
        rate = _columns(die_rate_c_per_s)
        # (g + h x) * dT/dt
        rate_term = (self.rate_gain_deg_per_c + self.rate_temp_gain_deg_per_c * x) * rate
        return self._coupled(self._static(temp_c) + rate_term)

    def history_drift_dps(self, time_s: np.ndarray, die_temp_c: np.ndarray, fs_hz: float) -> np.ndarray:
        """The drift along a die temperature history, shape (n, 3), deg/s: each axis through its ``axis_lag_s``."""
        if not np.any(self.axis_lag_s):
            return self.drift_dps(die_temp_c, np.gradient(die_temp_c, time_s))
        axis_c = np.column_stack([first_order_lag(die_temp_c, fs_hz, tau_s) for tau_s in self.axis_lag_s])
        return self.drift_dps(axis_c, np.gradient(axis_c, time_s, axis=0))

    def swing_dps(self) -> np.ndarray:
        """Peak-to-peak static bias over -40..60 degC, shape (3,), deg/s."""
        bias = self.static_bias_dps(np.linspace(*SPEC_RANGE_C, 1001))
        return bias.max(axis=0) - bias.min(axis=0)

    def die_temperature_c(self, time_s: np.ndarray, chamber_c: np.ndarray, fs_hz: float) -> np.ndarray:
        """True die temperature: the lagged chamber plus self-heating since power-on (t = 0), degC."""
        warm = self.self_heating_c * -np.expm1(-(time_s - time_s[0]) / self.warmup_tau_s)
        return first_order_lag(chamber_c, fs_hz, self.thermal_tau_s) + warm

    def to_dict(self) -> dict[str, Any]:
        """Plain numbers and lists, for JSON metadata (the survey's terms only when on, as before them)."""
        defaults = SensorModel.__dataclass_fields__
        return {k: (v.tolist() if isinstance(v, np.ndarray) else v)
                for k, v in dataclasses.asdict(self).items()
                if k not in SURVEY_FIELDS or not np.array_equal(v, defaults[k].default_factory())}


SURVEY_FIELDS = ("knee2_dps", "knee2_c", "knee2_width_c", "axis_lag_s", "coupling", "turn_on_bias_std_dps")


def _columns(values: Any) -> np.ndarray:
    """(n,) as (n, 1), (n, 3) as it is: one temperature for every axis, or one per axis."""
    array = np.asarray(values, dtype=float)
    return array[:, None] if array.ndim == 1 else array


def __getattr__(name: str):
    """``gyronet.sim.sensor.draw_sensor``, now in :mod:`gyronet.sim.draw` (below the survey's widening)."""
    if name == "draw_sensor":
        from gyronet.sim.draw import draw_sensor

        return draw_sensor
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
