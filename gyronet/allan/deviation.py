"""The overlapping Allan deviation (NIST SP 1065 eq. 11), apart from the noise terms read from it."""
from __future__ import annotations

import logging
import math
from typing import Sequence

import numpy as np

# the name the functions logged under before gyronet/allan was split into modules
log = logging.getLogger("gyronet.allan")

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
