"""The Whittle likelihood of AR(p) + white noise on a banded periodogram, apart from ``identify``'s checks and records."""
from __future__ import annotations

import math

import numpy as np
from scipy import optimize

_MAX_PACF = 1.0 - 1e-9


class Spectrum:
    """Band-averaged periodogram: band centres (rad/sample), band mean power, bins per band."""

    def __init__(self, omega: np.ndarray, power: np.ndarray, bins: np.ndarray):
        self.omega, self.power, self.bins = omega, power, bins
        self._trig: dict[int, tuple[np.ndarray, np.ndarray]] = {}

    def trig(self, p: int) -> tuple[np.ndarray, np.ndarray]:
        """cos(j omega) and sin(j omega) for lags j = 1..p, shape (bands, p), cached."""
        if p not in self._trig:
            phase = np.outer(self.omega, np.arange(1, p + 1))
            self._trig[p] = (np.cos(phase), np.sin(phase))
        return self._trig[p]


def banded_periodogram(x: np.ndarray, exact_bins: int, band_ratio: float) -> Spectrum:
    """The periodogram of ``x``, exact in its first ``exact_bins`` bins, then averaged in bands: fits cost bands."""
    n = len(x)
    k_max = (n - 1) // 2  # Fourier frequencies strictly between 0 and pi
    # I(omega_k) = |sum_t x_t exp(-i omega_k t)|^2 / n, E I = f(omega_k)
    power = np.abs(np.fft.rfft(x)[1:k_max + 1]) ** 2 / n
    starts, k = [0], 0
    while k < k_max:
        k = min(k_max, k + (1 if k < exact_bins else max(1, int(k * (band_ratio - 1.0)))))
        starts.append(k)
    starts = np.asarray(starts)
    bins = np.diff(starts).astype(np.float64)
    index = np.arange(1, k_max + 1, dtype=np.float64)
    centre = np.add.reduceat(index, starts[:-1]) / bins
    return Spectrum(2.0 * np.pi * centre / n, np.add.reduceat(power, starts[:-1]) / bins, bins)


def _pacf_to_ar(pacf: np.ndarray) -> np.ndarray:
    """Durbin-Levinson: partial autocorrelations in (-1, 1) -> stationary AR coefficients."""
    a = pacf[:1].copy()
    for r in pacf[1:]:
        # phi_{k,j} = phi_{k-1,j} - r_k phi_{k-1,k-j},  phi_{k,k} = r_k
        a = np.r_[a - r * a[::-1], r]
    return a


def unpack(theta: np.ndarray, p: int) -> tuple[np.ndarray, float, float]:
    """theta = (atanh pacf_1..p, ln q, ln R) -> (a, q, R); |pacf| < 1 keeps the AR stationary."""
    pacf = np.clip(np.tanh(theta[:p]), -_MAX_PACF, _MAX_PACF)
    return _pacf_to_ar(pacf), math.exp(min(theta[p], 700.0)), math.exp(min(theta[p + 1], 700.0))


def _density(spec: Spectrum, a: np.ndarray, q: float, r: float) -> tuple[np.ndarray, np.ndarray]:
    """f(omega) = q / |A|^2 + R with A = 1 - sum_j a_j exp(-i j omega); returns (f, A)."""
    cos, sin = spec.trig(len(a))
    # real arithmetic: a complex-by-real matmul is ~1000x slower in numpy
    A = (1.0 - cos @ a) + 1j * (sin @ a)
    return q / (A.real ** 2 + A.imag ** 2) + r, A


def fit_order(spec: Spectrum, p: int, r0: float, var0: float, previous) -> optimize.OptimizeResult:
    """The AR(``p``) + white noise that minimises the Whittle likelihood, started also from order p - 1's optimum."""
    def neg_log_likelihood(theta: np.ndarray) -> float:
        a, q, r = unpack(theta, p)
        f, _ = _density(spec, a, q, r)
        # Whittle: -log L = sum over bins of (log f + I / f)
        return float(np.sum(spec.bins * (np.log(f) + spec.power / f)))

    starts = []
    if previous is not None:  # the order p - 1 optimum with pacf_p = 0
        starts.append(np.r_[previous.x[:p - 1], 0.0, previous.x[p - 1:]])
    for phi in (0.5, 0.99, 0.999, 0.9999):
        q0 = max(var0 - r0, 1e-6 * r0) * (1.0 - phi ** 2)
        starts.append(np.r_[math.atanh(phi), np.zeros(p - 1), math.log(q0), math.log(r0)])
    results = [optimize.minimize(neg_log_likelihood, s, method="BFGS") for s in starts]
    return min(results, key=lambda res: res.fun)


def standard_errors(spec: Spectrum, a: np.ndarray, q: float, r: float) -> np.ndarray:
    """Standard errors of (a_1..a_p, q, R) from the Whittle Fisher information sum g g^T."""
    f, A = _density(spec, a, q, r)
    p = len(a)
    grad = np.empty((len(f), p + 2))  # g = d log f / d theta
    for j in range(1, p + 1):
        # df/da_j = 2 q Re(exp(i j omega) A) / |A|^4
        grad[:, j - 1] = 2.0 * q * np.real(np.exp(1j * j * spec.omega) * A) / np.abs(A) ** 4 / f
    grad[:, p] = 1.0 / np.abs(A) ** 2 / f
    grad[:, p + 1] = 1.0 / f
    fisher = (grad * spec.bins[:, None]).T @ grad
    try:
        cov = np.linalg.inv(fisher)
    except np.linalg.LinAlgError:
        return np.full(p + 2, math.nan)
    return np.sqrt(np.where(np.diag(cov) > 0, np.diag(cov), math.nan))
