"""Allan deviation of gyro rate and the noise terms read from it: arrays in, arrays out.

The overlapping Allan deviation is computed from the integrated rate (the "phase", in deg) the
way NIST SP 1065 eq. (11) writes it; the noise terms are read from the log-log curve with the
slope method of IEEE Std 952-1997 annex C:

- angle random walk N (white rate noise): the slope -1/2 line, read at tau = 1 s;
- bias instability B (flicker rate noise): the minimum of the curve divided by sqrt(2 ln2 / pi)
  = 0.664;
- rate random walk K: the slope +1/2 line, read at tau = 3 s.

Units: rate in deg/s, so ADEV is in deg/s; N is reported in deg/sqrt(h), B in deg/h and K in
deg/h/sqrt(h).
"""
from __future__ import annotations

import json
import logging
import math
from typing import Mapping, Sequence

import numpy as np

from gyronet.errors import GyronetError
from gyronet.recordings.guard import GYRO_RANGE_DPS, bad_gyro

log = logging.getLogger(__name__)

AXES = ("x", "y", "z")
# Flat part of the curve for flicker rate noise: sigma = B sqrt(2 ln 2 / pi) (IEEE Std 952 annex C).
BIAS_INSTABILITY_FACTOR = 0.664
# A gap is a sample interval over 1.5 nominal intervals: a break in the record (CONTRACT.md 1).
GAP_FACTOR = 1.5
# Fits ignore taus with fewer than this many independent clusters (record / tau): past it the
# estimate's error, 1 / sqrt(2 (clusters - 1)) (IEEE Std 952 annex C), is over 24 %.
MIN_CLUSTERS = 10.0
_SLOPE_TOLERANCE = 0.25
_WINDOW_DECADES = 0.5
_DEFAULT_CHUNK = 1 << 17


def log_taus(n_samples: int, fs_hz: float, per_decade: int = 10) -> tuple[np.ndarray, np.ndarray]:
    """Log-spaced averaging factors for an overlapping Allan deviation.

    Parameters
    ----------
    n_samples
        Number of rate samples.
    fs_hz
        Sampling rate, Hz.
    per_decade
        Points per decade of tau before rounding to whole samples (duplicates are dropped).

    Returns
    -------
    m
        Unique averaging factors, int64, from 1 to ``(n_samples - 1) // 2``: the largest tau that
        still has two terms, since allantools drops single-term estimates.
    taus_s
        ``m / fs_hz``, s.
    """
    m_max = (int(n_samples) - 1) // 2
    if m_max < 1:
        raise ValueError(f"an Allan deviation needs at least 3 samples, got {n_samples}")
    n_points = int(math.ceil(per_decade * math.log10(m_max))) + 1
    m = np.unique(np.round(np.logspace(0.0, math.log10(m_max), n_points)).astype(np.int64))
    return m, m / float(fs_hz)


def oadev(rate: np.ndarray, fs_hz: float, taus_s: Sequence[float] | np.ndarray | None = None, *,
          m: Sequence[int] | np.ndarray | None = None, chunk_size: int = _DEFAULT_CHUNK,
          ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Overlapping Allan deviation of a rate signal, all axes in one pass.

    Parameters
    ----------
    rate
        Rate samples, shape (n,) or (n, k), e.g. deg/s; finite.
    fs_hz
        Sampling rate, Hz.
    taus_s
        Averaging times, s; rounded to whole samples as ``m = round(tau * fs)``. Taus outside
        ``1 <= m <= (n - 1) // 2`` are dropped. Default: :func:`log_taus`.
    m
        Averaging factors instead of ``taus_s``.
    chunk_size
        Samples (over all axes) handled at once: the temporaries stay this small.

    Returns
    -------
    taus_s
        Sorted unique averaging times used, ``m / fs_hz``, s, shape (t,).
    adev
        Overlapping Allan deviation, units of ``rate``, shape (t,) or (t, k).
    n_terms
        Number of second differences in each estimate, ``n + 1 - 2 m``, shape (t,).

    Notes
    -----
    Equal to ``allantools.oadev(rate, rate=fs_hz, data_type="freq", taus=taus_s)``: the mean is
    removed before integrating, so the float64 cumulative sum keeps its precision, and
    ``sigma^2(m tau0) = sum (x[i+2m] - 2 x[i+m] + x[i])^2 / (2 (m tau0)^2 (n + 1 - 2m))`` over
    the phase ``x`` (n + 1 points, starting at 0).

    References
    ----------
    .. [1] W. J. Riley, "Handbook of Frequency Stability Analysis", NIST SP 1065, 2008,
       eq. (11), p. 16.
    .. [2] IEEE Std 952-1997, annex C.
    """
    values = np.asarray(rate, dtype=np.float64)
    if values.ndim not in (1, 2):
        raise ValueError(f"rate must have shape (n,) or (n, k), got {values.shape}")
    columns = values.reshape(len(values), -1)
    if not np.isfinite(columns).all():
        raise ValueError("rate contains NaN or inf")
    if not fs_hz > 0:
        raise ValueError(f"fs_hz must be positive, got {fs_hz}")
    factors = _averaging_factors(len(columns), fs_hz, taus_s, m)
    phase = _phase(columns)
    sums = _second_difference_power(phase, factors, chunk_size)
    n_terms = len(columns) + 1 - 2 * factors
    # With x = S / fs (S the cumulative sum): sigma^2 = sum (d2 S)^2 / (2 m^2 n_terms).
    adev = np.sqrt(sums / (2.0 * n_terms[:, None])) / factors[:, None]
    return factors / float(fs_hz), (adev[:, 0] if values.ndim == 1 else adev), n_terms


def _averaging_factors(n_samples: int, fs_hz: float, taus_s, m) -> np.ndarray:
    if m is None and taus_s is None:
        return log_taus(n_samples, fs_hz)[0]
    if m is None:
        m = np.round(np.asarray(taus_s, dtype=np.float64) * fs_hz)
    factors = np.unique(np.asarray(m).astype(np.int64).ravel())
    kept = factors[(factors >= 1) & (factors <= (n_samples - 1) // 2)]
    if len(kept) < len(factors):
        log.debug("dropped %d tau(s) outside 1..%d samples", len(factors) - len(kept), (n_samples - 1) // 2)
    if not len(kept):
        raise ValueError(f"no tau fits {n_samples} samples (m must be 1..{(n_samples - 1) // 2})")
    return kept


def _phase(columns: np.ndarray) -> np.ndarray:
    """Integrated, mean-removed rate, shape (k, n + 1), starting at 0, in rate x samples."""
    n, k = columns.shape
    phase = np.empty((k, n + 1))
    phase[:, 0] = 0.0
    for axis in range(k):
        np.cumsum(columns[:, axis] - columns[:, axis].mean(), out=phase[axis, 1:])
    return phase


def _second_difference_power(phase: np.ndarray, factors: np.ndarray, chunk_size: int) -> np.ndarray:
    """Sum over i of (x[i+2m] - 2 x[i+m] + x[i])^2 per m and row of ``phase``, in chunks.

    Short taus (m up to the chunk width) run chunk by chunk, all taus on a chunk while it is in
    cache; long taus run one tau at a time. Temporaries stay at ``chunk_size`` values either way.
    """
    k, length = phase.shape
    width = max(1, int(chunk_size) // k)
    buffers = (np.empty((k, 2 * width)), np.empty((k, width)))
    sums = np.zeros((len(factors), k))
    short = [(row, int(m)) for row, m in enumerate(factors) if m <= width]
    for start in range(0, length - 2 * short[0][1] if short else 0, width):
        for row, m in short:
            if start >= length - 2 * m:
                break
            sums[row] += _chunk_power(phase, m, start, min(start + width, length - 2 * m), buffers)
    for row, m in ((row, int(m)) for row, m in enumerate(factors) if m > width):
        for start in range(0, length - 2 * m, width):
            sums[row] += _chunk_power(phase, m, start, min(start + width, length - 2 * m), buffers)
    return sums


def _chunk_power(phase: np.ndarray, m: int, start: int, stop: int,
                 buffers: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    """Per row, sum of (x[i+2m] - 2 x[i+m] + x[i])^2 for i in [start, stop)."""
    size = stop - start
    out = buffers[1][:, :size]
    if m <= buffers[1].shape[1]:
        # D[i] = x[i+m] - x[i] once; then x[i+2m] - 2 x[i+m] + x[i] = D[i+m] - D[i].
        step = buffers[0][:, :size + m]
        np.subtract(phase[:, start + m:stop + 2 * m], phase[:, start:stop + m], out=step)
        np.subtract(step[:, m:], step[:, :size], out=out)
    else:
        np.subtract(phase[:, start + 2 * m:stop + 2 * m], phase[:, start + m:stop + m], out=out)
        np.subtract(out, phase[:, start + m:stop + m], out=out)
        np.add(out, phase[:, start:stop], out=out)
    # einsum, not np.dot: a threaded BLAS dot stalls by orders of magnitude on a busy machine.
    return np.einsum("ij,ij->i", out, out)


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
        ``bias_instability_tau_s``, ``rrw_deg_hr_rthr`` (K, deg/h/sqrt(h)), and the local slopes
        the fits used, ``arw_slope`` and ``rrw_slope``. A term is NaN when the curve has no
        region for it.

    Notes
    -----
    The log-log slope at each tau is the least-squares slope over the taus within half a decade
    around it (a single pair of neighbours is too noisy at long tau). N comes from the window left
    of the minimum whose slope is closest to -1/2, K from the window right of it closest to +1/2;
    the fixed-slope line is fitted to that window and read at 1 s (N) or 3 s (K), as in IEEE Std
    952 annex C and MATLAB's "Inertial Sensor Noise Analysis Using Allan Variance" example. When
    the best slope is more than 0.25 away from the target (e.g. a curve still falling at its end
    has no +1/2 region), the term is NaN instead of a number read off the wrong noise.
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
                  arw_slope=math.nan, rrw_slope=math.nan)
    if len(taus) < 2:
        return result
    lowest = int(np.argmin(dev))
    result["bias_instability_deg_hr"] = float(dev[lowest] / BIAS_INSTABILITY_FACTOR * 3600.0)
    result["bias_instability_tau_s"] = float(taus[lowest])
    log_tau, log_dev = np.log10(taus), np.log10(dev)
    # sigma = N / sqrt(tau): N is the line's value at tau = 1 s, deg/sqrt(s) -> deg/sqrt(h).
    arw = _fixed_slope_fit(log_tau, log_dev, slice(0, lowest + 1), -0.5, 1.0)
    if arw is not None:
        result["arw_deg_rthr"], result["arw_slope"] = arw[0] * 60.0, arw[1]
    # sigma = K sqrt(tau / 3): K is the line's value at tau = 3 s, deg/s/sqrt(s) -> deg/h/sqrt(h).
    rrw = _fixed_slope_fit(log_tau, log_dev, slice(lowest, len(taus)), 0.5, 3.0)
    if rrw is not None:
        result["rrw_deg_hr_rthr"], result["rrw_slope"] = rrw[0] * 3600.0 * 60.0, rrw[1]
    return result


def _fixed_slope_fit(log_tau: np.ndarray, log_dev: np.ndarray, centres: slice, slope: float,
                     read_at_s: float) -> tuple[float, float] | None:
    """Fit a line of the given slope where the local slope is closest to it; its value at a tau."""
    best: tuple[float, np.ndarray] | None = None
    for centre in range(*centres.indices(len(log_tau))):
        window = np.abs(log_tau - log_tau[centre]) <= _WINDOW_DECADES / 2
        if window.sum() < 2:
            continue
        local = float(np.polyfit(log_tau[window], log_dev[window], 1)[0])
        if best is None or abs(local - slope) < abs(best[0] - slope):
            best = (local, window)
    if best is None or abs(best[0] - slope) > _SLOPE_TOLERANCE:
        return None
    local, window = best
    # log sigma = slope * log tau + b, b fitted in least squares over the window.
    intercept = float(np.mean(log_dev[window] - slope * log_tau[window]))
    return 10.0 ** (intercept + slope * math.log10(read_at_s)), local


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
        log.warning("record has %d gaps; Allan analysis uses the longest continuous segment, %.6g..%.6g s"
                    " (%d of %d samples)", len(segments) - 1, time_s[start], time_s[stop - 1],
                    stop - start, len(time_s))
    m, _ = log_taus(stop - start, fs_hz, per_decade)
    taus_s, adev, n_terms = oadev(rate[start:stop], fs_hz, m=m)
    max_tau_s = (stop - start) / fs_hz / MIN_CLUSTERS
    report: dict = {}
    for column, axis in enumerate(axes[:rate.shape[1]]):
        report[axis] = {"taus_s": taus_s.tolist(), "adev_dps": adev[:, column].tolist(),
                        "n_terms": n_terms.tolist(), **noise_parameters(taus_s, adev[:, column], max_tau_s)}
    gaps_s = np.diff(time_s)[[s[0] - 1 for s in segments[1:]]]
    report["fs_hz"] = float(fs_hz)
    report["segments"] = {"count": len(segments), "used_time_s": [float(time_s[start]), float(time_s[stop - 1])],
                          "n_samples_used": int(stop - start), "n_samples_total": int(n_total),
                          "n_impossible": n_impossible, "largest_gap_s": float(gaps_s.max()) if len(gaps_s) else 0.0}
    return report


def report_to_json(report: Mapping) -> str:
    """The report as JSON, NaN written as ``null`` (strict JSON has no NaN)."""
    return json.dumps(_strict(report), indent=1) + "\n"


def _strict(value):
    if isinstance(value, Mapping):
        return {str(k): _strict(v) for k, v in value.items()}
    if isinstance(value, (list, tuple, np.ndarray)):
        return [_strict(v) for v in value]
    if isinstance(value, (float, np.floating)):
        return float(value) if math.isfinite(value) else None
    if isinstance(value, np.integer):
        return int(value)
    return value


def format_table(report: Mapping) -> str:
    """A short text table of N, B (at its tau) and K per axis, for a log."""
    lines = [f"{'axis':4} {'N deg/rt(h)':>12} {'B deg/h':>10} {'at tau s':>9} {'K deg/h/rt(h)':>14}"]
    for axis in _axes_of(report):
        row = report[axis]
        lines.append(f"{axis:4} {_num(row['arw_deg_rthr']):>12} {_num(row['bias_instability_deg_hr']):>10}"
                     f" {_num(row['bias_instability_tau_s']):>9} {_num(row['rrw_deg_hr_rthr']):>14}")
    return "\n".join(lines)


def _num(value) -> str:
    return "n/a" if value is None or not math.isfinite(value) else f"{value:.4g}"


def _axes_of(report: Mapping) -> list[str]:
    return [k for k, v in report.items() if isinstance(v, Mapping) and "taus_s" in v]


def plot_allan(report_or_curves: Mapping, path=None, title: str = "Allan deviation"):
    """Log-log Allan curves per axis with the fitted -1/2, 0 and +1/2 lines; N, B, K in the legend.

    Parameters
    ----------
    report_or_curves
        One :func:`allan_report` result, or several by label, e.g.
        ``{"raw": report, "compensated": report2}``.
    path
        Also save the figure here (PNG by suffix) when given.
    title
        Figure title.

    Returns
    -------
    matplotlib.figure.Figure
        Drawn on an Agg canvas, never shown; the caller may log it (TensorBoard) or close it.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.ticker import NullLocator

    curves = {None: report_or_curves} if _axes_of(report_or_curves) else dict(report_or_curves)
    axis_names = [a for a in AXES if any(a in r for r in curves.values())]
    axis_names += [a for r in curves.values() for a in _axes_of(r) if a not in axis_names]
    n_panels = max(1, len(axis_names))
    # A fixed layout: constrained layout measures every log tick and takes seconds.
    fig = Figure(figsize=(4.6 * n_panels, 4.4))
    FigureCanvasAgg(fig)
    fig.subplots_adjust(left=0.08 if n_panels > 1 else 0.18, right=0.98, bottom=0.12, top=0.86, wspace=0.08)
    panels = fig.subplots(1, n_panels, squeeze=False, sharey=True)[0]
    ranges = []
    for panel, axis in zip(panels, axis_names):
        ranges += [_plot_curve(panel, report[axis], f"C{index % 10}", label)
                   for index, (label, report) in enumerate(curves.items()) if axis in report]
        panel.set_title(f"{axis} axis")
        panel.set_xlabel("tau (s)")
        panel.grid(True, which="major", alpha=0.4)
        panel.xaxis.set_minor_locator(NullLocator())  # minor log ticks cost most of the drawing time
        panel.yaxis.set_minor_locator(NullLocator())
        panel.legend(fontsize=7, loc="lower left")
    ranges = [r for r in ranges if r is not None]
    if ranges:  # the fitted lines run over all taus; keep the view on the data
        panels[0].set_ylim(min(r[0] for r in ranges) / 3.0, max(r[1] for r in ranges) * 3.0)
    panels[0].set_ylabel("Allan deviation (deg/s)")
    fig.suptitle(title)
    if path is not None:
        fig.savefig(path, dpi=110)
    return fig


def _plot_curve(panel, curve: Mapping, color: str, label: str | None) -> tuple[float, float] | None:
    """Draw one axis' curve and its fitted lines; return the range of the positive ADEV values."""
    taus = np.asarray(curve["taus_s"], dtype=np.float64)
    dev = np.asarray(curve["adev_dps"], dtype=np.float64)
    arw, bias, rrw = (_finite(curve.get(k)) for k in ("arw_deg_rthr", "bias_instability_deg_hr", "rrw_deg_hr_rthr"))
    terms = f"N={_num(arw)} deg/rt(h), B={_num(bias)} deg/h, K={_num(rrw)} deg/h/rt(h)"
    panel.loglog(taus, dev, color=color, lw=1.6, label=f"{label}: {terms}" if label else terms)
    # sigma = N / sqrt(tau), sigma = 0.664 B, sigma = K sqrt(tau / 3), all back in deg/s.
    if math.isfinite(arw):
        panel.loglog(taus, arw / 60.0 / np.sqrt(taus), color=color, ls="--", lw=0.8)
    if math.isfinite(bias):
        flat_dps = bias / 3600.0 * BIAS_INSTABILITY_FACTOR
        panel.axhline(flat_dps, color=color, ls=":", lw=0.8)
        panel.plot([_finite(curve.get("bias_instability_tau_s"))], [flat_dps], marker="o", color=color, ms=4)
    if math.isfinite(rrw):
        panel.loglog(taus, rrw / 216000.0 * np.sqrt(taus / 3.0), color=color, ls="-.", lw=0.8)
    positive = dev[np.isfinite(dev) & (dev > 0)]
    return (float(positive.min()), float(positive.max())) if len(positive) else None


def _finite(value) -> float:
    return float(value) if value is not None and math.isfinite(float(value)) else math.nan
