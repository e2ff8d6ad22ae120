"""What the Kalman stage costs and buys, measured by running it: Allan terms and step response.

Both functions run a fresh copy of the stage (``KalmanStage.from_dict(stage.to_dict())``), so the
caller's stage keeps its state.
"""
from __future__ import annotations

import logging
import math
from typing import Any, Sequence

import numpy as np

from gyronet.model.kalman.identify import AXES
from gyronet.model.kalman.stage import KalmanStage

log = logging.getLogger(__name__)

_PRE_ROLL_CHUNK = 4096
_MAX_PRE_ROLL_SAMPLES = 10_000_000


def fresh_copy(stage: KalmanStage) -> KalmanStage:
    """A reset stage with the same model and options."""
    return KalmanStage.from_dict(stage.to_dict())


def allan_cost(stage: KalmanStage, rate_dps: np.ndarray, fs_hz: float, skip_s: float = 0.0) -> dict[str, Any]:
    """Angle random walk N and bias instability B of a static record without and with the stage.

    Parameters
    ----------
    stage
        The stage to measure (not modified).
    rate_dps
        A static compensated record, deg/s, shape (n, 3).
    fs_hz
        Its sampling rate, Hz (must be the stage model's).
    skip_s
        Leave out the first ``skip_s`` seconds of both signals (the filter's start-up).

    Returns
    -------
    dict
        Per axis name: ``{"without": terms, "with": terms}``, each with ``arw_deg_rthr`` (N),
        ``bias_instability_deg_hr`` (B), ``bias_instability_tau_s`` and ``std_dps`` (the
        per-sample standard deviation, what a low-pass lowers most). Also ``fs_hz``,
        ``n_samples``, ``skip_s`` and the stage's ``mode``.

    Notes
    -----
    The terms come from :mod:`gyronet.allan` (IEEE Std 952 slope method on the overlapping Allan
    deviation), with taus up to a tenth of the record as ``allan_report`` does. A causal low-pass
    of unit DC gain leaves the Allan deviation at taus well above its time constant unchanged; N is
    read where the curve has slope -1/2, so a filter lowers N only where its time constant reaches
    into that region.

    References
    ----------
    .. [1] IEEE Std 952-1997, annex C.
    """
    from gyronet.allan import MIN_CLUSTERS, noise_parameters, oadev

    _check_fs(stage, fs_hz)
    raw = np.asarray(rate_dps, dtype=np.float64)
    filtered = fresh_copy(stage).process(raw)
    start = int(round(skip_s * fs_hz))
    raw, filtered = raw[start:], filtered[start:]
    max_tau_s = len(raw) / fs_hz / MIN_CLUSTERS
    result: dict[str, Any] = {"fs_hz": fs_hz, "n_samples": len(raw), "skip_s": skip_s, "mode": stage.mode}
    curves = {name: oadev(values, fs_hz) for name, values in (("without", raw), ("with", filtered))}
    for i, axis in enumerate(AXES[:raw.shape[1]]):
        result[axis] = {}
        for name, values in (("without", raw), ("with", filtered)):
            taus_s, adev, _ = curves[name]
            terms = noise_parameters(taus_s, adev[:, i], max_tau_s=max_tau_s)
            result[axis][name] = {"arw_deg_rthr": terms["arw_deg_rthr"],
                                  "bias_instability_deg_hr": terms["bias_instability_deg_hr"],
                                  "bias_instability_tau_s": terms["bias_instability_tau_s"],
                                  "std_dps": float(np.std(values[:, i]))}
    return result


def step_response(stage: KalmanStage, fs_hz: float, step_dps: float | Sequence[float],
                  duration_s: float, settle_fractions: Sequence[float] = (0.02, 0.05)) -> dict[str, Any]:
    """Response of the stage's output to a true rotation-rate step, measured by simulation.

    A fresh copy of the stage is fed zeros until its gain is steady, then ``step_dps`` from sample
    0 (t = 0) for ``duration_s``; no noise: the stage is linear, so this is also its mean response
    under noise.

    Parameters
    ----------
    stage
        The stage to measure (not modified).
    fs_hz
        Sampling rate, Hz (must be the stage model's).
    step_dps
        Step size, deg/s: one for all axes or one per axis; non-zero.
    duration_s
        How long the step is held and watched, s.
    settle_fractions
        Bands for the settling times: 0.02 means within 2 % of the step.

    Returns
    -------
    dict
        Per axis name: ``delay_s`` (first sample time with output >= 50 % of the step; 0 for a
        pass-through), ``time_constant_s`` (the same at 63.2 %), ``rise_time_s`` (10 % to 90 %),
        ``settling_2pct_s`` etc. (the time from which the output stays within the band until the
        end; NaN if it never does within ``duration_s``), ``overshoot_pct``, ``final_ratio``
        (last output / step) and ``first_sample_ratio``. Also ``fs_hz``, ``step_dps``, ``duration_s``, ``mode`` and
        ``pre_roll_samples``.
    """
    _check_fs(stage, fs_hz)
    n_axes = len(stage.model.axes)
    step = np.broadcast_to(np.asarray(step_dps, dtype=np.float64), (n_axes,))
    if np.any(step == 0):
        raise ValueError("step_dps must be non-zero")
    copy = fresh_copy(stage)
    while not copy.steady and copy.n_samples < _MAX_PRE_ROLL_SAMPLES:
        copy.process(np.zeros((_PRE_ROLL_CHUNK, n_axes)))
    n = max(2, int(round(duration_s * fs_hz)))
    response = copy.process(np.tile(step, (n, 1))) / step
    result: dict[str, Any] = {"fs_hz": fs_hz, "step_dps": step.tolist(), "duration_s": n / fs_hz,
                              "mode": stage.mode, "pre_roll_samples": copy.n_samples - n}
    for i, axis in enumerate(AXES[:n_axes]):
        result[axis] = _step_figures(response[:, i], fs_hz, settle_fractions)
    return result


def _step_figures(y: np.ndarray, fs_hz: float, settle_fractions: Sequence[float]) -> dict[str, float]:
    """Figures of a unit step response y (sample k at t = k / fs)."""

    def first_time(reached: np.ndarray) -> float:
        hits = np.flatnonzero(reached)
        return hits[0] / fs_hz if len(hits) else math.nan

    out = {"delay_s": first_time(y >= 0.5), "time_constant_s": first_time(y >= 1.0 - math.exp(-1.0)),
           "rise_time_s": first_time(y >= 0.9) - first_time(y >= 0.1),
           "overshoot_pct": float(max(0.0, y.max() - 1.0) * 100.0),
           "final_ratio": float(y[-1]), "first_sample_ratio": float(y[0])}
    for fraction in settle_fractions:
        outside = np.flatnonzero(np.abs(y - 1.0) > fraction)
        if not len(outside):
            settle = 0.0
        elif outside[-1] == len(y) - 1:
            settle = math.nan
        else:
            settle = (outside[-1] + 1) / fs_hz
        out[f"settling_{100 * fraction:g}pct_s"] = settle
    return out


def _check_fs(stage: KalmanStage, fs_hz: float) -> None:
    if not math.isclose(fs_hz, stage.model.fs_hz, rel_tol=1e-9):
        raise ValueError(f"the stage was identified at {stage.model.fs_hz} Hz, not {fs_hz} Hz")
