"""``allan_report`` and what the commands write from it (JSON, a text table), apart from the maths."""
from __future__ import annotations

import logging
import math
from typing import Mapping, Sequence

import numpy as np

from gyronet.allan.deviation import log_taus, oadev
from gyronet.allan.noise import MIN_CLUSTERS, noise_parameters
from gyronet.atomic import json_text
from gyronet.errors import GyronetError
from gyronet.recordings.data import GAP_FACTOR
from gyronet.recordings.guard import GYRO_RANGE_DPS, bad_gyro

# the name allan_report warned under before gyronet/allan was split into modules
log = logging.getLogger("gyronet.allan")

AXES = ("x", "y", "z")


def continuous_segments(time_s: np.ndarray, fs_hz: float) -> list[tuple[int, int]]:
    """Index ranges ``[start, stop)`` between gaps longer than ``GAP_FACTOR / fs_hz``."""
    breaks = np.flatnonzero(np.diff(np.asarray(time_s, dtype=np.float64)) > GAP_FACTOR / fs_hz) + 1
    edges = [0, *breaks.tolist(), len(time_s)]
    return list(zip(edges[:-1], edges[1:]))


def allan_report(time_s: np.ndarray, rate_dps: np.ndarray, fs_hz: float | None = None,
                 per_decade: int = 10, axes: Sequence[str] = AXES) -> dict:
    """Allan curves and noise terms per axis, as CONTRACT.md section 3 writes them.

    Parameters
    ----------
    time_s
        Sample times, s, shape (n,), increasing.
    rate_dps
        Angular rate, deg/s, shape (n, k) with k <= len(axes), or (n,).
    fs_hz
        Sampling rate, Hz; default ``1 / median(diff(time_s))`` to 7 significant digits.
    per_decade
        Taus per decade (:func:`log_taus`).
    axes
        Names of the columns of ``rate_dps``.

    Returns
    -------
    dict
        One entry per axis: ``taus_s``, ``adev_dps`` (overlapping), ``n_terms`` and the terms of
        :func:`noise_parameters`; plus ``fs_hz`` and ``segments``. Gaps are never glued: the
        analysis uses the longest continuous segment, and ``segments`` says which (``count``,
        ``used_time_s``, ``n_samples_used``, ``n_samples_total``, ``largest_gap_s``). A sample with
        an impossible gyro value on any axis (``gyronet.recordings.guard.bad_gyro``: not finite, beyond 1e4
        deg/s) is dropped, a gap like any lost sample, counted in ``segments.n_impossible`` and
        named in one warning: the figures are those of the record without it.

    Raises
    ------
    GyronetError
        When the (longest continuous part of the) record is too short for an Allan curve.
    """
    if isinstance(per_decade, bool) or not isinstance(per_decade, (int, np.integer)) or per_decade < 1:
        # 0 gave a one-point curve and every figure n/a without a word, a negative number a numpy traceback
        raise GyronetError(f"per_decade must be a whole number of taus per decade, at least 1, got {per_decade!r}")
    time_s = np.asarray(time_s, dtype=np.float64)
    rate = np.asarray(rate_dps, dtype=np.float64)
    if len(time_s) < 3:
        raise GyronetError(f"Allan analysis needs at least 3 samples, got {len(time_s)}")
    if rate.ndim not in (1, 2) or len(rate) != len(time_s):
        raise ValueError(f"rate shape {rate.shape} does not match {len(time_s)} times")
    rate = rate.reshape(len(time_s), -1)
    if rate.shape[1] > len(axes):
        raise ValueError(f"rate has {rate.shape[1]} columns but only {len(axes)} axis names")
    # an impossible value (not finite, beyond any gyro's range) is a lost sample: a gap, as in the compensator
    impossible = bad_gyro(rate).any(1)
    n_impossible, n_total = int(np.count_nonzero(impossible)), len(time_s)
    if n_impossible:
        first_s = float(time_s[np.argmax(impossible)])
        time_s, rate = time_s[~impossible], rate[~impossible]
        if len(time_s) < 3:
            raise GyronetError(f"Allan analysis: {n_impossible} of {n_total} samples have an impossible gyro value "
                               f"(not finite or beyond {GYRO_RANGE_DPS:g} deg/s), fewer than 3 are left")
    if fs_hz is None:
        # 7 significant digits: 1 / 0.0100000000000002 (a CSV's rounded times) is 100 Hz.
        fs_hz = float(f"{1.0 / np.median(np.diff(time_s)):.7g}")
    segments = continuous_segments(time_s, fs_hz)
    start, stop = max(segments, key=lambda s: s[1] - s[0])
    if stop - start < 3:
        raise GyronetError(f"Allan analysis: the longest stretch without gaps has {stop - start} samples")
    if n_impossible:
        log.warning("%d samples with an impossible gyro value (not finite or beyond %g deg/s, the first at %.6g s) "
                    "dropped as gaps: Allan analysis uses the longest continuous segment, %.6g..%.6g s (%d of %d "
                    "samples)", n_impossible, GYRO_RANGE_DPS, first_s, time_s[start], time_s[stop - 1],
                    stop - start, n_total)
    elif len(segments) > 1:
        log.warning("record has %d gap%s; Allan analysis uses the longest continuous segment, %.6g..%.6g s"
                    " (%d of %d samples)", len(segments) - 1, "s" if len(segments) > 2 else "", time_s[start],
                    time_s[stop - 1], stop - start, len(time_s))
    m, _ = log_taus(stop - start, fs_hz, per_decade)
    taus_s, adev, n_terms = oadev(rate[start:stop], fs_hz, m=m)
    max_tau_s = (stop - start) / fs_hz / MIN_CLUSTERS
    report: dict = {}
    for column, axis in enumerate(axes[:rate.shape[1]]):
        report[axis] = {"taus_s": taus_s.tolist(), "adev_dps": adev[:, column].tolist(),
                        "n_terms": n_terms.tolist(), **noise_parameters(taus_s, adev[:, column], max_tau_s)}
    if all(not np.isfinite(report[a]["bias_instability_deg_hr"]) for a in report):
        log.warning("Allan analysis: %d samples (%.3g s) are too few to read N, B or K: every figure is n/a",
                    stop - start, (stop - start) / fs_hz)
    gaps_s = np.diff(time_s)[[s[0] - 1 for s in segments[1:]]]
    report["fs_hz"] = float(fs_hz)
    report["segments"] = {"count": len(segments), "used_time_s": [float(time_s[start]), float(time_s[stop - 1])],
                          "n_samples_used": int(stop - start), "n_samples_total": int(n_total),
                          "n_impossible": n_impossible, "largest_gap_s": float(gaps_s.max()) if len(gaps_s) else 0.0,
                          "max_fit_tau_s": float(max_tau_s)}  # N, B and K are read up to here
    return report


def report_to_json(report: Mapping) -> str:
    """The report as JSON, NaN written as ``null`` (strict JSON has no NaN)."""
    return json_text(report, indent=1)


def format_table(report: Mapping) -> str:
    """A short text table of N, B (at its tau) and K per axis, for a log."""
    lines = [f"{'axis':4} {'N deg/rt(h)':>12} {'B deg/h':>10} {'at tau s':>9} {'K deg/h/rt(h)':>14}"]
    for axis in axes_of(report):
        row = report[axis]
        bias = ("<=" if row.get("bias_instability_upper_bound") else "") + num(row["bias_instability_deg_hr"])
        lines.append(f"{axis:4} {num(row['arw_deg_rthr']):>12} {bias:>10}"
                     f" {num(row['bias_instability_tau_s']):>9} {num(row['rrw_deg_hr_rthr']):>14}")
    return "\n".join(lines)


def num(value) -> str:
    """A report's figure as 4 significant digits, or n/a where there is none."""
    return "n/a" if value is None or not math.isfinite(value) else f"{value:.4g}"


def axes_of(report: Mapping) -> list[str]:
    """The report's axes: the entries that carry an Allan curve."""
    return [k for k, v in report.items() if isinstance(v, Mapping) and "taus_s" in v]

