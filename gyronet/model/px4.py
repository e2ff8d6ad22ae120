"""PX4's two gyro thermal calibrations as PX4 users get them: the offline script and the onboard rule.

Both are per-axis cubics in (T - T_ref), applied as PX4's firmware applies them (the temperature
clamped to [T_min, T_max], the offset subtracted); they differ from ``TempPolynomial`` (poly3, plain
least squares on what it is given) only in how the four coefficients and the three temperatures
are found. Written from PX4-Autopilot at commit af44da25f0 (2022-09-27; the file is the same in
the fork m4v3r/PX4-Arrow at 86822171b9), cited by file and line:

- ``Tools/process_sensor_caldata.py`` (``Px4Cubic``, ``model=px4``): T_min, T_max from the raw
  temperatures and T_ref halfway (lines 670-672); a 31-sample median filter of each axis (lines
  67-68, 678-680: ``scipy.signal.medfilt``, which pads the ends with zeros); then, unless
  ``--no_resample``, the samples are averaged into 2000 equal temperature bins between the lowest
  and highest T - T_ref, empty bins dropped (``resampleWithDeltaX``, lines 36-65), and a cubic is
  fitted by least squares to the bin means (``np.polyfit``, lines 682-715), each bin counting once
  however many samples it holds: a dwell weighs as little as the ramp through it.
- ``src/modules/temperature_compensation/temperature_calibration/gyro.cpp`` (``Px4Onboard``,
  ``model=px4_onboard``): samples below SYS_CAL_TMIN are skipped (lines 91-94); the first one
  after 10 s since boot is the cold-soak point, refused if above SYS_CAL_TMAX (lines 96-114), and
  sets T_min = T_max = its temperature and T_ref = T_min + SYS_CAL_TDEL / 2 (lines 105-107); from
  then on only a sample that is a new highest temperature is used (lines 116-123) until T_max -
  T_min exceeds SYS_CAL_TDEL (lines 126-128; its ``hot_soak_sat`` counter is never incremented);
  the cubic is ordinary least squares (``polyfit.hpp``, normal equations in double), stored as
  float parameters (lines 196-212). A run that never rises far enough writes no calibration.
- ``src/modules/temperature_compensation/TemperatureCompensation.cpp``
  ``calc_thermal_offsets_3D`` (lines 341-370): the measured temperature clipped to [T_min, T_max],
  offset = X0 + X1 dT + X2 dT^2 + X3 dT^3; ``src/lib/sensor_calibration/Gyroscope.hpp``
  ``Correct()`` (line 83) subtracts it: the forward of ``TempPolynomial``.

Temperatures are taken as float32, the type of ``sensor_gyro.temperature``, and T_ref, the bin
edges and the onboard comparisons are computed in float32 as PX4 computes them (NumPy 2's
promotion for the script), so that every sample falls in PX4's bin.
"""
from __future__ import annotations

import logging

import numpy as np
import torch
from scipy.signal import medfilt
from torch import Tensor

from gyronet.model.baselines import TempPolynomial
from gyronet.errors import GyronetError

log = logging.getLogger(__name__)

MEDIAN_SAMPLES = 31  # process_sensor_caldata.py line 68
N_BINS = 2000  # process_sensor_caldata.py line 39
RAD_PER_DEG = np.pi / 180.0


def median_filter(values: np.ndarray, samples: int = MEDIAN_SAMPLES) -> np.ndarray:
    """Running median of each column over ``samples`` samples, the ends padded with zeros (PX4's medfilt).

    Parameters
    ----------
    values
        Shape (n,) or (n, k), in time order.
    samples
        Odd window length.
    """
    values = np.asarray(values, dtype=np.float64)
    if values.ndim == 1:
        return medfilt(values, samples)
    return np.column_stack([medfilt(column, samples) for column in values.T])


def temperature_bins(temp_rel_c: np.ndarray, values: np.ndarray,
                     n_bins: int = N_BINS) -> tuple[np.ndarray, np.ndarray]:
    """Means of temperature and values in ``n_bins`` equal bins of the temperature span, empty bins dropped.

    Parameters
    ----------
    temp_rel_c
        float32 temperatures relative to T_ref, shape (n,); the bin of a sample is
        floor((T - T_low) / width) in float32, the highest temperature in the last bin.
    values
        Shape (n, k).

    Returns
    -------
    tuple
        Bin mean temperatures (m,) and bin mean values (m, k), in order of temperature.
    """
    temp = np.asarray(temp_rel_c, dtype=np.float32)
    low, high = temp.min(), temp.max()
    width = (high - low) / np.float32(n_bins)
    index = np.full(len(temp), n_bins - 1, dtype=np.int64)
    below = temp < high
    if width > 0:
        index[below] = np.minimum(np.floor((temp[below] - low) / width).astype(np.int64), n_bins - 1)
    counts = np.bincount(index, minlength=n_bins)
    used = counts > 0
    temp_means = np.bincount(index, weights=temp.astype(np.float64), minlength=n_bins)[used] / counts[used]
    values = np.asarray(values, dtype=np.float64).reshape(len(temp), -1)
    sums = np.stack([np.bincount(index, weights=v, minlength=n_bins) for v in values.T], axis=1)
    return temp_means, sums[used] / counts[used, None]


def cubic_least_squares(temp_rel_c: np.ndarray, values: np.ndarray) -> np.ndarray:
    """Coefficients (4, k), lowest power first, of the least-squares cubic in ``temp_rel_c`` per column."""
    design = np.vander(np.asarray(temp_rel_c, dtype=np.float64), 4, increasing=True)
    return np.linalg.lstsq(design, np.asarray(values, dtype=np.float64), rcond=None)[0]


class _Px4Polynomial(TempPolynomial):
    """A cubic with PX4's clamp and sign; subclasses say how the coefficients are found."""

    def __init__(self, n_inputs: int, n_outputs: int = 3, temp_index: int = 0):
        super().__init__(n_inputs, n_outputs, degree=3, temp_index=temp_index)

    def _set(self, temp_min_c: float, temp_max_c: float, temp_ref_c: float, coef: np.ndarray) -> None:
        self.temp_min_c.fill_(float(temp_min_c))
        self.temp_max_c.fill_(float(temp_max_c))
        self.temp_ref_c.fill_(float(temp_ref_c))
        self.coef.copy_(torch.as_tensor(coef, dtype=torch.float64))

    def _temperature(self, x: Tensor) -> np.ndarray:
        return x[:, self.temp_index].detach().cpu().numpy().astype(np.float32)


class Px4Cubic(_Px4Polynomial):
    """PX4's offline thermal calibration (``process_sensor_caldata.py``): median filter, 2000 temperature bins, cubic.

    Fitted on every sample it is given, in time order (``conf/model/px4.yaml`` gives it the whole
    recording at its full rate, as PX4's script reads a whole log).

    Parameters
    ----------
    n_inputs, n_outputs, temp_index
        As ``TempPolynomial``; only the temperature input is read.
    resample
        False: PX4's ``--no_resample`` (the median-filtered samples themselves are fitted).
    median_samples, n_bins
        PX4's 31 and 2000.
    """

    linear_in_target = False  # the median filter: run offsets cannot be solved jointly with it

    def __init__(self, n_inputs: int, n_outputs: int = 3, temp_index: int = 0, resample: bool = True,
                 median_samples: int = MEDIAN_SAMPLES, n_bins: int = N_BINS):
        super().__init__(n_inputs, n_outputs, temp_index)
        if median_samples < 1 or median_samples % 2 == 0:
            raise GyronetError(f"model.median_samples must be an odd number >= 1, got {median_samples}")
        if n_bins < 4:
            raise GyronetError(f"model.n_bins must be at least 4 (a cubic has 4 coefficients), got {n_bins}")
        self.resample, self.median_samples, self.n_bins = bool(resample), int(median_samples), int(n_bins)

    @torch.no_grad()
    def fit_closed_form(self, x: Tensor, y: Tensor) -> None:
        """T_min, T_max, T_ref = mid-range; median filter; bins (unless ``resample`` is off); least squares."""
        temp = self._temperature(x)
        temp_min, temp_max = temp.min(), temp.max()
        # process_sensor_caldata.py line 672: 0.5 * (TMIN + TMAX), float32 like the temperatures
        temp_ref = np.float32(0.5) * (temp_min + temp_max)
        temp_rel = temp - temp_ref
        filtered = median_filter(y.detach().cpu().numpy(), self.median_samples)
        if self.resample:
            temp_fit, values_fit = temperature_bins(temp_rel, filtered, self.n_bins)
        else:
            temp_fit, values_fit = temp_rel.astype(np.float64), filtered
        if len(temp_fit) < 4:
            raise GyronetError(f"PX4's fit needs at least 4 distinct temperatures, got {len(temp_fit)}")
        self._set(temp_min, temp_max, temp_ref, cubic_least_squares(temp_fit, values_fit))


class Px4Onboard(_Px4Polynomial):
    """PX4's onboard thermal calibration (``gyro.cpp``): rising temperature only, T_ref = start + TDEL / 2.

    Fitted on every sample it is given, in time order, as the firmware sees them.

    Parameters
    ----------
    n_inputs, n_outputs, temp_index
        As ``TempPolynomial``; only the temperature (and time) inputs are read.
    temp_rise_c
        SYS_CAL_TDEL: the rise after the cold-soak point that ends the calibration, degC.
    start_temp_min_c, start_temp_max_c
        SYS_CAL_TMIN, SYS_CAL_TMAX: samples below the first are skipped, a cold-soak point above
        the second is an error, degC.
    settle_s
        The cold-soak point is the first sample at least this long after boot (the record's start).
    time_index
        The input holding the time since the start in hours (feature ``{kind: time}``); -1: none, and
        ``settle_s`` is not applied.
    """

    linear_in_target = False  # one rising sweep's samples in time order: offsets per run have no meaning

    def __init__(self, n_inputs: int, n_outputs: int = 3, temp_index: int = 0, temp_rise_c: float = 24.0,
                 start_temp_min_c: float = 5.0, start_temp_max_c: float = 10.0, settle_s: float = 10.0,
                 time_index: int = -1):
        super().__init__(n_inputs, n_outputs, temp_index)
        if temp_rise_c <= 0:
            raise GyronetError(f"model.temp_rise_c (SYS_CAL_TDEL) must be > 0, got {temp_rise_c}")
        if time_index >= n_inputs:
            raise GyronetError(f"model.time_index {time_index} is not one of the {n_inputs} inputs")
        self.temp_rise_c, self.settle_s, self.time_index = float(temp_rise_c), float(settle_s), int(time_index)
        self.start_temp_min_c, self.start_temp_max_c = float(start_temp_min_c), float(start_temp_max_c)

    def used_samples(self, temp_c: np.ndarray, time_s: np.ndarray | None = None) -> tuple[np.ndarray, float, float]:
        """Which samples gyro.cpp fits (a mask), its T_min and T_ref; a one-line error where it writes no calibration.

        Parameters
        ----------
        temp_c
            Temperatures in time order, degC (taken as float32).
        time_s
            Time since boot, s; None: every sample is past the settling time.
        """
        temp = np.asarray(temp_c, dtype=np.float32)
        warm_enough = temp >= np.float32(self.start_temp_min_c)
        settled = np.ones(len(temp), bool) if time_s is None else np.asarray(time_s) > self.settle_s
        candidates = np.flatnonzero(warm_enough & settled)
        if candidates.size == 0:
            raise GyronetError(f"PX4's onboard calibration never starts: no sample reaches SYS_CAL_TMIN = "
                               f"{self.start_temp_min_c:g} degC (model.start_temp_min_c) after {self.settle_s:g} s")
        start = int(candidates[0])
        low = temp[start]
        if low > np.float32(self.start_temp_max_c):
            raise GyronetError(f"PX4's onboard calibration refuses to start at {float(low):.2f} degC: above "
                               f"SYS_CAL_TMAX = {self.start_temp_max_c:g} degC (model.start_temp_max_c); it needs a "
                               "cold-soaked start and a rising temperature")
        # gyro.cpp line 107: ref_temp = T + 0.5f * min_temperature_rise, in float
        temp_ref = low + np.float32(0.5) * np.float32(self.temp_rise_c)
        after = temp[start + 1:]
        highest_before = np.maximum.accumulate(np.concatenate([[low], after]))[:-1]
        new_high = after > highest_before
        done = np.flatnonzero(new_high & ((after - low) > np.float32(self.temp_rise_c)))
        if done.size == 0:
            rise = float(np.max(after, initial=low) - low)
            raise GyronetError(f"PX4's onboard calibration does not finish: the temperature rises {rise:.2f} degC after "
                               f"the cold-soak point at {float(low):.2f} degC, and it needs more than SYS_CAL_TDEL = "
                               f"{self.temp_rise_c:g} degC (model.temp_rise_c); PX4 writes no parameters then")
        mask = np.zeros(len(temp), bool)
        mask[start + 1:start + 2 + int(done[0])] = new_high[:int(done[0]) + 1]
        return mask, float(low), float(temp_ref)

    @torch.no_grad()
    def fit_closed_form(self, x: Tensor, y: Tensor) -> None:
        """The rising samples only; cubic in T - T_ref by least squares; coefficients rounded to float as stored."""
        temp = self._temperature(x)
        time_s = None if self.time_index < 0 else x[:, self.time_index].detach().cpu().numpy() * 3600.0
        mask, temp_min, temp_ref = self.used_samples(temp, time_s)
        if mask.sum() < 4:
            raise GyronetError(f"PX4's onboard calibration used {int(mask.sum())} samples; a cubic needs at least 4")
        used = temp[mask]
        coef = cubic_least_squares(used.astype(np.float64) - temp_ref, y.detach().cpu().numpy()[mask])
        # gyro.cpp line 201: each coefficient is stored as a float parameter, in rad/s
        coef = (coef * RAD_PER_DEG).astype(np.float32).astype(np.float64) / RAD_PER_DEG
        # gyro.cpp lines 210-212: T_min is the cold-soak point, T_max the last sample used
        self._set(temp_min, used.max(), temp_ref, coef)
        log.info("PX4 onboard rule: %d rising samples from %.2f to %.2f degC, T_ref %.2f degC",
                 int(mask.sum()), float(temp_min), float(used.max()), temp_ref)


__all__ = ["MEDIAN_SAMPLES", "N_BINS", "Px4Cubic", "Px4Onboard", "cubic_least_squares", "median_filter",
           "temperature_bins"]
