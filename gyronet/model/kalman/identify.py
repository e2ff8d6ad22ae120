"""Identify the residual drift's time-series model from data: AR(p) + white noise, per axis.

The network's residual on its training record, ``c = gyro - drift_hat`` with its mean removed,
is modelled per axis as ``c_k = d_k + v_k``: a stationary AR(p) drift
``d_k = a_1 d_{k-1} + ... + a_p d_{k-p} + w_k`` (``var w = q``) plus white noise ``v_k``
(``var v = R``). Its spectral density, per sample, is

    f(omega) = q / |1 - sum_j a_j exp(-i j omega)|^2 + R.

The parameters are the Whittle (frequency-domain maximum-likelihood) estimates: the white part is
what the high frequencies show, the AR part what the low frequencies show above it, both fitted at
once. This is consistent with the white noise present, which an ordinary least-squares AR fit on
raw or block-averaged samples is not: the noise attenuates the lag-1 regression towards 0 (errors
in variables) and block averaging adds an MA term. Standard errors come from the Whittle Fisher
information; the order p (0, white noise alone, included) is the one with the smallest BIC.

The periodogram is used bin by bin below ``exact_bins`` and averaged over bands of relative width
``band_ratio - 1`` above it, where the spectrum is smooth: a 460k-sample axis costs ~0.3 s
instead of ~3 s with the same estimates to 1e-6.
"""
from __future__ import annotations

import logging
import math
from dataclasses import asdict, dataclass, field

import numpy as np

from gyronet.atomic import jsonable
from gyronet.model.kalman.whittle import banded_periodogram, fit_order, standard_errors, unpack

log = logging.getLogger(__name__)

AXES = ("x", "y", "z")
_MIN_SAMPLES = 64
# An AR coefficient whose standard error is larger than this is reported as not identified.
_SE_UNIDENTIFIED = 0.5


@dataclass(frozen=True)
class AxisModel:
    """The identified residual model of one axis, per sample at the model's ``fs_hz``.

    Attributes
    ----------
    ar
        AR coefficients ``a_1 .. a_p`` of the drift (stationary).
    ar_se
        Their standard errors.
    q_drift_dps2
        Variance of the drift's driving noise ``w_k``, (deg/s)^2.
    r_dps2
        Variance of the white measurement noise ``v_k``, (deg/s)^2.
    q_drift_se_dps2, r_se_dps2
        Standard errors of ``q_drift_dps2`` and ``r_dps2``.
    mean_dps
        Mean of the residual, deg/s. Not used by the filter: a constant is a true rate (the Earth
        rate) or a bias the network left, and nothing in one record tells which.
    bic
        BIC of each order tried, ``{"0": ..., "1": ...}``; the smallest won. Order 0 (``ar``
        empty, ``q_drift_dps2`` 0) means the data show no drift above the white noise.
    """

    ar: tuple[float, ...]
    ar_se: tuple[float, ...]
    q_drift_dps2: float
    r_dps2: float
    q_drift_se_dps2: float = math.nan
    r_se_dps2: float = math.nan
    mean_dps: float = 0.0
    bic: dict[str, float] = field(default_factory=dict)

    @property
    def order(self) -> int:
        return len(self.ar)

    def drift_sigma_dps(self) -> float:
        """Stationary standard deviation of the drift d, deg/s."""
        if not self.ar:
            return 0.0
        a = np.asarray(self.ar)
        # gamma(0) of AR(p) from the companion form: Sigma = F Sigma F^T + Q
        return float(math.sqrt(companion_covariance(a, self.q_drift_dps2)[0, 0]))

    def correlation_time_s(self, fs_hz: float) -> float:
        """Time for the drift's autocorrelation to fall to 1/e, s (from its slowest pole)."""
        pole = float(np.max(np.abs(np.roots(np.r_[1.0, -np.asarray(self.ar)])))) if self.ar else 0.0
        return math.inf if pole >= 1.0 else (0.0 if pole == 0.0 else -1.0 / (fs_hz * math.log(pole)))

    def arw_deg_rthr(self, fs_hz: float) -> float:
        """The white noise as an angle random walk N, deg/sqrt(h): sqrt(R / fs) * 60."""
        return math.sqrt(self.r_dps2 / fs_hz) * 60.0

    def to_dict(self, fs_hz: float) -> dict:
        """Strict-JSON fields (non-finite numbers as null) plus derived figures for people."""
        out = jsonable(asdict(self))
        out["derived"] = jsonable({"drift_sigma_dps": self.drift_sigma_dps(),
                                     "correlation_time_s": self.correlation_time_s(fs_hz),
                                     "white_arw_deg_rthr": self.arw_deg_rthr(fs_hz)})
        return out

    @classmethod
    def from_dict(cls, data: dict) -> "AxisModel":
        """Inverse of :meth:`to_dict` (``derived`` is ignored, null reads as NaN)."""
        known = {k: data[k] for k in cls.__dataclass_fields__ if k in data}
        known["ar"] = tuple(_number(v) for v in known["ar"])
        known["ar_se"] = tuple(_number(v) for v in known.get("ar_se", [None] * len(known["ar"])))
        for key in ("q_drift_dps2", "r_dps2", "q_drift_se_dps2", "r_se_dps2", "mean_dps"):
            if key in known:
                known[key] = _number(known[key])
        known["bic"] = {str(k): _number(v) for k, v in known.get("bic", {}).items()}
        return cls(**known)


@dataclass(frozen=True)
class KalmanModel:
    """The residual model of every axis and how it was obtained.

    Attributes
    ----------
    fs_hz
        Sampling rate the model is per-sample at, Hz.
    axes
        One :class:`AxisModel` per gyro axis (x, y, z).
    n_samples
        Length of the residual record it was fitted on.
    method
        ``"whittle"``.
    """

    fs_hz: float
    axes: tuple[AxisModel, ...]
    n_samples: int = 0
    method: str = "whittle"

    def to_dict(self) -> dict:
        return {"fs_hz": self.fs_hz, "n_samples": self.n_samples, "method": self.method,
                "axes": {name: m.to_dict(self.fs_hz) for name, m in zip(AXES, self.axes)}}

    @classmethod
    def from_dict(cls, data: dict) -> "KalmanModel":
        axes = tuple(AxisModel.from_dict(data["axes"][name]) for name in AXES[:len(data["axes"])])
        return cls(float(data["fs_hz"]), axes, int(data.get("n_samples", 0)), data.get("method", "whittle"))


def _number(value) -> float:
    return math.nan if value is None else float(value)


def companion_covariance(ar: np.ndarray, q: float) -> np.ndarray:
    """Stationary covariance of the AR(p) companion state ``[d_k, ..., d_{k-p+1}]``, (p, p)."""
    from scipy.linalg import solve_discrete_lyapunov

    a = np.asarray(ar, dtype=np.float64).reshape(-1)
    if not len(a):
        return np.zeros((0, 0))
    F, Q = companion(a), np.zeros((len(a), len(a)))
    Q[0, 0] = q
    # Sigma = F Sigma F^T + Q
    return solve_discrete_lyapunov(F, Q)


def companion(ar: np.ndarray) -> np.ndarray:
    """Companion (state transition) matrix of an AR(p): first row ``a``, shift below."""
    p = len(ar)
    F = np.zeros((p, p))
    if p:
        F[0, :] = ar
        F[1:, :-1] = np.eye(p - 1)
    return F


def identify(residual_dps: np.ndarray, fs_hz: float, *, max_order: int = 1, exact_bins: int = 2000,
             band_ratio: float = 1.01) -> KalmanModel:
    """Fit AR(p) + white noise to each axis of the network's residual drift.

    Parameters
    ----------
    residual_dps
        The compensated rate ``gyro - drift_hat`` on a static (training) record, deg/s, shape
        (n, k), usually k = 3; finite.
    fs_hz
        Its sampling rate, Hz.
    max_order
        Largest AR order tried; of 0 (white noise alone, no drift state) to ``max_order`` the
        order with the smallest BIC is kept. The default 1 is the
        first-order Gauss-Markov drift: on simulated residuals of a temperature fit, BIC picked
        orders 2-3 with near-unit and negative roots and a singular information matrix (the
        residual is a deterministic thermal error, not a stationary process), see docs/guides/kalman.md.
    exact_bins
        Periodogram bins used one by one (the lowest frequencies, where the drift is).
    band_ratio
        Above ``exact_bins``, bins are averaged over bands ``[k, k * band_ratio)``.

    Returns
    -------
    KalmanModel

    Raises
    ------
    ValueError
        If the residual is not 2-D, has fewer than 64 samples, or holds NaN or inf.

    References
    ----------
    .. [1] P. Whittle, "Estimation and information in stationary time series", Ark. Mat. 2, 1953.
    .. [2] P. J. Brockwell, R. A. Davis, "Time Series: Theory and Methods", 2nd ed., Springer,
       1991, sec. 10.8 (Whittle estimator, its asymptotic covariance) and 9.3 (order selection).
    .. [3] O. E. Barndorff-Nielsen, G. Schou, "On the parametrization of autoregressive models by
       partial autocorrelations", J. Multivariate Anal. 3, 1973.
    """
    values = np.asarray(residual_dps, dtype=np.float64)
    if values.ndim != 2 or len(values) < _MIN_SAMPLES:
        raise ValueError(f"residual_dps must have shape (n, k) with n >= {_MIN_SAMPLES}, got {values.shape}")
    bad = np.argwhere(~np.isfinite(values))
    if len(bad):
        raise ValueError(f"residual_dps is not finite at sample {bad[0][0]}, axis {bad[0][1]}")
    if not fs_hz > 0:
        raise ValueError(f"fs_hz must be positive, got {fs_hz}")
    if int(max_order) < 0:
        raise ValueError(f"max_order must be >= 0, got {max_order}")
    axes = tuple(_identify_axis(values[:, i], int(max_order), exact_bins, band_ratio) for i in range(values.shape[1]))
    for name, m in zip(AXES, axes):
        if not all(se < _SE_UNIDENTIFIED for se in m.ar_se):
            log.warning("kalman model %s: the drift's AR coefficients are poorly identified (SE %s)",
                        name, np.round(m.ar_se, 3).tolist())
        log.info("kalman model %s: AR%s %s, drift sigma %.3g deg/s, tau %.3g s, R %.3g (deg/s)^2", name,
                 m.order, np.round(m.ar, 6).tolist(), m.drift_sigma_dps(), m.correlation_time_s(fs_hz), m.r_dps2)
    return KalmanModel(float(fs_hz), axes, len(values))


def _identify_axis(x: np.ndarray, max_order: int, exact_bins: int, band_ratio: float) -> AxisModel:
    mean = float(x.mean())
    spec = banded_periodogram(x - mean, exact_bins, band_ratio)
    # order 0, white noise alone: the Whittle estimate of R is the mean periodogram
    r_white = float(np.sum(spec.bins * spec.power) / np.sum(spec.bins))
    if not r_white > 0:
        raise ValueError("residual_dps is constant on an axis: there is no noise to model")
    bic = {"0": 2.0 * float(np.sum(spec.bins * (np.log(r_white) + spec.power / r_white))) + math.log(len(x))}
    fits = {}
    # a white-noise start for the AR fits: R from first differences (var(dx) / 2)
    r0 = max(float(np.var(np.diff(x))) / 2.0, 1e-30)
    for p in range(1, max_order + 1):
        fits[p] = fit_order(spec, p, r0, float(np.var(x)), fits.get(p - 1))
        # BIC = -2 log L + k ln n, k = p AR coefficients + q + R
        bic[str(p)] = 2.0 * fits[p].fun + (p + 2) * math.log(len(x))
    best = int(min(bic, key=bic.get))
    if best == 0:
        # the data do not support a drift: no drift state, all the noise is white
        return AxisModel((), (), 0.0, r_white, 0.0, r_white / math.sqrt(np.sum(spec.bins)), mean, bic)
    ar, q, r = unpack(fits[best].x, best)
    se = standard_errors(spec, ar, q, r)
    return AxisModel(tuple(float(v) for v in ar), tuple(float(v) for v in se[:best]), float(q), float(r),
                     float(se[best]), float(se[best + 1]), mean, bic)
