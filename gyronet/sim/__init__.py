"""Simulated static MEMS gyro in a thermal chamber, with its ground truth.

The model, in the order it is computed:

1. **Chamber** (:mod:`.profiles`): ``paper`` (60 -> -40 degC at 1 degC/min with 1 h dwells
   every 10 degC, 12.67 h), ``cycle``, ``random`` or ``constant``.
2. **Die temperature** (:mod:`.sensor`): the chamber through a first-order lag of
   ``thermal_tau_s`` (200-500 s) plus self-heating ``self_heating_c (1 - exp(-t/warmup_tau_s))``.
   The recording's ``temp_c`` is that plus noise, quantised (0.0625 degC).
3. **Drift** per axis, deg/s, with ``x = (T - 10) / 50`` and the true die rate ``Tdot``::

       drift = offset + p1 x + p2 x^2 + p3 x^3 + knee tanh((T - knee_c) / knee_width_c)
               + (g + h x) Tdot  [+ the optional effects of :mod:`.effects`]

   1.2-3.8 deg/s of swing over -40..60 degC, a tanh knee a cubic cannot follow, 0.05-0.3 deg/s
   of dT/dt terms at 1 degC/min; all coefficients drawn from ``sensor_seed``.
4. **Noise** (:mod:`.noise`): white (ARW ``N``), flicker (bias instability ``B``, Allan plateau
   0.664 B) and random-walk (``K``) rate noise, then output quantisation.
5. **True rate**: the Earth rate (15.041 deg/h at a latitude and orientation) plus optional
   rate steps.

6. **Run** (:mod:`.run`, all off by default): a turn-on bias drawn per run ``seed``, the
   fixture's orientation (which axis is along gravity) and a g-sensitivity matrix of the sensor,
   averaging to a lower rate (``decimate``) and lost rows (``loss``).

``gyro = true_rate + drift + noise`` holds per sample, with the quantisation error counted in the
noise; the turn-on bias and the g-sensitivity term are part of the drift (and in their own truth
columns too).

May import: ``gyronet.errors``, ``gyronet.atomic``, ``gyronet.recordings``.
"""
from gyronet.sim.core import (AccelSpec, EarthSpec, Simulation, TemperatureSpec, rate_steps_dps,
                              simulate, write_simulation)
from gyronet.sim.effects import EFFECTS, apply_effect, play_operator
from gyronet.sim.noise import (NoiseSpec, earth_rate_dps, flicker_rate_noise_dps, gravity_g,
                               gyro_noise_dps, quantise, rate_random_walk_dps, white_rate_noise_dps)
from gyronet.sim.profiles import PROFILES, chamber_profile
from gyronet.sim.run import ORIENTATIONS_DEG, decimate_columns, g_sensitivity_matrix, loss_mask, turn_on_bias_dps
from gyronet.sim.draw import draw_sensor
from gyronet.sim.sensor import SensorModel, first_order_lag

__all__ = [
    "AccelSpec", "EFFECTS", "EarthSpec", "NoiseSpec", "ORIENTATIONS_DEG", "PROFILES", "SensorModel",
    "Simulation", "TemperatureSpec", "apply_effect", "chamber_profile", "decimate_columns",
    "draw_sensor", "earth_rate_dps", "first_order_lag", "flicker_rate_noise_dps",
    "g_sensitivity_matrix", "gravity_g", "gyro_noise_dps", "loss_mask", "play_operator", "quantise",
    "rate_random_walk_dps", "rate_steps_dps", "simulate", "turn_on_bias_dps",
    "white_rate_noise_dps", "write_simulation",
]
