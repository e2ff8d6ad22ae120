"""A wider sensor distribution for the survey: today's sensor, made harder in the ways real parts are.

``draw_sensor(seed, distribution="survey")`` draws today's sensor of that seed (its cubic, its
swing, its thermal time constants), then, from a stream of the seed's own that today's draw never
touches, redraws or adds what the default distribution keeps easy:

======================== ==========================================================================
what                     survey draw (today's default)
======================== ==========================================================================
knee width               2-10 degC on every axis (4-10)
a second knee            on one axis, 6-14 % of that axis's swing each way, 2-10 degC wide, centred
                         -25..45 degC and at least 15 degC from the first knee (none)
dT/dt gain ``|g|``       5-24 deg/degC, up to 2x (5-12)
T * dT/dt ``|h| / |g|``  0.1-0.8, up to 2x (0.1-0.4)
axis thermal lag         0-30 s per axis behind the die temperature the sensor reports (0)
cross-axis coupling      ``|C[a, b]|`` 0-0.1 of axis b's thermal terms on axis a, a != b (0)
turn-on bias             a constant per power-up, per axis normal of std 0.01-0.05 deg/s, drawn
                         anew from each run's ``seed`` (0)
======================== ==========================================================================

The cubic and knees are rescaled so each axis keeps today's static swing over -40..60 degC
(1.2-3.8 deg/s) before the coupling adds its share. Every range is in :data:`SURVEY_RANGES`, which
the tests check the draws against.
"""
from __future__ import annotations

import dataclasses
import logging

import numpy as np

from gyronet.errors import GyronetError
from gyronet.sim.sensor import N_AXES, SensorModel

log = logging.getLogger(__name__)

DISTRIBUTIONS = ("default", "survey")
SURVEY_RANGES: dict[str, tuple[float, float]] = {
    "knee_width_c": (2.0, 10.0),
    "knee2_share_of_swing": (0.06, 0.14),
    "knee2_width_c": (2.0, 10.0),
    "knee2_c": (-25.0, 45.0),
    "knee2_min_separation_c": (15.0, 15.0),
    "rate_gain_abs_deg_per_c": (5.0, 24.0),
    "rate_temp_gain_share": (0.1, 0.8),
    "axis_lag_s": (0.0, 30.0),
    "coupling_abs": (0.0, 0.1),
    "turn_on_bias_std_dps": (0.01, 0.05),
}


def check_distribution(name: str) -> None:
    """Refuse an unknown distribution name in one line."""
    if name not in DISTRIBUTIONS:
        raise GyronetError(f"unknown sensor distribution {name!r}; known: {', '.join(DISTRIBUTIONS)}")


def widen(model: SensorModel, sensor_seed: int, distribution: str = "survey") -> SensorModel:
    """Today's sensor ``model`` of ``sensor_seed`` redrawn with the survey's wider ranges (module docstring).

    Parameters
    ----------
    model
        The default distribution's sensor of this seed (after its swing scaling).
    sensor_seed
        The same seed: the extra draws come from their own stream of it.
    distribution
        ``survey`` (``default`` returns ``model`` unchanged).

    Returns
    -------
    SensorModel
    """
    check_distribution(distribution)
    if distribution == "default":
        return model
    r = SURVEY_RANGES
    rng = np.random.default_rng([int(sensor_seed), 7003])  # apart from draw_sensor's 7001 and run.py's 7002
    swing = model.swing_dps()
    knee_width = rng.uniform(*r["knee_width_c"], N_AXES)
    axis = int(rng.integers(N_AXES))
    knee2 = np.zeros(N_AXES)
    knee2_c = np.zeros(N_AXES)
    knee2_width = np.ones(N_AXES)
    knee2[axis] = rng.choice([-1.0, 1.0]) * rng.uniform(*r["knee2_share_of_swing"]) * swing[axis]
    knee2_width[axis] = rng.uniform(*r["knee2_width_c"])
    centre = rng.uniform(*r["knee2_c"])
    while abs(centre - model.knee_c[axis]) < r["knee2_min_separation_c"][0]:
        centre = rng.uniform(*r["knee2_c"])
    knee2_c[axis] = centre
    sign = lambda: rng.choice([-1.0, 1.0], size=N_AXES)  # noqa: E731
    rate_gain = sign() * rng.uniform(*r["rate_gain_abs_deg_per_c"], N_AXES)
    rate_temp_gain = sign() * rng.uniform(*r["rate_temp_gain_share"], N_AXES) * np.abs(rate_gain)
    axis_lag = rng.uniform(*r["axis_lag_s"], N_AXES)
    coupling = rng.choice([-1.0, 1.0], size=(N_AXES, N_AXES)) * rng.uniform(*r["coupling_abs"], (N_AXES, N_AXES))
    np.fill_diagonal(coupling, 0.0)
    turn_on_std = rng.uniform(*r["turn_on_bias_std_dps"], N_AXES)

    wider = dataclasses.replace(model, knee_width_c=knee_width, knee2_dps=knee2, knee2_c=knee2_c,
                                knee2_width_c=knee2_width, rate_gain_deg_per_c=rate_gain,
                                rate_temp_gain_deg_per_c=rate_temp_gain)
    # each axis back to today's swing, then the coupling
    scale = swing / wider.swing_dps()
    wider = dataclasses.replace(wider, poly_dps=wider.poly_dps * scale[:, None], knee_dps=wider.knee_dps * scale,
                                knee2_dps=wider.knee2_dps * scale)
    log.debug("survey sensor %d: knees %s degC wide, second knee on axis %d", sensor_seed, knee_width, axis)
    return dataclasses.replace(wider, axis_lag_s=axis_lag, coupling=coupling, turn_on_bias_std_dps=turn_on_std)
