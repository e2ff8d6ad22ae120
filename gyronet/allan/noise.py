"""The noise terms N, B and K read from an Allan curve (IEEE Std 952 slope method), apart from computing it."""
from __future__ import annotations

import math

import numpy as np

# Flat part of the curve for flicker rate noise: sigma = B sqrt(2 ln 2 / pi) (IEEE Std 952 annex C).
BIAS_INSTABILITY_FACTOR = 0.664
# Fits ignore taus with fewer than this many independent clusters (record / tau): past it the
# estimate's error, 1 / sqrt(2 (clusters - 1)) (IEEE Std 952 annex C), is over 24 %.
MIN_CLUSTERS = 10.0
_SLOPE_TOLERANCE = 0.25
_RUN_TOLERANCE = 0.1  # a region of the slope: windows this close to it, side by side
_WINDOW_DECADES = 0.5


def noise_parameters(taus_s: np.ndarray, adev: np.ndarray, max_tau_s: float | None = None,
                     ) -> dict[str, float]:
    """Angle random walk, bias instability and rate random walk from one Allan curve.

    Parameters
    ----------
    taus_s
        Averaging times, s, shape (t,), increasing.
    adev
        Allan deviation of a rate in deg/s, shape (t,).
    max_tau_s
        Ignore longer taus, whose estimates rest on too few clusters (``allan_report`` passes the
        record length / ``MIN_CLUSTERS``). Default: use every tau.

    Returns
    -------
    dict
        ``arw_deg_rthr`` (N, deg/sqrt(h)), ``bias_instability_deg_hr`` (B, deg/h),
        ``bias_instability_tau_s``, ``bias_instability_upper_bound`` (B read at the last usable tau, where
        the curve still falls: the true minimum is lower), ``rrw_deg_hr_rthr`` (K, deg/h/sqrt(h)), and the local slopes
        the fits used, ``arw_slope`` and ``rrw_slope``, at the taus they were read at (the
        window's centre), ``arw_tau_s`` and ``rrw_tau_s``. A term is NaN when the curve has no
        region for it.

    Notes
    -----
    The log-log slope at each tau is the least-squares slope over the taus within half a decade
    around it (a single pair of neighbours is too noisy at long tau). N comes from the window left
    of the minimum whose slope is closest to -1/2, K from the window right of it closest to +1/2,
    each within the widest run of windows whose slopes are within 0.1 of it (a noise term holds
    its slope over a decade or more); the fixed-slope line is fitted to that window and read at
    1 s (N) or 3 s (K), as in IEEE Std 952 annex C and MATLAB's "Inertial Sensor Noise Analysis
    Using Allan Variance" example. When the best slope is more than 0.25 away from the target (e.g.
    a curve still falling at its end has no +1/2 region), the term is NaN instead of a number read
    off the wrong noise.
    B is ``min(adev) / 0.664``, the minimum taken over the usable taus.

    References
    ----------
    .. [1] IEEE Std 952-1997, "IEEE Standard Specification Format Guide and Test Procedure for
       Single-Axis Interferometric Fiber Optic Gyros", annex C.
    .. [2] N. El-Sheimy, H. Hou, X. Niu, "Analysis and Modeling of Inertial Sensors Using Allan
       Variance", IEEE Trans. Instrum. Meas. 57(1), 2008.
    """
    taus = np.asarray(taus_s, dtype=np.float64)
    dev = np.asarray(adev, dtype=np.float64)
    usable = np.isfinite(dev) & (dev > 0) & (taus > 0)
    if max_tau_s is not None:
        usable &= taus <= max_tau_s
    taus, dev = taus[usable], dev[usable]
    result = dict(arw_deg_rthr=math.nan, bias_instability_deg_hr=math.nan,
                  bias_instability_tau_s=math.nan, rrw_deg_hr_rthr=math.nan,
                  arw_slope=math.nan, rrw_slope=math.nan, arw_tau_s=math.nan, rrw_tau_s=math.nan,
                  bias_instability_upper_bound=False)
    if len(taus) < 2:
        return result
    lowest = int(np.argmin(dev))
    result["bias_instability_deg_hr"] = float(dev[lowest] / BIAS_INSTABILITY_FACTOR * 3600.0)
    result["bias_instability_tau_s"] = float(taus[lowest])
    result["bias_instability_upper_bound"] = lowest == len(taus) - 1  # still falling at the last tau read
    log_tau, log_dev = np.log10(taus), np.log10(dev)
    # sigma = N / sqrt(tau): N is the line's value at tau = 1 s, deg/sqrt(s) -> deg/sqrt(h).
    arw = _fixed_slope_fit(log_tau, log_dev, slice(0, lowest + 1), -0.5, 1.0)
    if arw is not None:
        result["arw_deg_rthr"], result["arw_slope"], result["arw_tau_s"] = arw[0] * 60.0, arw[1], arw[2]
    # sigma = K sqrt(tau / 3): K is the line's value at tau = 3 s, deg/s/sqrt(s) -> deg/h/sqrt(h).
    rrw = _fixed_slope_fit(log_tau, log_dev, slice(lowest, len(taus)), 0.5, 3.0)
    if rrw is not None:
        result["rrw_deg_hr_rthr"], result["rrw_slope"], result["rrw_tau_s"] = rrw[0] * 3600.0 * 60.0, rrw[1], rrw[2]
    return result


def _fixed_slope_fit(log_tau: np.ndarray, log_dev: np.ndarray, centres: slice, slope: float,
                     read_at_s: float) -> tuple[float, float, float] | None:
    """A line of the given slope fitted in the widest region of it: its value at a tau, the local slope, where.

    A noise term shows as a slope held over a decade or more. A single window at long tau can
    match the slope more closely by chance (a filtered rate's drift residual near 1,000 s), so the
    window is the best-matching one of the widest run of windows within ``_RUN_TOLERANCE`` of it.
    """
    kept, slopes = [], []  # window centres and their local slopes
    for centre in range(*centres.indices(len(log_tau))):
        window = np.abs(log_tau - log_tau[centre]) <= _WINDOW_DECADES / 2
        if window.sum() >= 2:
            kept.append(centre)
            slopes.append(float(np.polyfit(log_tau[window], log_dev[window], 1)[0]))
    if not kept:
        return None
    miss = np.abs(np.asarray(slopes) - slope)
    near = miss <= _RUN_TOLERANCE
    edges = np.flatnonzero(np.diff(near.astype(int))) + 1
    runs = [run for run in np.split(np.arange(len(kept)), edges) if near[run[0]]]  # side by side, near the slope
    pool = max(runs, key=lambda run: log_tau[kept[run[-1]]] - log_tau[kept[run[0]]]) if runs else np.arange(len(kept))
    best = int(pool[np.argmin(miss[pool])])
    if miss[best] > _SLOPE_TOLERANCE:
        return None
    window = np.abs(log_tau - log_tau[kept[best]]) <= _WINDOW_DECADES / 2
    # log sigma = slope * log tau + b, b fitted in least squares over the window.
    intercept = float(np.mean(log_dev[window] - slope * log_tau[window]))
    return 10.0 ** (intercept + slope * math.log10(read_at_s)), slopes[best], float(10.0 ** log_tau[kept[best]])
