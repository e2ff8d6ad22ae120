"""The simulation's option specs and its result, kept apart so that ``core.simulate`` fits in one short module."""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any, Mapping, Sequence, TypeVar

import numpy as np

from gyronet.errors import GyronetError
from gyronet.sim.sensor import N_AXES, SensorModel, per_axis


@dataclass(frozen=True)
class TemperatureSpec:
    """The sensor's temperature reading: true die temperature + noise, quantised.

    Attributes
    ----------
    lsb_c
        Quantisation step of ``temp_c``, degC (0: none).
    noise_c
        Standard deviation of the reading noise, degC.
    """

    lsb_c: float = 0.0625
    noise_c: float = 0.02


@dataclass(frozen=True)
class EarthSpec:
    """Where the sensor sits and how it is turned.

    Attributes
    ----------
    latitude_deg
        Latitude, degrees North.
    orientation_deg
        (roll, pitch, yaw) of the sensor from East-North-Up, degrees; see
        :func:`gyronet.sim.noise.body_from_enu`.
    rate_deg_hr
        Earth rate, deg/h (0 removes it from the true rate).
    """

    latitude_deg: float = 45.0
    orientation_deg: Sequence[float] = (0.0, 0.0, 0.0)
    rate_deg_hr: float = 15.041


@dataclass(frozen=True)
class AccelSpec:
    """The accelerometer: gravity on the static sensor plus white noise.

    Attributes
    ----------
    enabled
        Write ``acc_x_g``, ``acc_y_g``, ``acc_z_g``.
    noise_g
        Standard deviation of the accelerometer noise, g.
    lsb_g
        Quantisation step, g (0: none).
    """

    enabled: bool = True
    noise_g: float = 0.002
    lsb_g: float = 0.0


@dataclass
class Simulation:
    """A simulated recording and its ground truth.

    Attributes
    ----------
    recording
        The CONTRACT.md columns: ``time_s``, ``temp_c``, ``gyro_{x,y,z}_dps``, ``acc_{x,y,z}_g``
        (when on) and any auxiliary columns of the effects. Arrays of shape (n,).
    truth
        ``time_s``, ``die_temp_c``, ``chamber_temp_c``, ``drift_{x,y,z}_dps`` (all deterministic
        drift, effects included), ``noise_{x,y,z}_dps`` (what was added, quantisation included),
        ``true_rate_{x,y,z}_dps`` (Earth rate and rate steps), ``effect_<name>_{x,y,z}_dps``, and
        when on, ``turn_on_bias_{x,y,z}_dps`` and ``g_sensitivity_{x,y,z}_dps`` (parts of the
        drift that no temperature model can predict, see :mod:`gyronet.sim.run`).
        ``gyro = true_rate + drift + noise`` per axis.
    meta
        The ``# key=value`` lines of the recording.
    sensor
        The drawn sensor coefficients.
    effects
        Names of the effects switched on, in the order applied.
    run
        The run-level draws that are on (:mod:`gyronet.sim.run`): ``turn_on_bias_dps`` (3,),
        ``g_sensitivity_dps_per_g`` (3x3); written to the truth's metadata, never the recording's.
    """

    recording: dict[str, np.ndarray]
    truth: dict[str, np.ndarray]
    meta: dict[str, str]
    sensor: SensorModel
    effects: list[str] = field(default_factory=list)
    run: dict[str, Any] = field(default_factory=dict)


Spec = TypeVar("Spec")


def as_spec(cls: type[Spec], value: Spec | Mapping[str, Any] | None, what: str) -> Spec:
    """A spec dataclass from itself, a mapping of its fields, or None (the defaults)."""
    if value is None:
        return cls()
    if isinstance(value, cls):
        return value
    known = [f.name for f in dataclasses.fields(cls)]  # type: ignore[arg-type]
    unknown = sorted(set(value) - set(known))
    if unknown:
        raise GyronetError(f"unknown {what} option(s) {', '.join(unknown)}; known: {', '.join(known)}")
    return cls(**value)


def rate_steps_dps(time_s: np.ndarray, rate_steps: Sequence[Mapping[str, Any]] | None) -> np.ndarray:
    """True rotation steps: each ``{start_s, duration_s, rate_dps: [x, y, z]}`` adds its rate on
    ``start_s <= t < start_s + duration_s``. Shape (n, 3), deg/s."""
    out = np.zeros((len(time_s), N_AXES))
    for k, step in enumerate(rate_steps or []):
        missing = {"start_s", "duration_s", "rate_dps"} - set(step)
        if missing or len(step) != 3:
            raise GyronetError(f"rate_steps[{k}] needs exactly start_s, duration_s, rate_dps; "
                               f"got {dict(step)}")
        on = (time_s >= step["start_s"]) & (time_s < step["start_s"] + step["duration_s"])
        out[on] += per_axis(step["rate_dps"], f"rate_steps[{k}].rate_dps")
    return out
