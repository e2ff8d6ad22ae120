"""What changes from one run of a sensor to the next: turn-on bias, orientation, lost and averaged samples.

Real calibration comes as campaigns of runs of one unit (cats-tag: one run per orientation), and
a compensator trained on one run meets the next run's own offset. These are the run-level parts of
:func:`gyronet.sim.simulate`, all off by default (the simulation is then bit for bit what it was):

==================== =================================================================================
setting              what it does
==================== =================================================================================
``sensor.turn_on_    standard deviation (deg/s, one or three values) of a constant offset per axis,
bias_dps``           drawn from the run's ``seed``: a new one each power-up, unlike the repeatable
                     temperature curve drawn from ``sensor_seed``
``sensor.g_sensiti   the sensor's g-sensitivity matrix ``G`` (deg/s per g), drawn from ``sensor_seed``
vity_dps_per_g``     with this standard deviation per entry (one number), or given as a 3x3 matrix;
                     the drift gains ``G @ f``, ``f`` the specific force of the run's orientation (g)
``orientation``      ``z_up``, ``z_down``, ``y_up``, ``y_down``, ``x_up``, ``x_down``: which axis points
                     along gravity (``*_down``: that accelerometer reads -1 g, as in the cats-tag
                     names); it turns the Earth rate, the accelerometer and ``G @ f`` accordingly
``run_bump_dps``     standard deviation (deg/s, one or three values) of a bump per axis in the die
                     temperature that this run has and the next does not (one Gaussian, 1-3 degC wide,
                     centred where the run's temperatures are, drawn from the run's ``seed``): what
                     the real cats-tag x axis shows (a fall of about 0.17 deg/s at 5.5-8 degC in one
                     run only), and what a model fitted to one run adds to the next
``run_settle_dps``   standard deviation (deg/s, one or three values) of a settling per axis after this
                     run's power-up, ``amplitude * exp(-t / tau)``, tau uniform in 10-40 min, amplitude and
                     tau drawn from the run's ``seed``: what the real cats-tag y axis shows (its
                     residual moves by about +50 mdps over the first half hour of one run and -20 mdps
                     in the other), and what biases an offset measured just after power-up
``decimate``         average every ``decimate`` samples into one (e.g. 20 Hz to 1 Hz with 20), every
                     recording and truth column alike, as the real data were resampled
``loss``             ``{fraction, bursts_per_h, burst_s}``: rows dropped from the written recording
                     (single samples at random, plus bursts of about ``burst_s`` seconds), and the
                     same rows from the truth
==================== =================================================================================

The turn-on bias, the g-sensitivity term, the run's bump and its settling are part of the truth's ``drift_*`` (what a
compensator must remove, so ``gyro = true_rate + drift + noise`` still holds), and are also written on their own
as ``turn_on_bias_*_dps``, ``g_sensitivity_*_dps``, ``run_bump_*_dps`` and ``run_settle_*_dps``: none repeats
from run to run, so a model of temperature trained on other runs cannot predict them; a per-run offset
(``startup.still_s``) removes the first two, nothing removes the bump, and the settling biases the offset itself.
``drift - turn_on_bias - g_sensitivity - run_bump - run_settle`` is what the runs of one sensor share.
"""
from __future__ import annotations

import logging
from typing import Any, Mapping

import numpy as np

from gyronet.errors import GyronetError
from gyronet.sim.sensor import N_AXES, per_axis

log = logging.getLogger(__name__)

# (roll, pitch, yaw) from East-North-Up, degrees (gyronet.sim.noise.body_from_enu): which body axis
# is along Up (``*_up``: that accelerometer reads +1 g) or along Down (``*_down``: -1 g)
ORIENTATIONS_DEG = {
    "z_up": (0.0, 0.0, 0.0), "z_down": (180.0, 0.0, 0.0),
    "y_up": (90.0, 0.0, 0.0), "y_down": (-90.0, 0.0, 0.0),
    "x_up": (0.0, -90.0, 0.0), "x_down": (0.0, 90.0, 0.0),
}
LOSS_KEYS = ("fraction", "bursts_per_h", "burst_s")


def orientation_deg(name: str | None, earth_orientation_deg: Any) -> tuple[float, float, float]:
    """The (roll, pitch, yaw) of a named orientation, or the earth spec's when ``name`` is None."""
    if name is None:
        return tuple(float(v) for v in earth_orientation_deg)  # type: ignore[return-value]
    if name not in ORIENTATIONS_DEG:
        raise GyronetError(f"unknown orientation {name!r}; known: {', '.join(ORIENTATIONS_DEG)}")
    if any(float(v) != 0.0 for v in earth_orientation_deg):
        raise GyronetError(f"orientation={name} and earth.orientation_deg={list(earth_orientation_deg)}: "
                           "give one of them")
    return ORIENTATIONS_DEG[name]


def turn_on_bias_dps(seed: int, std_dps: Any, sensor_seed: int | None = None) -> np.ndarray:
    """This run's constant offset per axis, shape (3,), deg/s: normal of ``std_dps``, from ``seed``.

    With ``sensor_seed`` (the survey distribution's own spread) the draw is of the pair, so that
    sensors simulated with the same run seeds do not share their turn-on biases' signs and sizes.
    """
    std = per_axis(std_dps, "sensor.turn_on_bias_dps")
    if np.any(std < 0):
        raise GyronetError(f"sensor.turn_on_bias_dps must be >= 0, got {std_dps!r}")
    # its own stream: the noise, the profile and the effects keep theirs
    key = [int(seed), 8] if sensor_seed is None else [int(seed), int(sensor_seed), 8]
    return std * np.random.default_rng(key).standard_normal(N_AXES)


def run_bump_dps(seed: int, std_dps: Any, die_c: np.ndarray, sensor_seed: int = 0) -> np.ndarray:
    """This run's own bump in temperature, shape (n, 3), deg/s: per axis a Gaussian of amplitude normal(0, ``std_dps``).

    Centre uniform between the 5th and 95th percentiles of the run's die temperature, 1-sigma
    width uniform in 1-3 degC; drawn from the pair (``seed``, ``sensor_seed``) on a stream of its own.
    """
    std = per_axis(std_dps, "sensor.run_bump_dps")
    if np.any(std < 0):
        raise GyronetError(f"sensor.run_bump_dps must be >= 0, got {std_dps!r}")
    rng = np.random.default_rng([int(seed), int(sensor_seed), 10])
    low, high = np.percentile(die_c, [5.0, 95.0])
    amplitude, centre_c, width_c = std * rng.standard_normal(N_AXES), rng.uniform(low, high, N_AXES), \
        rng.uniform(1.0, 3.0, N_AXES)
    return amplitude * np.exp(-0.5 * ((np.asarray(die_c)[:, None] - centre_c) / width_c) ** 2)


def run_settle_dps(seed: int, std_dps: Any, time_s: np.ndarray, sensor_seed: int = 0) -> np.ndarray:
    """This run's settling after power-up, shape (n, 3), deg/s: per axis normal(0, ``std_dps``) * exp(-t / tau).

    tau uniform in 600-2400 s per axis, t from the run's first sample; drawn from the pair (``seed``,
    ``sensor_seed``) on a stream of its own.
    """
    std = per_axis(std_dps, "sensor.run_settle_dps")
    if np.any(std < 0):
        raise GyronetError(f"sensor.run_settle_dps must be >= 0, got {std_dps!r}")
    rng = np.random.default_rng([int(seed), int(sensor_seed), 11])
    amplitude, tau_s = std * rng.standard_normal(N_AXES), rng.uniform(600.0, 2400.0, N_AXES)
    elapsed_s = np.asarray(time_s, dtype=float) - float(time_s[0])
    return amplitude * np.exp(-elapsed_s[:, None] / tau_s)


def g_sensitivity_matrix(sensor_seed: int, value: Any) -> np.ndarray:
    """The sensor's g-sensitivity, shape (3, 3), deg/s per g: rows gyro axes, columns force axes.

    One number is the standard deviation of each entry, drawn from ``sensor_seed`` (the same
    sensor has the same matrix in every run); nine numbers (3x3) are the matrix itself.
    """
    array = np.asarray(value, dtype=float)
    if array.shape == (N_AXES, N_AXES):
        return array.copy()
    if array.ndim != 0 or array < 0:
        raise GyronetError(f"sensor.g_sensitivity_dps_per_g must be a number >= 0 or a 3x3 matrix, got {value!r}")
    # a stream of the sensor's own, apart from draw_sensor's (whose draws stay as they were)
    return float(array) * np.random.default_rng([int(sensor_seed), 7002]).standard_normal((N_AXES, N_AXES))


def decimate_columns(columns: Mapping[str, np.ndarray], factor: int) -> dict[str, np.ndarray]:
    """Average every ``factor`` consecutive rows of every column (a partial last group is dropped).

    ``time_s`` becomes each group's mean time; a linear identity between columns (``gyro = true_rate
    + drift + noise``) survives averaging.
    """
    factor = int(factor)
    if factor < 1:
        raise GyronetError(f"decimate must be a whole number >= 1, got {factor}")
    if factor == 1:
        return dict(columns)
    n = len(next(iter(columns.values()))) // factor * factor
    if n == 0:
        raise GyronetError(f"decimate={factor} leaves no sample of a record this short")
    return {k: np.asarray(v, dtype=float)[:n].reshape(-1, factor).mean(axis=1) for k, v in columns.items()}


def loss_mask(n: int, fs_hz: float, rng: np.random.Generator, fraction: float = 0.0,
              bursts_per_h: float = 0.0, burst_s: float = 10.0) -> np.ndarray:
    """Which of ``n`` rows are kept, shape (n,) bool.

    Parameters
    ----------
    n, fs_hz
        Rows and their rate, Hz (after decimation).
    rng
        The run's own random stream.
    fraction
        Each row is lost independently with this probability.
    bursts_per_h
        Mean number of burst losses an hour (Poisson), each of an exponential length of mean
        ``burst_s`` seconds (at least one row). The first and last rows are always kept, so the
        record keeps its length.
    """
    if not 0.0 <= fraction < 1.0 or bursts_per_h < 0 or burst_s <= 0:
        raise GyronetError(f"loss needs 0 <= fraction < 1, bursts_per_h >= 0, burst_s > 0; got "
                           f"fraction={fraction}, bursts_per_h={bursts_per_h}, burst_s={burst_s}")
    keep = rng.random(n) >= fraction
    n_bursts = rng.poisson(bursts_per_h * n / fs_hz / 3600.0)
    starts = rng.integers(0, n, n_bursts)
    lengths = np.maximum(1, np.round(rng.exponential(burst_s * fs_hz, n_bursts))).astype(int)
    for start, length in zip(starts, lengths):
        keep[start:start + length] = False
    keep[[0, -1]] = True
    return keep


def lose_rows(recording: dict[str, np.ndarray], truth: dict[str, np.ndarray], fs_hz: float, seed: int,
              loss: Mapping[str, Any] | None) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """Drop the same rows from the recording and the truth (``loss`` as in :func:`loss_mask`)."""
    options = dict(loss or {})
    unknown = sorted(set(options) - set(LOSS_KEYS))
    if unknown:
        raise GyronetError(f"unknown loss option(s) {', '.join(unknown)}; known: {', '.join(LOSS_KEYS)}")
    if not options.get("fraction", 0.0) and not options.get("bursts_per_h", 0.0):
        return recording, truth
    n = len(recording["time_s"])
    keep = loss_mask(n, fs_hz, np.random.default_rng([int(seed), 9]), **options)
    log.info("sample loss: %d of %d rows dropped", n - int(keep.sum()), n)
    return {k: v[keep] for k, v in recording.items()}, {k: v[keep] for k, v in truth.items()}
