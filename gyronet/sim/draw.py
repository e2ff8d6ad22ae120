"""Draw one simulated sensor's coefficients from its seed, from the default or the survey's distribution."""
from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from gyronet.errors import GyronetError
from gyronet.sim.sensor import N_AXES, SPEC_RANGE_C, SensorModel, per_axis
from gyronet.sim.survey_sensor import check_distribution, widen


def draw_sensor(sensor_seed: int, swing_dps: Any = None, distribution: str = "default",
                **overrides: Any) -> SensorModel:
    """Draw one sensor's coefficients from its own seed.

    Parameters
    ----------
    sensor_seed
        Seed of this sensor; the thermal history and the noise never touch this stream.
    distribution
        ``default``: the sensors every table of docs/results uses (described below), bit for bit as ever.
        ``survey``: the same sensor made harder, :func:`gyronet.sim.survey_sensor.widen`.
    swing_dps
        Peak-to-peak static bias over -40..60 degC per axis, deg/s; by default drawn in
        [1.2, 3.8] deg/s. The cubic and knee coefficients are scaled to reach it.
    **overrides
        Any :class:`SensorModel` field, replacing the drawn value (applied after the swing
        scaling), e.g. ``rate_gain_deg_per_c=0`` to switch the dT/dt term off.

    Returns
    -------
    SensorModel
        Time constants a few hundred s, 1.5-4 degC of self-heating, dT/dt terms of 0.05-0.3 deg/s
        at 1 degC/min, a tanh knee that leaves a cubic fit a misfit of a few % of the swing.
    """
    if distribution != "default":
        check_distribution(distribution)
    rng = np.random.default_rng([int(sensor_seed), 7001])
    sign = lambda: rng.choice([-1.0, 1.0], size=N_AXES)  # noqa: E731
    poly = np.column_stack([sign() * rng.uniform(0.4, 1.0, N_AXES),
                            rng.normal(0.0, 0.4, N_AXES), rng.normal(0.0, 0.4, N_AXES)])
    x = (np.linspace(*SPEC_RANGE_C, 1001)[:, None] - 10.0) / 50.0
    cubic = x * poly[:, 0] + x**2 * poly[:, 1] + x**3 * poly[:, 2]
    # the tanh knee: 10-18 % of the cubic's swing each way (a cubic misfit of a few % of the swing)
    knee = sign() * rng.uniform(0.10, 0.18, N_AXES) * np.ptp(cubic, axis=0)
    # g of 5-12 deg/degC is 0.08-0.2 deg/s at 1 degC/min; |h| <= 0.4 |g| keeps g + h x at
    # 0.05-0.28 deg/s over -40..60 degC
    rate_gain = sign() * rng.uniform(5.0, 12.0, N_AXES)
    model = SensorModel(
        thermal_tau_s=float(rng.uniform(200.0, 500.0)),
        self_heating_c=float(rng.uniform(1.5, 4.0)),
        warmup_tau_s=float(rng.uniform(300.0, 900.0)),
        offset_dps=rng.uniform(-1.0, 1.0, N_AXES),
        poly_dps=poly,
        knee_dps=knee,
        knee_c=rng.uniform(-25.0, 45.0, N_AXES),
        knee_width_c=rng.uniform(4.0, 10.0, N_AXES),
        rate_gain_deg_per_c=rate_gain,
        rate_temp_gain_deg_per_c=sign() * rng.uniform(0.1, 0.4, N_AXES) * np.abs(rate_gain),
    )
    target = rng.uniform(1.2, 3.8, N_AXES) if swing_dps is None else per_axis(swing_dps, "swing_dps")
    scale = target / model.swing_dps()
    model = dataclasses.replace(model, poly_dps=model.poly_dps * scale[:, None],
                                knee_dps=model.knee_dps * scale)
    if distribution != "default":
        model = widen(model, sensor_seed, distribution)
    return _override(model, overrides)


def _override(model: SensorModel, overrides: dict[str, Any]) -> SensorModel:
    fields = {f.name: f for f in dataclasses.fields(SensorModel)}
    unknown = sorted(set(overrides) - set(fields))
    if unknown:
        raise GyronetError(f"unknown sensor option(s) {', '.join(unknown)}; known: swing_dps, "
                           f"{', '.join(fields)}")
    changes: dict[str, Any] = {}
    for name, value in overrides.items():
        current = getattr(model, name)
        if isinstance(current, np.ndarray) and current.ndim == 2:
            changes[name] = np.broadcast_to(np.asarray(value, dtype=float), current.shape).copy()
        elif isinstance(current, np.ndarray):
            changes[name] = per_axis(value, f"sensor.{name}")
        else:
            changes[name] = float(value)
    return dataclasses.replace(model, **changes)
