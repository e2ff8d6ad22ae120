"""The error each flight stack's users get from a cubic: PX4's 1 Hz / 1 degC offset schedule, ArduPilot's boot calibration.

PX4 does not apply its cubic per sample. Read from PX4-Autopilot's source as the fork
m4v3r/PX4-Arrow holds it at 86822171b9 (2023-08; lines below are that commit's), and the same
logic in PX4-Autopilot main (``TemperatureCompensation.cpp`` at 09f282b282,
``TemperatureCompensationModule.cpp`` at 023e613467, ``Gyroscope.cpp`` at 04214a347e):

- ``src/modules/temperature_compensation/TemperatureCompensationModule.cpp``: ``init()`` runs the
  module on a 1 s interval (line 384, ``ScheduleOnInterval(1_s)``); each run, ``gyroPoll()`` takes
  the newest ``sensor_gyro`` sample, if there is one since the last run (line 173,
  ``_gyro_subs[uorb_index].update()``), and calls ``update_offsets_gyro`` with its temperature (line
  176); ``Run()`` publishes ``sensor_correction`` only when an update returned 2 (lines 348-353).
- ``src/modules/temperature_compensation/TemperatureCompensation.cpp`` ``update_offsets_gyro``
  (lines 448-472): the offset is recomputed (``calc_thermal_offsets_3D``, line 463) at every run,
  but it returns 2 (publish) only if ``fabsf(temperature - last_temperature) > 1.0f`` (line 466),
  and then sets ``last_temperature`` to this temperature (line 467). ``TemperatureCompensation.h``
  ``PerSensorData``: ``last_temperature`` starts at -100 degC (line 269), and ``reset_temperature()``
  (line 276, called from ``parameters_update``, ``TemperatureCompensation.cpp`` line 298) sets it
  back on every parameter change, so the first run publishes.
- ``src/lib/sensor_calibration/Gyroscope.cpp`` ``SensorCorrectionsUpdate`` (lines 72-99): the
  consumer copies the published offset into ``_thermal_offset``; ``Gyroscope.hpp`` ``Correct()``
  (line 83) subtracts it from every sample until the next publication.

So between publications the offset of the last published temperature is held, and the sample
the module read was already corrected (the gyro's own work queue runs first), so a new offset
applies from the next sample on. One more rule, not emulated: the offsets are written into the
shared ``sensor_correction`` message at every run, so a publication triggered by the accel or
baro compensation (``TC_A_ENABLE``, ``TC_B_ENABLE``, which gyronet's export leaves alone) also
carries the gyro's newest offset; with them enabled the gyro's offset is at least this fresh.

ArduPilot (ArduPilot/ardupilot at b44478217f: ``libraries/AP_InertialSensor/AP_InertialSensor_tempcal.cpp``
``correct_sensor``, and ``AP_InertialSensor_Backend.cpp`` ``_rotate_and_correct_gyro``): rate -= p(T) - p(T_cal), both
temperatures clamped to [TMIN, TMAX], then the boot gyro calibration's offset (measured at T_cal
with no correction applied) is removed. Against the bundle's curve b the user gets
e(T) - e(T_cal), e = p - b: the constant cancels, and the bound over T and T_cal is max e - min e.
"""
from __future__ import annotations

import logging

from typing import Any, Callable, Mapping

import numpy as np
from scipy.ndimage import maximum_filter1d, minimum_filter1d
from scipy.optimize import linprog

from gyronet.bundle.compensator import Compensated
from gyronet.errors import GyronetError

log = logging.getLogger(__name__)

PX4_PERIOD_S = 1.0  # TemperatureCompensationModule.cpp init(): ScheduleOnInterval(1_s)
PX4_THRESHOLD_C = 1.0  # TemperatureCompensation.cpp update_offsets_gyro: fabsf(dT) > 1.0f
PX4_START_TEMP_C = -100.0  # TemperatureCompensation.h PerSensorData: last_temperature = -100.0f
# bundles whose drift is PX4's cubic in temperature alone (TempPolynomial is model=poly3)
PX4_CLASSES = ("TempPolynomial", "Px4Cubic", "Px4Onboard")
# the temperature rate the stated PX4 bound allows for between two runs (1 degC/min, a chamber's)
DEFAULT_TEMP_RATE_C_PER_S = 1.0 / 60.0


def px4_published_index(time_s: np.ndarray, temp_c: np.ndarray, period_s: float = PX4_PERIOD_S,
                        threshold_c: float = PX4_THRESHOLD_C) -> np.ndarray:
    """For each sample, the index of the sample whose temperature set the offset PX4's firmware applies to it.

    The module runs at ``time_s[0]``, then every ``period_s``; a run reads the newest sample at or
    before it (none new: nothing happens) and publishes when its float32 temperature differs from
    the last published one by more than ``threshold_c``; the first run publishes (the firmware's
    last temperature starts at -100 degC). A publication applies from the sample after the one
    read; the first, read at the first sample, applies to it too (the module runs from boot, and
    a record starts after it). Causal: an index never exceeds its sample's.

    Parameters
    ----------
    time_s
        Sample times, s, increasing (gaps allowed: the 1 s clock runs on through them), shape (n,).
    temp_c
        The sensor's temperature, degC, shape (n,).
    period_s, threshold_c
        PX4's 1 s and 1 degC.

    Returns
    -------
    np.ndarray
        int64 (n,): index of the sample whose temperature the applied offset was computed at.
    """
    time_s = np.asarray(time_s, dtype=np.float64)
    temp = np.asarray(temp_c, dtype=np.float32)
    if time_s.shape != temp.shape or time_s.ndim != 1 or len(time_s) == 0:
        raise GyronetError(f"px4 schedule: time_s and temp_c must be two arrays of one length > 0, got "
                           f"{time_s.shape} and {temp.shape}")
    if period_s <= 0 or threshold_c < 0:
        raise GyronetError(f"px4 schedule: period_s must be > 0 and threshold_c >= 0, got {period_s}, {threshold_c}")
    n_runs = int(np.floor((time_s[-1] - time_s[0]) / period_s)) + 1
    run_times = time_s[0] + period_s * np.arange(n_runs)
    # the newest sample at or before each run
    read = np.searchsorted(time_s, run_times, side="right") - 1
    threshold = np.float32(threshold_c)
    last_c = np.float32(PX4_START_TEMP_C)
    previous = -1
    starts, sources = [], []
    for index in read.tolist():
        if index == previous:  # no new sensor_gyro sample since the last run
            continue
        previous = index
        # TemperatureCompensation.cpp: if (fabsf(temperature - last_temperature) > 1.0f) publish
        if np.abs(temp[index] - last_c) > threshold:
            last_c = temp[index]
            sources.append(index)
            starts.append(0 if not starts else index + 1)
    # sources increase with starts, so each sample's newest publication is a running maximum
    marks = np.full(len(time_s), -1, dtype=np.int64)
    marks[np.asarray(starts, dtype=np.int64)] = sources
    return np.maximum(np.maximum.accumulate(marks), 0)


def px4_as_run(time_s: np.ndarray, temp_c: np.ndarray, offset_dps: np.ndarray, **schedule) -> np.ndarray:
    """The per-sample offset ``offset_dps`` (n, k) as PX4's firmware applies it: held from each publication."""
    return np.asarray(offset_dps)[px4_published_index(time_s, temp_c, **schedule)]


def is_px4_cubic(meta: Mapping[str, Any]) -> bool:
    """Whether a bundle is a cubic in temperature alone that PX4's firmware would run (poly3, px4, px4_onboard)."""
    model = meta.get("model", {})
    cubic = model.get("class") in PX4_CLASSES and int(model.get("degree", 3)) == 3
    return bool(cubic and not meta.get("kalman"))


def px4_firmware_output(time_s: np.ndarray, temp_c: np.ndarray, out: Compensated, **schedule) -> Compensated:
    """A PX4 cubic bundle's compensated output as the firmware gives it: the drift held from each publication.

    ``out`` is the bundle's per-sample output (``is_px4_cubic``: its drift is a function of the
    temperature alone, so the drift at the publication's sample is the offset PX4 computed there).
    """
    held_dps = px4_as_run(time_s, temp_c, out.drift_dps, **schedule)
    return out._replace(rate_dps=out.rate_dps + out.drift_dps - held_dps, drift_dps=held_dps)


def _held_error_range(grid_c: np.ndarray, cubic_dps: np.ndarray, curve_dps: np.ndarray,
                      step_c: float) -> tuple[np.ndarray, np.ndarray]:
    """Per temperature T of the grid, the highest and lowest cubic(T') - curve(T) with |T' - T| <= ``step_c``."""
    spacing_c = float(grid_c[1] - grid_c[0])
    size = 2 * int(np.ceil(step_c / spacing_c - 1e-9)) + 1
    # mode="nearest": T' beyond the grid is its edge, as PX4 clamps to [TMIN, TMAX]
    highest = maximum_filter1d(cubic_dps, size, axis=0, mode="nearest")
    lowest = minimum_filter1d(cubic_dps, size, axis=0, mode="nearest")
    return highest - curve_dps, lowest - curve_dps


def px4_schedule_error(grid_c: np.ndarray, cubic_dps: np.ndarray, curve_dps: np.ndarray,
                       step_c: float) -> np.ndarray:
    """Largest |cubic(T') - curve(T)| over the grid with |T' - T| <= ``step_c``, per axis: the held offset's bound.

    Parameters
    ----------
    grid_c
        Equally spaced temperatures, degC (n,), over [TMIN, TMAX] (T' is clamped to it, as PX4 does).
    cubic_dps, curve_dps
        The exported cubic and the bundle's curve on the grid, (n, 3).
    step_c
        How far the temperature can move from the last published one: 1 degC plus the rate times 1 s.
    """
    high, low = _held_error_range(grid_c, cubic_dps, curve_dps, step_c)
    return np.maximum(np.abs(high), np.abs(low)).max(0)


def px4_calibrated_error(grid_c: np.ndarray, cubic_dps: np.ndarray, curve_dps: np.ndarray,
                         step_c: float) -> np.ndarray:
    """The held offset's bound after a PX4 gyro calibration at T_cal: e(T) - e(T_cal), both held, per axis.

    PX4's gyro calibrations average the rate with the thermal offset already subtracted
    (``src/modules/commander/gyro_calibration.cpp`` lines 114-117; the online one, on by default,
    ``IMU_GYRO_CAL_EN`` = 1, whenever the vehicle is disarmed and still:
    ``src/modules/gyro_calibration/GyroCalibration.cpp`` line 152), so ``CAL_GYROn_OFF`` takes up
    e(T_cal) and PX4 users get ArduPilot's difference form, with the held offsets.
    """
    high, low = _held_error_range(grid_c, cubic_dps, curve_dps, step_c)
    return high.max(0) - low.min(0)


def _axes(values: np.ndarray) -> dict[str, float]:
    return dict(zip(("x", "y", "z"), np.asarray(values, dtype=np.float64).tolist()))


def px4_stated_error(grid_c: np.ndarray, cubic_dps: np.ndarray, curve_dps: np.ndarray,
                     temp_rate_c_per_s: float = DEFAULT_TEMP_RATE_C_PER_S) -> dict[str, Any]:
    """The sidecar's ``px4_firmware`` block: the bound on the held offset's error against the bundle's curve."""
    if not np.isfinite(temp_rate_c_per_s) or temp_rate_c_per_s < 0:
        raise GyronetError(f"temp_rate_c_per_s must be a rate >= 0 in degC/s, got {temp_rate_c_per_s}")
    # a run sees at most 1 degC since the last publication; up to 1 s later the next run reads the sample
    step_c = PX4_THRESHOLD_C + temp_rate_c_per_s * PX4_PERIOD_S
    return {"period_s": PX4_PERIOD_S, "threshold_c": PX4_THRESHOLD_C, "temp_rate_c_per_s": temp_rate_c_per_s,
            "temp_step_c": step_c,
            "max_error_dps": _axes(px4_schedule_error(grid_c, cubic_dps, curve_dps, step_c)),
            "after_gyro_calibration_max_error_dps": _axes(px4_calibrated_error(grid_c, cubic_dps, curve_dps, step_c)),
            "source": "PX4 TemperatureCompensationModule.cpp (1 s schedule), TemperatureCompensation.cpp "
                      "update_offsets_gyro (published when |T - T_published| > 1 degC)"}


def history_error(time_s: np.ndarray, temp_c: np.ndarray, cubic: Callable[[np.ndarray], np.ndarray],
                  curve_dps: np.ndarray, stack: str) -> dict[str, Any]:
    """The exported cubic's error against the bundle's steady curve on a recording's temperature history.

    ``px4``: per sample, and as the firmware runs it (``px4_published_index``); ``ardupilot``: the
    difference form e(T) - e(T_cal) with the boot calibration at the first sample.
    """
    per_sample = cubic(temp_c) - curve_dps
    found: dict[str, Any] = {}
    if stack == "px4":
        temp_c = np.asarray(temp_c, dtype=np.float64)
        published_c = temp_c[px4_published_index(time_s, temp_c)]
        as_run = cubic(published_c) - curve_dps
        forms = {"per_sample": per_sample, "as_run": as_run, "schedule_only": as_run - per_sample}
        # more than px4_firmware's temp_step_c where the reading moves in steps (a quantum past 1 degC)
        found["temp_step_c"] = float(np.abs(temp_c - published_c).max())
    else:
        forms = {"difference": per_sample - per_sample[0]}
    for name, values in forms.items():
        found[name] = {"max_error_dps": _axes(np.abs(values).max(0)),
                       "rms_error_dps": _axes(np.sqrt(np.mean(values**2, 0)))}
    return found


def difference_error(error_dps: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """ArduPilot's error e(T) - e(T_cal) from e on a grid (n, 3): its bound (max - min) and RMS over all pairs.

    The RMS over every (T, T_cal) pair of the grid is sqrt(2) times the standard deviation of e.
    """
    error_dps = np.asarray(error_dps, dtype=np.float64)
    return np.ptp(error_dps, axis=0), np.sqrt(2.0) * error_dps.std(axis=0)


def minimax_cubic(delta_c: np.ndarray, target_dps: np.ndarray) -> np.ndarray:
    """The cubic (4, k) in ``delta_c`` whose largest error against each column of ``target_dps`` is least.

    That minimises ArduPilot's bound max e - min e, since the constant is free: shifting it moves
    max e and min e alike, and the minimax cubic centres them. A linear programme per column
    (minimise t subject to |V c - y| <= t, scipy's HiGHS); the powers are scaled to [-1, 1] first.

    References
    ----------
    Cheney, E. W., Introduction to Approximation Theory, ch. 2 (best uniform approximation).
    """
    delta = np.asarray(delta_c, dtype=np.float64)
    scale = max(float(np.abs(delta).max()), 1e-12)
    design = np.vander(delta / scale, 4, increasing=True)
    target = np.asarray(target_dps, dtype=np.float64).reshape(len(delta), -1)
    coef = np.empty((4, target.shape[1]))
    # variables (c0..c3, t): minimise t; V c - t <= y and -V c - t <= -y
    ones = np.ones((len(delta), 1))
    bounds = [(None, None)] * 4 + [(0, None)]
    for column in range(target.shape[1]):
        y = target[:, column]
        size = max(float(np.abs(y).max()), 1e-300)
        result = linprog(np.array([0, 0, 0, 0, 1.0]), A_ub=np.block([[design, -ones], [-design, -ones]]),
                         b_ub=np.concatenate([y, -y]) / size, bounds=bounds, method="highs")
        if not result.success:
            raise GyronetError(f"the minimax cubic did not solve on axis {column}: {result.message}")
        coef[:, column] = result.x[:4] * size
    return coef / scale ** np.arange(4)[:, None]


__all__ = ["DEFAULT_TEMP_RATE_C_PER_S", "PX4_CLASSES", "PX4_PERIOD_S", "PX4_START_TEMP_C", "PX4_THRESHOLD_C",
           "difference_error", "history_error", "is_px4_cubic", "minimax_cubic", "px4_as_run", "px4_calibrated_error",
           "px4_firmware_output", "px4_published_index", "px4_schedule_error", "px4_stated_error"]
